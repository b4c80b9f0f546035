"""The model `keo analyze` fits: the data it is fitted to, parameters -> predicted sensor
poses, the tracker registration and the robust least-squares fit. No I/O.

Unknowns are packed in one vector: the tracker registration T_bk (translation, rotation
vector), the sensor mount T_ns (6, or the reflector offset: 3), then each kept effect's
parameters (fit.effects). Residuals, per pose: predicted minus measured sensor position (m)
and, for a 6-DoF probe, orientation (rad, scaled by ROT_WEIGHT m/rad). Fitted with scipy's
robust least squares.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, TypeVar

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from keo_service.core.chain import Chain, times_constant_frames
from keo_service.core.errors import KeoError
from keo_service.core.model_corrections import ModelCorrections
from keo_service.core.rotations import log3_many, transposed_times

ROT_WEIGHT = 0.5  # m per rad: 20 um of position ~ 40 urad of orientation
RANK_TOL = 1e-3  # relative singular value below which a direction counts as unidentifiable
# residual rows above which the robust fit solves its steps from the normal equations
# (P x P) instead of an SVD of the whole Jacobian (rows x P) at every step (motion data
# always: their rows are many and the SVD's time grows with them)
LARGE_ROWS = 80_000


class NotIdentifiableError(KeoError):
    """The data cannot determine what was asked (e.g. registration from one moving joint)."""


class Effect(Protocol):
    """What the model needs of an effect."""

    @property
    def name(self) -> str:
        """As in report.json and the config's model.effects."""
        ...

    @property
    def description(self) -> str: ...

    @property
    def reduce(self) -> bool:
        """Fit only the directions the data identifies (fit.model.identifiable_basis)."""
        ...

    def size(self, nq: int) -> int:
        """Parameter count before any reduction."""
        ...

    def usable(self, data: Data) -> bool:
        """Whether these data carry what the effect needs (a column, a direction)."""
        ...

    def correct(self, corr: ModelCorrections, values: np.ndarray) -> ModelCorrections:
        """The joint-level corrections with this effect's values added."""
        ...

    def sensor_offset(self, values: np.ndarray, data: Data, model: Model) -> np.ndarray | None:
        """(N, 3) added to the predicted sensor positions (m), None: the effect acts on the
        joints only."""
        ...

    def records(
        self, values: np.ndarray, se: np.ndarray, joint_names: Sequence[str]
    ) -> list[dict[str, Any]]:
        """The values as named records {joint, parameter, unit, value, se} (SI units)."""
        ...

    def to_config(self, values: np.ndarray, nq: int) -> dict[str, Any]:
        """The [model] keys that carry these values."""
        ...

    def from_config(self, section: Mapping[str, Any]) -> tuple[Effect, np.ndarray]:
        """The effect as saved (with any structure it carries, e.g. knots) and its values."""
        ...


E = TypeVar("E", bound=Effect)


@dataclass
class Data:
    q: np.ndarray  # (N, nq)
    p_ks: np.ndarray  # (N, 3)
    R_ks: np.ndarray | None  # (N, 3, 3) or None (single reflector)
    t: np.ndarray
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    direction: np.ndarray | None = None  # (N, nq) direction of each joint's last move, +-1 / 0
    velocity: np.ndarray | None = None  # (N, nq) joint velocities (motion data), rad/s
    # (N, 3) the tracker's standard deviation of each measured coordinate (m), when known
    sigma: np.ndarray | None = None
    # (N,) the recording (session) each row comes from, 0..S-1; None: one session
    session: np.ndarray | None = None
    # (N,) how much each row counts in the fit and in the held-out judgement (e.g. each
    # session's rows weighted so that the sessions count equally); None: all rows alike
    weight: np.ndarray | None = None

    def subset(self, idx: np.ndarray) -> Data:
        return Data(
            self.q[idx],
            self.p_ks[idx],
            None if self.R_ks is None else self.R_ks[idx],
            self.t[idx],
            {k: v[idx] for k, v in self.extra.items()},
            None if self.direction is None else self.direction[idx],
            None if self.velocity is None else self.velocity[idx],
            None if self.sigma is None else self.sigma[idx],
            None if self.session is None else self.session[idx],
            None if self.weight is None else self.weight[idx],
        )

    def row_weights(self, width: int) -> np.ndarray | None:
        """sqrt(weight) per residual row (pose-major, `width` rows a pose), None: unweighted."""
        if self.weight is None:
            return None
        return np.repeat(np.sqrt(self.weight), width)

    def session_rows(self, sessions: int) -> list[np.ndarray]:
        """Each session's rows (all rows for one session)."""
        if sessions == 1 or self.session is None:
            return [np.arange(self.n)]
        return [np.flatnonzero(self.session == s) for s in range(sessions)]

    @property
    def n(self) -> int:
        return int(self.q.shape[0])


