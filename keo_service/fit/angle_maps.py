"""Joint-angle error maps: each joint's angle error as a piecewise-linear function of that
joint's own angle (encoder or gear transmission error, a ripple of tens of cycles per turn).

The maps are small (milliradians), so the residual is linear in them to first order:
r(q) ~ r0 + sum_j dr/dq_j * m_j(q_j), with m_j a hat-function (linear interpolation) basis on
knots every `spacing` rad over the training range. The registration, the geometry and every
other kept parameter are solved together with the maps in the same linear system (their
Jacobian columns beside the maps'), with a penalty on the maps' second differences
(smoothness) and a tiny ridge (a constant or linear map is the same as a joint offset or a
scale and would otherwise be undetermined). Knot spacing and smoothing weight are chosen by
cross-validation over blocks of the training poses. Outside its knots a map fades to zero (each
joint on its own) over a distance chosen on held-out bands at the ends of each joint's range
(choose_taper); the live estimator flags such samples (`outside_calibrated_range`).

One residual evaluation per joint gives every pose's derivative at once (each pose depends
only on its own joints), so building the system costs a few evaluations, and each solve is a
small dense one: cross-validating a grid of settings takes seconds, not minutes.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from scipy import sparse
from scipy.linalg import block_diag, cho_factor, cho_solve

from keo_service.core.model_corrections import MAP_TAPER_RAD, taper_weight
from keo_service.fit.analysis import KEEP_MARGIN, describe_remaining
from keo_service.fit.effects import JointMaps
from keo_service.fit.model import Data, Model, numeric_jacobian, stats
from keo_service.fit.model import fit as robust_fit
from keo_service.fit.prior import extrapolation_bands, prior_rows

SPACINGS = (0.02, 0.03, 0.05, 0.075, 0.1)  # rad between knots
SMOOTHING = (1e-3, 1e-2, 1e-1, 1.0, 10.0)  # weight of the second-difference penalty
RIDGE = 1e-9  # relative to the mean diagonal of the normal equations
CONSTRAINT = 1e3  # weight that keeps each map's mean and slope at zero
FOLDS = 4
# Whether the kept effects are solved again beside the maps (each held by its prior,
# fit.prior; then the maps fitted again alone on top of them, maps_on_top) or left as identified
# (only the registration solved with the maps, the maps the residual on top) is chosen per
# analysis ("auto"), like every effect, by the held-out blocks (choose_mode);
# "with" / "without" force one. Left as identified, the geometry stays biased by what only the
# maps carry (a simulated ripple then shows in the maps of joints without one); re-solved, the
# effects and maps can trade on the calibration poses (docs/analyze.md gives both ways on the
# UR10 series: neither wins on both).
EFFECTS_WITH_MAPS = "auto"
# a way of fitting that solves the effects again beside the maps is kept over leaving them as
# identified only when it lowers the judged error by this share, as every effect (choose_mode)
MODE_MARGIN = KEEP_MARGIN
MIN_POSES_PER_KNOT = 2.0  # a joint whose range gives fewer poses per knot gets no map
MIN_SUPPORT = 2  # poses within one spacing of a knot, else the knot is left out (a gap)
# the fade lengths outside the knots (rad) choose_taper judges: from cut at the edge to about
# a strain-wave ripple's period
TAPERS = (0.0, 0.025, 0.05, 0.1, 0.2, 0.4)


@dataclasses.dataclass
class MapFit:
    model: Model  # the model with the maps appended
    x: np.ndarray
    se: np.ndarray  # standard errors of all parameters (maps last)
    spacing: float
    smoothing: float
    cv_rms_mm: float
    parameters: int  # map values fitted


def knots_for(q: np.ndarray, spacing: float) -> tuple[np.ndarray, ...]:
    """Knots every `spacing` rad over each joint's range in `q`, where the data are: a knot
    whose neighbourhood (its hat function's support) holds fewer than MIN_SUPPORT poses is
    left out, so across a gap in the data the map is the straight line between the knots on
    either side instead of values only the smoothing penalty decides (with fine knots and
    light smoothing those are ill-determined). None for a joint that hardly moves."""
    out = []
    for j in range(q.shape[1]):
        lo, hi = float(q[:, j].min()), float(q[:, j].max())
        n = int(np.ceil((hi - lo) / spacing)) + 1
        if hi - lo < 2 * spacing or q.shape[0] < MIN_POSES_PER_KNOT * n:
            out.append(np.empty(0))
            continue
        grid = np.linspace(lo, lo + (n - 1) * spacing, n)
        qs = np.sort(q[:, j])
        support = np.searchsorted(qs, grid + spacing) - np.searchsorted(qs, grid - spacing)
        keep = support >= MIN_SUPPORT
        keep[0] = keep[-1] = True  # the range's ends: the data's first and last angle
        out.append(grid[keep] if keep.sum() >= 3 else np.empty(0))
    return tuple(out)


def hat_weights(
    q: np.ndarray, knots: np.ndarray, taper: float = MAP_TAPER_RAD
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per angle the left knot's index and the two knots' weights of linear interpolation,
    both scaled by the taper (`taper` rad) outside the knots (as
    core.model_corrections.tapered_interp)."""
    qc = np.clip(q, knots[0], knots[-1])
    i = np.clip(np.searchsorted(knots, qc) - 1, 0, knots.size - 2)
    w = (qc - knots[i]) / (knots[i + 1] - knots[i])
    fade = taper_weight(q, float(knots[0]), float(knots[-1]), taper)
    return i, (1.0 - w) * fade, w * fade


def hat_basis(q: np.ndarray, knots: np.ndarray, taper: float = MAP_TAPER_RAD) -> np.ndarray:
    """(N, K) weights of linear interpolation between knots (fading to zero outside)."""
    i, left, right = hat_weights(q, knots, taper)
    out = np.zeros((q.size, knots.size))
    rows = np.arange(q.size)
    out[rows, i] = left
    out[rows, i + 1] = right
    return out


@dataclasses.dataclass
class _Linearized:
    r0: np.ndarray  # (N, width) residuals at x
    joint_grad: list[np.ndarray]  # per joint (N, width): d residual / d q_j
    J: np.ndarray  # (N * width, P) Jacobian of the model's own parameters


def linearize(
    model: Model, x: np.ndarray, data: Data, tau: np.ndarray, effects_free: bool = False
) -> _Linearized:
    """The residual, its derivative by each joint's angle, and its Jacobian by the
    registration (by every parameter with `effects_free`; else the effects' columns are
    zero, so a solve leaves them where they are)."""
    r0 = model.residuals(x, data, tau)
    width = r0.size // data.n
    grads = []
    h = 1e-6
    for j in range(model.chain.nq):
        q = data.q.copy()
        q[:, j] += h
        shifted = dataclasses.replace(data, q=q)
        grads.append(((model.residuals(x, shifted, tau) - r0) / h).reshape(data.n, width))
    # the maps are the residual on top of the physical effects: only the registration is
    # solved with them (the effects' columns left zero, so their step is zero); solving the
    # effects beside the maps let both grow far beyond the robot's whole error and cancel
    # (docs/analyze.md)
    k = x.size if effects_free else model.n_reg
    J_reg = numeric_jacobian(
        lambda z: model.residuals(np.concatenate([z, x[k:]]), data, tau), x[:k], r0
    )
    J = np.zeros((r0.size, x.size))
    J[:, :k] = J_reg
    row_w = data.row_weights(width)
    if row_w is not None:  # weighted rows: the linear system and its errors weighted alike
        r0, J = r0 * row_w, J * row_w[:, None]
        grads = [g * row_w.reshape(data.n, width) for g in grads]
    return _Linearized(r0.reshape(data.n, width), grads, J)


@dataclasses.dataclass
class _Design:
    """The linear system of the maps and the model's own parameters: residual rows
    r + J dx + B dm, J dense (rows, P), B sparse (rows, K): each row depends on two knots
    of each joint's map, so B holds 2 x joints values a row and its normal matrix is built
    sparse; only the (P + K)^2 normal equations are dense."""

    J: np.ndarray
    B: sparse.csr_matrix
    r: np.ndarray

    def rows(self, idx: np.ndarray, width: int) -> _Design:
        """The rows of poses `idx`."""
        rows = (idx[:, None] * width + np.arange(width)).ravel()
        return _Design(self.J[rows], self.B[rows], self.r[rows])

    def normal(self) -> tuple[np.ndarray, np.ndarray]:
        """A^T A (dense) and A^T r of A = [J B]."""
        P, K = self.J.shape[1], self.B.shape[1]
        M = np.empty((P + K, P + K))
        M[:P, :P] = self.J.T @ self.J
        BtJ = np.asarray(self.B.T @ self.J)
        M[P:, :P] = BtJ
        M[:P, P:] = BtJ.T
        M[P:, P:] = (self.B.T @ self.B).toarray()
        g = np.concatenate([self.J.T @ self.r, np.asarray(self.B.T @ self.r)])
        return M, g

    def apply(self, step: np.ndarray) -> np.ndarray:
        """The residual rows after the step."""
        P = self.J.shape[1]
        out: np.ndarray = self.r + self.J @ step[:P] + self.B @ step[P:]
        return out


def _design(
    lin: _Linearized, q: np.ndarray, knots: Sequence[np.ndarray], taper: float = MAP_TAPER_RAD
) -> _Design:
    n, width = lin.r0.shape
    rows, cols, vals = [], [], []
    offset = 0
    row_of = (np.arange(n)[:, None] * width + np.arange(width)).ravel()  # pose-major
    for j, kn in enumerate(knots):
        if not kn.size:
            continue
        i, left, right = hat_weights(q[:, j], kn, taper)
        grad = lin.joint_grad[j]  # (n, width)
        for col, weight in ((i, left), (i + 1, right)):
            rows.append(row_of)
            cols.append(np.repeat(offset + col, width))
            vals.append((grad * weight[:, None]).ravel())
        offset += kn.size
    B = sparse.csr_matrix(
        (
            np.concatenate(vals) if vals else np.zeros(0),
            (
                np.concatenate(rows) if rows else np.zeros(0, dtype=int),
                np.concatenate(cols) if cols else np.zeros(0, dtype=int),
            ),
        ),
        shape=(n * width, offset),
    )
    return _Design(lin.J, B, lin.r0.ravel())


def _penalty(n_other: int, knots: Sequence[np.ndarray]) -> np.ndarray:
    """Second differences of each map, and (weighted far above them) each map's mean and
    slope over its knots: a constant or linear map is a joint offset or a scale error, which
    the other parameters already carry, so the maps keep only what those cannot express."""
    blocks = []
    for kn in knots:
        if kn.size >= 3:
            D = np.zeros((kn.size - 2 + 2, kn.size))
            for i in range(kn.size - 2):
                D[i, i : i + 3] = (1.0, -2.0, 1.0)
            centred = (kn - kn.mean()) / max(float(np.ptp(kn)), 1e-9)
            D[-2] = CONSTRAINT / kn.size
            D[-1] = CONSTRAINT * centred / kn.size
            blocks.append(D)
        elif kn.size:
            blocks.append(np.zeros((0, kn.size)))
    D = block_diag(*blocks) if blocks else np.zeros((0, 0))
    P = np.zeros((D.shape[0], n_other + D.shape[1]))
    P[:, n_other:] = D
    return P


def _normal(AtA: np.ndarray, PtP: np.ndarray, smoothing: float) -> np.ndarray:
    ridge = RIDGE * float(np.trace(AtA)) / AtA.shape[0]
    normal: np.ndarray = AtA + smoothing * PtP + ridge * np.eye(AtA.shape[0])
    return normal


def _solve(AtA: np.ndarray, g: np.ndarray, PtP: np.ndarray, smoothing: float) -> np.ndarray:
    """The penalised least-squares step: Cholesky of the normal equations (symmetric
    positive definite with the ridge), least squares if rounding breaks that."""
    M = _normal(AtA, PtP, smoothing)
    try:
        step: np.ndarray = -cho_solve(cho_factor(M), g)
    except np.linalg.LinAlgError:
        step = -np.linalg.lstsq(M, g, rcond=None)[0]
    return step


def _pos_rms_mm(r: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(r[:, :3] ** 2, axis=1))) * 1e3)


