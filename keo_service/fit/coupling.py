"""Effects across joints: joint j's angle error as a smooth function of another joint k's
angle (a gear train that couples a wrist's angle to the next one's, a parallelogram linkage).

Tried after the joint maps, and only where the residual points at it: joint k's angle
explains part of what remains (binned R^2 above PROPOSE_R2 and five times chance) although
every joint already has its own map. For such a k each other joint j is tried: a linear term
(about the centre of q_k's range) and a piecewise-linear map on knots of q_k, solved linearised
with the tracker registration (the maps' sparse machinery, smoothing chosen by
cross-validation over interleaved blocks of the training poses), then judged with the full
model like every effect: kept only if it lowers the held-out error by the keep margin on the
held-out blocks and on a held-out band of q_k. No I/O.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from scipy import sparse

from keo_service.fit.analysis import Analysis, describe_remaining
from keo_service.fit.angle_maps import (
    FOLDS,
    SMOOTHING,
    _Design,
    _normal,
    _penalty,
    _pos_rms_mm,
    _solve,
    cv_folds,
    hat_basis,
    held_out_band,
    knots_for,
)
from keo_service.fit.effects import Couplings
from keo_service.fit.model import Data, Model, numeric_jacobian, stats

SPACING = 0.1  # rad between a coupling map's knots
PROPOSE_R2 = 0.05  # q_k must explain this share of the residual (and 5x chance) to be tried


class _Lin:
    """The current model linearised on all poses: residual rows, each joint's derivative,
    and the registration's Jacobian (the other parameters stay as they are)."""

    def __init__(self, model: Model, x: np.ndarray, data: Data) -> None:
        tau = model.chain.gravity_torques(data.q)
        r0 = model.residuals(x, data, tau)
        self.width = r0.size // data.n
        self.r0 = r0
        self.grad = []
        h = 1e-6
        for j in range(model.chain.nq):
            q = data.q.copy()
            q[:, j] += h
            shifted = dataclasses.replace(data, q=q)
            self.grad.append(((model.residuals(x, shifted, tau) - r0) / h).reshape(data.n, -1))
        n_reg = model.n_reg

        def reg_only(z: np.ndarray) -> np.ndarray:
            xx = x.copy()
            xx[:n_reg] = z
            return model.residuals(xx, data, tau)

        self.J_reg = numeric_jacobian(reg_only, x[:n_reg].copy(), r0)
        self.session = data.session  # pooled recordings: each blocked alone for the folds
        row_w = data.row_weights(self.width)
        if row_w is not None:  # weighted rows: the linear system and its errors weighted alike
            self.r0 = r0 * row_w
            self.J_reg = self.J_reg * row_w[:, None]
            self.grad = [g * row_w.reshape(data.n, -1) for g in self.grad]


def _design(lin: _Lin, q: np.ndarray, j: int, k: int, knots: np.ndarray) -> _Design:
    """Columns: the registration, the slope (joint j's error per rad of q_k) and the map."""
    centre = 0.5 * (knots[0] + knots[-1])
    g = lin.grad[j]  # (n, width)
    slope = (g * (q[:, k] - centre)[:, None]).reshape(-1, 1)
    B = hat_basis(q[:, k], knots)  # (n, K)
    maps = (g[:, :, None] * B[:, None, :]).reshape(-1, knots.size)
    return _Design(np.hstack([lin.J_reg, slope]), sparse.csr_matrix(maps), lin.r0)


def _fit(
    lin: _Lin, q: np.ndarray, j: int, k: int, knots: np.ndarray, idx: np.ndarray, n_reg: int
) -> tuple[np.ndarray, float, np.ndarray]:
    """Step (registration, slope, map) on poses `idx`, smoothing by cross-validation over
    interleaved blocks; with the step's standard errors."""
    design = _design(lin, q, j, k, knots)
    sub = design.rows(idx, lin.width)
    P = _penalty(n_reg + 1, (knots,))
    PtP = P.T @ P
    fold = cv_folds(idx.size, None if lin.session is None else lin.session[idx])
    parts = [sub.rows(np.flatnonzero(fold == f), lin.width) for f in range(FOLDS)]
    normals = [part.normal() for part in parts]
    M_all = sum(m for m, _g in normals)
    g_all = sum(g for _m, g in normals)
    best: tuple[float, float] | None = None
    for smoothing in SMOOTHING:
        errors = [
            parts[f]
            .apply(_solve(M_all - normals[f][0], g_all - normals[f][1], PtP, smoothing))
            .reshape(-1, lin.width)
            for f in range(FOLDS)
        ]
        cv = _pos_rms_mm(np.vstack(errors))
        if best is None or cv < best[0]:
            best = (cv, smoothing)
    assert best is not None
    AtA, g = sub.normal()
    step = _solve(AtA, g, PtP, best[1])
    resid = sub.apply(step)
    s2 = float(resid @ resid) / max(1, resid.size - AtA.shape[1])
    M_inv = np.linalg.inv(_normal(AtA, PtP, best[1]))
    se = np.sqrt(np.clip(np.diag(M_inv @ AtA @ M_inv) * s2, 0.0, None))
    return step, best[1], se


