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

from keo_service.core.observer import estimate_variance
from keo_service.io import ros2_messages as rm
from keo_service.io.config import Config
from keo_service.live.messages import EstimateMessage
from keo_service.live.ros2 import Ros2Node


class EstimateBridge:
    def __init__(self, session: zenoh.Session, config: Config) -> None:
        ros = config.ros2
        self.cell = config.cell
        self.node = Ros2Node(session, f"keo_{config.cell}", ros.domain_id, ros.distro)
        self.types = self.node.store.types
        self._pose = self.node.publisher(rm.estimate_topic(config.cell), rm.POSE_COV)
        self._tf = self.node.publisher("/tf", rm.TF_MESSAGE) if ros.publish_tf else None
        self.published = 0

    def pose_message(self, msg: EstimateMessage, variance: np.ndarray | None) -> Any:
        return rm.pose_with_covariance(
            self.types, msg.stamp, rm.tool_frame(self.cell), msg.estimate, variance
        )

    def tf_message(self, msg: EstimateMessage) -> Any:
        frame = rm.tool_frame(self.cell)
        return rm.tf_message(self.types, msg.stamp, frame, f"{frame}_measured", msg.estimate)

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
