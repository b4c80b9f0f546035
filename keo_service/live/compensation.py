"""Live corrections on the wire: `keo/<cell>/correction` (CorrectionMessage) for each estimate
and, with ROS 2 on, `/keo/<cell>/correction` (geometry_msgs/msg/PoseStamped). The math is
`keo_service.core.compensation`; this module only builds it from the config and moves it.

For controller interfaces that send a correction with each reply (UR RTDE registers, KUKA
RSI, ABB EGM): `correction_to_send(latest, config.compensation)` gives the translation (m) and
rotation vector (rad) to send now, in the tool frame, for the right of the commanded tool
pose (T_cmd = T_goal * C); zero when none was received, it is not valid or it is older than
`max_age_s`.
"""

from __future__ import annotations

import logging
import time
from typing import Any

import numpy as np
import zenoh

from keo_service.core.correction import CompensationLimits, CorrectionFilter
from keo_service.core.correction import correction_to_send as _to_send
from keo_service.core.estimator import Estimate
from keo_service.core.kinematics import error_as_pose
from keo_service.core.rules import OUTSIDE_CALIBRATED_RANGE
from keo_service.io.config import CompensationConfig, Config
from keo_service.live.messages import CorrectionMessage, JointSample, encode, topic

__all__ = ["CorrectionPublisher", "CorrectionSink", "correction_to_send", "limits_of"]

log = logging.getLogger("keo.compensation")
MAX_AGE_S = 0.1  # a correction older than this is not applied by the controller interfaces


def limits_of(compensation: CompensationConfig, max_age_s: float = MAX_AGE_S) -> CompensationLimits:
    return CompensationLimits.from_config_values(
        compensation.max_mm, compensation.max_mrad, compensation.max_rate_mm_s, max_age_s
    )


def correction_to_send(
    latest: CorrectionMessage | None,
    compensation: CompensationConfig,
    now_ns: int | None = None,
    max_age_s: float = MAX_AGE_S,
) -> tuple[list[float], list[float]]:
    """(translation m, rotation vector rad) to send to the controller now; see the module."""
    return _to_send(
        latest, limits_of(compensation, max_age_s), time.time_ns() if now_ns is None else now_ns
    )


def correction_topic(cell: str) -> str:
    """The ROS 2 topic of a cell's correction."""
    return f"/keo/{cell}/correction"


def _feedforward(config: Config) -> Any:
    """The identified model's tool poses when the config holds a [model], else None (then
    nothing more is built or imported)."""
    from keo_service.io.cell import corrections_from_config, robot_from_config

    robot = robot_from_config(config)
    corrections = corrections_from_config(config.model, robot.nq, config.source)
    if corrections is None or corrections.is_zero:
        return None
    from keo_service.io.compensation_files import tool_model

    return tool_model(config)


