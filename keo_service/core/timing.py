"""Time alignment of the encoder and tracker streams (docs/design.md §3). No I/O.

The tracker's sample stamped t saw the tool at encoder time t - delay(t), with
delay(t) = offset + drift * (t - t_ref). `interpolate` evaluates the joints there from a
bounded buffer of encoder samples; `latest` (the reference method) is in `pipeline`.
"""

from __future__ import annotations

import bisect
import enum
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class DelayModel:
    """Sensor-to-encoder delay: offset_s + drift * (t - t_ref); drift is dimensionless (s/s)."""

    offset_s: float = 0.0
    drift: float = 0.0
    t_ref: float = 0.0

    def at(self, t: float) -> float:
        return self.offset_s + self.drift * (t - self.t_ref)

    def encoder_time(self, t_sensor: float) -> float:
        return t_sensor - self.at(t_sensor)

    def encoder_times(self, t_sensor: np.ndarray) -> np.ndarray:
        """`encoder_time` over an array of tracker stamps (the same arithmetic)."""
        t = np.asarray(t_sensor, dtype=float)
        out: np.ndarray = t - (self.offset_s + self.drift * (t - self.t_ref))
        return out


class Coverage(enum.Enum):
    OK = "ok"
    NOT_YET = "not_yet"  # the encoder stream has not reached that time yet
    TOO_OLD = "too_old"  # older than the buffer holds
    GAP = "gap"  # the bracketing samples are too far apart to interpolate
    EMPTY = "empty"


class EncoderBuffer:
    """Bounded ring of (t, q) with strictly increasing t; linear interpolation by time.

    Times are a list of floats and joints a list of row arrays: a lookup bisects the list
    and hands two rows to `lerp`, with no numpy call but the interpolation itself. Each
    sample is written twice (at i and i + capacity) so the newest `count` samples are always
    one contiguous run, which keeps lookups a single bisection.
    """

    def __init__(
        self,
        nq: int,
        capacity: int,
        lerp: Callable[[np.ndarray, np.ndarray, float], np.ndarray] | None = None,
    ) -> None:
        """`lerp(q0, q1, w)` = q0 + w (q1 - q0); the estimator passes Pinocchio's
        `interpolate` (one call, the same arithmetic, for the revolute joints keo loads)."""
        if capacity < 2:
            raise ValueError("capacity must be >= 2")
        self.nq = nq
        self.capacity = capacity
        self._times = [0.0] * (2 * capacity)
        self._rows: list[np.ndarray] = [np.zeros(nq)] * (2 * capacity)
        self._lerp = lerp or _lerp
        self._next = 0  # write position in [0, capacity)
        self._count = 0
        self.newest_t = -math.inf

    def __len__(self) -> int:
        return self._count

    @property
    def oldest_t(self) -> float:
        return self._times[self._next + self.capacity - self._count] if self._count else math.inf

    def push(self, t: float, q: np.ndarray) -> None:
        """Append (q is kept, not copied); the caller has checked that t is finite and newer
        than newest_t and owns no other reference to q."""
        i = self._next
        t = float(t)
        self._times[i] = self._times[i + self.capacity] = t
        self._rows[i] = self._rows[i + self.capacity] = q
        self._next = (i + 1) % self.capacity
        self._count = min(self._count + 1, self.capacity)
        self.newest_t = t

    def latest_at_or_before(self, t: float) -> tuple[float, np.ndarray] | None:
        end = self._next + self.capacity
        start = end - self._count
        k = bisect.bisect_right(self._times, t, start, end) - 1
        if k < start:
            return None
        return self._times[k], self._rows[k].copy()

    def interpolate(self, t: float, max_gap: float) -> np.ndarray | Coverage:
        """The joints at time t (a new array), or why there are none."""
        if self._count == 0:
            return Coverage.EMPTY
        end = self._next + self.capacity
        start = end - self._count
        times = self._times
        if t > times[end - 1]:
            return Coverage.NOT_YET
        if t < times[start]:
            return Coverage.TOO_OLD
        k = bisect.bisect_left(times, t, start, end)
        t1 = times[k]
        if t1 == t:
            return self._rows[k].copy()
        t0 = times[k - 1]
        if t1 - t0 > max_gap:
            return Coverage.GAP
        return self._lerp(self._rows[k - 1], self._rows[k], (t - t0) / (t1 - t0))


def _lerp(q0: np.ndarray, q1: np.ndarray, w: float) -> np.ndarray:
    return np.asarray(q0 + w * (q1 - q0))
