"""Live corrections on the wire: `keo/<cell>/correction` (CorrectionMessage) for each estimate
and, with ROS 2 on, `/keo/<cell>/correction` (geometry_msgs/msg/PoseStamped). The math is
`keo_service.core.compensation`; this module only builds it from the config and moves it.

For controller interfaces that send a correction with each reply (UR RTDE registers, KUKA
RSI, ABB EGM): `correction_to_send(latest, config.compensation)` gives the translation (m) and
rotation vector (rad) to send now, in the tool frame, for the right of the commanded tool
pose (T_cmd = T_goal * C); zero when none was received, it is not valid or it is older than
`[compensation] max_age_s`.

Validity is also timer-driven (`tick`, run on the correction's own cycle: `[compensation]
rate_hz`, else the observer's period, at least 2 ms): a correction is valid only while the
newest encoder sample, the newest tracker pose and the newest estimate arrived within
`[compensation] stale_after_s` (host time), besides the estimate's own verdict (held,
outside the calibrated range). The first cycle where one of them fails publishes a zero,
invalid correction with the reason (counted in `corrections_stale`, logged); while nothing
new comes, a cycle renews the newest correction (an invalid one only while some input still
arrives), so a stalled stream is never silent for much longer than a cycle and an idle
cell's is.
"""

from __future__ import annotations

import collections
import logging
import time
from typing import Any

import msgspec
import numpy as np
import zenoh

from keo_service.core.compensation import CorrectionFilter
from keo_service.core.compensation import correction_to_send as _to_send
from keo_service.core.estimator import Estimate
from keo_service.core.kinematics import error_as_pose
from keo_service.core.rules import OUTSIDE_CALIBRATED_RANGE
from keo_service.io.config import CompensationConfig, Config
from keo_service.live.bus import output_publisher
from keo_service.live.messages import (
    CorrectionMessage,
    JointSample,
    TrackerSample,
    encode,
    topic,
)

__all__ = ["CorrectionPublisher", "CorrectionSink", "correction_to_send"]

log = logging.getLogger("keo.compensation")
DEFAULT_CYCLE_S = 0.01  # the correction's cycle before the observer's period is known
# the observer's period as the cycle, kept within these: no faster than RTDE's 2 ms, the
# fastest controller cycle a correction feeds (at the estimates' 1 ms the cycle was a second
# timer at the estimate rate, renewing a correction at every late tick: docs/performance.md)
CYCLE_BOUNDS_S = (0.002, 0.1)
# a quiet cycle renews the newest correction once this many cycles passed without a put (not
# one: estimates at the cycle's own rate would be doubled by every tick that comes late)
RENEW_AFTER = 1.5
# the estimate message's flag while the delay in use is not settled (live/service.py sets it)
DELAY_UNSETTLED = "delay_unsettled"
WARN_EVERY_S = 1.0  # a correction going stale is a warning at most this often (always counted)


def correction_to_send(
    latest: CorrectionMessage | None,
    compensation: CompensationConfig,
    now_ns: int | None = None,
) -> tuple[list[float], list[float]]:
    """(translation m, rotation vector rad) to send to the controller now; see the module."""
    return _to_send(latest, compensation.limits(), time.time_ns() if now_ns is None else now_ns)


def correction_topic(cell: str) -> str:
    """The ROS 2 topic of a cell's correction."""
    return f"/keo/{cell}/correction"


def _feedforward(config: Config) -> Any:
    """The identified model's tool poses when the config holds a [model], else None (then
    nothing more is built or imported)."""
    from keo_service.io.cell import corrections_from_config, robot_from_config, tool_model

    robot = robot_from_config(config)
    corrections = corrections_from_config(config.model, robot.nq, config.source)
    if corrections is None or corrections.is_zero:
        return None
    return tool_model(config)


