"""What the measurement itself allows: the tracker's uncertainty, the floor a perfect model
would reach on the held-out poses, and the ISO 9283 pose and path figures. No I/O.

The floor: with a perfect model the held-out residual is the measurement's own error plus the
error of the fitted parameters. Per pose and coordinate the measurement's standard uncertainty
is taken from, in this order, the per-point standard deviations of the tracker file (columns
sx, sy, sz), the data's repeatability (repeated stop-and-measure poses), or the tracker's
specification (`[tracker] uncertainty_um` + `uncertainty_um_per_m` x the distance from the
tracker; keo's defaults are marked as assumed). The parameters' share: a linear least-squares
fit of p parameters to m residual rows leaves an expected held-out mean square of
sigma^2 (1 + p / m) (the held-out rows' leverage), so the floor is
sqrt(mean_i(sx_i^2 + sy_i^2 + sz_i^2) x (1 + p / m)) over the held-out poses.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

NOISE_RATIO = 1.2  # held out within this many times the floor: consistent with noise

ISO_MIN_CYCLES = 2  # ISO 9283 asks for 30 cycles per pose; below that a figure is indicative


@dataclass(frozen=True)
class TrackerUncertainty:
    """Standard uncertainty per coordinate: um + um_per_m x distance from the tracker."""

    um: float = 15.0
    um_per_m: float = 6.0
    assumed: bool = True  # keo's defaults, not stated by the user

    def sigma(self, p_ks: np.ndarray) -> np.ndarray:
        """(N, 3) standard uncertainty per coordinate (m) at tracker positions p_ks (m)."""
        d = np.linalg.norm(p_ks, axis=1)
        s = (self.um + self.um_per_m * d) * 1e-6
        return np.repeat(s[:, None], 3, axis=1)

    def as_dict(self) -> dict[str, Any]:
        return {"um": self.um, "um_per_m": self.um_per_m, "assumed": self.assumed}

    def text(self) -> str:
        head = f"{self.um:g} um + {self.um_per_m:g} um/m per coordinate"
        if self.assumed:
            return (
                f"{head} (keo's default, assumed: state the tracker's own with "
                "[tracker] uncertainty_um and uncertainty_um_per_m)"
            )
        return f"{head} ([tracker] uncertainty_um, uncertainty_um_per_m)"


def parameter_factor(parameters: int, rows: int) -> float:
    """sqrt(1 + p / m): how much a fit of p parameters to m residual rows lifts the
    expected held-out RMS above the noise alone."""
    return float(np.sqrt(1.0 + parameters / max(rows, 1)))


def rms3(sigma: np.ndarray) -> float:
    """RMS of the 3D norm of an error with per-coordinate standard deviations (N, 3) (m)."""
    return float(np.sqrt(np.mean(np.sum(np.asarray(sigma) ** 2, axis=1))))


def floor_report(
    sigma_points: np.ndarray | None,
    p_ks_held: np.ndarray,
    tracker: TrackerUncertainty,
    repeatability_mm: float | None,
    parameters: int,
    rows: int,
) -> dict[str, Any]:
    """The floor for the held-out poses from every source available, the first of them used.
    `sigma_points`: the held-out poses' per-point standard deviations (N, 3) (m) or None;
    `repeatability_mm`: the RMS 3D scatter of repeated poses, None when not usable."""
    factor = parameter_factor(parameters, rows)
    sources: list[dict[str, Any]] = []
    if sigma_points is not None and np.all(np.isfinite(sigma_points)):
        sources.append(
            {
                "source": "per-point standard deviations in the tracker file (sx, sy, sz)",
                "label": "per-point standard deviations",
                "noise_rms_mm": rms3(sigma_points) * 1e3,
                "assumed": False,
            }
        )
    if repeatability_mm is not None:
        sources.append(
            {
                "source": "repeatability of the repeated poses in these data",
                "label": "repeatability",
                "noise_rms_mm": repeatability_mm,
                "assumed": False,
            }
        )
    sources.append(
        {
            "source": f"tracker specification {tracker.text()}",
            "label": f"tracker specification {tracker.um:g} um + {tracker.um_per_m:g} um/m"
            + (", assumed" if tracker.assumed else ""),
            "noise_rms_mm": rms3(tracker.sigma(p_ks_held)) * 1e3,
            "assumed": tracker.assumed,
        }
    )
    for s in sources:
        s["floor_mm"] = s["noise_rms_mm"] * factor
    used = sources[0]
    return {
        "pos_rms_mm": used["floor_mm"],
        "source": used["source"],
        "label": used["label"],
        "assumed": used["assumed"],
        "held_out_poses": int(p_ks_held.shape[0]),
        "parameters": int(parameters),
        "parameter_factor": factor,
        "sources": sources,
        "tracker_uncertainty": tracker.as_dict(),
    }


# ---- ISO 9283 ------------------------------------------------------------------------------


def iso_pose_figures(
    groups: np.ndarray, measured: np.ndarray, residual: dict[str, np.ndarray]
) -> dict[str, Any] | None:
    """ISO 9283 pose accuracy AP and pose repeatability RP from repeated poses.

    `groups` (N,): the repeated pose each row belongs to (-1: none); `measured` (N, 3): the
    attained positions (any fixed frame, m); `residual`: per model (e.g. "before", "after")
    the predicted minus measured positions (N, 3) (m), the prediction standing for the
    commanded position. Per pose: AP = |mean attained - commanded| = |mean residual|,
    RP = mean(l) + 3 S_l with l each attained position's distance from their barycentre.
    Figures in mm: mean and max over the repeated poses."""
    ids = np.unique(groups[groups >= 0])
    if ids.size == 0:
        return None
    rp, cycles = [], []
    ap: dict[str, list[float]] = {k: [] for k in residual}
    for g in ids:
        rows = np.flatnonzero(groups == g)
        pts = measured[rows]
        dist = np.linalg.norm(pts - pts.mean(axis=0), axis=1)
        s_l = float(np.sqrt(np.sum((dist - dist.mean()) ** 2) / max(rows.size - 1, 1)))
        rp.append(float(dist.mean()) + 3.0 * s_l)
        cycles.append(rows.size)
        for k, r in residual.items():
            ap[k].append(float(np.linalg.norm(r[rows].mean(axis=0))))
    out: dict[str, Any] = {
        "poses": int(ids.size),
        "cycles_median": float(np.median(cycles)),
        "RP_mm": {"mean": float(np.mean(rp)) * 1e3, "max": float(np.max(rp)) * 1e3},
        "AP_mm": {
            k: {"mean": float(np.mean(v)) * 1e3, "max": float(np.max(v)) * 1e3}
            for k, v in ap.items()
        },
    }
    return out


def iso_path_figures(residual: dict[str, np.ndarray]) -> dict[str, Any]:
    """ISO 9283 path accuracy AT from one pass of motion: the largest distance between the
    attained and the commanded path (the model's prediction from the joints), mm, per model;
    with one pass the barycentre path is the pass itself."""
    return {
        "AT_mm": {k: float(np.max(np.linalg.norm(r, axis=1))) * 1e3 for k, r in residual.items()},
        "passes": 1,
    }
