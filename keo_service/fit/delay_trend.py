"""A value that walks, seen through noisy measurements at irregular times: its level and its
rate of change. No I/O.

The delay between two mapped streams is such a value: each mapped stream's stamps carry its
clock mapping's error, which moves as the mapping follows its transport floor (the host
answering faster for tens of seconds) and as its drift converges, often steadily for tens
of seconds. A mean of recent fits, however weighted, lags such a walk by about half its span,
where a level and a rate follow it (docs/timing-delay.md has the figures).

A Kalman filter over x = [level, rate]: between measurements the rate random-walks
(`rate_walk`, (s/s)^2 per second) and relaxes towards zero with `rate_relax_s` (a walk of a
clock mapping's error does not go on for minutes; nor should a long pause in the
measurements be extrapolated by a stale rate), and the level random-walks too
(`level_walk`, s^2 per second). Each measurement says the level at its time, with its
variance.
"""

from __future__ import annotations

import collections
import math

import numpy as np

__all__ = ["LevelAndRate", "SteadyOrMoving"]


class LevelAndRate:
    """The Kalman filter over [level, rate] described above (a rate that stays zero when
    `rate_walk` and `rate_prior` are zero: a level that only walks)."""

    def __init__(
        self,
        level_walk: float,
        rate_walk: float,
        rate_relax_s: float,
        rate_prior: float,
    ) -> None:
        self.level_walk = level_walk
        self.rate_walk = rate_walk
        self.rate_relax_s = rate_relax_s
        self.rate_prior = rate_prior
        self._x: np.ndarray | None = None
        self._p = np.zeros((2, 2))
        self._t = math.nan

    @property
    def started(self) -> bool:
        return self._x is not None

    @property
    def rate(self) -> float:
        """The rate of change (per second of the measurements' time), 0 before a start."""
        return 0.0 if self._x is None else float(self._x[1])

    def start(self, value: float, variance: float, t: float) -> None:
        """Start afresh from one measurement: its level, no rate (known to `rate_prior`)."""
        self._x = np.array([value, 0.0])
        self._p = np.diag([variance, self.rate_prior**2])
        self._t = t

    def reset(self) -> None:
        self._x = None

    @property
    def t(self) -> float:
        """The time of the newest measurement (nan before a start)."""
        return self._t if self._x is not None else math.nan

    def shift(self, delta: float, rate_delta: float = 0.0) -> None:
        """Move the level (and the rate, where this filter has one) by known amounts: the
        measurements' frame moved. The uncertainty is unchanged."""
        if self._x is None:
            return
        self._x[0] += delta
        if self.rate_walk > 0.0 or self.rate_prior > 0.0:
            self._x[1] += rate_delta

    def _propagated(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        assert self._x is not None
        dt = max(0.0, t - self._t)
        decay = math.exp(-dt / self.rate_relax_s)
        # the level gains the rate's integral over dt as it relaxes
        gain = (
            dt
            if math.isinf(self.rate_relax_s)
            else -self.rate_relax_s * math.expm1(-dt / self.rate_relax_s)
        )
        f = np.array([[1.0, gain], [0.0, decay]])
        q = self.rate_walk * np.array([[dt**3 / 3.0, dt**2 / 2.0], [dt**2 / 2.0, dt]])
        q[0, 0] += self.level_walk * dt
        return f @ self._x, f @ self._p @ f.T + q

    def predict(self, t: float) -> tuple[float, float]:
        """(level, its variance) at time t (not before the newest measurement)."""
        x, p = self._propagated(t)
        return float(x[0]), float(p[0, 0])

    def update(self, value: float, variance: float, t: float) -> float | None:
        """Fold in a measurement of the level at time t, with its variance; how far the
        level predicted there missed it (None: the first measurement, nothing predicted)."""
        if self._x is None:
            self.start(value, variance, t)
            return None
        x, p = self._propagated(t)
        innovation = value - x[0]
        s = p[0, 0] + variance
        k = p[:, 0] / s
        self._x = x + k * innovation
        self._p = p - np.outer(k, p[0, :])
        self._p = 0.5 * (self._p + self._p.T)  # keep it symmetric against rounding
        self._t = max(self._t, t)
        return float(innovation)


class SteadyOrMoving:
    """Two views of the same measurements, and the one that has been predicting them better:
    a level that only walks ("steady": the delay is constant and fits scatter about it) and
    a level with a rate ("moving": it walks steadily). Each new measurement is first
    predicted by both; the view whose last `judged` predictions missed by less (their sum
    of squares) gives the estimate. Fits that scatter widely make the moving view chase
    each of them (a rate from a few noisy fits, extrapolated): the steady one wins there;
    precise fits of a delay that walks leave the steady one behind: the moving one wins.
    The views see the same measurements; each is only judged by how it predicted them."""

    def __init__(self, steady: LevelAndRate, moving: LevelAndRate, judged: int = 6) -> None:
        self.views = {"steady": steady, "moving": moving}
        self._missed: dict[str, collections.deque[float]] = {
            name: collections.deque(maxlen=judged) for name in self.views
        }

    @property
    def started(self) -> bool:
        return self.views["steady"].started

    @property
    def chosen(self) -> str:
        """ "moving" once it has predicted `judged` measurements and missed them by less than
        half as much as "steady" did (a few noisy fits can favour either by chance),
        else "steady"."""
        steady, moving = self._missed["steady"], self._missed["moving"]
        if len(moving) == moving.maxlen and sum(moving) < 0.5 * sum(steady):
            return "moving"
        return "steady"

    @property
    def rate(self) -> float:
        return self.views[self.chosen].rate

    def start(self, value: float, variance: float, t: float) -> None:
        for name, view in self.views.items():
            view.start(value, variance, t)
            self._missed[name].clear()

    def reset(self) -> None:
        for name, view in self.views.items():
            view.reset()
            self._missed[name].clear()

    def predict(self, t: float) -> tuple[float, float]:
        return self.views[self.chosen].predict(t)

    @property
    def t(self) -> float:
        return self.views["steady"].t

    def shift(self, delta: float, rate_delta: float = 0.0) -> None:
        """Both views moved by known amounts (not a miss of either)."""
        for view in self.views.values():
            view.shift(delta, rate_delta)

    def update(self, value: float, variance: float, t: float) -> None:
        for name, view in self.views.items():
            missed = view.update(value, variance, t)
            if missed is not None:
                self._missed[name].append(missed * missed)