class CorrectionPublisher:
    """Turns each estimate into a CorrectionMessage and puts it on the bus (and ROS 2).

    With a model, `on_joints` also publishes at every encoder sample: the feedforward at
    those (the current) joints with the newest estimate's feedback and validity, so the
    model's part follows the arm at the encoder rate instead of a tracker delay late. The
    limits' rate is per second of the host's monotonic clock (how fast the robot is moved).
    Without `local_subscribers` the corrections go to other sessions only (a service that
    opened its session itself has no subscriber of them in its process)."""

    def __init__(
        self,
        config: Config,
        session: zenoh.Session,
        ros2_node: Any = None,
        local_subscribers: bool = True,
    ) -> None:
        self.cell = config.cell
        from keo_service.io.cell import probe_in_tool

        self.filter = CorrectionFilter(
            config.compensation.limits(), _feedforward(config), probe_in_tool(config)
        )
        self._max_age_s = config.compensation.max_age_s
        self._pub = output_publisher(session, topic(config.cell, "correction"), local_subscribers)
        self._ros2 = None
        self._types: Any = None
        if ros2_node is not None:
            from keo_service.io.ros2_messages import POSE_STAMPED

            self._types = ros2_node.store.types
            self._ros2 = ros2_node.publisher(correction_topic(config.cell), POSE_STAMPED)
        self.seq = 0
        self.failures = 0
        self.stale_events = 0  # times the freshness check turned the correction invalid
        # estimates measured with a delay not yet settled (issue 45): their corrections held
        self.unsettled_held = 0
        # with robot.correction = "none" no correction reaches a robot: its validity is
        # counted, not logged (issue 45: 19 warnings about corrections nobody sends)
        self._quiet = config.robot.correction == "none"
        self.latest: CorrectionMessage | None = None
        # the newest estimate: (monotonic time, its values, why not valid ("" if valid))
        self._estimate: tuple[float, list[float], str] | None = None
        self._stamp = 0.0  # the newest estimate's stream time
        self._joints: Any = None  # the joints of the newest correction
        self._stale_after_s = config.compensation.stale_after_s
        self._rate_hz = config.compensation.rate_hz
        # monotonic arrival of the newest encoder sample and tracker pose (None: none seen,
        # not checked: a publisher fed estimates without its inputs)
        self._encoder_at: float | None = None
        self._tracker_at: float | None = None
        self._stale = ""  # the freshness verdict of the last check ("" fresh)
        self._warned_at = -WARN_EVERY_S  # monotonic time of the newest warning about it
        self._put_at = 0.0  # monotonic time of the newest put
        self._steps: collections.deque[float] = collections.deque(maxlen=50)

    @property
    def counters(self) -> dict[str, int]:
        return {
            **self.filter.counters,
            "corrections_publish_failed": self.failures,
            "corrections_stale": self.stale_events,
            "corrections_delay_unsettled": self.unsettled_held,
        }

    @property
    def cycle_s(self) -> float:
        """The correction's own cycle: 1 / rate_hz, else the observer's mean step over its
        last estimates (stream time), within CYCLE_BOUNDS_S."""
        if self._rate_hz > 0.0:
            return 1.0 / self._rate_hz
        steps = self._steps
        if len(steps) < 2 or steps[-1] <= steps[0]:
            return DEFAULT_CYCLE_S
        period = (steps[-1] - steps[0]) / (len(steps) - 1)
        return min(max(period, CYCLE_BOUNDS_S[0]), CYCLE_BOUNDS_S[1])

    def note_input(self, sample: JointSample | TrackerSample, now: float | None = None) -> None:
        """An input sample arrived (monotonic `now`): encoder samples and tracker poses keep
        the correction fresh (a tracker gap does not)."""
        now = time.monotonic() if now is None else now
        if isinstance(sample, JointSample):
            self._encoder_at = now
        elif sample.status == "ok" and sample.position is not None:
            self._tracker_at = now

    def freshness(self, now: float) -> str:
        """Why the inputs are not fresh enough for a valid correction ("" when they are)."""
        limit = self._stale_after_s
        if self._encoder_at is not None and now - self._encoder_at > limit:
            return "encoder_stale"
        if self._tracker_at is not None and now - self._tracker_at > limit:
            return "tracker_stale"
        if self._estimate is not None and now - self._estimate[0] > limit:
            return "estimate_stale"
        return ""

    def _verdict(self, now: float) -> tuple[str, bool]:
        """The freshness verdict now and whether it changed since the last check; a change
        is logged, one to stale counted."""
        reason = self.freshness(now)
        changed = reason != self._stale
        if changed and reason and not self._stale:  # fresh -> stale (not one stale reason
            self.stale_events += 1  # giving way to another)
            ages = {
                "encoder_stale": self._encoder_at,
                "tracker_stale": self._tracker_at,
                "estimate_stale": None if self._estimate is None else self._estimate[0],
            }
            since = ages.get(reason)
            due = now - self._warned_at >= WARN_EVERY_S and not self._quiet
            level = logging.WARNING if due else logging.DEBUG
            self._warned_at = now if level == logging.WARNING else self._warned_at
            log.log(
                level,
                "correction invalid: %s (nothing for %.3f s, compensation.stale_after_s = %g; "
                "%d so far)",
                reason,
                now - since if since is not None else float("nan"),
                self._stale_after_s,
                self.stale_events,
            )
        elif changed and not reason:
            log.log(
                logging.DEBUG if self._quiet else logging.INFO,
                "correction inputs fresh again (was %s)",
                self._stale,
            )
        self._stale = reason
        return reason, changed

    def _renew_due(self, now: float) -> bool:
        """RENEW_AFTER cycles without a put, and either the newest correction is valid or an
        input still arrives (a stall of one stream: its reason stays on the wire). Once every
        input is quiet, the invalid correction said it once and the stream rests (the
        controller interfaces zero a correction that is not renewed; an idle cell is quiet)."""
        latest = self.latest
        if latest is None or now - self._put_at < RENEW_AFTER * self.cycle_s:
            return False
        limit = self._stale_after_s
        flowing = any(
            at is not None and now - at <= limit for at in (self._encoder_at, self._tracker_at)
        )
        return latest.valid or flowing

    def tick(self, now: float | None = None) -> CorrectionMessage | None:
        """One cycle of the correction's own clock (see the module): the first cycle where
        the inputs are not fresh publishes a zero, invalid correction with the reason; a
        cycle after RENEW_AFTER cycles without a put renews the newest correction (an invalid one
        only while an input still arrives). Returns what it
        published. Nothing before the first estimate."""
        now = time.monotonic() if now is None else now
        if self._estimate is None:
            return None
        reason, changed = self._verdict(now)
        if reason and changed:
            _at, values, _ = self._estimate
            msg = self._make(self._stamp, values, self._joints, reason)
        elif self.latest is not None and self._renew_due(now):
            msg = msgspec.structs.replace(self.latest, seq=self.seq + 1, host_ns=time.time_ns())
            self.seq += 1
        else:
            return None
        self._put(msg, now)
        return msg

    def message(
        self, estimate: Estimate, joints: Any = None, delay_unsettled: bool = False
    ) -> CorrectionMessage:
        """`joints`: the newest joints (the feedforward's "now"; the estimate's own joints
        are a tracker delay and a transport older), else the estimate's. `delay_unsettled`:
        the estimate was measured with a delay the service has not settled yet (its message
        carries the flag): a correction from it is held, invalid, and counted (the delay in
        use may still be milliseconds off: at 0.25 m/s a millisecond is 250 um)."""
        reason = ""
        if estimate.held:
            reason = estimate.flags[0] if estimate.flags else "held"
        elif delay_unsettled:
            reason = DELAY_UNSETTLED
            self.unsettled_held += 1
        elif OUTSIDE_CALIBRATED_RANGE in estimate.flags:
            reason = OUTSIDE_CALIBRATED_RANGE
        values = estimate.estimate_values()
        now = time.monotonic()
        if not estimate.held:
            self._steps.append(estimate.stamp)
        self._estimate = (now, values, reason)
        self._stamp = estimate.stamp
        stale, _ = self._verdict(now)
        joints = estimate.joints if joints is None else joints
        return self._make(estimate.stamp, values, joints, reason or stale)

    def _make(
        self, stamp: float, values: list[float], joints: Any, reason: str
    ) -> CorrectionMessage:
        c = self.filter.step(time.monotonic(), values, joints, reason)
        self._joints = joints
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

    def publish(
        self, estimate: Estimate, estimator: Any = None, delay_unsettled: bool = False
    ) -> CorrectionMessage:
        """Publish the correction for `estimate`; `estimator`: the service's, whose newest
        encoder sample gives the joints for the feedforward; `delay_unsettled` as in
        `message`."""
        joints = None
        if estimator is not None and self.filter.model is not None:
            newest = estimator.encoder.latest_at_or_before(estimator.encoder.newest_t)
            joints = None if newest is None else newest[1]
        msg = self.message(estimate, joints, delay_unsettled)
        self._put(msg)
        return msg

    def on_joints(self, t: float, q: Any) -> None:
        """An encoder sample (stream time t, joints q): with a model and an estimate newer
        than `[compensation] max_age_s`, the correction with the feedforward at q (else nothing: the
        controller interfaces zero a correction that is not renewed)."""
        if self.filter.model is None or self._estimate is None:
            return
        at, values, reason = self._estimate
        now = time.monotonic()
        if now - at > self._max_age_s:
            return
        stale, _ = self._verdict(now)
        self._put(self._make(t, values, np.asarray(q, dtype=float), reason or stale), now)

    def _put(self, msg: CorrectionMessage, now: float | None = None) -> None:
        self.latest = msg
        self._put_at = time.monotonic() if now is None else now
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

    def __init__(self, publisher: CorrectionPublisher, estimator: Any) -> None:
        self.publisher = publisher
        self.estimator = estimator

    @property
    def period_s(self) -> float:
        """The correction's own cycle (read again at every cycle: the observer's period is
        learnt from the estimates)."""
        return self.publisher.cycle_s

    def on_input(self, sample: Any) -> None:
        self.publisher.note_input(sample)
        if isinstance(sample, JointSample):  # with a model: feedforward at these joints
            self.publisher.on_joints(sample.stamp, sample.joints)

    def on_estimate(self, estimate: Estimate, message: Any) -> None:
        unsettled = DELAY_UNSETTLED in getattr(message, "flags", ())
        self.publisher.publish(estimate, self.estimator, unsettled)

    def on_tick(self) -> None:
        self.publisher.tick()

    def counters(self) -> dict[str, int]:
        return self.publisher.counters

    def close(self) -> None:
        self.publisher.close()
