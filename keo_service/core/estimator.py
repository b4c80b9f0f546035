"""The streaming estimator: validation, alignment, measured error and observer, one sample
at a time.

It serves `keo run` (live), replay, and `keo estimate --streaming` (and `keo estimate` for
what the batch path does not cover: see `batch`). Samples go in as they arrive (any
interleaving of the two streams, each in its own time order) and estimates come out. Only
stream time stamps are used, never the wall clock, so the same input gives the same output
however it is delivered. What it refuses, when it holds a step, the step cap, the joints'
directions and the range flags are the rules of `rules`, which the batch path applies to
whole recordings. No I/O here.
"""

from __future__ import annotations

import functools
import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from keo_service.core.kinematics import (
    POSE_CHANNELS,
    POSITION_CHANNELS,
    Cell,
    corrected_joints,
    fold_frames,
    measured_error,
    measured_error_folded,
)
from keo_service.core.observer import KinematicErrorObserver
from keo_service.core.rejects import RejectLog
from keo_service.core.rules import (
    CAP_MIN_INTERVALS,
    CAP_REFRESH,
    MAX_MESSAGES,
    MAX_PENDING,
    OBSERVER_REJECTED,
    OUTSIDE_CALIBRATED_RANGE,
    TRACKER_GAP,
    CalibratedRanges,
    cap_is_due,
    direction_update,
    encoder_reject,
    held_reason,
    sensor_values,
    step_cap,
    tracker_stamp_problem,
    tracker_value_problem,
    waits_for_encoder,
)
from keo_service.core.settings import EstimatorSettings, encoder_capacity
from keo_service.core.timing import DelayModel, EncoderBuffer

DELAY_SLEW = 0.001  # a new delay is approached at this many s per s of stream time


class Estimate:
    """One observer output. `measured` is None when the step was held (see `flags`).

    The one estimate record: the wire's `EstimateMessage` is made from it
    (`live.messages.estimate_message`), the batch path's `BatchResult` holds its fields as
    columns under the same names, the Rerun pipe carries its fields.

    Read-only by convention. The two vectors are kept as they were made (plain floats: the
    hot path makes one estimate per tracker sample, and two arrays each would be a real share
    of its cost, docs/performance.md) and become arrays on first read; `measured_values` and
    `estimate_values` give the floats without arrays.

    Attributes:
        stamp: the tracker sample's stream time (s), or the tick's for "latest" alignment.
        measured: the measured error of this sample, one value per channel (m for px, py, pz;
            rad for rx, ry, rz: a rotation vector), in the measurement frame; None when held.
        estimate: the observer's estimate of the error, per channel (m, rad).
        flags: why the step was held (its only flag then) or what to know about it.
        encoder_stamp: the stream time (s) the joints were taken at: the tracker's stamp
            minus the delay (None for a gap the tracker reported).
        channels: the channel names, ("px", "py", "pz") or with ("rx", "ry", "rz").
        joints: the joints (rad, m for a prismatic joint) the measured error was computed
            with, or None.
        device_stamp: the tracker's own time of the sample (s, its clock), or None when it
            gives none.
        held: no measured error this step (`measured` is None; the reason is the only
            flag): the estimate held.
    """

    __slots__ = (
        "_estimate",
        "_measured",
        "channels",
        "device_stamp",
        "encoder_stamp",
        "flags",
        "held",
        "joints",
        "stamp",
    )

    def __init__(
        self,
        stamp: float,  # the tracker sample's stream time (or the tick's, for "latest")
        measured: np.ndarray | list[float] | None,
        estimate: np.ndarray | list[float],
        flags: tuple[str, ...],
        encoder_stamp: float | None,  # stream time at which the joints were evaluated
        channels: tuple[str, ...],
        joints: np.ndarray | None = None,  # the joints the measured error was computed with
        device_stamp: float | None = None,  # the tracker's own stamp, from on_tracker()
    ) -> None:
        self.stamp = stamp
        self._measured = measured
        # no measured error this step (the reason is the only flag); the estimate held. An
        # attribute, not a property: the service reads it for every estimate it publishes
        self.held = measured is None
        self._estimate = estimate
        self.flags = flags
        self.encoder_stamp = encoder_stamp
        self.channels = channels
        self.joints = joints
        self.device_stamp = device_stamp

    @property
    def measured(self) -> np.ndarray | None:
        """The measured error per channel (m, rad), an array; None when held."""
        m = self._measured
        if m is None or isinstance(m, np.ndarray):
            return m
        self._measured = m = np.array(m, dtype=float)
        return m

    @property
    def estimate(self) -> np.ndarray:
        """The observer's estimate per channel (m, rad), an array."""
        e = self._estimate
        if isinstance(e, np.ndarray):
            return e
        self._estimate = e = np.array(e, dtype=float)
        return e

    def measured_values(self) -> list[float] | None:
        """`measured` as plain floats (m, rad), without making an array; None when held."""
        m = self._measured
        return m.tolist() if isinstance(m, np.ndarray) else m

    def estimate_values(self) -> list[float]:
        """`estimate` as plain floats (m, rad), without making an array."""
        e = self._estimate
        return e.tolist() if isinstance(e, np.ndarray) else e

    def __repr__(self) -> str:
        return (
            f"Estimate(stamp={self.stamp!r}, measured={self.measured_values()!r}, "
            f"estimate={self.estimate_values()!r}, flags={self.flags!r})"
        )


