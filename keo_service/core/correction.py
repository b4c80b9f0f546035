"""Live corrections: the transform to apply to the commanded tool pose now, from keo's
estimate (feedback) and an identified model (feedforward), with the [compensation] limits.
numpy only (a controller interface imports it). Frames: see `keo_service.core.compensation`.

    T_cmd = T_goal * C,   C = C_fb * C_ff,   C_fb = T_ts^-1,   C_ff = F(q)^-1

with T_ts the estimated error transform (tool frame) and F(q) the model's predicted error at
the current joints (the estimate is then what the model leaves). C is in the tool frame, for
the right of the commanded tool pose (URScript: pose_trans(goal, C)).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from keo_service.core.rotations import log3_many


def exp3(r: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (Rodrigues; exact for small angles too)."""
    theta = math.sqrt(float(r @ r))
    K = np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
    if theta < 1e-8:  # series: sin(t)/t ~ 1 - t^2/6, (1 - cos t)/t^2 ~ 1/2 - t^2/24
        a, b = 1.0 - theta * theta / 6.0, 0.5 - theta * theta / 24.0
    else:
        a, b = math.sin(theta) / theta, (1.0 - math.cos(theta)) / (theta * theta)
    out: np.ndarray = np.eye(3) + a * K + b * (K @ K)
    return out


def log3(R: np.ndarray) -> np.ndarray:
    out: np.ndarray = log3_many(R[:, :, None])[0]
    return out


