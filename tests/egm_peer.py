"""A second EGM implementation for the tests: messages built and read with the classes protoc
generated from ABB's egm.proto, field by field, without keo's codec (adapters.abb_egm)."""

from __future__ import annotations

from keo_service.adapters.egm import egm_pb2


def robot_datagram(
    seqno: int, tm: int, joints_deg: list[float], external: list[float] | None = None
) -> bytes:
    msg = egm_pb2.EgmRobot()
    msg.header.seqno = seqno
    msg.header.tm = tm
    msg.header.mtype = egm_pb2.EgmHeader.MSGTYPE_DATA
    msg.feedBack.joints.joints.extend(joints_deg)
    if external is not None:
        msg.feedBack.externalJoints.joints.extend(external)
    msg.feedBack.cartesian.pos.x = 1000.0
    msg.feedBack.cartesian.pos.y = 0.0
    msg.feedBack.cartesian.pos.z = 1200.0
    msg.feedBack.cartesian.orient.u0 = 1.0
    msg.feedBack.cartesian.orient.u1 = 0.0
    msg.feedBack.cartesian.orient.u2 = 0.0
    msg.feedBack.cartesian.orient.u3 = 0.0
    msg.planned.joints.joints.extend(joints_deg)
    msg.motorState.state = egm_pb2.EgmMotorState.MOTORS_ON
    msg.mciState.state = egm_pb2.EgmMCIState.MCI_RUNNING
    msg.mciConvergenceMet = True
    msg.rapidExecState.state = egm_pb2.EgmRapidCtrlExecState.RAPID_RUNNING
    msg.utilizationRate = 12.5
    return bytes(msg.SerializeToString())


def read_sensor(data: bytes) -> tuple[int, int, int, list[float], list[float]]:
    """(seqno, tm, mtype, position mm, quaternion u0..u3) of an EgmSensor."""
    msg = egm_pb2.EgmSensor()
    msg.ParseFromString(data)
    pose = msg.planned.cartesian
    return (
        msg.header.seqno,
        msg.header.tm,
        msg.header.mtype,
        [pose.pos.x, pose.pos.y, pose.pos.z],
        [pose.orient.u0, pose.orient.u1, pose.orient.u2, pose.orient.u3],
    )