def _band_rms(
    lin: _Lin, q: np.ndarray, j: int, k: int, keep: np.ndarray, band: np.ndarray, n_reg: int
) -> tuple[float, float]:
    """Held-out RMS on a band of q_k, registration refitted on the rest: without and with the
    coupling (its knots from the rest only)."""
    kn = knots_for(q[keep][:, [k]], SPACING)[0]
    width = lin.width
    base = _Design(lin.J_reg, sparse.csr_matrix((lin.r0.size, 0)), lin.r0)
    AtA, g = base.rows(keep, width).normal()
    step = _solve(AtA, g, np.zeros_like(AtA), 0.0)
    before = _pos_rms_mm(base.rows(band, width).apply(step).reshape(-1, width))
    if kn.size < 3:
        return before, before
    step, _s, _se = _fit(lin, q, j, k, kn, keep, n_reg)
    after = _pos_rms_mm(_design(lin, q, j, k, kn).rows(band, width).apply(step).reshape(-1, width))
    return before, after


def proposed_joints(report: dict[str, Any], nq: int) -> list[int]:
    """The joints k whose angle the residual still correlates with, strongest first."""
    out = []
    for c in report.get("correlations", []):
        m = re.fullmatch(r"q(\d+)", c["variable"])
        if m and c["r2"] > max(PROPOSE_R2, 5 * c["chance"]) and int(m.group(1)) <= nq:
            out.append(int(m.group(1)) - 1)
    return out


def _with_coupling(
    model: Model, x: np.ndarray, pair: tuple[int, int, np.ndarray], values: np.ndarray
) -> tuple[Model, np.ndarray]:
    """The model with one more coupling (merged into its Couplings effect, which goes last)."""
    old = model.find(Couplings)
    effects = [e for e in model.effects if e is not old]
    if old is None:
        keep = x
        pairs: tuple[tuple[int, int, np.ndarray], ...] = (pair,)
        old_values = np.zeros(0)
    else:
        at = model.effects.index(old)
        sizes = model.sizes(model.chain.nq)
        start = model.n_reg + sum(sizes[:at])
        keep = np.concatenate([x[:start], x[start + sizes[at] :]])
        old_values = x[start : start + sizes[at]]
        pairs = (*old.pairs, pair)
    new = Couplings(pairs)
    x_new = np.concatenate([keep, old_values, values])
    trial = Model(
        model.chain,
        model.position_only,
        [*effects, new],
        x_new,
        dict(model.basis),
        model.temperature_ref,
        model.time_ref,
        model.sessions,
        model.tools,
    )
    return trial, x_new


@dataclasses.dataclass(frozen=True)
class _Rows:
    """The poses a coupling is fitted and judged on, with their gravity torques."""

    data: Data
    train_idx: np.ndarray
    train: Data
    val: Data
    tau_tr: np.ndarray
    tau_va: np.ndarray


@dataclasses.dataclass(frozen=True)
class _Tried:
    """The best coupling with joint k's angle: the model with it, its report entry, and its
    held-out RMS and gains on the blocks and the band."""

    j: int  # the joint whose angle error moves with joint k's angle
    model: Model
    x: np.ndarray
    entry: dict[str, Any]
    held_mm: float
    gain: float
    band_gain: float