def invert(translation: np.ndarray, rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The inverse of the transform (p, r): (-R^T p, -r)."""
    R = exp3(np.asarray(rotation, dtype=float))
    return -(R.T @ np.asarray(translation, dtype=float)), -np.asarray(rotation, dtype=float)


def compose(
    a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """A * B for transforms given as (translation, rotation vector)."""
    Ra, Rb = exp3(a[1]), exp3(b[1])
    return a[0] + Ra @ b[0], log3(Ra @ Rb)


@dataclass(frozen=True)
class CompensationLimits:
    """[compensation] in SI units, and how old a received correction may be when applied."""

    max_m: float = 5e-3
    max_rad: float = 5e-3
    max_rate_m_s: float = 0.05  # the rotation's rate is limited at the same number in rad/s
    max_age_s: float = 0.1

    @classmethod
    def from_config_values(
        cls, max_mm: float, max_mrad: float, max_rate_mm_s: float, max_age_s: float = 0.1
    ) -> CompensationLimits:
        return cls(max_mm * 1e-3, max_mrad * 1e-3, max_rate_mm_s * 1e-3, max_age_s)


def _clamp_norm(v: np.ndarray, limit: float) -> tuple[np.ndarray, bool]:
    size = float(np.linalg.norm(v))
    if size > limit:
        return v * (limit / size), True
    return v, False


class CorrectionLike(Protocol):
    """What `correction_to_send` reads of a received correction (keo's CorrectionMessage)."""

    @property
    def host_ns(self) -> int: ...
    @property
    def translation(self) -> Sequence[float]: ...
    @property
    def rotation(self) -> Sequence[float]: ...
    @property
    def valid(self) -> bool: ...


def correction_to_send(
    latest: CorrectionLike | None, limits: CompensationLimits, now_ns: int
) -> tuple[list[float], list[float]]:
    """For a controller interface that sends a correction with every reply (UR registers,
    KUKA RSI, ABB EGM): the translation (m) and rotation vector (rad) to send now, in the
    tool frame and meant for the right of the commanded tool pose (T_cmd = T_goal * C, see
    the module text). Zero when there is none, when it is not valid, or when it is older than
    `limits.max_age_s` (host clock, ns since the epoch); never larger than the limits."""
    zero = [0.0, 0.0, 0.0]
    if latest is None or not latest.valid:
        return zero, list(zero)
    if (now_ns - latest.host_ns) * 1e-9 > limits.max_age_s:
        return zero, list(zero)
    p = np.asarray(latest.translation, dtype=float)
    r = np.asarray(latest.rotation, dtype=float)
    finite = bool(np.all(np.isfinite(p)) and np.all(np.isfinite(r)))
    if p.shape != (3,) or r.shape != (3,) or not finite:
        return zero, list(zero)
    p, _ = _clamp_norm(p, limits.max_m)
    r, _ = _clamp_norm(r, limits.max_rad)
    return p.tolist(), r.tolist()


@dataclass
class LiveCorrection:
    """One correction: total = feedback then feedforward (each (translation, rotation)),
    zero when not valid."""

    translation: np.ndarray
    rotation: np.ndarray
    feedback: tuple[np.ndarray, np.ndarray]
    feedforward: tuple[np.ndarray, np.ndarray]
    valid: bool
    reason: str = ""
    clamped: bool = False


def feedback_part(estimate: Sequence[float] | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """C_fb = T_ts^-1 from the estimate [p_ts; r_ts] (3 numbers for a single reflector: no
    rotation known, none corrected)."""
    e = np.asarray(estimate, dtype=float)
    r = e[3:6] if e.size >= 6 else np.zeros(3)
    return invert(e[:3], r)


class FeedforwardModel(Protocol):
    """What the filter needs of a model (`core.compensation.ToolModel`)."""

    def predicted_error(
        self, q: np.ndarray, direction: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]: ...

    def outside_calibrated_range(self, q: np.ndarray) -> np.ndarray: ...


class CorrectionFilter:
    """The live correction from each estimate: validity, the feedforward of a model, and the
    [compensation] limits on size and rate of change (clamps counted in `counters`)."""

    def __init__(self, limits: CompensationLimits, model: FeedforwardModel | None = None) -> None:
        self.limits = limits
        self.model = model
        self.counters: dict[str, int] = {
            "corrections": 0,
            "corrections_invalid": 0,
            "corrections_clamped_size": 0,
            "corrections_clamped_rate": 0,
        }
        self._last: tuple[float, np.ndarray, np.ndarray] | None = None  # t, p, r sent

    def step(
        self,
        t: float,
        estimate: Sequence[float] | np.ndarray,
        joints: np.ndarray | None,
        invalid_reason: str = "",
        direction: np.ndarray | None = None,
    ) -> LiveCorrection:
        """`t`: stream time (s) of the estimate; `invalid_reason` non-empty for a held step,
        stale input or joints outside the calibrated range (the caller's flags)."""
        self.counters["corrections"] += 1
        zero = np.zeros(3)
        values = np.asarray(estimate, dtype=float)
        if not invalid_reason and not np.all(np.isfinite(values)):
            invalid_reason = "non_finite_estimate"
        if not invalid_reason and self.model is not None and joints is None:
            invalid_reason = "no_joints"
        if invalid_reason:
            self.counters["corrections_invalid"] += 1
            self._last = (t, zero, zero)
            return LiveCorrection(zero, zero, (zero, zero), (zero, zero), False, invalid_reason)
        fb = feedback_part(values)
        ff: tuple[np.ndarray, np.ndarray] = (zero, zero)
        if self.model is not None and joints is not None:
            if self.model.outside_calibrated_range(np.asarray(joints))[0]:
                self.counters["corrections_invalid"] += 1
                self._last = (t, zero, zero)
                return LiveCorrection(
                    zero, zero, (zero, zero), (zero, zero), False, "outside_calibrated_range"
                )
            ff = invert(*self.model.predicted_error(np.asarray(joints), direction))
        p, r = compose(fb, ff) if self.model is not None else fb
        p, size_p = _clamp_norm(p, self.limits.max_m)
        r, size_r = _clamp_norm(r, self.limits.max_rad)
        clamped = size_p or size_r
        if clamped:
            self.counters["corrections_clamped_size"] += 1
        if self._last is None:  # nothing applied before: ramp up from zero
            self._last = (t, zero, zero)
        dt = t - self._last[0]
        step_limit = self.limits.max_rate_m_s * max(dt, 0.0)
        dp, rate_p = _clamp_norm(p - self._last[1], step_limit)
        dr, rate_r = _clamp_norm(r - self._last[2], step_limit)
        if rate_p or rate_r:
            self.counters["corrections_clamped_rate"] += 1
            clamped = True
            p, r = self._last[1] + dp, self._last[2] + dr
        self._last = (t, p, r)
        return LiveCorrection(p, r, fb, ff, True, "", clamped)