def cv_folds(n: int, session: np.ndarray | None = None) -> np.ndarray:
    """The cross-validation fold (0..FOLDS-1) of each training pose: interleaved blocks, like
    the held-out split (analysis.split_data). Contiguous quarters would make each fold an
    extrapolation where poses are ordered by configuration (UR10 Series B) and choose the
    settings for the wrong task. Pooled sessions are blocked each on its own (1/40 of its
    poses a block, as one recording alone): blocks of the pooled count would span a small
    session in a few large chunks, again an extrapolation that chose far coarser knots than
    either session alone (docs/results/ur10_notes.md).
    `session`: each pose's recording (None: one)."""
    if session is None:
        return (np.arange(n) // max(2, n // 40)) % FOLDS
    fold = np.empty(session.size, dtype=int)
    for s in np.unique(session):
        rows = np.flatnonzero(session == s)
        fold[rows] = (np.arange(rows.size) // max(2, rows.size // 40)) % FOLDS
    return fold


def _prior_terms(
    prior: np.ndarray | None, x: np.ndarray, size: int
) -> tuple[np.ndarray, np.ndarray]:
    """The prior's part of the normal equations of [x step; map values] (size square): the
    prior residual P (x + dx) adds P^T P to the matrix and P^T P x to the gradient."""
    M = np.zeros((size, size))
    g = np.zeros(size)
    if prior is not None:
        PtP = prior.T @ prior
        M[: x.size, : x.size] = PtP
        g[: x.size] = PtP @ x
    return M, g


def fit_maps(
    model: Model,
    x: np.ndarray,
    train: Data,
    tau: np.ndarray,
    spacings: Sequence[float] = SPACINGS,
    smoothings: Sequence[float] = SMOOTHING,
    joints: Sequence[int] | None = None,
    prior: np.ndarray | None = None,
) -> MapFit | None:
    """Maps for every joint that moved (or `joints`), spacing and smoothing chosen by
    cross-validation over blocks of the training poses; None when no joint can carry one.
    `prior`: the kept effects' prior rows (fit.prior, on x): with it the effects are solved
    beside the maps, each held near its physical size by its prior; without it only the
    registration is solved with the maps."""
    lin = linearize(model, x, train, tau, effects_free=prior is not None)
    width = lin.r0.shape[1]
    fold = cv_folds(train.n, train.session)
    best: tuple[float, float, float, tuple[np.ndarray, ...]] | None = None
    for spacing in spacings:
        knots = knots_for(train.q, spacing)
        if joints is not None:
            knots = tuple(k if j in joints else np.empty(0) for j, k in enumerate(knots))
        if not any(k.size for k in knots):
            continue
        P = _penalty(x.size, knots)
        PtP = P.T @ P
        design = _design(lin, train.q, knots)
        fixed_M, fixed_g = _prior_terms(prior, x, PtP.shape[0])
        # each fold's normal equations once; a fold's training set is the total minus it
        parts = [design.rows(np.flatnonzero(fold == f), width) for f in range(FOLDS)]
        normals = [part.normal() for part in parts]
        M_all = sum(m for m, _g in normals)
        g_all = sum(g for _m, g in normals)
        for smoothing in smoothings:
            errors = []
            for f in range(FOLDS):
                step = _solve(
                    M_all - normals[f][0] + fixed_M, g_all - normals[f][1] + fixed_g, PtP, smoothing
                )
                errors.append(parts[f].apply(step).reshape(-1, width))
            cv = _pos_rms_mm(np.vstack(errors))
            if best is None or cv < best[0]:
                best = (cv, spacing, smoothing, knots)
    if best is None:
        return None
    cv, spacing, smoothing, knots = best
    design = _design(lin, train.q, knots)
    P = _penalty(x.size, knots)
    PtP = P.T @ P
    AtA, g = design.normal()
    fixed_M, fixed_g = _prior_terms(prior, x, PtP.shape[0])
    AtA, g = AtA + fixed_M, g + fixed_g
    step = _solve(AtA, g, PtP, smoothing)
    n_maps = sum(k.size for k in knots)
    trial = dataclasses.replace(model, effects=[*model.effects, JointMaps(knots)])
    x_new = np.concatenate([x, np.zeros(n_maps)]) + step
    # standard errors: the penalised normal equations' inverse, scaled by the residual variance
    resid = design.apply(step)
    dof = max(1, resid.size - AtA.shape[1])
    s2 = float(resid @ resid) / dof
    M_inv = np.linalg.inv(_normal(AtA, PtP, smoothing))
    cov = M_inv @ AtA @ M_inv * s2
    se = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    trial.x = x_new
    return MapFit(trial, x_new, se, spacing, smoothing, cv, n_maps)


def fit_maps_either(
    model: Model,
    x: np.ndarray,
    train: Data,
    tau: np.ndarray,
    prior: np.ndarray | None,
    judge: Callable[[MapFit], float] | None = None,
) -> tuple[MapFit | None, dict[str, Any]]:
    """The maps with the kept effects solved again beside them under their priors (`prior`:
    their rows; None: the effects have no prior, so they are left as identified), then the
    maps fitted again on top of the effects so solved (`maps_on_top`), and with the effects
    left as identified; per EFFECTS_WITH_MAPS, chosen by `choose_mode` on the scores of
    `judge` ("auto"; keo judges every effect on the held-out blocks; None: the
    cross-validated error over the training blocks), or the one forced. Returns the fit and
    what was chosen, with every figure."""
    tried: dict[str, MapFit | None] = {}
    if EFFECTS_WITH_MAPS in ("auto", "without") or prior is None:
        tried["without"] = fit_maps(model, x, train, tau)
    if EFFECTS_WITH_MAPS in ("auto", "with") and prior is not None:
        tried["with"] = fit_maps(model, x, train, tau, prior=prior)
        if tried["with"] is not None:
            tried["with_on_top"] = maps_on_top(tried["with"], train, tau)
    found = {k: f for k, f in tried.items() if f is not None}
    if not found:
        return None, {}
    score = {k: (judge(f) if judge is not None else f.cv_rms_mm) for k, f in found.items()}
    chosen = choose_mode(score)
    return found[chosen], {
        "re_solved": chosen != "without",
        "maps_on_top": chosen == "with_on_top",
        "judged_on": "cross-validation" if judge is None else "held-out blocks",
        "pos_rms_mm": score,
        "cv_pos_rms_mm": {k: f.cv_rms_mm for k, f in found.items()},
    }


def choose_mode(score: dict[str, float]) -> str:
    """Which way of fitting the maps to keep, from each way's held-out figure: the effects
    left as identified ("without") unless a way that solves them again beside the maps is
    lower by MODE_MARGIN. Solving the effects again is freedom added to the model, and like
    every effect it must earn its place: on UR10 Series B it won by 0.06 % on the held-out
    blocks and carried to Series A 12 % worse (docs/analyze.md)."""
    best = min(score, key=lambda k: score[k])
    earned = "without" not in score or score[best] <= (1.0 - MODE_MARGIN) * score["without"]
    return best if earned else "without"


def maps_on_top(joint: MapFit, train: Data, tau: np.ndarray) -> MapFit | None:
    """The maps fitted again, alone, on top of the effects as the joint solve left them (only
    the registration solved beside them), their smoothing chosen again by cross-validation at
    the joint solve's knot spacing. Solved beside the effects, the maps' smoothing is chosen
    for the pair and comes out heavy (the effects move with every map value); the residual
    the settled effects leave has finer structure that the maps then carry (docs/analyze.md:
    on UR10 Series A, lower held out and no worse carried to Series B)."""
    effects = joint.model.effects[:-1]
    x = joint.x[: joint.x.size - joint.parameters]
    settled = dataclasses.replace(joint.model, effects=list(effects), x=x)
    return fit_maps(settled, x, train, tau, spacings=(joint.spacing,))


def held_out_band(data: Data, joint: int = 0, fraction: float = 0.2) -> tuple[np.ndarray, ...]:
    """A second split: the poses whose `joint` angle lies in the middle `fraction` of its
    range are held out (a region of the workspace the fit never saw)."""
    q = data.q[:, joint]
    lo, hi = np.quantile(q, [0.5 - fraction / 2, 0.5 + fraction / 2])
    band = (q >= lo) & (q <= hi)
    return np.flatnonzero(~band), np.flatnonzero(band)


def map_records(fit: MapFit, joint_names: Sequence[str]) -> list[dict[str, Any]]:
    """Each joint's map as a record: knots, values and standard errors (rad), its range."""
    maps = fit.model.find(JointMaps)
    assert maps is not None
    k = fit.x.size - fit.parameters
    return maps.records(fit.x[k:], fit.se[k:], joint_names)


def variance_inflation(
    lin: _Linearized,
    q: np.ndarray,
    knots: Sequence[np.ndarray],
    smoothing: float,
    n_other: int,
) -> list[float | None]:
    """Per joint, how much solving every joint's map together inflates the variance of that
    joint's map values over solving its map alone beside the registration: the mean over its
    knots of the ratio of the two variances (rows of `lin`, the penalised normal equations the
    maps are fitted with). 1: the poses separate the joint's angle error from the other
    joints'; large: the poses move joints together so that the data cannot tell whose error it
    is, and the split between them is set by the smoothing. None for a joint without a map."""
    design = _design(lin, q, knots)
    AtA, _g = design.normal()
    P = _penalty(n_other, knots)
    normal = _normal(AtA, P.T @ P, smoothing)

    def variances(idx: np.ndarray) -> np.ndarray:
        sub = normal[np.ix_(idx, idx)]
        inverse: np.ndarray = cho_solve(cho_factor(sub), np.eye(idx.size))
        return np.diag(inverse)

    every = variances(np.arange(normal.shape[0]))
    out: list[float | None] = []
    start = n_other
    for kn in knots:
        if not kn.size:
            out.append(None)
            continue
        own = np.arange(start, start + kn.size)
        alone = variances(np.concatenate([np.arange(n_other), own]))[n_other:]
        out.append(float(np.mean(every[own] / alone)))
        start += kn.size
    return out


def _linear_rms(
    lin: _Linearized,
    q: np.ndarray,
    knots: Sequence[np.ndarray],
    fit_idx: np.ndarray,
    test_idx: np.ndarray,
    smoothing: float,
    n_other: int,
    with_maps: bool,
) -> float:
    """Held-out position RMS of a linear refit on `fit_idx` rows, judged on `test_idx`."""
    width = lin.r0.shape[1]
    use = knots if with_maps else tuple(np.empty(0) for _ in knots)
    design = _design(lin, q, use)
    P = _penalty(n_other, use)
    AtA, g = design.rows(fit_idx, width).normal()
    step = _solve(AtA, g, P.T @ P, smoothing)
    return _pos_rms_mm(design.rows(test_idx, width).apply(step).reshape(-1, width))


def try_maps(
    analysis: Any,
    data: Data,
    train_idx: np.ndarray,
    val_idx: np.ndarray,
    keep_margin: float,
    joint_names: Sequence[str],
    say: Any = None,
) -> None:
    """Try joint-angle maps after the other effects: kept (appended to `analysis`) only if
    they lower the held-out error by `keep_margin` on the held-out blocks and on a held-out
    band of the first joint's angle. The report gets the maps' entry either way, with the
    parameter count, both splits and a learning curve."""
    say = say or (lambda _m: None)
    model, x = analysis.model, analysis.x
    chain = model.chain
    train, val = data.subset(train_idx), data.subset(val_idx)
    tau_tr, tau_va = chain.gravity_torques(train.q), chain.gravity_torques(val.q)
    say("trying joint_maps (cross-validating knot spacing and smoothing)")
    noise = analysis.report["registration"]["noise_estimate_mm"] * 1e-3
    prior = prior_rows(model, analysis.report.get("prior_weights", {}), noise)
    fit, effects_mode = fit_maps_either(
        model, x, train, tau_tr, prior, lambda f: stats(f.model, f.x, val, tau_va).judged_mm
    )
    if fit is None:
        say("joint_maps: no joint moves enough to carry a map")
        return
    if model.sessions > 1 and model.tools == 1:
        model, x, fit = _session_tools(analysis, fit, data, train_idx, val_idx, keep_margin, say)
    lin = linearize(model, x, data, chain.gravity_torques(data.q))
    taper = choose_taper(lin, data.q, train_idx, fit.spacing, fit.smoothing, x.size)
    fit = with_taper(fit, taper["taper_rad"])
    before = stats(model, x, val, tau_va)
    after = stats(fit.model, fit.x, val, tau_va)
    gain = 1 - after.judged_mm / before.judged_mm
    band, band_before, band_after, curve = _band_and_curve(lin, x, fit, data, train_idx, val_idx)
    band_gain = 1 - band_after / band_before
    entry: dict[str, Any] = {
        "name": JointMaps.name,
        "description": JointMaps.description,
        "parameters": {"maps": map_records(fit, joint_names)},
        "parameter_count": fit.parameters,
        "knot_spacing_rad": fit.spacing,
        "smoothing": fit.smoothing,
        "cv_pos_rms_mm": fit.cv_rms_mm,
        "effects_beside_maps": effects_mode,
        "taper": taper,
        "train": stats(fit.model, fit.x, train, tau_tr).as_dict(),
        "validation": after.as_dict(),
        "held_out_improvement_pct": 100 * gain,
        "band_split": {
            "joint": joint_names[0] if joint_names else "joint_1",
            "held_out_poses": int(band.size),
            "pos_rms_mm_before": band_before,
            "pos_rms_mm_after": band_after,
            "improvement_pct": 100 * band_gain,
        },
        "learning_curve": curve,
    }
    if gain >= keep_margin and band_gain >= keep_margin:
        analysis.model, analysis.x = fit.model, fit.x
        analysis.report["effects"].append(entry)
        analysis.report["final"]["validation"] = after.as_dict()
        analysis.report["final"]["train"] = entry["train"]
        # the verdict and the floor were for the model before the maps
        describe_remaining(analysis.report, fit.model, fit.x, data)
        if fit.model.tools > 1:  # a mount per session came with the maps
            reg = analysis.report["registration"]
            reg["T_ns"] = fit.model.mount(fit.x).tolist()
            reg["T_ns_sessions"] = [fit.model.mount(fit.x, t).tolist() for t in range(model.tools)]
        say(f"kept joint_maps: held-out position RMS {after.pos_rms_mm:.4f} mm")
    else:
        if model.tools > analysis.model.tools:  # the mounts came with the maps: both dropped
            analysis.report["registration"]["tools"]["with_effects_and_maps"]["per_session"] = False
        analysis.report["rejected"].append(entry)
        say(f"not kept joint_maps: held-out {100 * gain:+.1f} %, band {100 * band_gain:+.1f} %")


def with_taper(fit: MapFit, taper: float) -> MapFit:
    """`fit` with its maps fading over `taper` rad outside their knots (the values as
    fitted: the training poses lie within the knots, so the fit does not depend on it)."""
    maps = fit.model.effects[-1]
    assert isinstance(maps, JointMaps)
    effects = [*fit.model.effects[:-1], JointMaps(maps.knots, taper)]
    return dataclasses.replace(fit, model=dataclasses.replace(fit.model, effects=effects))


def choose_taper(
    lin: _Linearized,
    q: np.ndarray,
    train_idx: np.ndarray,
    spacing: float,
    smoothing: float,
    n_other: int,
    tapers: Sequence[float] = TAPERS,
) -> dict[str, Any]:
    """The distance over which the maps fade to zero outside their knots, chosen on the
    extrapolation bands (fit.prior.extrapolation_bands of the training poses: the lowest and
    highest part of each joint's range): per band the maps (at the chosen knot spacing and
    smoothing) and the registration are solved on the training poses outside it, linearized
    in `lin`, so the band lies beyond the knots of its own joint, and the band's poses are
    judged at each fade length; the length with the lowest mean square over the bands is
    kept. Only the band's own joint is outside there, so this judges what the fade does where
    a map is carried to angles it never saw. Why per analysis: the right length depends on
    how fast the robot's error changes beyond the range (a gear ripple's period, a slope), and
    the only poses that speak for it without being the figures' own held-out poses are
    these. No bands (no joint moves enough): the default, MAP_TAPER_RAD."""
    width = lin.r0.shape[1]
    bands = extrapolation_bands(q[train_idx])
    per_taper: dict[float, list[float]] = {float(t): [] for t in tapers}
    rows_out = []
    for label, rows in bands:
        band = train_idx[rows]
        fit_idx = np.setdiff1d(train_idx, band)
        knots = knots_for(q[fit_idx], spacing)
        if not any(k.size for k in knots):
            continue
        P = _penalty(n_other, knots)
        AtA, g = _design(lin, q, knots).rows(fit_idx, width).normal()
        step = _solve(AtA, g, P.T @ P, smoothing)
        sub = _Linearized(
            lin.r0[band],
            [grad[band] for grad in lin.joint_grad],
            lin.J[(band[:, None] * width + np.arange(width)).ravel()],
        )
        entry: dict[str, Any] = {"band": label, "poses": int(band.size)}
        for t, squares in per_taper.items():
            r = _design(sub, q[band], knots, t).apply(step).reshape(-1, width)
            rms = _pos_rms_mm(r)
            squares.append(rms**2)
            entry[f"{t:g}"] = rms
        rows_out.append(entry)
    if not rows_out:
        return {"taper_rad": MAP_TAPER_RAD, "judged_on": "default (no extrapolation bands)"}
    score = {t: float(np.sqrt(np.mean(ms))) for t, ms in per_taper.items()}
    best = min(score, key=lambda t: score[t])
    return {
        "taper_rad": best,
        "judged_on": "extrapolation bands (each band's joint beyond the maps' knots)",
        "bands_pos_rms_mm": {f"{t:g}": v for t, v in score.items()},
        "per_band_pos_rms_mm": rows_out,
    }


def _band_and_curve(
    lin: _Linearized,
    x: np.ndarray,
    fit: MapFit,
    data: Data,
    train_idx: np.ndarray,
    val_idx: np.ndarray,
) -> tuple[np.ndarray, float, float, list[dict[str, Any]]]:
    """The maps' second split (a band of joint 1's angle held out, a region of the workspace:
    its poses and RMS without and with the maps, linearized at the model before the maps,
    `lin`) and their learning curve."""
    keep_band, band = held_out_band(data)
    knots = knots_for(data.q[keep_band], fit.spacing)
    band_before = _linear_rms(lin, data.q, knots, keep_band, band, fit.smoothing, x.size, False)
    band_after = _linear_rms(lin, data.q, knots, keep_band, band, fit.smoothing, x.size, True)
    curve = []
    for share in (0.25, 0.5, 0.75, 1.0):
        sub = train_idx[: max(10, int(share * train_idx.size))]
        kn = knots_for(data.q[sub], fit.spacing)
        rms = _linear_rms(lin, data.q, kn, sub, val_idx, fit.smoothing, x.size, True)
        curve.append({"train_poses": int(sub.size), "held_out_pos_rms_mm": rms})
    return band, band_before, band_after, curve


def session_rms(model: Model, x: np.ndarray, data: Data, idx: np.ndarray) -> list[float]:
    """Position RMS (mm) of each session's rows among `idx`."""
    out = []
    for rows in data.session_rows(model.sessions):
        mine = data.subset(np.intersect1d(idx, rows))
        out.append(stats(model, x, mine, model.chain.gravity_torques(mine.q)).pos_rms_mm)
    return out


def own_tools(
    model: Model,
    x: np.ndarray,
    train: Data,
    noise: float,
    weights: dict[str, float] | None = None,
) -> tuple[Model, np.ndarray]:
    """`model` with a sensor mount per session (each starting from the shared one), fitted
    robustly on the training rows with everything else it holds."""
    k = 6 * model.sessions
    size = 3 if model.position_only else 6
    tool = x[k : k + size]
    x0 = np.concatenate([x[:k], np.tile(tool, model.sessions), x[k + size :]])
    own = Model(
        model.chain,
        model.position_only,
        list(model.effects),
        x0,
        dict(model.basis),
        model.temperature_ref,
        model.time_ref,
        model.sessions,
        model.sessions,
    )
    prior = prior_rows(own, weights or {}, noise)  # the effects' priors, as in their own fit
    tau = model.chain.gravity_torques(train.q)
    return own, robust_fit(own, train, tau, x0, noise, prior=prior).x


def _session_tools(
    analysis: Any,
    shared: MapFit,
    data: Data,
    train_idx: np.ndarray,
    val_idx: np.ndarray,
    keep_margin: float,
    say: Any,
) -> tuple[Model, np.ndarray, MapFit]:
    """Several sessions: a sensor mount per session judged again with the effects and the maps
    (at the 0.1 mm level the nominal model's judgement cannot see): kept if some session's
    held-out error falls by `keep_margin` and none rises (each session judged on its own
    held-out blocks). Returns the model before the maps, its parameters and the maps' fit."""
    model, x = analysis.model, analysis.x
    train = data.subset(train_idx)
    noise = analysis.report["registration"]["noise_estimate_mm"] * 1e-3
    weights = analysis.report.get("prior_weights", {})
    own, x_own = own_tools(model, x, train, noise, weights)
    prior = prior_rows(own, weights, noise)
    fit, _mode = fit_maps_either(own, x_own, train, own.chain.gravity_torques(train.q), prior)
    before = session_rms(shared.model, shared.x, data, val_idx)
    after = before if fit is None else session_rms(fit.model, fit.x, data, val_idx)
    gains = [1 - a / b for a, b in zip(after, before, strict=True)]
    kept = fit is not None and max(gains) >= keep_margin and min(gains) >= 0.0
    tools = analysis.report["registration"].setdefault("tools", {})
    tools["with_effects_and_maps"] = {
        "held_out_pos_rms_mm_shared": before,
        "held_out_pos_rms_mm_per_session": after,
        "per_session": bool(kept),
    }
    changes = ", ".join(f"{100 * g:+.1f} %" for g in gains)
    if not kept or fit is None:
        say(f"a sensor mount per session, with the maps: held-out change {changes}; not kept")
        return model, x, shared
    say(f"a sensor mount per session, with the maps: held-out change {changes}; kept")
    return own, x_own, fit
