"""ABB Externally Guided Motion (EGM) datagrams: `EgmRobot` in, `EgmSensor` out.

The messages are ABB's `egm.proto` (adapters/egm), compiled by protoc; this module only maps
them to keo's units and checks them. Pure codec: bytes in, typed frames out, no I/O.

- `EgmRobot`: header.seqno (uint32, wraps) and header.tm (the controller's ms clock), the
  measured joints `feedBack.joints` in degrees (-> rad), external axes `feedBack.externalJoints`
  (degrees or mm, kept as sent), motor / EGM / RAPID states.
- `EgmSensor`: header (seqno counting keo's answers, tm echoing the controller's, type
  CORRECTION) and `planned.cartesian`: the correction as a pose (position mm, orientation a
  unit quaternion u0..u3, scalar first) relative to EGMActPose's correction frame. No
  correction is the identity pose.

Sequence numbers are checked: a repeated or older seqno is refused, a jump forward counts the
datagrams lost in between (`lost`) and the gap (`seq_gap`); three refused in a row mean the
controller counts anew (a restart, a new EGM session): the third is accepted and `restarts`
counted.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from google.protobuf.message import DecodeError

from keo_service.adapters.egm import egm_pb2
from keo_service.core.rejects import RejectLog

MAX_DATAGRAM = 8192  # an EgmRobot with every field is ~400 bytes
SEQ_MOD = 2**32
RESTART_AFTER = 3  # this many refused seqnos in a row: the controller counts anew
_HALF = 2**31


@dataclass(frozen=True)
class EgmRobotFrame:
    seqno: int
    tm_ms: int
    joints_rad: tuple[float, ...]
    external: tuple[float, ...] | None
    motors_on: bool | None
    egm_running: bool | None  # mciState == MCI_RUNNING
    rapid_running: bool | None


@dataclass(frozen=True)
class EgmSensorFrame:
    seqno: int
    tm_ms: int
    position_mm: tuple[float, float, float] | None
    quaternion: tuple[float, float, float, float] | None  # u0 (scalar) u1 u2 u3


def format_sensor(
    seqno: int,
    tm_ms: int,
    position_mm: tuple[float, float, float] | list[float] = (0.0, 0.0, 0.0),
    quaternion: tuple[float, float, float, float] | list[float] = (1.0, 0.0, 0.0, 0.0),
) -> bytes:
    msg = egm_pb2.EgmSensor()
    msg.header.seqno = seqno % SEQ_MOD
    msg.header.tm = tm_ms % SEQ_MOD
    msg.header.mtype = egm_pb2.EgmHeader.MSGTYPE_CORRECTION
    pose = msg.planned.cartesian
    pose.pos.x, pose.pos.y, pose.pos.z = (float(v) for v in position_mm)
    pose.orient.u0, pose.orient.u1, pose.orient.u2, pose.orient.u3 = (float(v) for v in quaternion)
    return bytes(msg.SerializeToString())


def format_robot(
    seqno: int,
    tm_ms: int,
    joints_deg: tuple[float, ...] | list[float],
    external: tuple[float, ...] | list[float] | None = None,
    motors_on: bool = True,
) -> bytes:
    """A controller's datagram (for the mock controller)."""
    msg = egm_pb2.EgmRobot()
    msg.header.seqno = seqno % SEQ_MOD
    msg.header.tm = tm_ms % SEQ_MOD
    msg.header.mtype = egm_pb2.EgmHeader.MSGTYPE_DATA
    msg.feedBack.joints.joints.extend(float(v) for v in joints_deg)
    if external is not None:
        msg.feedBack.externalJoints.joints.extend(float(v) for v in external)
    msg.planned.joints.joints.extend(float(v) for v in joints_deg)
    msg.motorState.state = (
        egm_pb2.EgmMotorState.MOTORS_ON if motors_on else egm_pb2.EgmMotorState.MOTORS_OFF
    )
    msg.mciState.state = egm_pb2.EgmMCIState.MCI_RUNNING
    msg.rapidExecState.state = egm_pb2.EgmRapidCtrlExecState.RAPID_RUNNING
    return bytes(msg.SerializeToString())


def _finite(values: tuple[float, ...]) -> bool:
    return all(math.isfinite(v) for v in values)


