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

A model carried to another session (another day, tracker station, mount) meets more than
what its own held-out poses show: what differs between sessions (the tracker's own
angle-dependent error, a remount, the temperature) is in no held-out block of the session it
was fitted on. `session_mm` is that between-session term, added in quadrature when the model
is judged off-session (`off_session=True`). With two or more sessions it is measured, from
leave-one-session-out: what the carried models missed beyond what they stated
(`session_term`). With one session there is nothing to measure it on, and the default is the
extrapolation bands' excess over the held-out blocks (`default_session_mm`): a session not
seen is taken to cost what angles not seen cost, a stated assumption (docs/analyze.md gives
how it covered the UR10 series).
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
    session_mm: float = 0.0  # the between-session term (off-session use), see module doc
    session_source: str = "held-out bands"  # how session_mm was found

    def as_dict(self) -> dict[str, Any]:
        return {
            "inside_mm": self.inside_mm,
            "outside_mm": self.outside_mm,
            "lower_rad": self.lower.tolist(),
            "upper_rad": self.upper.tolist(),
            "taper_rad": self.taper_rad,
            "growth_mm_per_rad": self.growth_mm_per_rad,
            "session_mm": self.session_mm,
            "session_source": self.session_source,
        }


def distance_outside(q: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Per pose (..., nq) -> (...): the largest distance (rad) of a joint outside its range."""
    d = np.maximum(lower - q, 0.0) + np.maximum(q - upper, 0.0)
    out: np.ndarray = np.max(d, axis=-1)
    return out


def predicted_position_sigma(
    accuracy: Accuracy, q: np.ndarray, off_session: bool = False
) -> np.ndarray:
    """Expected position error (RMS of its length, mm) of the identified model at joint
    configurations q (N, nq) or (nq,): `keo compensate` writes it per target, `keo analyze`
    per held-out pose. `off_session`: in a session other than the one it was fitted on (the
    between-session term added in quadrature). Multiply by BAND_95 for the 95 % band of the
    error's length."""
    q = np.asarray(q, dtype=float)
    d = distance_outside(q, accuracy.lower, accuracy.upper)
    fade = np.clip(d / max(accuracy.taper_rad, 1e-12), 0.0, 1.0)
    inside, outside = accuracy.inside_mm, max(accuracy.outside_mm, accuracy.inside_mm)
    extra = accuracy.growth_mm_per_rad * np.maximum(d - accuracy.taper_rad, 0.0)
    session = accuracy.session_mm if off_session else 0.0
    out: np.ndarray = np.sqrt((inside + (outside - inside) * fade) ** 2 + extra**2 + session**2)
    return out


def default_session_mm(inside_mm: float, outside_mm: float) -> float:
    """The between-session term when only one session was seen: the extrapolation bands'
    excess over the held-out blocks, sqrt(outside^2 - inside^2) (see the module doc)."""
    return float(np.sqrt(max(outside_mm**2 - inside_mm**2, 0.0)))


def session_term(measured_rms_mm: list[float], predicted_rms_mm: list[float]) -> float:
    """The between-session term from sessions left out: per session the part of the measured
    held-out RMS its carried model did not state (sqrt(measured^2 - predicted^2), 0 where it
    stated more), pooled as an RMS over the sessions."""
    excess = [max(m**2 - p**2, 0.0) for m, p in zip(measured_rms_mm, predicted_rms_mm, strict=True)]
    return float(np.sqrt(np.mean(excess))) if excess else 0.0


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


def stated_accuracy(report: dict[str, Any], q_fitted: np.ndarray) -> Accuracy:
    """The accuracy `keo analyze` states for its model: inside, the final held-out RMS;
    outside, the physical effects' figure on the extrapolation bands (fit.prior) or their
    held-out RMS, whichever is larger (the maps fade to zero outside); the calibrated ranges
    from the poses the model was fitted on, `q_fitted` (the training rows only: a held-out
    pose beyond them is extrapolation, and stating it at the in-range figure is what the
    coverage check exists to catch); the between-session term from leave-one-session-out when
    the report has it (`leave_one_session_out.session_term`), else the bands' default."""
    inside = float(report["final"]["validation"]["pos_rms_mm"])
    physical = [e for e in report["effects"] if "bands" in e]
    candidates = [inside, float(report["baseline"]["validation"]["pos_rms_mm"])]
    if physical:
        last = physical[-1]
        candidates = [inside, last["bands"]["pos_rms_mm_with"], last["validation"]["pos_rms_mm"]]
    outside = max(candidates)
    measured = report.get("leave_one_session_out", {}).get("session_term")
    taper = map_taper(report)
    if measured is not None:
        return Accuracy(
            inside,
            outside,
            q_fitted.min(axis=0),
            q_fitted.max(axis=0),
            taper,
            session_mm=float(measured["session_mm"]),
            session_source="leave one session out",
        )
    return Accuracy(
        inside,
        outside,
        q_fitted.min(axis=0),
        q_fitted.max(axis=0),
        taper,
        session_mm=default_session_mm(inside, outside),
    )


def map_taper(report: dict[str, Any]) -> float:
    """The fade length of the kept joint maps (fit.angle_maps.choose_taper), MAP_TAPER_RAD
    without maps or without a chosen one."""
    for entry in report.get("effects", []):
        if entry.get("name") == "joint_maps" and "taper" in entry:
            return float(entry["taper"]["taper_rad"])
    return MAP_TAPER_RAD
