"""Time alignment of the encoder and tracker streams (DESIGN.md section 3). No I/O.

The tracker's sample stamped t saw the tool at encoder time t - delay(t), with
delay(t) = offset + drift * (t - t_ref). `interpolate` evaluates the joints there from a
bounded buffer of encoder samples; `latest` (the reference method) is in `pipeline`.
"""

from __future__ import annotations

import enum
import math
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


class Coverage(enum.Enum):
    OK = "ok"
    NOT_YET = "not_yet"  # the encoder stream has not reached that time yet
    TOO_OLD = "too_old"  # older than the buffer holds
    GAP = "gap"  # the bracketing samples are too far apart to interpolate
    EMPTY = "empty"


class EncoderBuffer:
    """Bounded ring of (t, q) with strictly increasing t; linear interpolation by time.

    Each sample is written twice (at i and i + capacity) so the newest `count` samples are
    always one contiguous slice, which keeps lookups a single searchsorted.
    """

    def __init__(self, nq: int, capacity: int) -> None:
        if capacity < 2:
            raise ValueError("capacity must be >= 2")
        self.nq = nq
        self.capacity = capacity
        self._t = np.zeros(2 * capacity)
        self._q = np.zeros((2 * capacity, nq))
        self._next = 0  # write position in [0, capacity)
        self._count = 0

    def __len__(self) -> int:
        return self._count

    @property
    def newest_t(self) -> float:
        return float(self._t[self._next + self.capacity - 1]) if self._count else -math.inf

    @property
    def oldest_t(self) -> float:
        return float(self._window()[0][0]) if self._count else math.inf

    def _window(self) -> tuple[np.ndarray, np.ndarray]:
        end = self._next + self.capacity
        start = end - self._count
        return self._t[start:end], self._q[start:end]

    def push(self, t: float, q: np.ndarray) -> None:
        """Append; the caller has checked that t is finite and newer than newest_t."""
        i = self._next
        self._t[i] = self._t[i + self.capacity] = t
        self._q[i] = self._q[i + self.capacity] = q
        self._next = (i + 1) % self.capacity
        self._count = min(self._count + 1, self.capacity)

    def latest_at_or_before(self, t: float) -> tuple[float, np.ndarray] | None:
        ts, qs = self._window()
        k = int(np.searchsorted(ts, t, side="right")) - 1
        if k < 0:
            return None
        return float(ts[k]), qs[k].copy()

    def interpolate(self, t: float, max_gap: float) -> tuple[Coverage, np.ndarray | None]:
        if self._count == 0:
            return Coverage.EMPTY, None
        # the usual case at tracker rates: t within one of the newest few intervals (the
        # delay is a few encoder periods); a short walk back costs less than a search
        last = self._next + self.capacity - 1
        t1 = float(self._t[last])
        for k in range(last, last - min(self._count - 1, 8), -1):
            t0 = float(self._t[k - 1])
            if t0 < t < t1:
                if t1 - t0 > max_gap:
                    return Coverage.GAP, None
                q0 = self._q[k - 1]
                return Coverage.OK, q0 + ((t - t0) / (t1 - t0)) * (self._q[k] - q0)
            if t >= t1:
                break
            t1 = t0
        ts, qs = self._window()
        if t > ts[-1]:
            return Coverage.NOT_YET, None
        if t < ts[0]:
            return Coverage.TOO_OLD, None
        k = int(np.searchsorted(ts, t, side="left"))
        if ts[k] == t:
            return Coverage.OK, qs[k].copy()
        t0, t1 = ts[k - 1], ts[k]
        if t1 - t0 > max_gap:
            return Coverage.GAP, None
        w = (t - t0) / (t1 - t0)
        return Coverage.OK, qs[k - 1] + w * (qs[k] - qs[k - 1])
