"""A ROS 2 driver nobody here wrote: `pyzeros` (an rmw_zenoh implementation in pure Python,
PyPI) publishes sensor_msgs/JointState (~50 Hz, joints shuffled, one extra joint) and
geometry_msgs/PoseStamped (~100 Hz) of a moving robot, both stamped from ONE clock (the
host's: ROS time on one host), as a robot driver and a tracker driver on one host (or on
PTP-synchronised hosts) do. No keo code on the wire; keo_service.core only computes the pose
a tracker would measure: nominal forward kinematics composed with a constant tool error.

    python -m tests.pyzeros_peer ENDPOINT URDF_CONFIG T0 DURATION

The joints move back and forth at constant speed along legs whose turns fall on joint-state
stamps, so interpolating between two joint states is exact: any error the service shows
comes from how it places the stamps.
"""

from __future__ import annotations

import asyncio
import sys
import time

import numpy as np

JOINT_PERIOD_S = 0.02  # 50 Hz
POSE_PERIOD_S = 0.01  # 100 Hz
POSE_PHASE_S = 0.003  # the tracker measures between joint states
LEG_S = 1.2  # seconds per leg (a multiple of JOINT_PERIOD_S)
Q0 = np.array([0.0, -1.3, 1.6, -1.9, -1.57, 0.0])
# joint travel per leg (rad): ~0.23 m/s at the tool of the UR10 (median)
TRAVEL = np.array([0.27, 0.18, -0.21, 0.15, 0.18, 0.225])
# the injected constant tool error: [p (m); rotation vector (rad)] in the nominal tool frame
LATE_S = 0.05  # events further behind the wall clock than this are skipped
TOOL_ERROR = np.array([0.3e-3, -0.1e-3, 0.2e-3, 0.2e-3, -0.1e-3, 0.15e-3])


def joints(t: float | np.ndarray, t0: float) -> np.ndarray:
    """Triangle wave in joint space: constant speed, turning every LEG_S from t0."""
    phase = np.mod(np.asarray(t, dtype=float) - t0, 2 * LEG_S) / LEG_S  # 0..2
    tri = np.where(phase < 1.0, phase, 2.0 - phase)
    return Q0 + np.multiply.outer(tri, TRAVEL)


def tracker_pose(cell, data, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What the tracker measures: T_ks = T_bk^-1 T_bt(q) T_ts with T_ts the tool error."""
    from keo_service.core.kinematics import quat_wxyz, sensor_pose_from_error, tool_pose

    T_bs = sensor_pose_from_error(tool_pose(cell, data, q), TOOL_ERROR)
    T_ks = cell.T_bk.actInv(T_bs)
    return np.asarray(T_ks.translation), quat_wxyz(T_ks.rotation)


def tool_speed(cell, t0: float) -> float:
    """Median tool speed (m/s) over one back-and-forth, from forward kinematics."""
    from keo_service.core.kinematics import tool_pose

    data = cell.robot.create_data()
    t = t0 + np.arange(0.0, 2 * LEG_S, 0.005)
    p = np.array([tool_pose(cell, data, q).translation for q in joints(t, t0)])
    return float(np.median(np.linalg.norm(np.diff(p, axis=0), axis=1) / 0.005))


def warm_up() -> None:
    """Build pyzeros' codecs (its attachment is serialised by cydr, compiled on first use)."""
    from pyzeros.builtin_msgs import Attachment

    Attachment(source_gid=np.zeros(16, dtype=np.uint8)).serialize()


async def play(endpoint: str, config_path: str, t0: float, duration: float) -> None:
    import pyzeros
    import zenoh
    from ros2_pyterfaces.cyclone.all_msgs import (
        Header,
        JointState,
        Point,
        Pose,
        PoseStamped,
        Quaternion,
        Time,
    )

    from keo_service.io.cell import cell_from_config
    from keo_service.io.config import load_config

    started = time.time()
    cell = cell_from_config(load_config(config_path))
    data = cell.robot.create_data()
    names = list(cell.robot.joint_names)
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", f'["{endpoint}"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(conf)
    print(f"pyzeros peer: session open after {time.time() - started:.2f} s", flush=True)

    def stamp(t: float) -> Time:
        ns = round(t * 1e9)
        return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)

    with pyzeros.auto_context(node="pyzeros_driver", zenoh_session=session):
        joint_pub = pyzeros.Pub(JointState, "/joint_states")
        pose_pub = pyzeros.Pub(PoseStamped, "/lasertracker/pose")
        print(f"pyzeros peer: publishers after {time.time() - started:.2f} s", flush=True)
        events = sorted(
            [(t0 + k * JOINT_PERIOD_S, 0) for k in range(int(duration / JOINT_PERIOD_S))]
            + [
                (t0 + POSE_PHASE_S + k * POSE_PERIOD_S, 1)
                for k in range(int(duration / POSE_PERIOD_S))
            ]
        )
        for t, kind in events:
            wait = t - time.time()
            if wait > 0:
                await asyncio.sleep(wait)
            elif wait < -LATE_S:  # started late (a loaded machine): no backlog, real time only
                continue
            # the stamp as sent (ns): the joints and the pose are those of that instant
            st = stamp(t)
            t_sent = st.sec + st.nanosec * 1e-9
            q = joints(t_sent, t0)
            if kind == 0:
                joint_pub.publish(
                    JointState(
                        header=Header(stamp=st, frame_id=""),
                        name=["gripper_finger", *reversed(names)],
                        position=[0.01, *map(float, q[::-1])],
                        velocity=[],
                        effort=[],
                    )
                )
            else:
                p, (w, x, y, z) = tracker_pose(cell, data, q)
                pose_pub.publish(
                    PoseStamped(
                        header=Header(stamp=st, frame_id="tracker"),
                        pose=Pose(
                            position=Point(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                            orientation=Quaternion(x=float(x), y=float(y), z=float(z), w=float(w)),
                        ),
                    )
                )
        joint_pub.close()
        pose_pub.close()
    session.close()


if __name__ == "__main__":
    endpoint, config_path, t0, duration = sys.argv[1:5]
    asyncio.run(play(endpoint, config_path, float(t0), float(duration)))