class EgmCodec:
    """Decodes `EgmRobot` datagrams with the sequence check (and `EgmSensor` answers, for the
    mock controller); bad datagrams are counted by reason in `counters`."""

    def __init__(self) -> None:
        self._rejects = RejectLog(keep=16)
        self.counters = self._rejects.counters
        self.messages = self._rejects.messages
        self._last_seq: int | None = None
        self._behind = 0
        self.datagrams = 0  # datagrams parsed so far: a reject names its number

    def _next_datagram(self) -> None:
        self.datagrams += 1
        self._rejects.at = f"datagram {self.datagrams}"

    def reset(self) -> None:
        """A new controller session: the sequence check starts over."""
        self._last_seq = None
        self._behind = 0

    def _check_seq(self, seqno: int) -> bool:
        if self._last_seq is None:
            self._last_seq = seqno
            return True
        step = (seqno - self._last_seq) % SEQ_MOD
        if step == 0 or step >= _HALF:
            reason = "duplicate" if step == 0 else "out_of_order"
            self._rejects.reject(reason, f"seqno {seqno} after {self._last_seq}")
            self._behind += 1
            if self._behind >= RESTART_AFTER:
                # the controller started counting anew (restart, a new EGM session)
                self._rejects.note("restarts", f"seqno restarted at {seqno}")
                self._last_seq, self._behind = seqno, 0
                return True
            return False
        self._behind = 0
        if step > 1:
            self.counters["seq_gap"] += 1
            self.counters["lost"] += step - 1
            self.messages.append(f"seqno {seqno} after {self._last_seq}: {step - 1} lost")
        self._last_seq = seqno
        return True

    def parse_robot(self, data: bytes) -> EgmRobotFrame | None:
        self._next_datagram()
        if len(data) > MAX_DATAGRAM:
            self._rejects.reject("too_long", f"datagram of {len(data)} bytes")
            return None
        msg = egm_pb2.EgmRobot()
        try:
            msg.ParseFromString(data)
        except DecodeError as exc:
            self._rejects.reject("malformed", f"not an EgmRobot: {exc}")
            return None
        if not msg.HasField("header") or not msg.header.HasField("seqno"):
            self._rejects.reject("missing_field", "EgmRobot without header.seqno")
            return None
        seqno, tm = msg.header.seqno, msg.header.tm
        if not msg.HasField("feedBack") or not msg.feedBack.HasField("joints"):
            self._rejects.reject("missing_field", f"seqno {seqno}: no feedBack.joints")
            return None
        joints = tuple(msg.feedBack.joints.joints)
        if not joints or not _finite(joints):
            self._rejects.reject("non_finite", f"seqno {seqno}: feedBack.joints {joints!r}")
            return None
        if not msg.header.HasField("tm"):
            self._rejects.reject("missing_field", f"seqno {seqno}: no header.tm")
            return None
        if not self._check_seq(seqno):
            return None
        external = None
        if msg.feedBack.HasField("externalJoints"):
            external = tuple(msg.feedBack.externalJoints.joints) or None
        self.counters["frames"] += 1
        return EgmRobotFrame(
            seqno=seqno,
            tm_ms=tm,
            joints_rad=tuple(math.radians(v) for v in joints),
            external=external,
            motors_on=(
                msg.motorState.state == egm_pb2.EgmMotorState.MOTORS_ON
                if msg.HasField("motorState")
                else None
            ),
            egm_running=(
                msg.mciState.state == egm_pb2.EgmMCIState.MCI_RUNNING
                if msg.HasField("mciState")
                else None
            ),
            rapid_running=(
                msg.rapidExecState.state == egm_pb2.EgmRapidCtrlExecState.RAPID_RUNNING
                if msg.HasField("rapidExecState")
                else None
            ),
        )

    def parse_sensor(self, data: bytes) -> EgmSensorFrame | None:
        self._next_datagram()
        msg = egm_pb2.EgmSensor()
        try:
            msg.ParseFromString(data)
        except DecodeError as exc:
            self._rejects.reject("malformed", f"not an EgmSensor: {exc}")
            return None
        position: tuple[float, float, float] | None = None
        quaternion: tuple[float, float, float, float] | None = None
        if msg.planned.HasField("cartesian"):
            pose = msg.planned.cartesian
            if pose.HasField("pos"):
                position = (pose.pos.x, pose.pos.y, pose.pos.z)
            if pose.HasField("orient"):
                o = pose.orient
                quaternion = (o.u0, o.u1, o.u2, o.u3)
        if not _finite((*(position or ()), *(quaternion or ()))):
            self._rejects.reject("non_finite", f"seqno {msg.header.seqno}: {position} {quaternion}")
            return None
        self.counters["frames"] += 1
        return EgmSensorFrame(msg.header.seqno, msg.header.tm, position, quaternion)