@dataclass(slots=True)
class _TrackerSample:
    stamp: float
    # [x, y, z, qx, qy, qz, qw] (Pinocchio's order, unit quaternion) or [x, y, z] for a
    # single reflector; None: a gap reported by the tracker
    sensor: list[float] | None
    device_stamp: float | None = None


class Estimator:
    """Feeds samples through alignment, the measured error and the observer.

    Samples go in one at a time, stamped in stream time (s: the host clock the adapters stamp
    with, or a recording's time axis); each call returns the estimates it completed, none,
    one or several (samples that waited for encoder data). A bad sample is refused, counted
    in `counters` with a message in `messages`, and never raises: a stream keeps going.

    Args:
        cell: robot, measurement frame and tracker registration (`cell_from_config`).
        settings: gains (1/s), delay (s), alignment and the buffer and gap limits (s)
            (`estimator_settings`).

    Raises:
        ValueError: `settings.alignment` is neither "interpolate" nor "latest" (a config
            file cannot give one: `load_config` refuses it first).
    """

    def __init__(self, cell: Cell, settings: EstimatorSettings) -> None:
        if settings.alignment not in ("interpolate", "latest"):
            raise ValueError(f"unknown alignment {settings.alignment!r}")
        self.cell = cell
        self.settings = settings
        self._data = cell.robot.create_data()
        self._model = cell.robot.model
        self._folded = fold_frames(cell)
        self._folded_data = self._folded.model.createData() if self._folded else None
        # where the folded model alone gives the measured error (no joint corrections)
        self._folded_only = self._folded if cell.corrections is None else None
        self._nq = cell.robot.nq
        self._max_gap_s = settings.max_gap_s  # read once per sample: kept at hand
        self._buffer_s = settings.buffer_s
        self._interpolating = settings.alignment == "interpolate"
        self.encoder = EncoderBuffer(
            self._nq, encoder_capacity(settings), functools.partial(pin.interpolate, self._model)
        )
        self._rejects = RejectLog(keep=MAX_MESSAGES)
        self.counters = self._rejects.counters
        self.messages = self._rejects.messages
        self.observer: KinematicErrorObserver | None = None
        self.channels: tuple[str, ...] | None = None
        # the delay in use: offset (s) and drift (s/s) of the tracker behind the encoder; an
        # attribute, not a property, as the service reads it for every estimate it publishes
        # (set it with `set_delay` / `set_delay_target`)
        self.delay: DelayModel = settings.delay
        self._delay_target: float | None = None
        self._prev_q: np.ndarray | None = None
        self._direction = np.zeros(self._nq)  # each joint's direction of its last move
        # followed only where it matters: the identified model has backlash
        self._track_direction = cell.corrections is not None and bool(
            np.any(cell.corrections.backlash)
        )
        self._ranges = CalibratedRanges(cell.corrections)
        self._check_ranges = bool(self._ranges)
        self._recent_dt: deque[float] = deque(maxlen=64)
        self._step_cap: float | None = None
        self._dt_seen = 0
        self._last_tracker_t = -math.inf
        self._last_update_t: float | None = None
        self._pending: deque[_TrackerSample] = deque()
        # "latest" alignment state
        self._recent_tracker: deque[_TrackerSample] = deque(maxlen=4096)
        self._next_tick: float | None = None
        self.last: Estimate | None = None

    # ---- public -------------------------------------------------------------------------

    def set_delay(self, delay: DelayModel) -> None:
        """Use `delay` from the next sample on, as a step (a pending target is dropped).

        Args:
            delay: offset (s) and drift (s/s): the tracker sample stamped t is compared with
                the joints at t - delay.at(t).
        """
        self.delay = delay
        self._delay_target = None

    def set_delay_target(self, offset_s: float) -> None:
        """Move the delay toward `offset_s` gradually, so estimates see no step.

        Args:
            offset_s: the delay to reach (s); approached at DELAY_SLEW (s per s of stream
                time) as tracker samples come.
        """
        self._delay_target = offset_s

    def _slew_delay(self, t: float) -> None:
        if self._delay_target is None or not math.isfinite(self._last_tracker_t):
            return
        dt = min(max(t - self._last_tracker_t, 0.0), 1.0)
        gap = self._delay_target - self.delay.offset_s
        step = max(-DELAY_SLEW * dt, min(DELAY_SLEW * dt, gap))
        # built directly: `dataclasses.replace` introspects the fields at every call, and this
        # runs per tracker sample for the seconds a slew lasts (docs/performance.md)
        delay = self.delay
        self.delay = DelayModel(delay.offset_s + step, delay.drift, delay.t_ref)
        if step == gap:
            self._delay_target = None

    def set_gains(self, gains: Sequence[float]) -> None:
        """New observer gains from the next step on; the estimate so far is kept.

        Args:
            gains: per channel in the order px, py, pz, rx, ry, rz (1/s); a position-only
                stream uses the first three.

        Raises:
            ValueError: once the stream's channels are known, fewer gains than channels, or
                a gain that is not finite and > 0.
        """
        self.settings = EstimatorSettings(**{**self.settings.__dict__, "gains": tuple(gains)})
        if self.observer is not None:
            self.observer.set_gain(self._gains_for(len(self.observer.gain)))

    def on_encoder(self, t: float, q: Sequence[float] | np.ndarray) -> list[Estimate]:
        """An encoder sample.

        Args:
            t: its stream time (s), after the previous encoder sample's.
            q: the joint positions, one per joint of the robot (rad; m for a prismatic joint).

        Returns:
            The estimates it completed: tracker samples that waited for the encoder stream to
            cover their time (and, with "latest" alignment, the ticks now due). Empty when
            none did or the sample was refused (counted in `counters`).
        """
        if isinstance(q, np.ndarray):
            values = q.tolist() if q.shape == (self._nq,) else []
        else:
            values = q if isinstance(q, list) else list(q) if isinstance(q, Sequence) else []
        if len(values) != self._nq:
            return self._reject(
                "encoder_wrong_length",
                f"encoder sample at t={t!r}: {np.size(q)} joints, expected {self._nq}",
            )
        newest = self.encoder.newest_t
        try:  # a good sample passes in one test (a finite sum proves finite joints) ...
            good = newest < t < math.inf and math.isfinite(sum(values))
        except TypeError:
            good = False
        if not good:  # ... and `encoder_reject` judges the rest
            refused = encoder_reject(t, values, newest)
            if refused is not None:
                return self._reject(*refused)
        q_arr = np.array(values, dtype=float)  # our own copy: the buffer keeps it
        if self._track_direction:
            if self._prev_q is not None:
                direction_update(self._direction, self._prev_q, q_arr, t - newest)
            self._prev_q = q_arr
        self.encoder.push(t, q_arr)
        self.counters["encoder_samples"] += 1
        if self._pending or not self._interpolating:
            return self._advance()
        return []

    # complexity (C901, PLR0912): the hot path keeps its checks and its steady state inline,
    # since a Python call per check is a real share of a sample's cost (docs/performance.md
    # times the pieces)
    def on_tracker(  # noqa: C901, PLR0912
        self,
        t: float,
        p: Sequence[float] | np.ndarray | None,
        quat: Sequence[float] | np.ndarray | None = None,
        ok: bool = True,
        device_stamp: float | None = None,
    ) -> list[Estimate]:
        """A tracker sample.

        Args:
            t: its stream time (s), after the previous tracker sample's.
            p: the probe's position in the tracker frame (m); None for a gap.
            quat: its orientation as a unit quaternion (qw, qx, qy, qz), or None for a
                single reflector (position only: three channels).
            ok: False for a gap the tracker reported (a beam break): the step is held.
            device_stamp: the tracker's own time of the sample (s, its clock), when it gives
                one; carried to the estimate it makes.

        Returns:
            The estimates it completed: usually this sample's, at once, when the encoder
            stream already covers t minus the delay; none while it waits for encoder data
            (or when refused, counted in `counters`).
        """
        last = self._last_tracker_t
        if not last < t < math.inf:  # one comparison for a good stamp
            return self._reject(*tracker_stamp_problem(t, last))
        if self._delay_target is not None:
            self._slew_delay(t)
        if not ok or p is None:
            self._last_tracker_t = t
            self.counters["tracker_gaps"] += 1
            return self._enqueue(_TrackerSample(t, None, device_stamp))
        sensor = sensor_values(p, quat)
        if isinstance(sensor, tuple):
            return self._reject(*tracker_value_problem(t, sensor))
        channels = POSITION_CHANNELS if len(sensor) == 3 else POSE_CHANNELS
        if channels is not self.channels:  # a good sample: the same tuple, one comparison
            if self.channels is None:
                self.channels = channels
                self.observer = KinematicErrorObserver(self._gains_for(len(channels)))
                self.counters["channels"] = len(channels)
            elif channels != self.channels:
                return self._reject(
                    "tracker_channel_mismatch",
                    f"tracker sample at t={t!r}: "
                    f"{len(channels)} channels on a {len(self.channels)}-channel stream",
                )
        if last > -math.inf:
            self._recent_dt.append(t - last)
            self._dt_seen += 1
        self._last_tracker_t = t
        self.counters["tracker_samples"] += 1
        if self._interpolating and not self._pending:
            delay = self.delay  # `DelayModel.encoder_time`, its arithmetic inline
            target = t - (delay.offset_s + delay.drift * (t - delay.t_ref))
            encoder = self.encoder
            if encoder.newest_t >= target:  # the steady state: nothing waits
                # `_resolve_at` spelled out: one Python frame fewer per sample
                q = encoder.interpolate(target, self._max_gap_s)
                if isinstance(q, np.ndarray) and not target < encoder.newest_t - self._buffer_s:
                    folded = self._folded_only
                    if folded is not None:
                        measured = measured_error_folded(folded, self._folded_data, q, sensor)
                    else:
                        measured = self._measure(q, sensor)
                    return [self._update(t, measured, target, q, device_stamp)]
                reason = held_reason(q, target, encoder.newest_t, self._buffer_s)
                assert reason is not None
                return [self._held(t, reason, target, device_stamp)]
        return self._enqueue(_TrackerSample(t, sensor, device_stamp))

    @property
    def has_pending(self) -> bool:
        """Tracker samples wait for encoder data (or "latest" ticks wait to be run): `flush`
        would return estimates."""
        if self.settings.alignment == "interpolate":
            return bool(self._pending)
        return (
            self._next_tick is not None
            and bool(self._recent_tracker)
            and self._next_tick <= self._recent_tracker[-1].stamp
        )

    def flush(self) -> list[Estimate]:
        """End of input: resolve what still waits (their encoder data will never come).

        Returns:
            The remaining estimates in stamp order, held where no encoder data covers them.
        """
        out: list[Estimate] = []
        if self.settings.alignment == "interpolate":
            while self._pending:
                out.append(self._resolve(self._pending.popleft()))
        else:
            out.extend(self._run_ticks(final=True))
        return out

    # ---- internals ----------------------------------------------------------------------

    def _gains_for(self, n: int) -> np.ndarray:
        return np.asarray(self.settings.gains[:n], dtype=float)

    def _max_step(self) -> float:
        """The longest dt one update may use (`rules.step_cap`), cached as `rules.cap_is_due`
        says."""
        if len(self._recent_dt) < CAP_MIN_INTERVALS:
            return self.settings.max_dt_s
        if cap_is_due(self._dt_seen, self._step_cap):
            self._step_cap = step_cap(self.settings, self._recent_dt)
        assert self._step_cap is not None
        return self._step_cap

    def _reject(self, counter: str, message: str) -> list[Estimate]:
        self._rejects.reject(counter, message)
        return []

    def _enqueue(self, sample: _TrackerSample) -> list[Estimate]:
        if self.settings.alignment == "latest":
            self._recent_tracker.append(sample)
            if self._next_tick is None:
                self._next_tick = sample.stamp
            return self._run_ticks(final=False)
        if not self._pending and (
            sample.sensor is None or self.encoder.newest_t >= self.delay.encoder_time(sample.stamp)
        ):
            return [self._resolve(sample)]  # the steady state: nothing waits, no queueing
        if len(self._pending) >= MAX_PENDING:
            dropped = self._pending.popleft()
            self.counters["pending_overflow"] += 1
            self.messages.append(
                f"tracker sample at t={dropped.stamp!r} dropped: no encoder data came"
            )
        self._pending.append(sample)
        return self._advance()

    def _advance(self) -> list[Estimate]:
        if self.settings.alignment == "latest":
            return self._run_ticks(final=False)
        out: list[Estimate] = []
        while self._pending:
            head = self._pending[0]
            if head.sensor is not None:
                target = self.delay.encoder_time(head.stamp)
                waited = self._last_tracker_t - head.stamp
                if waits_for_encoder(
                    self.encoder.newest_t, target, waited, self.settings.stale_after_s
                ):
                    break  # wait for the encoder stream to cover it
            self._pending.popleft()
            out.append(self._resolve(head))
        return out

    def _resolve(self, sample: _TrackerSample) -> Estimate:
        if sample.sensor is None:
            return self._held(sample.stamp, TRACKER_GAP, None, sample.device_stamp)
        target = self.delay.encoder_time(sample.stamp)
        return self._resolve_at(sample.stamp, target, sample.sensor, sample.device_stamp)

    def _resolve_at(
        self, t: float, target: float, sensor: list[float], device_stamp: float | None
    ) -> Estimate:
        encoder = self.encoder
        q = encoder.interpolate(target, self._max_gap_s)
        # `held_reason`'s two tests inline; it names the reason when one holds
        if not isinstance(q, np.ndarray) or target < encoder.newest_t - self._buffer_s:
            reason = held_reason(q, target, encoder.newest_t, self._buffer_s)
            assert reason is not None
            return self._held(t, reason, target, device_stamp)
        if self._folded_only is not None:
            measured = measured_error_folded(self._folded_only, self._folded_data, q, sensor)
        else:
            measured = self._measure(q, sensor)
        return self._update(t, measured, target, q, device_stamp)

    def _measure(self, q: np.ndarray, sensor: list[float]) -> list[float]:
        if self._folded is None or self._folded_data is None:
            p = sensor[:3]
            quat = None if len(sensor) == 3 else [sensor[6], sensor[3], sensor[4], sensor[5]]
            error = measured_error(self.cell, self._data, q, p, quat, self._direction)
            values: list[float] = error.tolist()
            return values
        if self.cell.corrections is not None:
            q = corrected_joints(self.cell, q, self._direction)
        return measured_error_folded(self._folded, self._folded_data, q, sensor)

    def _update(
        self,
        t: float,
        measured: list[float],
        encoder_stamp: float,
        joints: np.ndarray,
        device_stamp: float | None = None,
    ) -> Estimate:
        observer = self.observer
        assert observer is not None
        assert self.channels is not None
        last = self._last_update_t
        if last is None:
            if self.settings.start == "first":
                observer.reset(measured)
            else:
                observer.reset()
                # the reference start: zero state, first step as if one sample period passed
                observer.update(measured, 1.0 / self.settings.sample_rate_hz)
        else:
            cap = self._step_cap
            if cap is None or self._dt_seen % CAP_REFRESH == 0:  # `cap_is_due`, inline
                cap = self._max_step()
            dt = t - last
            if not observer.update(measured, cap if dt > cap else dt):
                self.counters[OBSERVER_REJECTED] += 1
                return self._held(t, OBSERVER_REJECTED, encoder_stamp, device_stamp)
        self._last_update_t = t
        self.counters["estimates"] += 1
        flags: tuple[str, ...] = ()
        if self._check_ranges and self._ranges.outside(joints):
            flags = (OUTSIDE_CALIBRATED_RANGE,)
            self.counters[OUTSIDE_CALIBRATED_RANGE] += 1
        est = Estimate(
            t,
            measured,
            observer.values,
            flags,
            encoder_stamp,
            self.channels,
            joints,
            device_stamp,
        )
        self.last = est
        return est

    def _held(
        self,
        t: float,
        reason: str,
        encoder_stamp: float | None,
        device_stamp: float | None = None,
    ) -> Estimate:
        self.counters[f"held_{reason}"] += 1
        channels = self.channels or ()
        state = self.observer.values if self.observer is not None else [0.0] * len(channels)
        est = Estimate(t, None, state, (reason,), encoder_stamp, channels, None, device_stamp)
        self.last = est
        return est

    # "latest": the reference method, sampled at a fixed rate in stream time
    def _run_ticks(self, final: bool) -> list[Estimate]:
        out: list[Estimate] = []
        if self._next_tick is None or not self._recent_tracker:
            return out
        period = 1.0 / self.settings.sample_rate_hz
        newest_tracker = self._recent_tracker[-1].stamp
        while True:
            tau = self._next_tick
            if tau > newest_tracker:
                break
            target = self.delay.encoder_time(tau)
            if not final and waits_for_encoder(
                self.encoder.newest_t, target, newest_tracker - tau, self.settings.stale_after_s
            ):
                break
            out.append(self._tick(tau, target))
            self._next_tick = tau + period
        return out

    def _tick(self, tau: float, target: float) -> Estimate:
        trk = None
        for s in reversed(self._recent_tracker):
            if s.stamp <= tau:
                trk = s
                break
        enc = self.encoder.latest_at_or_before(target)
        stale = self.settings.stale_after_s
        if trk is None or trk.sensor is None:
            return self._held(tau, TRACKER_GAP, target)
        if enc is None or target - enc[0] > stale:
            return self._held(tau, "encoder_stale", target)
        if tau - trk.stamp > stale:
            return self._held(tau, "tracker_stale", target)
        est = self._update(tau, self._measure(enc[1], trk.sensor), enc[0], enc[1])
        if trk.device_stamp is not None and not est.held:
            est.device_stamp = trk.device_stamp
        return est


def run_offline(
    estimator: Estimator,
    encoder_t: np.ndarray,
    encoder_q: np.ndarray,
    tracker_t: np.ndarray,
    tracker_p: np.ndarray,
    tracker_quat: np.ndarray | None,
) -> list[Estimate]:
    """Feed two recorded streams in time-stamp order (encoder first on ties), then flush.

    This is the order a live service sees when each sample arrives at its stamp, so replaying
    the files through the service gives the same estimates.
    """
    out: list[Estimate] = []
    i = j = 0
    n_enc, n_trk = encoder_t.size, tracker_t.size
    while i < n_enc or j < n_trk:
        take_encoder = j >= n_trk or (i < n_enc and not encoder_t[i] > tracker_t[j])
        if take_encoder:
            out.extend(estimator.on_encoder(float(encoder_t[i]), encoder_q[i]))
            i += 1
        else:
            quat = None if tracker_quat is None else tracker_quat[j]
            out.extend(estimator.on_tracker(float(tracker_t[j]), tracker_p[j], quat))
            j += 1
    out.extend(estimator.flush())
    return out
