"""keo's estimate as ROS 2 messages: `/keo/<cell>/kinematic_error`
(geometry_msgs/msg/PoseWithCovarianceStamped) and, when asked, the transform tool ->
tool_measured on `/tf`.

The pose is the estimated error transform T_ts: position p_ts [m], orientation the quaternion
of exp(r). The covariance is diagonal, in SI units: per channel the observer's steady-state
variance for the measured noise, (noise gain(L, T) * noise std)^2, T the tracker's period. A
single-reflector tracker estimates no orientation: identity quaternion, orientation
variances -1 (unknown, the ROS convention). Held steps are not published.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import zenoh

from keo_service.core.kinematics import error_as_pose
from keo_service.core.observer import estimate_variance
from keo_service.io.config import Config
from keo_service.live.messages import EstimateMessage
from keo_service.live.ros2 import Ros2Node

POSE_TYPE = "geometry_msgs/msg/PoseWithCovarianceStamped"
TF_TYPE = "tf2_msgs/msg/TFMessage"


def estimate_topic(cell: str) -> str:
    return f"/keo/{cell}/kinematic_error"


def tool_frame(cell: str) -> str:
    """The nominal tool frame's name in ROS (frame_id of the estimate)."""
    return f"{cell}_tool"


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


class EstimateBridge:
    def __init__(self, session: zenoh.Session, config: Config) -> None:
        ros = config.ros2
        self.cell = config.cell
        self.node = Ros2Node(session, f"keo_{config.cell}", ros.domain_id, ros.distro)
        self.types = self.node.store.types
        self._pose = self.node.publisher(estimate_topic(config.cell), POSE_TYPE)
        self._tf = self.node.publisher("/tf", TF_TYPE) if ros.publish_tf else None
        self.published = 0

    def _header(self, stamp: float, frame: str) -> Any:
        sec = int(np.floor(stamp))
        nanosec = min(round((stamp - sec) * 1e9), 999_999_999)
        time_type = self.types["builtin_interfaces/msg/Time"]
        return self.types["std_msgs/msg/Header"](stamp=time_type(sec, nanosec), frame_id=frame)

    def pose_message(self, msg: EstimateMessage, variance: np.ndarray | None) -> Any:
        t = self.types
        p, q = error_as_pose(np.asarray(msg.estimate))
        w, x, y, z = (1.0, 0.0, 0.0, 0.0) if q is None else q
        pose = t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](*map(float, p)),
            orientation=t["geometry_msgs/msg/Quaternion"](float(x), float(y), float(z), float(w)),
        )
        return t[POSE_TYPE](
            header=self._header(msg.stamp, tool_frame(self.cell)),
            pose=t["geometry_msgs/msg/PoseWithCovariance"](
                pose=pose, covariance=covariance(variance, len(msg.estimate))
            ),
        )

    def tf_message(self, msg: EstimateMessage) -> Any:
        t = self.types
        p, q = error_as_pose(np.asarray(msg.estimate))
        w, x, y, z = (1.0, 0.0, 0.0, 0.0) if q is None else q
        transform = t["geometry_msgs/msg/TransformStamped"](
            header=self._header(msg.stamp, tool_frame(self.cell)),
            child_frame_id=f"{tool_frame(self.cell)}_measured",
            transform=t["geometry_msgs/msg/Transform"](
                translation=t["geometry_msgs/msg/Vector3"](*map(float, p)),
                rotation=t["geometry_msgs/msg/Quaternion"](float(x), float(y), float(z), float(w)),
            ),
        )
        return t[TF_TYPE](transforms=[transform])

    def publish(
        self,
        msg: EstimateMessage,
        noise_std: np.ndarray | None,
        gains: list[float],
        period: float,
    ) -> None:
        if msg.measured is None:  # a held step says nothing new
            return
        variance = None if noise_std is None else estimate_variance(noise_std, gains, period)
        self._pose.publish(self.pose_message(msg, variance), source_ns=msg.host_ns)
        if self._tf is not None:
            self._tf.publish(self.tf_message(msg), source_ns=msg.host_ns)
        self.published += 1

    def close(self) -> None:
        self.node.close()