def try_couplings(
    analysis: Analysis,
    data: Data,
    train_idx: np.ndarray,
    val_idx: np.ndarray,
    keep_margin: float,
    joint_names: Sequence[str],
    say: Callable[[str], None] | None = None,
) -> None:
    """Couplings where the residual points at another joint's angle; kept ones are appended
    to `analysis` (model, report effects, final numbers, verdict), the others reported as
    rejected."""
    say = say or (lambda _m: None)
    model = analysis.model
    ks = proposed_joints(analysis.report, model.chain.nq)
    if not ks:
        return
    val, train = data.subset(val_idx), data.subset(train_idx)
    tau_va, tau_tr = model.chain.gravity_torques(val.q), model.chain.gravity_torques(train.q)
    rows = _Rows(data, train_idx, train, val, tau_tr, tau_va)
    current = stats(model, analysis.x, val, tau_va).judged_mm
    for k in ks:
        knots = knots_for(train.q[:, [k]], SPACING)[0]
        if knots.size < 3:
            continue
        name = _name(joint_names, k)
        say(f"trying couplings with {name}'s angle (the residual correlates with it)")
        best = _best_coupling(analysis.model, analysis.x, rows, k, knots, current, joint_names)
        entry = best.entry
        if best.gain >= keep_margin and best.band_gain >= keep_margin:
            current = best.held_mm
            analysis.model, analysis.x = best.model, best.x
            analysis.report["effects"].append(entry)
            analysis.report["final"]["validation"] = entry["validation"]
            analysis.report["final"]["train"] = entry["train"]
            describe_remaining(analysis.report, best.model, best.x, data)
            text = entry["parameters"]["records"][-1]["text"]
            say(f"kept coupling: {text}; held out {best.held_mm:.4f} mm")
        else:
            analysis.report["rejected"].append(entry)
            say(
                f"not kept coupling of {_name(joint_names, best.j)} with {name}: "
                f"held-out {100 * best.gain:+.1f} %, band {100 * best.band_gain:+.1f} %"
            )


def _name(joint_names: Sequence[str], j: int) -> str:
    return joint_names[j] if j < len(joint_names) else f"joint_{j + 1}"


def _best_coupling(
    model: Model,
    x: np.ndarray,
    rows: _Rows,
    k: int,
    knots: np.ndarray,
    current: float,
    joint_names: Sequence[str],
) -> _Tried:
    """Every other joint's angle error as a function of joint k's angle, each solved
    linearised beside the registration; the one that lowers the held-out blocks most, with
    its band split and report entry."""
    nq, n_reg, data = model.chain.nq, model.n_reg, rows.data
    lin = _Lin(model, x, data)
    tried = []
    for j in range(nq):
        if j == k:
            continue
        step, smoothing, se = _fit(lin, data.q, j, k, knots, rows.train_idx, n_reg)
        values = step[n_reg:]
        x_reg = x.copy()
        x_reg[:n_reg] += step[:n_reg]
        trial, x_new = _with_coupling(model, x_reg, (j, k, knots), values)
        held = stats(trial, x_new, rows.val, rows.tau_va)
        tried.append((held.judged_mm, j, trial, x_new, smoothing, se))
    held_rms, j, trial, x_new, smoothing, se = min(tried, key=lambda t: t[0])
    gain = 1 - held_rms / current
    keep_band, band = held_out_band(data, joint=k)
    band_before, band_after = _band_rms(lin, data.q, j, k, keep_band, band, n_reg)
    band_gain = 1 - band_after / band_before
    effect = trial.find(Couplings)
    assert effect is not None
    n_new = 1 + knots.size
    values_all = x_new[-effect.size(nq) :]
    se_all = np.concatenate([np.zeros(values_all.size - n_new), se[n_reg:]])
    records = effect.records(values_all, se_all, joint_names)
    entry: dict[str, Any] = {
        "name": Couplings.name,
        "description": Couplings.description,
        "parameters": {"records": records[-1:], "couplings": [r["text"] for r in records]},
        "parameter_count": n_new,
        "knot_spacing_rad": SPACING,
        "smoothing": smoothing,
        "train": stats(trial, x_new, rows.train, rows.tau_tr).as_dict(),
        "validation": stats(trial, x_new, rows.val, rows.tau_va).as_dict(),
        "held_out_improvement_pct": 100 * gain,
        "band_split": {
            "joint": _name(joint_names, k),
            "held_out_poses": int(band.size),
            "pos_rms_mm_before": band_before,
            "pos_rms_mm_after": band_after,
            "improvement_pct": 100 * band_gain,
        },
        "others_tried": {_name(joint_names, jj): rms for rms, jj, *_rest in tried if jj != j},
    }
    return _Tried(j, trial, x_new, entry, held_rms, gain, band_gain)
