"""keo's samples and estimates as ROS 2 message objects (rosbags' types), and back.

One place for the mapping, used by the live bridge (rmw_zenoh) and by MCAP recordings:
joints -> sensor_msgs/msg/JointState, a tracker pose -> geometry_msgs/msg/PoseStamped (a
single reflector: PointStamped), an estimate -> geometry_msgs/msg/PoseWithCovarianceStamped
(the error transform T_ts: position, quaternion of exp(r); diagonal covariance in SI units,
orientation variances -1 when there is no orientation) and tf2_msgs/msg/TFMessage.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_typestore

from keo_service.core.kinematics import error_as_pose

JOINT_STATE = "sensor_msgs/msg/JointState"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
POINT_STAMPED = "geometry_msgs/msg/PointStamped"
POSE_COV = "geometry_msgs/msg/PoseWithCovarianceStamped"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"

STORES = {
    "humble": Stores.ROS2_HUMBLE,
    "iron": Stores.ROS2_IRON,
    "jazzy": Stores.ROS2_JAZZY,
    "kilted": Stores.ROS2_KILTED,
    "rolling": Stores.LATEST,
}


def estimate_topic(cell: str) -> str:
    """The ROS 2 topic of a cell's estimate."""
    return f"/keo/{cell}/kinematic_error"


def tool_frame(cell: str) -> str:
    """The nominal tool frame's name in ROS (frame_id of the estimate)."""
    return f"{cell}_tool"


def typestore(distro: str = "jazzy") -> Any:
    return get_typestore(STORES[distro])


def stamp_of(t: float) -> tuple[int, int]:
    """Seconds and nanoseconds of a time in seconds (nanoseconds rounded, never 1e9)."""
    sec = math.floor(t)
    return sec, min(round((t - sec) * 1e9), 999_999_999)


def seconds_of(header: Any) -> float:
    return float(header.stamp.sec) + float(header.stamp.nanosec) * 1e-9


def header(types: Any, t: float, frame: str) -> Any:
    sec, nanosec = stamp_of(t)
    time_type = types["builtin_interfaces/msg/Time"]
    return types["std_msgs/msg/Header"](stamp=time_type(sec, nanosec), frame_id=frame)


def _quaternion(types: Any, q_wxyz: Sequence[float] | None) -> Any:
    w, x, y, z = (1.0, 0.0, 0.0, 0.0) if q_wxyz is None else map(float, q_wxyz)
    return types["geometry_msgs/msg/Quaternion"](x, y, z, w)


def joint_state(
    types: Any, t: float, names: Sequence[str], q: Sequence[float], dq: Sequence[float] | None
) -> Any:
    return types[JOINT_STATE](
        header=header(types, t, ""),
        name=list(names),
        position=np.asarray(q, dtype=float),
        velocity=np.asarray(dq if dq is not None else [], dtype=float),
        effort=np.array([], dtype=float),
    )


def pose_stamped(
    types: Any, t: float, frame: str, p: Sequence[float], q_wxyz: Sequence[float]
) -> Any:
    pose = types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](*map(float, p)),
        orientation=_quaternion(types, q_wxyz),
    )
    return types[POSE_STAMPED](header=header(types, t, frame), pose=pose)


def point_stamped(types: Any, t: float, frame: str, p: Sequence[float]) -> Any:
    return types[POINT_STAMPED](
        header=header(types, t, frame), point=types["geometry_msgs/msg/Point"](*map(float, p))
    )


def covariance(variance: np.ndarray | None, channels: int) -> np.ndarray:
    """The 6x6 row-major covariance of a pose from per-channel variances (px..rz)."""
    cov = np.zeros(36)
    if variance is not None:
        for i, v in enumerate(variance[:6]):
            cov[7 * i] = v
    if channels < 6:
        for i in range(3, 6):
            cov[7 * i] = -1.0  # orientation unknown
    return cov


def pose_with_covariance(
    types: Any, t: float, frame: str, estimate: Sequence[float], variance: np.ndarray | None
) -> Any:
    p, q = error_as_pose(np.asarray(estimate, dtype=float))
    pose = types["geometry_msgs/msg/Pose"](
        position=types["geometry_msgs/msg/Point"](*map(float, p)),
        orientation=_quaternion(types, None if q is None else q.tolist()),
    )
    return types[POSE_COV](
        header=header(types, t, frame),
        pose=types["geometry_msgs/msg/PoseWithCovariance"](
            pose=pose, covariance=covariance(variance, len(estimate))
        ),
    )


def tf_message(types: Any, t: float, frame: str, child: str, estimate: Sequence[float]) -> Any:
    p, q = error_as_pose(np.asarray(estimate, dtype=float))
    transform = types["geometry_msgs/msg/TransformStamped"](
        header=header(types, t, frame),
        child_frame_id=child,
        transform=types["geometry_msgs/msg/Transform"](
            translation=types["geometry_msgs/msg/Vector3"](*map(float, p)),
            rotation=_quaternion(types, None if q is None else q.tolist()),
        ),
    )
    return types[TF_MESSAGE](transforms=[transform])