@dataclass
class Stats:
    n: int
    pos_rms_mm: float
    pos_max_mm: float
    rot_rms_mrad: float | None
    # the position RMS with the data's row weights (what effects are judged by; equal to
    # pos_rms_mm without weights); not in the report
    judged_mm: float = 0.0

    def as_dict(self) -> dict[str, Any]:
        return {
            "n": self.n,
            "pos_rms_mm": self.pos_rms_mm,
            "pos_max_mm": self.pos_max_mm,
            "rot_rms_mrad": self.rot_rms_mrad,
        }


@dataclass
class Model:
    chain: Chain
    position_only: bool
    effects: list[Effect]  # kept effects, in order (fit.effects)
    x: np.ndarray  # all parameters
    basis: dict[str, np.ndarray] = field(default_factory=dict)  # identifiable directions
    temperature_ref: float = 0.0
    time_ref: float = 0.0
    # recordings with their own tracker registration (T_bk each), one robot and one tool
    sessions: int = 1
    # sensor mounts: 1 (one tool for every session) or `sessions` (each session its own)
    tools: int = 1
    # the newest chain evaluation: (data, tau, corrections' key, R_bn, p_bn)
    _frames: tuple[Any, ...] | None = field(default=None, repr=False, compare=False)

    @property
    def n_reg(self) -> int:
        """Registration parameters: T_bk per session (translation, rotation vector), then the
        sensor mount T_ns (translation and rotation vector, or the reflector offset)."""
        return 6 * self.sessions + self.tools * (3 if self.position_only else 6)

    @property
    def names(self) -> list[str]:
        return [e.name for e in self.effects]

    def find(self, kind: type[E]) -> E | None:
        """The kept effect of this class, if any."""
        return next((e for e in self.effects if isinstance(e, kind)), None)

    def sizes(self, nq: int) -> list[int]:
        """Fitted parameters per effect (an effect reduced to its identifiable directions
        fits one per direction)."""
        return [
            self.basis[e.name].shape[1] if e.name in self.basis else e.size(nq)
            for e in self.effects
        ]

    def parts(self, x: np.ndarray) -> Iterator[tuple[Effect, np.ndarray]]:
        """Each effect with its values in its own parameters (basis directions expanded)."""
        k = self.n_reg
        for effect, size in zip(self.effects, self.sizes(self.chain.nq), strict=True):
            part = x[k : k + size]
            k += size
            if effect.name in self.basis:
                part = self.basis[effect.name] @ part
            yield effect, part

    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, ModelCorrections]:
        """The first session's T_bk, the mount T_ns and the corrections."""
        corr = ModelCorrections(nq=self.chain.nq)
        for effect, part in self.parts(x):
            corr = effect.correct(corr, part)
        return self.registrations(x)[0], self.mount(x), corr

    def registrations(self, x: np.ndarray) -> list[np.ndarray]:
        """T_bk of each session (4x4)."""
        out = []
        for s in range(self.sessions):
            reg = x[6 * s : 6 * s + 6]
            T_bk = np.eye(4)
            T_bk[:3, :3] = Rotation.from_rotvec(reg[3:6]).as_matrix()
            T_bk[:3, 3] = reg[:3]
            out.append(T_bk)
        return out

    def mount(self, x: np.ndarray, tool: int = 0) -> np.ndarray:
        """T_ns (4x4): the sensor in the flange frame (of session `tool` when each session
        has its own)."""
        size = 3 if self.position_only else 6
        start = 6 * self.sessions + tool * size
        reg = x[start : start + size]
        T_ns = np.eye(4)
        T_ns[:3, 3] = reg[:3]
        if not self.position_only:
            T_ns[:3, :3] = Rotation.from_rotvec(reg[3:6]).as_matrix()
        return T_ns

    def residuals(self, x: np.ndarray, data: Data, tau: np.ndarray) -> np.ndarray:
        """Per pose, predicted minus measured sensor position in the base frame (m) and, for a
        6-DoF probe, ROT_WEIGHT x log3(R_meas^T R_pred); (N * 3) or (N * 6), pose-major."""
        T_bk, T_ns, corr = self.unpack(x)
        # the sensor frame for every pose, component-major: (3, 3, N) and (3, N)
        R_bs, p_bs = self.flange_frames(corr, data, tau)
        if self.tools == 1:
            times_constant_frames(R_bs, p_bs, T_ns)
        else:  # each session's rows through its own mount
            for tool, rows in enumerate(data.session_rows(self.sessions)):
                R_sub, p_sub = R_bs[:, :, rows], p_bs[:, rows]
                times_constant_frames(R_sub, p_sub, self.mount(x, tool))
                R_bs[:, :, rows], p_bs[:, rows] = R_sub, p_sub
        if self.sessions > 1:
            return self._session_residuals(x, data, R_bs, p_bs)
        p_meas = data.p_ks @ T_bk[:3, :3].T + T_bk[:3, 3]
        p_pred = p_bs.T
        for effect, part in self.parts(x):  # effects that move the sensor, not the joints
            offset = effect.sensor_offset(part, data, self)
            if offset is not None:
                p_pred = p_pred + offset
        pos: np.ndarray = p_pred - p_meas
        if self.position_only or data.R_ks is None:
            return pos.ravel()
        # R_meas^T R_bs = R_ks^T (R_bk^T R_bs), one 3x3 product over rows at a time
        R_kb = T_bk[:3, :3].T
        R_ks_pred = np.stack([R_kb @ R_bs[:, k, :] for k in range(3)], axis=1)
        R_err = transposed_times(data.R_ks.transpose(1, 2, 0), R_ks_pred)
        out = np.empty((data.n, 6))
        out[:, :3] = pos
        out[:, 3:] = ROT_WEIGHT * log3_many(R_err)
        return out.ravel()

    def _session_residuals(
        self, x: np.ndarray, data: Data, R_bs: np.ndarray, p_bs: np.ndarray
    ) -> np.ndarray:
        """residuals() for several sessions: each row measured through its session's T_bk."""
        p_pred = p_bs.T
        for effect, part in self.parts(x):
            offset = effect.sensor_offset(part, data, self)
            if offset is not None:
                p_pred = p_pred + offset
        six = not (self.position_only or data.R_ks is None)
        out = np.empty((data.n, 6 if six else 3))
        for T_bk, rows in zip(self.registrations(x), data.session_rows(self.sessions), strict=True):
            if not rows.size:
                continue
            p_meas = data.p_ks[rows] @ T_bk[:3, :3].T + T_bk[:3, 3]
            out[rows, :3] = p_pred[rows] - p_meas
            if six:
                assert data.R_ks is not None
                R_kb = T_bk[:3, :3].T
                R_sub = R_bs[:, :, rows]
                R_ks_pred = np.stack([R_kb @ R_sub[:, k, :] for k in range(3)], axis=1)
                R_err = transposed_times(data.R_ks[rows].transpose(1, 2, 0), R_ks_pred)
                out[rows, 3:] = ROT_WEIGHT * log3_many(R_err)
        return out.ravel()

    def flange_frames(
        self, corr: ModelCorrections, data: Data, tau: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Base -> flange of every pose (copies), the chain reused when the corrections and
        the data are the same as the last call's: a finite-difference Jacobian moves the
        registration parameters one at a time, and those leave the chain as it was. The data
        must not change in place (nothing here does: subsets are new objects)."""
        key = _corrections_key(corr)
        cached = self._frames
        if cached is None or cached[0] is not data or cached[1] is not tau or cached[2] != key:
            R, p = self.chain.flange_frames(data.q, corr=corr, tau=tau, direction=data.direction)
            cached = self._frames = (data, tau, key, R, p)
        return cached[3].copy(), cached[4].copy()


def _corrections_key(corr: ModelCorrections) -> bytes:
    parts = [
        getattr(corr, name).tobytes()
        for name in ("joint_offsets", "compliance", "backlash", "cyclic", "placement")
    ]
    for knots, values in corr.maps:
        parts += [knots.tobytes(), b"|", values.tobytes(), b"|"]
    for j, k, slope, knots, values in corr.couplings:
        parts += [repr((j, k, slope)).encode(), knots.tobytes(), b"|", values.tobytes(), b"|"]
    parts.append(repr(corr.ripple).encode())
    return b"/".join(parts)


def stats(model: Model, x: np.ndarray, data: Data, tau: np.ndarray) -> Stats:
    r = model.residuals(x, data, tau)
    width = 3 if model.position_only or data.R_ks is None else 6
    r = r.reshape(-1, width)
    pos = np.linalg.norm(r[:, :3], axis=1) * 1e3
    rot = (
        None
        if width == 3
        else float(np.sqrt(np.mean(np.sum((r[:, 3:] / ROT_WEIGHT) ** 2, axis=1))) * 1e3)
    )
    rms = float(np.sqrt(np.mean(pos**2)))
    judged = rms
    if data.weight is not None:
        judged = float(np.sqrt(np.sum(data.weight * pos**2) / np.sum(data.weight)))
    return Stats(int(data.n), rms, float(pos.max()), rot, judged)


# ---- registration --------------------------------------------------------------------------


def _kabsch(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R, p minimizing |R a + p - b| over corresponding points (scipy's Kabsch solver on the
    centred point sets)."""
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    rot, _rssd = Rotation.align_vectors(b - cb, a - ca)
    R = rot.as_matrix()
    return R, cb - R @ ca


def initial_registration(
    chain: Chain, data: Data, tool_guess: np.ndarray | None, position_only: bool
) -> np.ndarray:
    """From the data itself: flange positions vs tracker positions (Kabsch), then the mount
    by linear least squares, then the mount's rotation by averaging."""
    T_bn = chain.flange_poses(data.q)
    spread = np.linalg.svd(T_bn[:, :3, 3] - T_bn[:, :3, 3].mean(axis=0), compute_uv=False)
    if data.n < 6 or spread[1] < 0.02:
        raise NotIdentifiableError(
            f"the flange positions span too little ({spread[0] * 1e3:.0f} x "
            f"{spread[1] * 1e3:.0f} mm in their two largest directions): registration needs poses "
            "spread out in space (move several joints)"
        )
    R_kb, p_kb = _kabsch(T_bn[:, :3, 3], data.p_ks)  # tracker <- base, roughly
    R_bk, p_bk = R_kb.T, -R_kb.T @ p_kb
    # p_bk + R_bk p_ks = p_bn + R_bn p_ns  ->  unknowns p_bk, p_ns (linear)
    A = np.zeros((3 * data.n, 6))
    b = np.zeros(3 * data.n)
    for i in range(data.n):
        A[3 * i : 3 * i + 3, :3] = np.eye(3)
        A[3 * i : 3 * i + 3, 3:] = -T_bn[i, :3, :3]
        b[3 * i : 3 * i + 3] = T_bn[i, :3, 3] - R_bk @ data.p_ks[i]
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    p_bk, p_ns = sol[:3], sol[3:]
    reg = np.concatenate([p_bk, Rotation.from_matrix(R_bk).as_rotvec(), p_ns])
    if position_only:
        return reg
    R_ns = [T_bn[i, :3, :3].T @ R_bk @ data.R_ks[i] for i in range(data.n)]  # type: ignore[index]
    mean = Rotation.from_matrix(np.array(R_ns)).mean().as_rotvec()
    return np.concatenate([reg, mean])


def initial_registration_sessions(
    chain: Chain, data: Data, position_only: bool, sessions: int, tools: int = 1
) -> np.ndarray:
    """initial_registration per session; T_bk of each, the mount averaged over them (or each
    session's own with `tools` = sessions)."""
    if sessions == 1:
        return initial_registration(chain, data, None, position_only)
    regs = [
        initial_registration(chain, data.subset(rows), None, position_only)
        for rows in data.session_rows(sessions)
    ]
    out = [r[:6] for r in regs]
    if tools > 1:
        return np.concatenate(out + [r[6:] for r in regs])
    out.append(np.mean([r[6:9] for r in regs], axis=0))
    if not position_only:
        out.append(Rotation.from_rotvec(np.array([r[9:12] for r in regs])).mean().as_rotvec())
    return np.concatenate(out)


@dataclass
class FitResult:
    x: np.ndarray
    se: np.ndarray
    cost: float
    rank: int | None = None
    full: int | None = None


def numeric_jacobian(
    f: Callable[[np.ndarray], np.ndarray], x: np.ndarray, base: np.ndarray, step: float = 1e-7
) -> np.ndarray:
    """Forward differences of f at x (f(x) = base): the identifiability checks' Jacobian."""
    J = np.empty((base.size, x.size))
    for k in range(x.size):
        xp = x.copy()
        xp[k] += step
        J[:, k] = (f(xp) - base) / step
    return J


def fit(
    model: Model,
    data: Data,
    tau: np.ndarray,
    x0: np.ndarray,
    noise_m: float,
    fixed: np.ndarray | None = None,
    iterations: int = 20,
    prior: np.ndarray | None = None,
) -> FitResult:
    """Robust least squares over the free parameters: scipy's trust-region reflective solver
    with a Huber loss at 3 noise sigmas, parameters scaled by the Jacobian's columns (so
    metres and radians weigh alike). Standard errors from the Huber-weighted Jacobian at the
    solution. `iterations` bounds the Jacobian evaluations (the model is close to linear in
    these small parameters). `prior`: rows P (m x x0.size) appended to the residuals as
    P @ x (fit.prior: each term's size against its physical size)."""
    free = np.ones(x0.size, dtype=bool) if fixed is None else ~fixed
    x = x0.copy()

    width = 3 if model.position_only or data.R_ks is None else 6
    row_w = data.row_weights(width)
    if prior is not None and row_w is not None:
        row_w = np.concatenate([row_w, np.ones(prior.shape[0])])

    def fun(z: np.ndarray) -> np.ndarray:
        xx = x.copy()
        xx[free] = z
        r = model.residuals(xx, data, tau)
        return r if prior is None else np.concatenate([r, prior @ xx])

    k_huber = 3.0 * noise_m
    if data.n * width > LARGE_ROWS or data.velocity is not None:  # many rows, or motion
        x[free], r = _robust_gauss_newton(fun, x[free], k_huber, row_w, iterations)
    else:
        result = least_squares(
            fun,
            x[free],
            method="trf",
            tr_solver="exact",
            loss="huber" if row_w is None else _weighted_huber(row_w**2),
            f_scale=k_huber,
            x_scale="jac",
            diff_step=1e-7 / np.maximum(1.0, np.abs(x[free])),
            max_nfev=iterations * 5,
            xtol=1e-12,
            ftol=1e-10,
            gtol=1e-12,
        )
        x[free], r = result.x, result.fun
    J = numeric_jacobian(fun, x[free], r)
    w = np.sqrt(np.minimum(1.0, k_huber / np.maximum(np.abs(r), 1e-300)))
    if row_w is not None:
        w = w * row_w
    Jw = J * w[:, None]
    dof = max(1, r.size - J.shape[1])
    s2 = float(np.sum((r * w) ** 2)) / dof
    cov = np.linalg.pinv(Jw.T @ Jw, rcond=1e-10) * s2
    se = np.zeros(x0.size)
    se[free] = np.sqrt(np.clip(np.diag(cov), 0, None))
    return FitResult(x, se, float(np.sum(r * r)))


def _robust_cost(r: np.ndarray, k: float, weight: np.ndarray | None) -> float:
    """sum of scipy's Huber rho((r / k)^2) k^2, each term times its row's weight."""
    z = (r / k) ** 2
    rho = np.where(z <= 1, z, 2 * np.sqrt(z) - 1) * k * k
    return float(np.sum(rho if weight is None else rho * weight))


def _robust_gauss_newton(
    fun: Callable[[np.ndarray], np.ndarray],
    x0: np.ndarray,
    k: float,
    row_w: np.ndarray | None,
    iterations: int,
) -> tuple[np.ndarray, np.ndarray]:
    """The robust fit for many residual rows: Levenberg-Marquardt steps on the Huber-weighted
    normal equations (iteratively reweighted least squares; P x P, so a step costs one
    product with the Jacobian, not its SVD). The parameters are few and the model close to
    linear in them: it converges in a few steps. (scipy's trust-region solver with LSMR steps,
    used here before, crawled on large registrations; docs/analyze.md.) Returns x and its
    residuals."""
    weight = None if row_w is None else row_w**2
    x = x0.copy()
    r = fun(x)
    cost = _robust_cost(r, k, weight)
    lam = 1e-3
    for _ in range(iterations):
        J = numeric_jacobian(fun, x, r)
        w = np.minimum(1.0, k / np.maximum(np.abs(r), 1e-300))  # IRLS weights of Huber
        if weight is not None:
            w = w * weight
        Jw = J * w[:, None]
        A = J.T @ Jw
        g = Jw.T @ r
        diag = np.maximum(np.diag(A), 1e-300)
        improved = False
        while lam < 1e12:
            step = -np.linalg.solve(A + lam * np.diag(diag), g)
            r_new = fun(x + step)
            cost_new = _robust_cost(r_new, k, weight)
            if cost_new < cost:
                improved = True
                break
            lam *= 10.0
        if not improved:
            break
        x, r, done = x + step, r_new, cost - cost_new <= 1e-10 * cost
        cost = cost_new
        lam = max(lam / 10.0, 1e-9)
        if done or np.linalg.norm(step) <= 1e-12 * (np.linalg.norm(x) + 1e-12):
            break
    return x, r


def _weighted_huber(weight: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """scipy's Huber loss with each residual's term times its row's weight (a callable loss:
    rho, rho', rho'' of z = (r / f_scale)^2), so every row keeps its own outlier threshold."""

    def loss(z: np.ndarray) -> np.ndarray:
        out = np.empty((3, z.size))
        inlier = z <= 1
        root = np.sqrt(np.maximum(z, 1e-300))
        out[0] = np.where(inlier, z, 2 * root - 1)
        out[1] = np.where(inlier, 1.0, 1 / root)
        out[2] = np.where(inlier, 0.0, -0.5 / (root * np.maximum(z, 1e-300)))
        out *= weight
        return out

    return loss


def identifiable_basis(
    model: Model, data: Data, tau: np.ndarray, x: np.ndarray, effect: Effect
) -> tuple[np.ndarray, int, int, np.ndarray]:
    """Directions of an effect's parameters that the data can determine alongside the
    registration: the right singular vectors of the identification Jacobian above RANK_TOL
    (basis, rank, parameter count), and the directions below it (the null space, in the
    same scaled parameters) that the report puts into words."""
    nq = model.chain.nq
    full = effect.size(nq)
    trial = Model(
        model.chain,
        model.position_only,
        [*model.effects, effect],
        np.concatenate([x, np.zeros(full)]),
        dict(model.basis),
        model.temperature_ref,
        model.time_ref,
        model.sessions,
        model.tools,
    )
    x_t = trial.x
    base = trial.residuals(x_t, data, tau)
    J = numeric_jacobian(lambda z: trial.residuals(z, data, tau), x_t, base)
    J_reg = J[:, : x.size]
    J_eff = J[:, x.size :]
    # what the effect adds beyond the parameters already there
    Q, _ = np.linalg.qr(J_reg)
    J_perp = J_eff - Q @ (Q.T @ J_eff)
    # scale by each parameter's own effect (not what is left of it), so a parameter the
    # registration already absorbs stays small instead of being blown up to unit size
    col = np.linalg.norm(J_eff, axis=0)
    scale = np.where(col > 0, col, 1.0)
    _U, S, Vt = np.linalg.svd(J_perp / scale, full_matrices=False)
    rank = int(np.sum(RANK_TOL * S[0] < S)) if S.size and S[0] > 0 else 0
    basis = Vt[:rank].T / scale[:, None]
    basis /= np.linalg.norm(basis, axis=0)
    # the unseen directions: the rest of the right singular vectors (all of them come with
    # the thin SVD unless there are fewer residuals than parameters)
    if Vt.shape[0] < full:
        Vt = np.linalg.svd(J_perp / scale, full_matrices=True)[2]
    null = Vt[rank:].T / scale[:, None]
    if null.size:
        null /= np.linalg.norm(null, axis=0)
    return basis, rank, full, null
