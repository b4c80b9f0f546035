"""The estimator's rules, written once: what it refuses and why, when a step is held, how long
one step may be, each joint's direction of motion, the calibrated ranges and the flags.

Two paths apply them. The streaming estimator (`estimator`) asks one sample at a time; the
batch path (`batch`, `keo estimate`) asks for whole recordings at once. Each rule therefore
comes as a pair, side by side below: a scalar form and an array form that must give the
same verdicts (tests/test_rules.py checks each pair against the other; tests/test_batch.py
checks the two paths end to end). Changing a rule means changing both forms here. No I/O.

The words they use (counters, flags, messages) are what a service's status and estimates
carry to users; the time model behind the waiting and holding is docs/design.md §3.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from keo_service.core.model_corrections import ModelCorrections
from keo_service.core.observer import finite_numbers
from keo_service.core.settings import EstimatorSettings, encoder_capacity
from keo_service.core.timing import Coverage

__all__ = [
    "CAP_MIN_INTERVALS",
    "CAP_REFRESH",
    "DIRECTION_DEADBAND",
    "HELD_REASONS",
    "MAX_MESSAGES",
    "MAX_PENDING",
    "NON_FINITE_VALUE",
    "OBSERVER_REJECTED",
    "OUTSIDE_CALIBRATED_RANGE",
    "RECENT_INTERVALS",
    "TRACKER_GAP",
    "UNIT_QUATERNION_TOLERANCE",
    "CalibratedRanges",
    "EncoderVerdicts",
    "TrackerVerdicts",
    "cap_is_due",
    "direction_update",
    "directions",
    "encoder_non_finite",
    "encoder_reject",
    "encoder_stamp_problem",
    "encoder_verdicts",
    "first_beyond",
    "held_reason",
    "held_reasons",
    "not_unit_quaternion",
    "sensor_values",
    "step_cap",
    "step_caps",
    "tracker_stamp_problem",
    "tracker_value_problem",
    "tracker_verdicts",
    "waits_for_encoder",
]

UNIT_QUATERNION_TOLERANCE = 1e-4
DIRECTION_DEADBAND = 1e-4  # rad/s: a joint slower than this keeps its last direction
MAX_PENDING = 2048  # tracker samples that may wait for encoder data at once
MAX_MESSAGES = 32  # reject messages kept (the newest); every reject is counted
RECENT_INTERVALS = 64  # tracker intervals whose median sets the step cap
CAP_REFRESH = 16  # ... refreshed every this many intervals
CAP_MIN_INTERVALS = 8  # ... once this many were seen (max_dt_s before)

# flags of an estimate; a held one carries its reason as its only flag
OUTSIDE_CALIBRATED_RANGE = "outside_calibrated_range"
TRACKER_GAP = "tracker_gap"
OBSERVER_REJECTED = "observer_rejected"
# interpolation's verdicts in the estimator's words; code 0 (array form) is "not held"
HELD_REASONS = ("", "encoder_stale", "encoder_too_old", "encoder_gap")
HELD_BECAUSE = {
    Coverage.NOT_YET: "encoder_stale",
    Coverage.EMPTY: "encoder_stale",
    Coverage.TOO_OLD: "encoder_too_old",
    Coverage.GAP: "encoder_gap",
}

WRONG_LENGTH = ("tracker_wrong_length", "expected 3 position and 4 quaternion values")
NON_FINITE_VALUE = ("tracker_non_finite", "non-finite value")


# ---- rejects: (counter, message) -------------------------------------------------------------


def encoder_non_finite(t: float) -> tuple[str, str]:
    return "encoder_non_finite", f"encoder sample at t={t!r}: non-finite time or joint value"


def encoder_stamp_problem(t: float, newest: float) -> tuple[str, str]:
    """A finite encoder stamp that is not newer than the newest accepted one."""
    if t == newest:
        return "encoder_duplicate", f"encoder sample at t={t!r}: duplicate stamp"
    return "encoder_out_of_order", f"encoder sample at t={t!r}: older than the newest ({newest!r})"


def tracker_stamp_problem(t: float, last: float) -> tuple[str, str]:
    """Why a tracker stamp is refused: not finite, or not newer than the last accepted one."""
    if not math.isfinite(t):
        return "tracker_non_finite", f"tracker sample: non-finite time {t!r}"
    if t == last:
        return "tracker_duplicate", f"tracker sample at t={t!r}: duplicate stamp"
    return (
        "tracker_out_of_order",
        f"tracker sample at t={t!r}: older than the previous one ({last!r})",
    )


def tracker_value_problem(t: float, problem: tuple[str, str]) -> tuple[str, str]:
    """A tracker sample whose stamp is fine but whose values are not (`sensor_values`)."""
    counter, what = problem
    return counter, f"tracker sample at t={t!r}: {what}"


def not_unit_quaternion(norm: float) -> tuple[str, str]:
    return "tracker_not_unit_quaternion", f"quaternion norm {norm:.6g}, expected 1"


# scalar: one encoder sample


def encoder_reject(t: float, values: list[Any], newest: float) -> tuple[str, str] | None:
    """Why an encoder sample of the right length is refused (None: accepted). `newest` is the
    newest accepted stamp (-inf before the first)."""
    if not (math.isfinite(t) and finite_numbers(values)):
        return encoder_non_finite(t)
    if not t > newest:
        return encoder_stamp_problem(t, newest)
    return None


# array: a whole encoder stream in arrival order


@dataclass(frozen=True)
class EncoderVerdicts:
    finite: np.ndarray  # stamp and joints finite
    newest: np.ndarray  # the newest accepted stamp before each sample (-inf: none)
    ok: np.ndarray  # accepted
    duplicate: np.ndarray
    out_of_order: np.ndarray


def encoder_verdicts(t: np.ndarray, q: np.ndarray) -> EncoderVerdicts:
    """`encoder_reject` for every sample of a stream (t (n,), q (n, nq)) in one pass."""
    finite = np.isfinite(t) & np.isfinite(q).all(axis=1)
    newest = _prior_max(t, finite)
    return EncoderVerdicts(
        finite=finite,
        newest=newest,
        ok=finite & (t > newest),
        duplicate=finite & (t == newest),
        out_of_order=finite & (t < newest),
    )


# scalar: one tracker sample (the stamp first, then the values)


def sensor_values(
    p: Sequence[float] | np.ndarray, quat: Sequence[float] | np.ndarray | None
) -> list[float] | tuple[str, str]:
    """The tracker's pose as [x, y, z, qx, qy, qz, qw] (unit quaternion) or [x, y, z], or
    (counter, what is wrong) for a bad one. Checked on plain floats: for a good sample this
    costs less than one numpy call."""
    try:
        x, y, z = p.tolist() if type(p) is np.ndarray else p
        if quat is None:
            qw, qx, qy, qz = 1.0, 0.0, 0.0, 0.0
        else:
            qw, qx, qy, qz = quat.tolist() if type(quat) is np.ndarray else quat
    except (TypeError, ValueError):  # not 3 (and 4) values
        return WRONG_LENGTH
    try:
        finite = math.isfinite(x + y + z + qw + qx + qy + qz)
    except TypeError:
        finite = False
    if not finite:
        values = (x, y, z, qw, qx, qy, qz)
        if not all(_finite(v) for v in values):
            return NON_FINITE_VALUE
        x, y, z, qw, qx, qy, qz = (float(v) for v in values)
    if quat is None:
        return [x, y, z]
    norm = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    if abs(norm - 1.0) > UNIT_QUATERNION_TOLERANCE:
        return not_unit_quaternion(norm)
    return [x, y, z, qx / norm, qy / norm, qz / norm, qw / norm]


def _finite(value: Any) -> bool:
    """A finite number (a huge but finite sum lands here, as does a non-number)."""
    try:
        return math.isfinite(float(value))
    except (TypeError, ValueError):
        return False


# array: a whole tracker stream in arrival order


@dataclass(frozen=True)
class TrackerVerdicts:
    last: np.ndarray  # the last accepted stamp before each sample (-inf: none)
    timely: np.ndarray  # a finite stamp newer than `last`
    non_finite: np.ndarray  # counted as tracker_non_finite (its stamp or a value)
    duplicate: np.ndarray
    out_of_order: np.ndarray
    non_finite_value: np.ndarray  # timely, but a value is not finite
    not_unit: np.ndarray  # timely and finite, but the quaternion is not a unit one
    norm: np.ndarray  # the quaternion's norm (1 without orientation)
    accepted: np.ndarray


def tracker_verdicts(t: np.ndarray, p: np.ndarray, quat: np.ndarray | None) -> TrackerVerdicts:
    """`tracker_stamp_problem` and `sensor_values` for every sample of a stream (t (n,),
    p (n, 3), quat (n, 4) scalar first or None) in one pass."""
    t_finite = np.isfinite(t)
    values_finite = np.isfinite(p).all(axis=1)
    norm = np.ones(t.size)
    if quat is not None:
        values_finite &= np.isfinite(quat).all(axis=1)
        with np.errstate(invalid="ignore"):
            norm = np.sqrt(np.einsum("ij,ij->i", quat, quat))
    unit = ~(np.abs(norm - 1.0) > UNIT_QUATERNION_TOLERANCE)
    last = _prior_max(t, t_finite & values_finite & unit)
    duplicate = t_finite & (t == last)
    out_of_order = t_finite & (t < last)
    timely = t_finite & ~duplicate & ~out_of_order
    non_finite_value = timely & ~values_finite
    return TrackerVerdicts(
        last=last,
        timely=timely,
        non_finite=~t_finite | non_finite_value,
        duplicate=duplicate,
        out_of_order=out_of_order,
        non_finite_value=non_finite_value,
        not_unit=timely & values_finite & ~unit,
        norm=norm,
        accepted=timely & values_finite & unit,
    )


def _prior_max(t: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """For each sample, the largest stamp among earlier samples for which `counts` is True
    (-inf when none)."""
    masked = np.where(counts, t, -np.inf)
    prior = np.empty_like(masked)
    if masked.size:
        prior[0] = -np.inf
        prior[1:] = np.maximum.accumulate(masked)[:-1]
    return prior


# ---- waiting: a tracker sample waits for the encoder stream, up to stale_after_s -------------


def waits_for_encoder(newest_encoder: float, target: float, waited: float, stale: float) -> bool:
    """A tracker sample whose encoder time `target` the encoder stream has not reached waits,
    until `waited` (tracker time since it came) exceeds `stale` (then it is resolved)."""
    return newest_encoder < target and waited <= stale


def first_beyond(t_acc: np.ndarray, limit: float) -> np.ndarray:
    """For each accepted tracker sample a, the first later b with t_b - t_a > limit (so a
    waits no longer once b came: `waits_for_encoder`'s subtraction), or t_acc.size."""
    n = t_acc.size
    b = np.searchsorted(t_acc, t_acc + limit, side="right")
    np.maximum(b, np.arange(1, n + 1), out=b)
    # t_a + limit and t_b - t_a may round apart at the boundary: settle those few one by one
    unsettled = t_acc[b - 1] - t_acc > limit
    unsettled |= (b < n) & ~(t_acc[np.minimum(b, n - 1)] - t_acc > limit)
    for a in np.flatnonzero(unsettled).tolist():
        k = int(b[a])
        while k > a + 1 and t_acc[k - 1] - t_acc[a] > limit:
            k -= 1
        while k < n and not t_acc[k] - t_acc[a] > limit:
            k += 1
        b[a] = k
    return b


# ---- held: interpolation's verdict ---------------------------------------------------------


def held_reason(
    interpolated: np.ndarray | Coverage, target: float, newest: float, buffer_s: float
) -> str | None:
    """Why the step at encoder time `target` is held, given the encoder buffer's answer
    (`EncoderBuffer.interpolate`) and its newest stamp; None: it is not."""
    if not isinstance(interpolated, np.ndarray):
        return HELD_BECAUSE[interpolated]
    if target < newest - buffer_s:
        return "encoder_too_old"
    return None


def held_reasons(
    settings: EstimatorSettings,
    E: np.ndarray,
    have: np.ndarray,
    target: np.ndarray,
    bracket: tuple[np.ndarray, np.ndarray, np.ndarray],
) -> np.ndarray:
    """`held_reason` per tracker sample as an index into HELD_REASONS (0: not held), from the
    accepted encoder stamps E and how many of them were buffered when it was resolved
    (`have`); `bracket` is (t0, t1, on_sample): the encoder stamps around `target` and
    whether it falls on one."""
    t0, t1, on_sample = bracket
    capacity = encoder_capacity(settings)
    reason = np.zeros(target.size, dtype=np.int8)
    newest = np.where(have > 0, E[np.maximum(have - 1, 0)] if E.size else 0.0, -np.inf)
    oldest = np.where(have > 0, E[np.maximum(have - capacity, 0)] if E.size else 0.0, np.inf)
    reason[(have == 0) | (target > newest)] = 1
    reason[(reason == 0) & (target < oldest)] = 2
    reason[(reason == 0) & ~on_sample & (t1 - t0 > settings.max_gap_s)] = 3
    reason[(reason == 0) & (target < newest - settings.buffer_s)] = 2
    return reason


# ---- the step cap: after a gap, one sample is one sample's worth of measurement -------------


def cap_is_due(seen: int, cap: float | None) -> bool:
    """Whether the step cap is (re)computed after `seen` tracker intervals."""
    return cap is None or seen % CAP_REFRESH == 0


def step_cap(settings: EstimatorSettings, recent: Sequence[float]) -> float:
    """The longest dt one update may use, from the last RECENT_INTERVALS tracker intervals:
    max_dt_s until CAP_MIN_INTERVALS were seen, then 3 typical periods (their median), at
    most max_dt_s. "latest" alignment updates at a fixed rate: never below its period."""
    if len(recent) < CAP_MIN_INTERVALS:
        return settings.max_dt_s
    typical = statistics.median(recent)  # np.median's value, a tenth the cost
    if settings.alignment == "latest":
        typical = max(typical, 1.0 / settings.sample_rate_hz)
    return min(settings.max_dt_s, 3.0 * typical)


def step_caps(settings: EstimatorSettings, intervals: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """`step_cap` for updates that saw `seen` tracker intervals (of all `intervals`), as the
    streaming estimator caches it: computed at the first update with CAP_MIN_INTERVALS and
    whenever `cap_is_due`. "interpolate" alignment (the batch path's only one)."""
    caps = np.full(seen.size, settings.max_dt_s)
    valid = seen >= CAP_MIN_INTERVALS
    if not valid.any():
        return caps
    first = int(np.argmax(valid))
    recompute = valid & (seen % CAP_REFRESH == 0)
    recompute[first] = True
    where = np.flatnonzero(recompute)
    counts = seen[where]
    values = np.empty(where.size)
    full = counts >= RECENT_INTERVALS
    if full.any():
        starts = counts[full] - RECENT_INTERVALS
        every_window = sliding_window_view(intervals, RECENT_INTERVALS)
        if starts.size > 1 and (np.diff(starts) == CAP_REFRESH).all():  # the usual: a view
            windows = every_window[starts[0] :: CAP_REFRESH][: starts.size]
        else:
            windows = every_window[starts]
        medians = np.empty(windows.shape[0])
        for lo in range(0, windows.shape[0], MEDIAN_WINDOWS):  # sorted copies stay in cache
            rows = slice(lo, lo + MEDIAN_WINDOWS)
            medians[rows] = _sorted_median(np.sort(windows[rows]))
        values[full] = medians
    for k in np.flatnonzero(~full):
        values[k] = _sorted_median(np.sort(intervals[: counts[k]])[None, :])[0]
    values = np.minimum(settings.max_dt_s, 3.0 * values)
    last = np.maximum.accumulate(np.where(recompute, np.arange(seen.size), -1))
    rank = np.cumsum(recompute) - 1  # a recomputing update's index in `where`
    caps[valid] = values[rank[last[valid]]]
    return caps


MEDIAN_WINDOWS = 1024  # step-cap windows sorted at once


def _sorted_median(rows: np.ndarray) -> np.ndarray:
    """np.median of each sorted row: the middle value, or (a + b) / 2 of the two middle values
    as median computes it (for an odd count that is (a + a) / 2 = a, exactly). On rows this
    short a sort is much faster than median's partition (docs/performance.md)."""
    k = rows.shape[1]
    out: np.ndarray = (rows[:, (k - 1) // 2] + rows[:, k // 2]) / 2.0
    return out


# ---- direction of motion (backlash): each joint's direction of its last move ---------------


def direction_update(direction: np.ndarray, previous: np.ndarray, q: np.ndarray, dt: float) -> None:
    """After an accepted encoder sample q, `dt` after the previous one: each joint that moved
    faster than DIRECTION_DEADBAND takes the sign of its move (`direction` in place)."""
    step = q - previous
    moved = np.abs(step) > DIRECTION_DEADBAND * max(dt, 1e-6)
    direction[moved] = np.sign(step[moved])


def directions(t: np.ndarray, q: np.ndarray) -> np.ndarray:
    """`direction_update` over accepted encoder samples (t (n,), q (n, nq)): the directions
    after each one, zeros before any move."""
    out = np.zeros_like(q)
    if q.shape[0] < 2:
        return out
    step = np.diff(q, axis=0)
    dt = np.maximum(np.diff(t), 1e-6)
    moved = np.abs(step) > DIRECTION_DEADBAND * dt[:, None]
    rows = np.arange(1, q.shape[0])[:, None]
    last = np.maximum.accumulate(np.where(moved, rows, 0), axis=0)
    signs = np.zeros_like(q)
    signs[1:] = np.sign(step)
    out[1:] = np.take_along_axis(signs, last, axis=0)
    return out


# ---- calibrated ranges: joint-angle maps hold their edge value outside them ----------------


class CalibratedRanges:
    """The joints with a joint-angle map and the range each map was calibrated on: an estimate
    made outside is flagged OUTSIDE_CALIBRATED_RANGE (and counted), not extrapolated."""

    __slots__ = ("high", "joints", "low")

    def __init__(self, corrections: ModelCorrections | None) -> None:
        ranges = corrections.map_ranges() if corrections is not None else []
        spans = [(j, r) for j, r in enumerate(ranges) if r is not None]
        self.joints = [j for j, _r in spans]
        self.low = np.array([r[0] for _j, r in spans])
        self.high = np.array([r[1] for _j, r in spans])

    def __bool__(self) -> bool:
        return bool(self.joints)

    def outside(self, q: np.ndarray) -> bool:
        """One configuration (nq,)."""
        mapped = q[self.joints]
        return bool(np.any(mapped < self.low) or np.any(mapped > self.high))

    def outside_rows(self, q: np.ndarray) -> np.ndarray:
        """Each row of (n, nq) configurations."""
        mapped = q[:, self.joints]
        out: np.ndarray = np.any((mapped < self.low) | (mapped > self.high), axis=1)
        return out
