"""A prior that keeps each effect's terms near their physical size, its weight chosen by what
carries to poses the fit never saw: held-out blocks (interpolation) and held-out bands at the
ends of each joint's range (extrapolation). No I/O.

Why: with only the data's interleaved blocks to judge, a fit is free to use terms of many
times the robot's whole error that cancel on the calibration poses and nowhere else; carried
to another session they made the model worse than the nominal robot (docs/analyze.md gives
the UR10 figures). A term's
physical size (`SCALES`: a joint's placement is known to a millimetre, a gear's error to
about a milliradian) turns that freedom into a cost. The penalty is
`weight * noise^2 * sum((value / scale)^2)`: at weight 1 a term at its physical size costs as
much as one residual at the noise level. The weight is chosen on a linearization around the
registered model (one Jacobian over all rows, then a small solve per weight and split), so
the choice costs seconds, and the nonlinear fit then runs once with it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from keo_service.fit.model import Data, Effect, Model, numeric_jacobian

# physical size of one parameter, per effect name and per parameter of a joint (SI)
SCALES: dict[str, tuple[float, ...]] = {
    "joint_offsets": (1e-3,),  # rad
    "geometry": (1e-3, 1e-3, 1e-3, 1e-3, 1e-3, 1e-3),  # m, m, m, rad, rad, rad
    "compliance": (5e-6,),  # rad/(N m): ~0.5 mrad at 100 N m
    "backlash": (3e-4,),  # rad
    "cyclic": (5e-4, 5e-4, 5e-4, 5e-4),  # rad
    "joint_ripple": (5e-4,),  # rad
}
WEIGHTS = (0.0, 1.0, 10.0, 100.0, 1e3, 1e4, 1e5)
WITHOUT = 1e12  # a weight that holds the effect at zero: the bands without it
BAND_FRACTION = 0.15  # of a joint's range held out at each end
MIN_BAND_RANGE = 0.3  # rad: a joint that moves less has no bands


def scales_of(effect: Effect, nq: int) -> np.ndarray | None:
    """Per full parameter of `effect` its physical size; None: the effect has no prior."""
    per_joint = SCALES.get(effect.name)
    if per_joint is None:
        return None
    size = effect.size(nq)
    out = np.resize(np.asarray(per_joint, dtype=float), size)
    return out


def prior_rows(model: Model, weights: dict[str, float], noise: float) -> np.ndarray | None:
    """Rows P (m x model.x.size) whose P @ x are the prior's residuals (m), one per full
    parameter of each effect with a weight: sqrt(weight) * noise * value / scale."""
    nq = model.chain.nq
    blocks: list[np.ndarray] = []
    k = model.n_reg
    for effect, size in zip(model.effects, model.sizes(nq), strict=True):
        w = weights.get(effect.name, 0.0)
        scale = scales_of(effect, nq)
        if w > 0 and scale is not None:
            B = model.basis.get(effect.name, np.eye(size))
            rows = np.zeros((B.shape[0], model.x.size))
            rows[:, k : k + size] = np.sqrt(w) * noise * B / scale[:, None]
            blocks.append(rows)
        k += size
    return np.vstack(blocks) if blocks else None


def extrapolation_bands(q: np.ndarray) -> list[tuple[str, np.ndarray]]:
    """Per joint that moves at least MIN_BAND_RANGE: the poses in the lowest and in the
    highest BAND_FRACTION of its range (by angle, not by count), each a held-out band."""
    out = []
    for j in range(q.shape[1]):
        lo, hi = float(q[:, j].min()), float(q[:, j].max())
        if hi - lo < MIN_BAND_RANGE:
            continue
        edge = BAND_FRACTION * (hi - lo)
        for side, rows in (("low", q[:, j] <= lo + edge), ("high", q[:, j] >= hi - edge)):
            if 10 <= rows.sum() <= 0.5 * q.shape[0]:
                out.append((f"q{j + 1} {side}", np.flatnonzero(rows)))
    return out


@dataclass
class PriorChoice:
    weight: float
    table: list[dict[str, Any]]  # per weight: blocks and bands RMS (mm)
    without_bands_mm: float  # the bands' RMS without the effect (linearized)
    without_blocks_mm: float

    def as_dict(self) -> dict[str, Any]:
        return {
            "weight": self.weight,
            "candidates": self.table,
            "without_effect": {
                "blocks_pos_rms_mm": self.without_blocks_mm,
                "bands_pos_rms_mm": self.without_bands_mm,
            },
        }


def choose_weight(
    trial: Model,
    x0: np.ndarray,
    data: Data,
    tau: np.ndarray,
    train_idx: np.ndarray,
    val_idx: np.ndarray,
    noise: float,
    name: str,
    huber_noise: float | None = None,
) -> PriorChoice:
    """The prior weight of effect `name` (the last of `trial`) that minimises the mean square
    of the held-out blocks' RMS and the extrapolation bands' RMS, on the model linearized at
    x0 (registration and every earlier effect free, their own priors ignored). `noise`: the
    prior's unit; `huber_noise`: the residual's scale on top of the model before the effect,
    whose 3 sigmas down-weight gross outliers (default `noise`)."""
    r0 = trial.residuals(x0, data, tau)
    width = r0.size // data.n
    J = numeric_jacobian(lambda z: trial.residuals(z, data, tau), x0, r0)
    row_w = data.row_weights(width)
    # Huber-like weights from the starting residual: a few gross outliers must not choose
    k = 3.0 * (noise if huber_noise is None else huber_noise)
    w = np.sqrt(np.minimum(1.0, k / np.maximum(np.abs(r0), 1e-300)))
    if row_w is not None:
        w = w * row_w
    Jw, rw = J * w[:, None], r0 * w
    size = trial.sizes(trial.chain.nq)[-1]
    scale = scales_of(trial.effects[-1], trial.chain.nq)
    assert scale is not None
    B = trial.basis.get(name, np.eye(size))
    P = np.zeros((B.shape[0], x0.size))
    P[:, x0.size - size :] = noise * B / scale[:, None]
    PtP = P.T @ P
    ridge = 1e-12 * np.eye(x0.size)

    def rows_of(idx: np.ndarray) -> np.ndarray:
        out: np.ndarray = (idx[:, None] * width + np.arange(width)).ravel()
        return out

    def normal(idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        A, b = Jw[rows_of(idx)], rw[rows_of(idx)]
        return A.T @ A, A.T @ b

    def solve(M: np.ndarray, g: np.ndarray, weight: float) -> np.ndarray:
        lhs = M + weight * PtP + ridge * max(1.0, float(np.trace(M)))
        step: np.ndarray = -np.linalg.lstsq(lhs, g, rcond=None)[0]
        return step

    def rms(test_rows: np.ndarray, step: np.ndarray) -> float:
        r = (r0[test_rows] + J[test_rows] @ step).reshape(-1, width)[:, :3]
        return float(np.sqrt(np.mean(np.sum(r**2, axis=1))) * 1e3)

    # each split's normal equations once (a band's fit: the training rows minus the band's)
    bands = extrapolation_bands(data.q)
    M_tr, g_tr = normal(train_idx)
    va_rows = rows_of(val_idx)
    splits = []
    for _label, band in bands:
        M_b, g_b = normal(np.intersect1d(train_idx, band))
        splits.append((M_tr - M_b, g_tr - g_b, rows_of(band)))
    table = []
    for weight in (*WEIGHTS, WITHOUT):
        blocks = rms(va_rows, solve(M_tr, g_tr, weight))
        band_rms = [rms(rows, solve(M, g, weight)) for M, g, rows in splits]
        band_ms = float(np.mean(np.square(band_rms))) if band_rms else blocks**2
        table.append(
            {
                "weight": weight,
                "blocks_pos_rms_mm": blocks,
                "bands_pos_rms_mm": float(np.sqrt(band_ms)),
                "score": float(np.sqrt(0.5 * (blocks**2 + band_ms))),
            }
        )
    without = table.pop()
    best = min(table, key=lambda e: e["score"])
    return PriorChoice(
        float(best["weight"]),
        table,
        without["bands_pos_rms_mm"],
        without["blocks_pos_rms_mm"],
    )
