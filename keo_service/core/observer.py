"""The Kinematic Error Observer (docs/design.md §2) and its analytic properties. No I/O.

Model: de/dt = 0, e_m = e + n. Observer: de_hat/dt = L (e_m - e_hat), L = diag(L_i) > 0.
Each step is discretized exactly for its own dt (zero-order hold on the new measurement):
    e_hat_k = e_hat_{k-1} + (1 - exp(-L dt_k)) (e_m_k - e_hat_{k-1})
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

SETTLING_FRACTION = 0.02


class KinematicErrorObserver:
    """Per-channel first-order observer; the number of channels comes from the gains given."""

    def __init__(
        self,
        gains: Sequence[float] | np.ndarray,
        initial: Sequence[float] | np.ndarray | None = None,
    ) -> None:
        gain = np.asarray(gains, dtype=float)
        if gain.ndim != 1 or gain.size == 0:
            raise ValueError("gains must be a non-empty 1-D sequence")
        if not np.all(np.isfinite(gain)) or np.any(gain <= 0):
            raise ValueError(f"every gain must be finite and > 0, got {gain.tolist()}")
        self._gain = gain
        # the step runs on plain floats: for a handful of channels, Python arithmetic costs
        # less than the equivalent numpy calls (docs/performance.md)
        self._neg_gain = [-g for g in gain.tolist()]
        self._one_neg_gain = self._neg_gain[0] if len(set(self._neg_gain)) == 1 else None
        # the state as plain floats: a list the observer never changes (each step makes a new
        # one), so it may be kept as it is; an attribute, read once per estimate
        self.values: list[float] = [0.0] * gain.size
        self._initialized = False
        self.rejected = 0
        self.updates = 0
        if initial is not None:
            self.reset(initial)

    @property
    def gain(self) -> np.ndarray:
        return self._gain.copy()

    @property
    def channels(self) -> int:
        return int(self._gain.size)

    @property
    def estimate(self) -> np.ndarray:
        return np.array(self.values)

    def set_gain(self, gains: Sequence[float] | np.ndarray) -> None:
        """Change gains without touching the state (used by a live reload)."""
        gain = np.asarray(gains, dtype=float)
        if gain.shape != self._gain.shape or np.any(~np.isfinite(gain)) or np.any(gain <= 0):
            raise ValueError(f"need {self.channels} finite gains > 0, got {gain.tolist()}")
        self._gain = gain
        self._neg_gain = [-g for g in gain.tolist()]
        self._one_neg_gain = self._neg_gain[0] if len(set(self._neg_gain)) == 1 else None

    def reset(self, initial: Sequence[float] | np.ndarray | None = None) -> None:
        """Restart from `initial` (default zero: the reference experiment's start)."""
        value = np.zeros_like(self._gain) if initial is None else np.asarray(initial, dtype=float)
        if value.shape != self._gain.shape or not np.all(np.isfinite(value)):
            raise ValueError(f"initial state must be {self.channels} finite numbers")
        self.values = value.tolist()
        self._initialized = True

    def update(self, measured: np.ndarray | Sequence[float], dt: float) -> bool:
        """One exact ZOH step. Returns False (state unchanged, counted) for bad input: a dt
        that is not a finite positive number, the wrong number of values, or values that are
        not finite numbers (or would take the state out of the finite numbers)."""
        if type(measured) is list:
            meas = measured
        else:
            meas = measured.tolist() if isinstance(measured, np.ndarray) else list(measured)
        old = self.values
        n = len(old)
        if not 0.0 < dt < math.inf or len(meas) != n:
            self.rejected += 1
            return False
        try:
            if self._one_neg_gain is not None:  # one gain for all: one exponential
                a = math.expm1(self._one_neg_gain * dt)
                if n == 6:  # the 6-DoF probe's step spelled out: no comprehension's frame
                    s0, s1, s2, s3, s4, s5 = old
                    m0, m1, m2, m3, m4, m5 = meas
                    state = [
                        s0 - a * (m0 - s0),
                        s1 - a * (m1 - s1),
                        s2 - a * (m2 - s2),
                        s3 - a * (m3 - s3),
                        s4 - a * (m4 - s4),
                        s5 - a * (m5 - s5),
                    ]
                else:
                    state = [s - a * (m - s) for s, m in zip(old, meas, strict=True)]
            else:
                expm1 = math.expm1
                state = [
                    s - expm1(g * dt) * (m - s)
                    for s, g, m in zip(old, self._neg_gain, meas, strict=True)
                ]
            # one check of the result covers the input; a finite sum proves it
            finite = math.isfinite(sum(state)) or all(map(math.isfinite, state))
        except TypeError:
            finite = False
        if not finite:
            self.rejected += 1
            return False
        self.values = state
        self.updates += 1
        return True


# ---- analytic properties -------------------------------------------------------------------


def time_constant(gain: float) -> float:
    """1/L seconds."""
    return 1.0 / gain


def settling_time(gain: float, fraction: float = SETTLING_FRACTION) -> float:
    """Continuous-time settling time to within `fraction` of a step: ln(1/fraction)/L."""
    return math.log(1.0 / fraction) / gain


def step_alpha(gain: float, period: float) -> float:
    """Fraction of the innovation taken per step: a = 1 - exp(-L T)."""
    return -math.expm1(-gain * period)


def discrete_settling_time(
    gain: float, period: float, fraction: float = SETTLING_FRACTION
) -> float:
    """First sample time at which a step from zero is within `fraction` of its final value."""
    a = step_alpha(gain, period)
    if a >= 1.0:  # exp(-L T) rounds to 0: the first sample is taken whole
        return period
    steps = math.ceil(math.log(fraction) / math.log1p(-a) - 1e-12)
    return max(steps, 1) * period


def noise_gain(gain: float, period: float) -> float:
    """Estimate std / white measurement noise std in steady state: sqrt(a/(2-a))."""
    a = step_alpha(gain, period)
    return math.sqrt(a / (2.0 - a))


def steady_state_mse(alpha: float, noise_std: float, drift: float, period: float) -> float:
    """Mean square estimate error for true error = random walk, plus white measurement noise.

    `drift` is the random walk's intensity: std of its change over one second (units/sqrt(s)).
    With q = drift^2 T and r = noise_std^2 the error obeys
    eps_k = (1-a)(eps_{k-1} - w_k) + a v_k, so V = ((1-a)^2 q + a^2 r) / (a (2-a)).
    """
    q = drift * drift * period
    r = noise_std * noise_std
    return ((1.0 - alpha) ** 2 * q + alpha * alpha * r) / (alpha * (2.0 - alpha))


def kalman_alpha(noise_std: float, drift: float, period: float) -> float:
    """Steady-state Kalman gain of the random-walk model: the a that minimises the MSE."""
    q = drift * drift * period
    r = noise_std * noise_std
    if q <= 0.0:
        return 0.0
    if r <= 0.0:
        return 1.0
    prior = 0.5 * (q + math.sqrt(q * q + 4.0 * q * r))
    return prior / (prior + r)


def best_gain(noise_std: float, drift: float, rate_hz: float) -> float:
    """Observer gain L (1/s) whose ZOH step equals the steady-state Kalman gain."""
    period = 1.0 / rate_hz
    a = kalman_alpha(noise_std, drift, period)
    if a <= 0.0:
        return 0.0
    if a >= 1.0:
        return math.inf
    return -math.log1p(-a) / period


def finite_numbers(values: list[Any]) -> bool:
    """True when every item is a finite number (a nested list or a string is not). A finite
    sum proves it for the good case; only a non-finite sum (or an overflow) looks closer."""
    try:
        if math.isfinite(sum(values)):
            return True
        return all(math.isfinite(v) for v in values)
    except TypeError:
        return False


def all_finite(values: np.ndarray) -> bool:
    """True when every value is finite. A finite sum proves it (a NaN or an infinity makes the
    sum non-finite); summing the short hot-path vectors as Python floats costs less than
    isfinite().all() (docs/performance.md) and warns about nothing. Only a non-finite sum (or
    an overflow of huge finite values) takes the exact test."""
    return math.isfinite(sum(values.ravel().tolist())) or bool(np.isfinite(values).all())


@dataclass(frozen=True)
class GainReport:
    gain: float
    rate_hz: float
    time_constant_s: float
    settling_time_s: float
    discrete_settling_time_s: float
    step_alpha: float
    noise_gain: float
    extras: dict[str, float] = field(default_factory=dict)


def describe_gain(gain: float, rate_hz: float) -> GainReport:
    period = 1.0 / rate_hz
    return GainReport(
        gain=gain,
        rate_hz=rate_hz,
        time_constant_s=time_constant(gain),
        settling_time_s=settling_time(gain),
        discrete_settling_time_s=discrete_settling_time(gain, period),
        step_alpha=step_alpha(gain, period),
        noise_gain=noise_gain(gain, period),
    )


class NoiseMeter:
    """The measurement noise per channel, online: an exponentially weighted mean of half the
    squared change between consecutive measurements (for white noise E[(n_k - n_k-1)^2] / 2
    = s^2; a slowly varying true error adds little at tracker rates). Bounded: one number per
    channel."""

    def __init__(self, weight: float = 0.01) -> None:
        self.weight = weight
        self._last: np.ndarray | None = None
        self._var: np.ndarray | None = None

    def add(self, measured: np.ndarray) -> None:
        if self._last is not None and self._last.shape == measured.shape:
            half_sq = 0.5 * (measured - self._last) ** 2
            if self._var is None or self._var.shape != half_sq.shape:
                self._var = half_sq
            else:
                self._var = self._var + self.weight * (half_sq - self._var)
        self._last = np.array(measured, dtype=float)

    def std(self) -> np.ndarray | None:
        return None if self._var is None else np.sqrt(self._var)


def estimate_variance(
    noise_std: np.ndarray, gains: Sequence[float] | np.ndarray, period: float
) -> np.ndarray:
    """The observer's steady-state estimate variance per channel for white measurement noise
    of `noise_std` at sample period `period` [s]: (noise gain * noise std)^2."""
    gains = np.asarray(gains, dtype=float)[: noise_std.size]
    factor = np.array([noise_gain(float(g), period) for g in gains])
    out: np.ndarray = (factor * noise_std) ** 2
    return out


# ---- the noise behind a published covariance --------------------------------------------------

# A 6-DoF probe's orientation comes from targets about this far apart: its orientation noise
# is the position noise over this base (15 um over 0.1 m: 150 urad, a probe datasheet's 0.01
# degree). keo's config gives the tracker's position uncertainty only.
PROBE_BASE_M = 0.1
# Never claim perfect knowledge: below these a tracker resolves nothing (0.1 um, 1 urad).
MIN_NOISE_M = 1e-7
MIN_NOISE_RAD = 1e-6


def tracker_noise_floor(
    uncertainty_um: float,
    uncertainty_um_per_m: float,
    p_ks: Sequence[float] | None,
    channels: int,
) -> np.ndarray:
    """The configured measurement noise per channel (std; m, rad): a datasheet's
    "u0 + u1 per metre" at the distance of the measured point from the tracker (`p_ks`, its
    position in the tracker frame; unknown: 0 m), rotations over PROBE_BASE_M."""
    distance = 0.0 if p_ks is None else math.sqrt(sum(float(v) * float(v) for v in p_ks))
    sigma_p = max((uncertainty_um + uncertainty_um_per_m * distance) * 1e-6, MIN_NOISE_M)
    out = np.full(channels, sigma_p)
    out[3:] = max(sigma_p / PROBE_BASE_M, MIN_NOISE_RAD)
    return out


def covariance_noise(measured_std: np.ndarray | None, floor: np.ndarray) -> np.ndarray:
    """The noise a published covariance stands on: the measured noise where it exceeds the
    configured floor, the floor otherwise (before anything is measured, or on noise-free
    input): never zero."""
    if measured_std is None or measured_std.shape != floor.shape:
        return floor
    out: np.ndarray = np.maximum(measured_std, floor)
    return out
