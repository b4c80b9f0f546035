"""The model's own statement of how accurate it is at a joint configuration: the expected
position error (RMS of its length, mm) after compensation with the identified model. No I/O.

Two figures measured by `keo analyze` carry it: `inside_mm`, the held-out position RMS on
poses within the calibrated joint ranges (interpolation), and `outside_mm`, the RMS the model
reaches on held-out bands at the ends of the joint ranges (extrapolation: the fit never saw
those angles; at least the model's error without its maps, which fade to zero there). A pose
outside the calibrated range of any joint by d rad moves from the first towards the second,
reaching it at `taper_rad` (the maps' fade length) and growing by `growth_mm_per_rad` beyond.
The 95 % band of the error's length for an isotropic Gaussian error of that RMS is
BAND_95 x the RMS (chi distribution with 3 degrees of freedom: 2.795 / sqrt(3)).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from keo_service.core.model_corrections import MAP_TAPER_RAD

BAND_95 = 2.795 / np.sqrt(3.0)  # 95 % quantile of |e| / RMS(|e|) for a 3-D Gaussian


@dataclass(frozen=True)
class Accuracy:
    inside_mm: float
    outside_mm: float
    lower: np.ndarray  # per joint, rad: the calibrated range
    upper: np.ndarray
    taper_rad: float = MAP_TAPER_RAD
    growth_mm_per_rad: float = 0.0

    def as_dict(self) -> dict[str, Any]:
        return {
            "inside_mm": self.inside_mm,
            "outside_mm": self.outside_mm,
            "lower_rad": self.lower.tolist(),
            "upper_rad": self.upper.tolist(),
            "taper_rad": self.taper_rad,
            "growth_mm_per_rad": self.growth_mm_per_rad,
        }


def distance_outside(q: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Per pose (..., nq) -> (...): the largest distance (rad) of a joint outside its range."""
    d = np.maximum(lower - q, 0.0) + np.maximum(q - upper, 0.0)
    out: np.ndarray = np.max(d, axis=-1)
    return out


def predicted_position_sigma(accuracy: Accuracy, q: np.ndarray) -> np.ndarray:
    """Expected position error (RMS of its length, mm) of the identified model at joint
    configurations q (N, nq) or (nq,): `keo compensate` writes it per target, `keo analyze`
    per held-out pose. Multiply by BAND_95 for the 95 % band of the error's length."""
    q = np.asarray(q, dtype=float)
    d = distance_outside(q, accuracy.lower, accuracy.upper)
    fade = np.clip(d / max(accuracy.taper_rad, 1e-12), 0.0, 1.0)
    inside, outside = accuracy.inside_mm, max(accuracy.outside_mm, accuracy.inside_mm)
    extra = accuracy.growth_mm_per_rad * np.maximum(d - accuracy.taper_rad, 0.0)
    out: np.ndarray = np.sqrt((inside + (outside - inside) * fade) ** 2 + extra**2)
    return out


def coverage(sigma_mm: np.ndarray, error_mm: np.ndarray) -> dict[str, Any]:
    """How well the stated accuracy covers measured errors: the fraction of poses whose error
    length lies within the 95 % band, and the RMS predicted against the RMS measured."""
    sigma_mm, error_mm = np.asarray(sigma_mm), np.asarray(error_mm)
    if not sigma_mm.size:
        return {"n": 0}
    return {
        "n": int(sigma_mm.size),
        "within_95_pct": 100.0 * float(np.mean(error_mm <= BAND_95 * sigma_mm)),
        "predicted_rms_mm": float(np.sqrt(np.mean(sigma_mm**2))),
        "measured_rms_mm": float(np.sqrt(np.mean(error_mm**2))),
    }


def stated_accuracy(report: dict[str, Any], q: np.ndarray) -> Accuracy:
    """The accuracy `keo analyze` states for its model: inside, the final held-out RMS;
    outside, the physical effects' figure on the extrapolation bands (fit.prior) or their
    held-out RMS, whichever is larger (the maps fade to zero outside); the calibrated ranges
    from the calibration poses `q`."""
    inside = float(report["final"]["validation"]["pos_rms_mm"])
    physical = [e for e in report["effects"] if "bands" in e]
    candidates = [inside, float(report["baseline"]["validation"]["pos_rms_mm"])]
    if physical:
        last = physical[-1]
        candidates = [inside, last["bands"]["pos_rms_mm_with"], last["validation"]["pos_rms_mm"]]
    return Accuracy(inside, max(candidates), q.min(axis=0), q.max(axis=0))