class CorrectionPublisher:
    """Turns each estimate into a CorrectionMessage and puts it on the bus (and ROS 2).

    With a model, `on_joints` also publishes at every encoder sample: the feedforward at
    those (the current) joints with the newest estimate's feedback and validity, so the
    model's part follows the arm at the encoder rate instead of a tracker delay late. The
    limits' rate is per second of the host's monotonic clock (how fast the robot is moved)."""

    def __init__(self, config: Config, session: zenoh.Session, ros2_node: Any = None) -> None:
        self.cell = config.cell
        self.filter = CorrectionFilter(limits_of(config.compensation), _feedforward(config))
        self._pub = session.declare_publisher(topic(config.cell, "correction"), express=True)
        self._ros2 = None
        self._types: Any = None
        if ros2_node is not None:
            from keo_service.io.ros2_messages import POSE_STAMPED

            self._types = ros2_node.store.types
            self._ros2 = ros2_node.publisher(correction_topic(config.cell), POSE_STAMPED)
        self.seq = 0
        self.failures = 0
        self.latest: CorrectionMessage | None = None
        # the newest estimate: (monotonic time, its values, why not valid ("" if valid))
        self._estimate: tuple[float, list[float], str] | None = None

    @property
    def counters(self) -> dict[str, int]:
        return {**self.filter.counters, "corrections_publish_failed": self.failures}

    def message(self, estimate: Estimate, joints: Any = None) -> CorrectionMessage:
        """`joints`: the newest joints (the feedforward's "now"; the estimate's own joints
        are a tracker delay and a transport older), else the estimate's."""
        reason = ""
        if estimate.held:
            reason = estimate.flags[0] if estimate.flags else "held"
        elif OUTSIDE_CALIBRATED_RANGE in estimate.flags:
            reason = OUTSIDE_CALIBRATED_RANGE
        values = estimate.estimate_values()
        self._estimate = (time.monotonic(), values, reason)
        return self._make(estimate.t, values, estimate.joints if joints is None else joints, reason)

    def _make(
        self, stamp: float, values: list[float], joints: Any, reason: str
    ) -> CorrectionMessage:
        c = self.filter.step(time.monotonic(), values, joints, reason)
        self.seq += 1
        return CorrectionMessage(
            stamp=stamp,
            host_ns=time.time_ns(),
            seq=self.seq,
            translation=c.translation.tolist(),
            rotation=c.rotation.tolist(),
            feedback_translation=c.feedback[0].tolist(),
            feedback_rotation=c.feedback[1].tolist(),
            feedforward_translation=c.feedforward[0].tolist(),
            feedforward_rotation=c.feedforward[1].tolist(),
            valid=c.valid,
            reason=c.reason,
            clamped=c.clamped,
        )

    def publish(self, estimate: Estimate, estimator: Any = None) -> CorrectionMessage:
        """Publish the correction for `estimate`; `estimator`: the service's, whose newest
        encoder sample gives the joints for the feedforward."""
        joints = None
        if estimator is not None and self.filter.model is not None:
            newest = estimator.encoder.latest_at_or_before(estimator.encoder.newest_t)
            joints = None if newest is None else newest[1]
        msg = self.message(estimate, joints)
        self._put(msg)
        return msg

    def on_joints(self, t: float, q: Any) -> None:
        """An encoder sample (stream time t, joints q): with a model and an estimate newer
        than MAX_AGE_S, the correction with the feedforward at q (else nothing: the
        controller interfaces zero a correction that is not renewed)."""
        if self.filter.model is None or self._estimate is None:
            return
        at, values, reason = self._estimate
        if time.monotonic() - at > MAX_AGE_S:
            return
        self._put(self._make(t, values, np.asarray(q, dtype=float), reason))

    def _put(self, msg: CorrectionMessage) -> None:
        self.latest = msg
        try:
            self._pub.put(encode(msg))
        except zenoh.ZError as exc:  # counted; the next one may pass
            self.failures += 1
            if self.failures == 1 or self.failures % 1000 == 0:
                log.warning("publishing a correction failed (%d so far): %s", self.failures, exc)
        if self._ros2 is not None:
            from keo_service.io.ros2_messages import pose_stamped, tool_frame

            p, q = error_as_pose(np.array([*msg.translation, *msg.rotation]))
            assert q is not None
            self._ros2.publish(
                pose_stamped(self._types, msg.stamp, tool_frame(self.cell), p.tolist(), q.tolist()),
                source_ns=msg.host_ns,
            )

    def close(self) -> None:
        self._pub.undeclare()


class CorrectionSink:
    """The correction publisher as one of the service's outputs (`keo_service.live.sinks`):
    a correction for each estimate, and with a model the feedforward at each encoder sample.
    `estimator`: the service's (its newest joints feed the feedforward)."""

    name = "correction"
    period_s: float | None = None

    def __init__(self, publisher: CorrectionPublisher, estimator: Any) -> None:
        self.publisher = publisher
        self.estimator = estimator

    def on_input(self, sample: Any) -> None:
        if isinstance(sample, JointSample):  # with a model: feedforward at these joints
            self.publisher.on_joints(sample.t, sample.q)

    def on_estimate(self, estimate: Estimate, message: Any) -> None:
        self.publisher.publish(estimate, self.estimator)

    def on_tick(self) -> None:
        pass

    def counters(self) -> dict[str, int]:
        return self.publisher.counters

    def close(self) -> None:
        self.publisher.close()
