"""`keo analyze`: registration, the nominal model's residual, and effects that explain it,
each judged on held-out rows. No I/O here (see analysis_report for files).

Unknowns are packed in one vector: the tracker registration T_bk (translation, rotation
vector), the sensor mount T_ns (6, or the reflector offset: 3), then each kept effect's
parameters. Residuals, per pose: predicted minus measured sensor position (m) and, for a 6-DoF
probe, orientation (rad, scaled by ROT_WEIGHT m/rad). Fitted with scipy's robust least squares
(soft-L1 loss: a few outliers do not pull the fit).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation
from scipy.stats import median_abs_deviation

from keo_service.core.chain import Chain, times_constant_frames
from keo_service.core.corrections import Corrections
from keo_service.core.errors import KeoError
from keo_service.core.kinematics import RobotModel
from keo_service.core.rotations import log3_many, transposed_times
from keo_service.fit.diagnostics import describe_null_space, repeatability

ROT_WEIGHT = 0.5  # m per rad: 20 um of position ~ 40 urad of orientation
KEEP_MARGIN = 0.05  # an effect must lower the held-out position RMS by 5 % to be kept
MAPS = "joint_maps"  # joint-angle error maps (fit.angle_maps): knots depend on the data
NOISE_MARGIN = 2.0  # a residual above this many times the data's repeatability is not noise
RANK_TOL = 1e-3  # relative singular value below which a direction counts as unidentifiable


class NotIdentifiableError(KeoError):
    """The data cannot determine what was asked (e.g. registration from one moving joint)."""


@dataclass
class Data:
    q: np.ndarray  # (N, nq)
    p_ks: np.ndarray  # (N, 3)
    R_ks: np.ndarray | None  # (N, 3, 3) or None (single reflector)
    t: np.ndarray
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    direction: np.ndarray | None = None  # (N, nq) direction of each joint's last move, +-1 / 0
    velocity: np.ndarray | None = None  # (N, nq) joint velocities (motion data), rad/s

    def subset(self, idx: np.ndarray) -> Data:
        return Data(
            self.q[idx],
            self.p_ks[idx],
            None if self.R_ks is None else self.R_ks[idx],
            self.t[idx],
            {k: v[idx] for k, v in self.extra.items()},
            None if self.direction is None else self.direction[idx],
            None if self.velocity is None else self.velocity[idx],
        )

    @property
    def n(self) -> int:
        return int(self.q.shape[0])


@dataclass
class Stats:
    n: int
    pos_rms_mm: float
    pos_max_mm: float
    rot_rms_mrad: float | None

    def as_dict(self) -> dict[str, Any]:
        return {
            "n": self.n,
            "pos_rms_mm": self.pos_rms_mm,
            "pos_max_mm": self.pos_max_mm,
            "rot_rms_mrad": self.rot_rms_mrad,
        }


# ---- the model: parameters -> predicted sensor poses -----------------------------------------


@dataclass(frozen=True)
class EffectSpec:
    name: str
    size: Callable[[int], int]
    apply: Callable[[Corrections, np.ndarray], Corrections]
    describe: str


def _set(corr: Corrections, **kw: np.ndarray) -> Corrections:
    fields: dict[str, Any] = kw
    return dataclasses.replace(corr, **fields)


EFFECTS: dict[str, EffectSpec] = {
    "joint_offsets": EffectSpec(
        "joint_offsets",
        lambda nq: nq,
        lambda c, x: _set(c, joint_offsets=c.joint_offsets + x),
        "zero offset of each joint (rad)",
    ),
    "geometry": EffectSpec(
        "geometry",
        lambda nq: 6 * nq,
        lambda c, x: _set(c, placement=c.placement + x.reshape(-1, 6)),
        "joint placement errors, identifiable combinations only (m, rad)",
    ),
    "compliance": EffectSpec(
        "compliance",
        lambda nq: nq,
        lambda c, x: _set(c, compliance=c.compliance + x),
        "joint deflection per gravity torque (rad/(N m))",
    ),
    "backlash": EffectSpec(
        "backlash",
        lambda nq: nq,
        lambda c, x: _set(c, backlash=c.backlash + x),
        "joint offset that follows the direction of the last move (rad)",
    ),
    "cyclic": EffectSpec(
        "cyclic",
        lambda nq: 4 * nq,
        lambda c, x: _set(c, cyclic=c.cyclic + x.reshape(-1, 2, 2)),
        "1st and 2nd harmonics of each joint angle (rad)",
    ),
}
CANDIDATES = (
    "joint_offsets",
    "geometry",
    "compliance",
    "backlash",
    "cyclic",
    "temperature",
    "time_drift",
)


def split_maps(
    knots: tuple[np.ndarray, ...], values: np.ndarray
) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
    """A flat vector of map values as (knots, values) per joint."""
    out, k = [], 0
    for kn in knots:
        out.append((kn, values[k : k + kn.size]))
        k += kn.size
    return tuple(out)


@dataclass
class Model:
    chain: Chain
    position_only: bool
    effects: list[str]  # kept effects, in order
    x: np.ndarray  # all parameters
    basis: dict[str, np.ndarray] = field(default_factory=dict)  # identifiable directions
    temperature_ref: float = 0.0
    time_ref: float = 0.0
    knots: tuple[np.ndarray, ...] = ()  # joint_maps: each joint's knots (rad), empty: none
    # the newest chain evaluation: (data, tau, corrections' key, R_bn, p_bn)
    _frames: tuple[Any, ...] | None = field(default=None, repr=False, compare=False)

    @property
    def n_reg(self) -> int:
        return 9 if self.position_only else 12

    def sizes(self, nq: int) -> list[int]:
        out = []
        for name in self.effects:
            if name in self.basis:
                out.append(self.basis[name].shape[1])
            elif name in ("temperature", "time_drift"):
                out.append(3)
            elif name == MAPS:
                out.append(sum(k.size for k in self.knots))
            else:
                out.append(EFFECTS[name].size(nq))
        return out

    def unpack(
        self, x: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, Corrections, dict[str, np.ndarray]]:
        nq = self.chain.nq
        reg = x[: self.n_reg]
        corr = Corrections(nq=nq)
        drifts: dict[str, np.ndarray] = {}
        k = self.n_reg
        for name, size in zip(self.effects, self.sizes(nq), strict=True):
            part = x[k : k + size]
            k += size
            if name in self.basis:
                part = self.basis[name] @ part
            if name in EFFECTS:
                corr = EFFECTS[name].apply(corr, part)
            elif name == MAPS:
                corr = dataclasses.replace(corr, maps=split_maps(self.knots, part))
            else:
                drifts[name] = part
        T_bk = np.eye(4)
        T_bk[:3, :3] = Rotation.from_rotvec(reg[3:6]).as_matrix()
        T_bk[:3, 3] = reg[:3]
        if self.position_only:
            T_ns = np.eye(4)
            T_ns[:3, 3] = reg[6:9]
        else:
            T_ns = np.eye(4)
            T_ns[:3, :3] = Rotation.from_rotvec(reg[9:12]).as_matrix()
            T_ns[:3, 3] = reg[6:9]
        return T_bk, T_ns, corr, drifts

    def residuals(self, x: np.ndarray, data: Data, tau: np.ndarray) -> np.ndarray:
        """Per pose, predicted minus measured sensor position in the base frame (m) and, for a
        6-DoF probe, ROT_WEIGHT x log3(R_meas^T R_pred); (N * 3) or (N * 6), pose-major."""
        T_bk, T_ns, corr, drifts = self.unpack(x)
        # the sensor frame for every pose, component-major: (3, 3, N) and (3, N)
        R_bs, p_bs = self.flange_frames(corr, data, tau)
        times_constant_frames(R_bs, p_bs, T_ns)
        p_meas = data.p_ks @ T_bk[:3, :3].T + T_bk[:3, 3]
        p_pred = p_bs.T
        if "temperature" in drifts:
            p_pred = p_pred + np.outer(
                data.extra["temperature_c"] - self.temperature_ref, drifts["temperature"]
            )
        if "time_drift" in drifts:
            p_pred = p_pred + np.outer(data.t - self.time_ref, drifts["time_drift"])
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

    def flange_frames(
        self, corr: Corrections, data: Data, tau: np.ndarray
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


def _corrections_key(corr: Corrections) -> bytes:
    parts = [
        getattr(corr, name).tobytes()
        for name in ("joint_offsets", "compliance", "backlash", "cyclic", "placement")
    ]
    for knots, values in corr.maps:
        parts += [knots.tobytes(), b"|", values.tobytes(), b"|"]
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
    return Stats(int(data.n), float(np.sqrt(np.mean(pos**2))), float(pos.max()), rot)


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
) -> FitResult:
    """Robust least squares over the free parameters: scipy's trust-region reflective solver
    with a Huber loss at 3 noise sigmas, parameters scaled by the Jacobian's columns (so
    metres and radians weigh alike). Standard errors from the Huber-weighted Jacobian at the
    solution. `iterations` bounds the Jacobian evaluations (the model is close to linear in
    these small parameters)."""
    free = np.ones(x0.size, dtype=bool) if fixed is None else ~fixed
    x = x0.copy()

    def fun(z: np.ndarray) -> np.ndarray:
        xx = x.copy()
        xx[free] = z
        return model.residuals(xx, data, tau)

    k_huber = 3.0 * noise_m
    result = least_squares(
        fun,
        x[free],
        method="trf",
        loss="huber",
        f_scale=k_huber,
        x_scale="jac",
        diff_step=1e-7 / np.maximum(1.0, np.abs(x[free])),
        max_nfev=iterations * 5,
        xtol=1e-12,
        ftol=1e-10,
        gtol=1e-12,
    )
    x[free] = result.x
    r = result.fun
    J = numeric_jacobian(fun, result.x, r)
    w = np.sqrt(np.minimum(1.0, k_huber / np.maximum(np.abs(r), 1e-300)))
    Jw = J * w[:, None]
    dof = max(1, r.size - J.shape[1])
    s2 = float(np.sum((r * w) ** 2)) / dof
    cov = np.linalg.pinv(Jw.T @ Jw, rcond=1e-10) * s2
    se = np.zeros(x0.size)
    se[free] = np.sqrt(np.clip(np.diag(cov), 0, None))
    return FitResult(x, se, float(np.sum(r * r)))


def identifiable_basis(
    model: Model, data: Data, tau: np.ndarray, x: np.ndarray, name: str
) -> tuple[np.ndarray, int, int, np.ndarray]:
    """Directions of an effect's parameters that the data can determine alongside the
    registration: the right singular vectors of the identification Jacobian above RANK_TOL
    (basis, rank, parameter count), and the directions below it (the null space, in the
    same scaled parameters) that the report puts into words."""
    nq = model.chain.nq
    full = EFFECTS[name].size(nq)
    trial = Model(
        model.chain,
        model.position_only,
        [*model.effects, name],
        np.concatenate([x, np.zeros(full)]),
        dict(model.basis),
        model.temperature_ref,
        model.time_ref,
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


# ---- the analysis ----------------------------------------------------------------------------


def split(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Train / validation rows: blocks in time order, every 4th block held out, so effects
    that follow time (drift) are judged on stretches the fit never saw."""
    block = 50 if n >= 800 else max(2, n // 40)
    idx = np.arange(n)
    val = (idx // block) % 4 == 3
    return idx[~val], idx[val]


# what each number of an effect is, per joint: (parameter, unit), in the order of its values
_PER_JOINT = {
    "joint_offsets": [("zero offset", "rad")],
    "compliance": [("compliance", "rad/(N m)")],
    "backlash": [("backlash", "rad")],
    "cyclic": [
        ("1st harmonic sin", "rad"),
        ("1st harmonic cos", "rad"),
        ("2nd harmonic sin", "rad"),
        ("2nd harmonic cos", "rad"),
    ],
    "geometry": [
        ("link x", "m"),
        ("link y", "m"),
        ("link z", "m"),
        ("link rx", "rad"),
        ("link ry", "rad"),
        ("link rz", "rad"),
    ],
}
_SENSOR_DRIFT = {"temperature": "m/C", "time_drift": "m/s"}


def parameter_records(
    name: str, values: np.ndarray, se: np.ndarray, joint_names: Sequence[str]
) -> list[dict[str, Any]]:
    """An effect's numbers as named records {joint, parameter, unit, value, se} (SI units)."""
    if name in _SENSOR_DRIFT:
        return [
            {
                "joint": "sensor",
                "parameter": f"drift {axis}",
                "unit": _SENSOR_DRIFT[name],
                "value": float(v),
                "se": float(s),
            }
            for axis, v, s in zip("xyz", values, se, strict=True)
        ]
    per_joint = _PER_JOINT.get(name)
    if per_joint is None:
        return []
    out = []
    for i, (v, s) in enumerate(zip(values, se, strict=True)):
        j, k = divmod(i, len(per_joint))
        parameter, unit = per_joint[k]
        joint = joint_names[j] if j < len(joint_names) else f"joint_{j + 1}"
        out.append(
            {
                "joint": joint,
                "parameter": parameter,
                "unit": unit,
                "value": float(v),
                "se": float(s),
            }
        )
    return out


def _effect_parameters(model: Model, name: str, x: np.ndarray, se: np.ndarray) -> dict[str, Any]:
    """An effect's parameters (and standard errors) in physical units, as arrays and as
    named records per joint."""
    nq = model.chain.nq
    names = model.chain.robot.joint_names
    k = model.n_reg
    for other, size in zip(model.effects, model.sizes(nq), strict=True):
        if other == name:
            part, part_se = x[k : k + size], se[k : k + size]
            if name in model.basis:
                B = model.basis[name]
                values = B @ part
                std = np.sqrt((B**2) @ (part_se**2))
                return {
                    "identifiable": int(B.shape[1]),
                    "of": int(B.shape[0]),
                    "values": values.tolist(),
                    "se": std.tolist(),
                    "records": parameter_records(name, values, std, names),
                }
            return {
                "values": part.tolist(),
                "se": part_se.tolist(),
                "records": parameter_records(name, part, part_se, names),
            }
        k += size
    raise KeyError(name)


def correlations(model: Model, x: np.ndarray, data: Data, tau: np.ndarray) -> list[dict[str, Any]]:
    """How much of the position residual each candidate variable explains (R^2 of a quadratic
    fit), strongest first."""
    r = model.residuals(x, data, tau).reshape(data.n, -1)[:, :3]
    _T_bk, _T_ns, _c, _d = model.unpack(x)
    variables: dict[str, np.ndarray] = {f"q{j + 1}": data.q[:, j] for j in range(data.q.shape[1])}
    variables.update({f"gravity_torque_{j + 1}": tau[:, j] for j in range(tau.shape[1])})
    variables["time"] = data.t
    variables["tracker_distance"] = np.linalg.norm(data.p_ks, axis=1)
    if data.velocity is not None:  # motion data: how fast each joint moved
        variables.update(
            {
                f"joint_speed_{j + 1}": np.abs(data.velocity[:, j])
                for j in range(data.velocity.shape[1])
            }
        )
        variables["joint_speed_norm"] = np.linalg.norm(data.velocity, axis=1)
    if data.direction is not None:  # direction of the last move of each joint
        variables.update(
            {f"direction_{j + 1}": data.direction[:, j] for j in range(data.direction.shape[1])}
        )
    for name, values in data.extra.items():
        variables[name] = values
    out = []
    centred = r - r.mean(axis=0)
    total = float(np.sum(centred**2))
    bins = 12
    for name, v in variables.items():
        if not np.all(np.isfinite(v)) or np.ptp(v) == 0:
            continue
        # binned means: any smooth dependence shows, not only a linear one
        edges = np.quantile(v, np.linspace(0, 1, bins + 1))
        which = np.clip(np.searchsorted(edges, v, side="right") - 1, 0, bins - 1)
        explained = 0.0
        for b in range(bins):
            rows = which == b
            if rows.sum() > 1:
                explained += rows.sum() * float(np.sum(centred[rows].mean(axis=0) ** 2))
        # expected by chance with noise alone: (bins - 1) / n of the total
        r2 = explained / total if total > 0 else 0.0
        out.append({"variable": name, "r2": r2, "chance": (bins - 1) / data.n})
    return sorted(out, key=lambda d: -d["r2"])


@dataclass
class Analysis:
    report: dict[str, Any]
    model: Model
    x: np.ndarray


def analyze(
    robot: RobotModel,
    data: Data,
    position_only: bool,
    fixed_model: Model | None = None,
    progress: Callable[[str], None] | None = None,
    candidates: tuple[str, ...] = CANDIDATES,
) -> Analysis:
    say = progress or (lambda _msg: None)
    chain = Chain(robot)
    train_idx, val_idx = split(data.n)
    train, val = data.subset(train_idx), data.subset(val_idx)
    say(f"{data.n} poses: {train.n} to fit, {val.n} held out")
    tau_all = chain.gravity_torques(data.q)
    tau_tr, tau_va = tau_all[train_idx], tau_all[val_idx]
    t_ref = float(np.mean(data.t))
    temp_ref = float(np.mean(data.extra["temperature_c"])) if "temperature_c" in data.extra else 0.0

    reg0 = initial_registration(chain, train, None, position_only)
    base = Model(chain, position_only, [], reg0, temperature_ref=temp_ref, time_ref=t_ref)
    _check_registration(base, train, tau_tr)
    noise = 50e-6
    fitted = fit(base, train, tau_tr, reg0, noise)
    r = base.residuals(fitted.x, train, tau_tr)
    noise = max(1e-6, float(median_abs_deviation(r, scale="normal")))
    fitted = fit(base, train, tau_tr, fitted.x, noise)
    say("registered the tracker and the sensor mount")
    report: dict[str, Any] = {
        "baseline": {
            "train": stats(base, fitted.x, train, tau_tr).as_dict(),
            "validation": stats(base, fitted.x, val, tau_va).as_dict(),
        },
        "effects": [],
        "rejected": [],
    }
    model, x = base, fitted.x

    if fixed_model is not None:  # --registration-only: the saved robot model, new registration
        model = Model(
            chain,
            position_only,
            list(fixed_model.effects),
            np.concatenate([x, fixed_model.x[fixed_model.n_reg :]]),
            dict(fixed_model.basis),
            fixed_model.temperature_ref,
            fixed_model.time_ref,
            fixed_model.knots,
        )
        fixed = np.zeros(model.x.size, dtype=bool)
        fixed[model.n_reg :] = True
        x = fit(model, train, tau_tr, model.x, noise, fixed=fixed).x
        candidates = ()
        if MAPS in model.effects:
            model, x = _judge_carried_maps(model, x, data, train, val, noise, report)
            say(f"carried joint maps {'kept' if MAPS in model.effects else 'dropped'}")
    current_val = stats(model, x, val, tau_va).pos_rms_mm
    for name in candidates:
        if name == "temperature" and "temperature_c" not in data.extra:
            continue
        if name == "backlash" and data.direction is None:
            continue
        say(f"trying {name}")
        trial_basis = dict(model.basis)
        if name in EFFECTS:  # never fit what the data cannot tell apart from what is there
            B, rank, full, null = identifiable_basis(model, train, tau_tr, x, name)
            if rank == 0:
                say(f"{name}: nothing identifiable from these poses")
                continue
            trial_basis[name] = B
            say(f"{name}: {rank} of {full} parameters identifiable from these poses")
        else:
            null = np.zeros((0, 0))
        trial = Model(chain, position_only, [*model.effects, name], x, trial_basis, temp_ref, t_ref)
        size = trial.sizes(chain.nq)[-1]
        x0 = np.concatenate([x, np.zeros(size)])
        trial.x = x0
        res = fit(trial, train, tau_tr, x0, noise)
        val_stats = stats(trial, res.x, val, tau_va)
        entry: dict[str, Any] = {
            "name": name,
            "parameters": _effect_parameters(trial, name, res.x, res.se),
            "train": stats(trial, res.x, train, tau_tr).as_dict(),
            "validation": val_stats.as_dict(),
            "description": EFFECTS[name].describe
            if name in EFFECTS
            else (
                "sensor position drift per degree C (m/C)"
                if name == "temperature"
                else "sensor position drift per second (m/s)"
            ),
        }
        if null.size:
            labels = [
                f"{rec['joint']} {rec['parameter']}"
                for rec in parameter_records(
                    name, np.zeros(null.shape[0]), np.zeros(null.shape[0]), chain.robot.joint_names
                )
            ]
            entry["parameters"]["unidentifiable"] = describe_null_space(null, labels)
        gain = 1 - val_stats.pos_rms_mm / current_val
        entry["held_out_improvement_pct"] = 100 * gain
        if gain >= KEEP_MARGIN:
            model, x = trial, res.x
            current_val = val_stats.pos_rms_mm
            report["effects"].append(entry)
            say(f"kept {name}: held-out position RMS {val_stats.pos_rms_mm:.4f} mm")
        else:
            report["rejected"].append(entry)
            say(f"not kept {name}: held-out change {100 * gain:+.1f} %")
    # refit the registration with everything on all rows? no: final numbers stay held-out
    report["final"] = {
        "train": stats(model, x, train, tau_tr).as_dict(),
        "validation": stats(model, x, val, tau_va).as_dict(),
    }
    rep = repeatability(data.q, data.p_ks)
    report["repeatability"] = None if rep is None else rep.as_dict()
    describe_remaining(report, model, x, data)
    T_bk, T_ns, _c, _d = model.unpack(x)
    report["registration"] = {
        "T_bk": T_bk.tolist(),
        "T_ns": T_ns.tolist(),
        "noise_estimate_mm": noise * 1e3,
    }
    return Analysis(report, model, x)


def _check_registration(model: Model, data: Data, tau: np.ndarray) -> None:
    """Refuse when the poses cannot pin down the registration (rank of its Jacobian)."""
    x = model.x
    base = model.residuals(x, data, tau)
    J = numeric_jacobian(lambda z: model.residuals(z, data, tau), x, base, step=1e-6)
    S = np.linalg.svd(J / np.maximum(np.linalg.norm(J, axis=0), 1e-12), compute_uv=False)
    if S[-1] < 1e-4 * S[0]:
        raise NotIdentifiableError(
            f"the poses cannot determine the tracker registration and sensor mount (condition "
            f"{S[0] / max(S[-1], 1e-300):.1e}): e.g. only one joint moved; use poses that move "
            "several joints and orientations"
        )


def _judge_carried_maps(
    model: Model,
    x: np.ndarray,
    data: Data,
    train: Data,
    val: Data,
    noise: float,
    report: dict[str, Any],
) -> tuple[Model, np.ndarray]:
    """Angle maps carried to new data (registration refitted, model fixed) are judged like
    any effect: on the new data's held-out blocks, against the same model without them, and
    dropped unless they lower the held-out error by KEEP_MARGIN. Part of what a map absorbs
    belongs to the setup it was identified in (the tracker's own angle error moves with the
    tracker), and outside its calibrated angles a map only holds its edge value."""
    k = model.n_reg
    sizes = model.sizes(model.chain.nq)
    at = model.effects.index(MAPS)
    start = k + sum(sizes[:at])
    keep = np.r_[0:start, start + sizes[at] : x.size]
    without = Model(
        model.chain,
        model.position_only,
        [e for e in model.effects if e != MAPS],
        x[keep],
        dict(model.basis),
        model.temperature_ref,
        model.time_ref,
    )
    fixed = np.zeros(without.x.size, dtype=bool)
    fixed[without.n_reg :] = True
    tau_tr = without.chain.gravity_torques(train.q)
    tau_va = without.chain.gravity_torques(val.q)
    x_without = fit(without, train, tau_tr, without.x, noise, fixed=fixed).x
    with_maps = stats(model, x, val, tau_va).pos_rms_mm
    without_maps = stats(without, x_without, val, tau_va).pos_rms_mm
    lo = np.array([kn[0] if kn.size else -np.inf for kn in model.knots])
    hi = np.array([kn[-1] if kn.size else np.inf for kn in model.knots])
    outside = np.any((data.q < lo) | (data.q > hi), axis=1)
    kept = 1 - with_maps / without_maps >= KEEP_MARGIN
    report["carried_maps"] = {
        "held_out_pos_rms_mm_with": with_maps,
        "held_out_pos_rms_mm_without": without_maps,
        "kept": bool(kept),
        "poses_outside_calibrated_range_pct": 100.0 * float(np.mean(outside)),
    }
    return (model, x) if kept else (without, x_without)


def describe_remaining(report: dict[str, Any], model: Model, x: np.ndarray, data: Data) -> None:
    """What the residual of `model` still correlates with, and the verdict in words (called
    again when a later stage, the angle maps, changes the final model)."""
    corr = correlations(model, x, data, model.chain.gravity_torques(data.q))
    report["correlations"] = corr[:10]
    report["unexplained"] = _verdict(report, corr)


def _verdict(report: dict[str, Any], corr: list[dict[str, Any]]) -> str:
    strong = [c for c in corr if c["r2"] > max(0.15, 5 * c["chance"])]
    final = report["final"]["validation"]["pos_rms_mm"]
    rep = report.get("repeatability")
    if not strong:
        head = (
            f"the remaining {final:.4f} mm RMS shows no structure against the candidate "
            f"variables (largest R^2 {corr[0]['r2']:.2f} with {corr[0]['variable']})"
        )
        if rep is not None and final > NOISE_MARGIN * rep["rms_mm"]:
            return (
                f"{head}, yet it is {final / rep['rms_mm']:.1f}x this data's repeatability "
                f"({rep['rms_mm']:.4f} mm): model error that none of these variables explains "
                "alone, not noise"
            )
        return f"{head}: consistent with noise"
    names = ", ".join(f"{c['variable']} (R^2 {c['r2']:.2f})" for c in strong[:4])
    return (
        f"structured residual remains ({final:.4f} mm RMS held out) that no effect in the "
        f"library explains; it correlates with {names}"
    )
