"""`keo analyze`: registration, the nominal model's residual, and effects that explain it,
each judged on held-out rows. No I/O here (see analysis_report for files).

The model and its fit live in fit.model, the effects in fit.effects; this module is the loop:
register, try each candidate effect (reduced to what the data identifies), keep it only if it
lowers the held-out error, and say what the residual still correlates with.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.stats import median_abs_deviation

from keo_service.core.chain import Chain
from keo_service.core.kinematics import RobotModel
from keo_service.fit.diagnostics import describe_null_space, repeatability
from keo_service.fit.effects import (
    CANDIDATES,
    EFFECTS,
    MAPS,
    JointMaps,
    JointRipple,
    Temperature,
    TimeDrift,
    split_maps,
)
from keo_service.fit.model import (
    ROT_WEIGHT,
    Data,
    Effect,
    Model,
    NotIdentifiableError,
    fit,
    identifiable_basis,
    initial_registration_sessions,
    numeric_jacobian,
    stats,
)
from keo_service.fit.prior import PriorChoice, choose_weight, prior_rows, scales_of
from keo_service.fit.uncertainty import NOISE_RATIO, TrackerUncertainty, floor_report

__all__ = [
    "CANDIDATES",
    "EFFECTS",
    "KEEP_MARGIN",
    "MAPS",
    "ROT_WEIGHT",
    "Analysis",
    "Data",
    "Model",
    "NotIdentifiableError",
    "TrackerUncertainty",
    "analyze",
    "describe_remaining",
    "parameter_records",
    "split",
]

KEEP_MARGIN = 0.05  # an effect must lower the held-out position RMS by 5 % to be kept


# ---- the analysis ----------------------------------------------------------------------------


def split(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Train / validation rows: blocks in time order, every 4th block held out, so effects
    that follow time (drift) are judged on stretches the fit never saw."""
    block = 50 if n >= 800 else max(2, n // 40)
    idx = np.arange(n)
    val = (idx // block) % 4 == 3
    return idx[~val], idx[val]


def sessions_of(data: Data) -> int:
    """How many recordings the data pool (1 without session labels)."""
    return 1 if data.session is None else int(data.session.max()) + 1


def split_data(data: Data) -> tuple[np.ndarray, np.ndarray]:
    """split() within each session, so every session has held-out blocks."""
    if data.session is None:
        return split(data.n)
    train, val = [], []
    for rows in data.session_rows(sessions_of(data)):
        a, b = split(rows.size)
        train.append(rows[a])
        val.append(rows[b])
    return np.sort(np.concatenate(train)), np.sort(np.concatenate(val))


def parameter_records(
    name: str, values: np.ndarray, se: np.ndarray, joint_names: Sequence[str]
) -> list[dict[str, Any]]:
    """An effect's numbers as named records {joint, parameter, unit, value, se} (SI units)."""
    return EFFECTS[name].records(values, se, joint_names)


def _effect_parameters(
    model: Model, effect: Effect, x: np.ndarray, se: np.ndarray
) -> dict[str, Any]:
    """An effect's parameters (and standard errors) in physical units, as arrays and as
    named records per joint."""
    nq = model.chain.nq
    names = model.chain.robot.joint_names
    k = model.n_reg
    for other, size in zip(model.effects, model.sizes(nq), strict=True):
        if other is effect:
            part, part_se = x[k : k + size], se[k : k + size]
            if effect.name in model.basis:
                B = model.basis[effect.name]
                values = B @ part
                std = np.sqrt((B**2) @ (part_se**2))
                records = effect.records(values, std, names)
                return {
                    "identifiable": int(B.shape[1]),
                    "of": int(B.shape[0]),
                    "values": values.tolist(),
                    "se": std.tolist(),
                    "records": records,
                    "combinations": _combinations(B, records),
                }
            return {
                "values": part.tolist(),
                "se": part_se.tolist(),
                "records": effect.records(part, part_se, names),
            }
        k += size
    raise KeyError(effect.name)


def _combinations(B: np.ndarray, records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Parameters the data see only together: rows of the identifiable basis B that are
    parallel (each member's value a fixed multiple of the others', so any split of their sum
    fits alike). Each group once: its members with their ratios, and the value of the
    combination sum(ratio_i x member_i) / sum(ratio_i^2) (the first member's value, with the
    others at their ratio). The members' records are marked, so a report shows the group once
    instead of an arbitrary split as separate findings."""
    norms = np.linalg.norm(B, axis=1)
    unit = np.where(norms[:, None] > 1e-12, B / np.maximum(norms, 1e-300)[:, None], 0.0)
    seen = np.zeros(B.shape[0], dtype=bool)
    out: list[dict[str, Any]] = []
    for i in range(B.shape[0]):
        if seen[i] or norms[i] <= 1e-12:
            continue
        same = np.flatnonzero((np.abs(unit @ unit[i]) > 1 - 1e-6) & ~seen)
        seen[same] = True
        if same.size < 2:
            continue
        ratios = (B[same] @ B[i]) / (B[i] @ B[i])
        group = len(out)
        members = []
        for k, ratio in zip(same, ratios, strict=True):
            records[k]["combination"] = group
            members.append(
                {
                    "joint": records[k]["joint"],
                    "parameter": records[k]["parameter"],
                    "ratio": float(ratio),
                }
            )
        out.append(
            {
                "members": members,
                "unit": records[i]["unit"],
                "value": records[i]["value"],
                "se": records[i]["se"],
                "sum": float(sum(records[k]["value"] for k in same)),
            }
        )
    return out


def correlations(model: Model, x: np.ndarray, data: Data, tau: np.ndarray) -> list[dict[str, Any]]:
    """How much of the position residual each candidate variable explains (R^2 of a quadratic
    fit), strongest first."""
    r = model.residuals(x, data, tau).reshape(data.n, -1)[:, :3]
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


@dataclass(frozen=True)
class _Rows:
    """The poses of one analysis split into fitted and held-out rows, with their gravity
    torques, and what every trial model shares (chain, references, sessions, noise)."""

    chain: Chain
    data: Data
    position_only: bool
    train_idx: np.ndarray
    val_idx: np.ndarray
    train: Data
    val: Data
    tau_all: np.ndarray
    tau_tr: np.ndarray
    tau_va: np.ndarray
    refs: tuple[float, float]  # temperature and time references
    sessions: int


@dataclass(frozen=True)
class _Trial:
    """A candidate effect fitted on top of the model: the trial model and its parameters,
    its report entry, the prior's weights with it, whether the extrapolation bands allow it,
    and its held-out judged RMS."""

    model: Model
    x: np.ndarray
    entry: dict[str, Any]
    weights: dict[str, float]
    band_ok: bool
    judged_mm: float


def analyze(
    robot: RobotModel,
    data: Data,
    position_only: bool,
    fixed_model: Model | None = None,
    progress: Callable[[str], None] | None = None,
    candidates: tuple[str, ...] = CANDIDATES,
    uncertainty: TrackerUncertainty | None = None,
) -> Analysis:
    """Register, try each candidate effect, keep what lowers the held-out error, and judge
    what remains against the floor (`uncertainty`: the tracker's specification; None: keo's
    assumed default)."""
    say = progress or (lambda _msg: None)
    rows = _rows(Chain(robot), data, position_only)
    say(f"{data.n} poses: {rows.train.n} to fit, {rows.val.n} held out")
    base, x, noise, tools = _register(rows, fixed_model is None)
    say("registered the tracker and the sensor mount")
    report: dict[str, Any] = {
        "baseline": {
            "train": stats(base, x, rows.train, rows.tau_tr).as_dict(),
            "validation": stats(base, x, rows.val, rows.tau_va).as_dict(),
        },
        "effects": [],
        "rejected": [],
    }
    model = base
    if fixed_model is not None:  # --registration-only: the saved robot model, new registration
        model, x = _carried(rows, fixed_model, x, noise, report, say)
        candidates = ()
    current_val = stats(model, x, rows.val, rows.tau_va).judged_mm
    weights: dict[str, float] = {}  # the prior's weight of each kept effect (fit.prior)
    scale = noise  # the residual's scale with the effects kept so far (residual_scale)
    for name in candidates:
        tried = _try_effect(rows, model, x, scale, noise, name, weights, report, say)
        if tried is None:
            continue
        entry = tried.entry
        gain = 1 - tried.judged_mm / current_val
        entry["held_out_improvement_pct"] = 100 * gain
        if gain >= KEEP_MARGIN and tried.band_ok:
            model, x, weights, current_val = tried.model, tried.x, tried.weights, tried.judged_mm
            scale = residual_scale(model, x, rows.train, rows.tau_tr)
            report["effects"].append(entry)
            say(f"kept {name}: held-out position RMS {entry['validation']['pos_rms_mm']:.4f} mm")
        else:
            entry["reason"] = _rejection(entry, gain)
            report["rejected"].append(entry)
            say(f"not kept {name}: {entry['reason']}")
    report["prior_weights"] = weights
    _bands_transfer(report)
    # refit the registration with everything on all rows? no: final numbers stay held-out
    report["final"] = {
        "train": stats(model, x, rows.train, rows.tau_tr).as_dict(),
        "validation": stats(model, x, rows.val, rows.tau_va).as_dict(),
    }
    report["repeatability"] = _repeatability_entry(data)
    describe_remaining(report, model, x, data, uncertainty or TrackerUncertainty())
    _registration_entry(report, model, x, noise, rows.sessions, tools)
    return Analysis(report, model, x)


def _rows(chain: Chain, data: Data, position_only: bool) -> _Rows:
    train_idx, val_idx = split_data(data)
    tau_all = chain.gravity_torques(data.q)
    return _Rows(
        chain,
        data,
        position_only,
        train_idx,
        val_idx,
        data.subset(train_idx),
        data.subset(val_idx),
        tau_all,
        tau_all[train_idx],
        tau_all[val_idx],
        (Temperature.reference(data), TimeDrift.reference(data)),
        sessions_of(data),
    )


def _register(
    rows: _Rows, new_model: bool
) -> tuple[Model, np.ndarray, float, dict[str, Any] | None]:
    """The nominal model registered (one tracker registration per session); a new model of
    several sessions gives each session its own sensor mount when that lowers the held-out
    error by KEEP_MARGIN (`tools`: the judgement, None when not judged)."""
    sessions, refs = rows.sessions, rows.refs
    chain, train, tau_tr, position_only = rows.chain, rows.train, rows.tau_tr, rows.position_only
    base, x, noise = _registered(chain, train, tau_tr, position_only, sessions, 1, refs)
    tools = None
    if sessions > 1 and new_model:  # each session its own tool, judged held out
        own = _registered(chain, train, tau_tr, position_only, sessions, sessions, refs)
        shared_mm = stats(base, x, rows.val, rows.tau_va).judged_mm
        own_mm = stats(own[0], own[1], rows.val, rows.tau_va).judged_mm
        tools = {
            "held_out_judged_mm_shared": shared_mm,
            "held_out_judged_mm_per_session": own_mm,
            "per_session": bool(1 - own_mm / shared_mm >= KEEP_MARGIN),
        }
        if tools["per_session"]:
            base, x, noise = own
    return base, x, noise, tools


def _carried(
    rows: _Rows,
    fixed_model: Model,
    x_reg: np.ndarray,
    noise: float,
    report: dict[str, Any],
    say: Callable[[str], None],
) -> tuple[Model, np.ndarray]:
    """A saved robot model with this data's registration (`x_reg`), refitted with the model
    held; carried joint maps judged per joint (_judge_carried_maps)."""
    model = Model(
        rows.chain,
        rows.position_only,
        list(fixed_model.effects),
        np.concatenate([x_reg, fixed_model.x[fixed_model.n_reg :]]),
        dict(fixed_model.basis),
        fixed_model.temperature_ref,
        fixed_model.time_ref,
    )
    fixed = np.zeros(model.x.size, dtype=bool)
    fixed[model.n_reg :] = True
    x = fit(model, rows.train, rows.tau_tr, model.x, noise, fixed=fixed).x
    if model.find(JointMaps) is not None:
        model, x = _judge_carried_maps(model, x, rows.data, rows.train, rows.val, noise, report)
        kept = model.find(JointMaps) is not None
        say(f"carried joint maps {'kept' if kept else 'dropped'}")
    if model.find(JointRipple) is not None:
        model, x = _judge_carried_ripple(model, x, rows.train, noise, report)
        dropped = report["carried_ripple"]["joints_dropped"]
        if dropped:
            say(f"carried periodic terms dropped on {', '.join(d['joint'] for d in dropped)}")
    return model, x


def _judge_carried_ripple(
    model: Model, x: np.ndarray, train: Data, noise: float, report: dict[str, Any]
) -> tuple[Model, np.ndarray]:
    """Carried periodic joint terms judged per joint, as the carried maps are
    (_judge_carried_maps) and on the same rows (the new session's registration rows; the
    held-out blocks stay untouched for the figures): joint by joint, the terms whose removal
    lowers the error there are dropped. A term found in one session's spectrum can belong to
    that session (docs/analyze.md: Series A's shoulder_pan terms raise its model's error on
    Series B)."""
    ripple = model.find(JointRipple)
    assert ripple is not None
    tau_tr = model.chain.gravity_torques(train.q)
    names = model.chain.robot.joint_names
    current = stats(model, x, train, tau_tr).judged_mm
    dropped: list[dict[str, Any]] = []
    for j in sorted({j for j, _p in ripple.terms}):
        trial, x_trial = _without_ripple_of(model, x, j, train, tau_tr, noise)
        rms = stats(trial, x_trial, train, tau_tr).judged_mm
        if rms < current:
            model, x, current = trial, x_trial, rms
            dropped.append({"joint": names[j], "fitted_rows_pos_rms_mm_without": rms})
    report["carried_ripple"] = {"joints_dropped": dropped, "fitted_rows_pos_rms_mm": current}
    return model, x


def _without_ripple_of(
    model: Model, x: np.ndarray, joint: int, train: Data, tau_tr: np.ndarray, noise: float
) -> tuple[Model, np.ndarray]:
    """The carried model without joint `joint`'s periodic terms, its registration refitted
    on the training rows with the robot model held."""
    effects: list[Effect] = []
    values: list[np.ndarray] = []
    for effect, part in model.parts(x):
        if isinstance(effect, JointRipple):
            keep = [i for i, (j, _p) in enumerate(effect.terms) if j != joint]
            if keep:
                effects.append(JointRipple(tuple(effect.terms[i] for i in keep)))
                values.append(np.concatenate([part[2 * i : 2 * i + 2] for i in keep]))
            continue
        effects.append(effect)
        values.append(part)
    return _registration_refitted(model, x, effects, values, train, tau_tr, noise)


def residual_scale(model: Model, x: np.ndarray, data: Data, tau: np.ndarray) -> float:
    """The robust scale (normal-consistent MAD, m) of `model`'s residual rows on `data`: the
    noise level an effect fitted on top of it meets, whose 3 sigmas are that fit's Huber
    threshold (and the prior weight choice's). Taken from the nominal model alone, the
    threshold stays at the robot's whole error, far above what the kept effects leave, and a
    few gross outliers then pull every later effect at full weight (docs/analyze.md gives
    the UR10 figures)."""
    r = model.residuals(x, data, tau)
    return max(1e-6, float(median_abs_deviation(r, scale="normal")))


def _try_effect(
    rows: _Rows,
    model: Model,
    x: np.ndarray,
    scale_now: float,
    unit: float,
    name: str,
    weights: dict[str, float],
    report: dict[str, Any],
    say: Callable[[str], None],
) -> _Trial | None:
    """Candidate `name` on top of `model`: its structure from the data where it has one,
    reduced to what the poses identify, its prior's weight from blocks and bands, fitted on
    the training rows (None: nothing to try). `scale_now`: the residual's scale on top of
    `model` (residual_scale: the Huber threshold of the weight choice and of the fit);
    `unit`: the registered nominal model's noise, the prior's unit (fit.prior: the weights
    were always stated against it, so a weight means the same prior whatever scale a fit
    meets) and the periodogram's threshold (ripple.find_terms: at the smaller scale it
    down-weights the residual's own structure, and on UR10 Series B found terms that
    extrapolated worse, docs/analyze.md)."""
    chain = rows.chain
    effect = EFFECTS[name]
    if not effect.usable(rows.data):
        return None
    say(f"trying {name}")
    found: dict[str, Any] | None = None
    prepare = getattr(effect, "prepare", None)
    if prepare is not None:  # an effect whose structure comes from the data (its terms)
        effect, found = prepare(model, x, rows.train, rows.tau_tr, unit)
        if not effect.size(chain.nq):
            say(f"{name}: nothing significant in the residual's spectra")
            report.setdefault("spectra", {})[name] = found
            return None
    trial_basis = dict(model.basis)
    if effect.reduce:  # never fit what the data cannot tell apart from what is there
        B, rank, full, null = identifiable_basis(model, rows.train, rows.tau_tr, x, effect)
        if rank == 0:
            say(f"{name}: nothing identifiable from these poses")
            return None
        trial_basis[name] = B
        say(f"{name}: {rank} of {full} parameters identifiable from these poses")
    else:
        null = np.zeros((0, 0))
    trial = Model(
        chain,
        rows.position_only,
        [*model.effects, effect],
        x,
        trial_basis,
        rows.refs[0],
        rows.refs[1],
        rows.sessions,
        model.tools,
    )
    x0 = np.concatenate([x, np.zeros(trial.sizes(chain.nq)[-1])])
    trial.x = x0
    trial_weights = dict(weights)
    choice = None
    if scales_of(effect, chain.nq) is not None:  # its weight from blocks and bands
        choice = choose_weight(
            trial,
            x0,
            rows.data,
            rows.tau_all,
            rows.train_idx,
            rows.val_idx,
            unit,
            name,
            huber_noise=scale_now,
        )
        trial_weights[name] = choice.weight
    prior = prior_rows(trial, trial_weights, unit)
    res = fit(trial, rows.train, rows.tau_tr, x0, scale_now, prior=prior)
    val_stats = stats(trial, res.x, rows.val, rows.tau_va)
    entry: dict[str, Any] = {
        "name": name,
        "parameters": _effect_parameters(trial, effect, res.x, res.se),
        "train": stats(trial, res.x, rows.train, rows.tau_tr).as_dict(),
        "validation": val_stats.as_dict(),
        "description": effect.description,
        "residual_scale_mm": scale_now * 1e3,
    }
    if found is not None:
        entry["spectra"] = found
        report.setdefault("spectra", {})[name] = found
    band_ok = True if choice is None else _prior_entry(entry, choice)
    if null.size:
        _mark_unidentifiable(entry, effect, null, chain.robot.joint_names)
    return _Trial(trial, res.x, entry, trial_weights, band_ok, val_stats.judged_mm)


def _prior_entry(entry: dict[str, Any], choice: PriorChoice) -> bool:
    """The prior's choice in the entry, with the extrapolation bands without and with the
    effect; whether the bands allow it (they did not rise)."""
    entry["prior"] = choice.as_dict()
    chosen = next(c for c in choice.table if c["weight"] == choice.weight)
    entry["bands"] = {
        "pos_rms_mm_without": choice.without_bands_mm,
        "pos_rms_mm_with": chosen["bands_pos_rms_mm"],
    }
    return bool(chosen["bands_pos_rms_mm"] <= choice.without_bands_mm)


def _mark_unidentifiable(
    entry: dict[str, Any], effect: Effect, null: np.ndarray, joint_names: Sequence[str]
) -> None:
    """The directions the poses cannot see, in the entry's parameters; a parameter they
    cannot see alone is held at zero, and its record says so."""
    zeros = np.zeros(null.shape[0])
    labels = [
        f"{rec['joint']} {rec['parameter']}" for rec in effect.records(zeros, zeros, joint_names)
    ]
    unseen = describe_null_space(null, labels)
    entry["parameters"]["unidentifiable"] = unseen
    held = {u["members"][0]["parameter"] for u in unseen if len(u["members"]) == 1}
    for rec in entry["parameters"].get("records", []):
        if f"{rec['joint']} {rec['parameter']}" in held:
            rec["held"] = True


def _rejection(entry: dict[str, Any], gain: float) -> str:
    """Why a candidate was not kept: too little held-out gain, or the bands rose."""
    if gain < KEEP_MARGIN:
        return f"held-out change {100 * gain:+.1f} %, below the {100 * KEEP_MARGIN:.0f} % needed"
    return (
        f"held-out change {100 * gain:+.1f} %, but the extrapolation bands rose "
        f"({entry['bands']['pos_rms_mm_without']:.4f} -> "
        f"{entry['bands']['pos_rms_mm_with']:.4f} mm)"
    )


def _bands_transfer(report: dict[str, Any]) -> None:
    """One session: the extrapolation bands stand for a session not seen."""
    judged = [e for e in (*report["effects"], *report["rejected"]) if "prior" in e]
    if not judged:
        return
    banded = [e for e in report["effects"] if "bands" in e]
    nominal = judged[0]["prior"]["without_effect"]["bands_pos_rms_mm"]
    report["transfer"] = {
        "kind": "held-out bands at the ends of each joint's range (one session)",
        "nominal_bands_pos_rms_mm": nominal,
        "model_bands_pos_rms_mm": banded[-1]["bands"]["pos_rms_mm_with"] if banded else nominal,
    }


def _registration_entry(
    report: dict[str, Any],
    model: Model,
    x: np.ndarray,
    noise: float,
    sessions: int,
    tools: dict[str, Any] | None,
) -> None:
    """The registration the final model holds: tracker and mount (per session when several)."""
    T_bk, T_ns, _c = model.unpack(x)
    report["registration"] = {
        "T_bk": T_bk.tolist(),
        "T_ns": T_ns.tolist(),
        "noise_estimate_mm": noise * 1e3,
    }
    if sessions > 1:
        report["registration"]["T_bk_sessions"] = [T.tolist() for T in model.registrations(x)]
        if tools is not None:
            report["registration"]["tools"] = tools
        if model.tools > 1:
            report["registration"]["T_ns_sessions"] = [
                model.mount(x, s).tolist() for s in range(model.tools)
            ]


def _registered(
    chain: Chain,
    train: Data,
    tau_tr: np.ndarray,
    position_only: bool,
    sessions: int,
    tools: int,
    refs: tuple[float, float],
) -> tuple[Model, np.ndarray, float]:
    """The nominal model registered on the training rows (tracker per session, `tools`
    sensor mounts), robustly, with the noise its residuals show."""
    reg0 = initial_registration_sessions(chain, train, position_only, sessions, tools)
    base = Model(chain, position_only, [], reg0, {}, refs[0], refs[1], sessions, tools)
    _check_registration(base, train, tau_tr)
    noise = 50e-6
    fitted = fit(base, train, tau_tr, reg0, noise)
    r = base.residuals(fitted.x, train, tau_tr)
    noise = max(1e-6, float(median_abs_deviation(r, scale="normal")))
    fitted = fit(base, train, tau_tr, fitted.x, noise)
    return base, fitted.x, noise


def session_report(report: dict[str, Any], model: Model, x: np.ndarray, data: Data) -> None:
    """Several recordings: the final model's numbers on each one's held-out and fitted rows
    (the pooled ones are report["final"])."""
    train_idx, val_idx = split_data(data)
    tau = model.chain.gravity_torques(data.q)
    out = []
    for s, rows in enumerate(data.session_rows(model.sessions)):
        entry: dict[str, Any] = {"session": s}
        for label, idx in (("train", train_idx), ("validation", val_idx)):
            mine = np.intersect1d(idx, rows)
            entry[label] = stats(model, x, data.subset(mine), tau[mine]).as_dict()
        entry["T_bk"] = model.registrations(x)[s].tolist()
        out.append(entry)
    report["sessions"] = out


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
    """Angle maps carried to new data (registration refitted, model fixed) are judged per
    joint: part of what a map absorbs belongs to the setup it was identified in (the
    tracker's own angle error moves with the tracker), so each joint's map is kept only where
    it helps here. The choice is made on the new data's registration rows (the maps never saw
    them; the held-out blocks stay untouched for the figures): joint by joint, a map whose
    removal lowers the error is dropped; then the maps left must lower the error by
    KEEP_MARGIN against the same model without any. Outside its calibrated angles each map
    fades to zero (over the distance the model states, `JointMaps.taper`), so a pose outside on
    one joint keeps the other joints' maps."""
    maps = model.find(JointMaps)
    assert maps is not None
    tau_tr = model.chain.gravity_torques(train.q)
    tau_va = model.chain.gravity_torques(val.q)
    names = model.chain.robot.joint_names

    def with_joints(keep: list[int]) -> tuple[Model, np.ndarray]:
        return _with_maps_of(model, x, maps, keep, train, tau_tr, noise)

    joints = [j for j, kn in enumerate(maps.knots) if kn.size]
    current = stats(model, x, train, tau_tr).judged_mm
    dropped: list[dict[str, Any]] = []
    for j in list(joints):
        rest = [i for i in joints if i != j]
        trial, x_trial = with_joints(rest)
        rms = stats(trial, x_trial, train, tau_tr).judged_mm
        if rms < current:
            joints, current = rest, rms
            dropped.append({"joint": names[j], "fitted_rows_pos_rms_mm_without": rms})
    kept_model, kept_x = with_joints(joints) if dropped else (model, x)
    without, x_without = with_joints([])
    with_maps_tr = stats(kept_model, kept_x, train, tau_tr).judged_mm
    without_tr = stats(without, x_without, train, tau_tr).judged_mm
    kept = bool(joints) and 1 - with_maps_tr / without_tr >= KEEP_MARGIN
    lo, hi = maps.ranges()
    outside = (data.q < lo) | (data.q > hi)
    report["carried_maps"] = {
        "taper_rad": maps.taper,
        "held_out_pos_rms_mm_with": stats(kept_model, kept_x, val, tau_va).judged_mm,
        "held_out_pos_rms_mm_without": stats(without, x_without, val, tau_va).judged_mm,
        "fitted_rows_pos_rms_mm_with": with_maps_tr,
        "fitted_rows_pos_rms_mm_without": without_tr,
        "kept": kept,
        "joints_kept": [names[j] for j in joints] if kept else [],
        "joints_dropped": dropped,
        "poses_outside_calibrated_range_pct": 100.0 * float(np.mean(np.any(outside, axis=1))),
        "outside_pct_per_joint": {
            names[j]: 100.0 * float(np.mean(outside[:, j])) for j in range(outside.shape[1])
        },
    }
    return (kept_model, kept_x) if kept else (without, x_without)


def _with_maps_of(
    model: Model,
    x: np.ndarray,
    maps: JointMaps,
    keep: list[int],
    train: Data,
    tau_tr: np.ndarray,
    noise: float,
) -> tuple[Model, np.ndarray]:
    """The carried model with only the maps of joints `keep` (the others dropped), its
    registration refitted on the training rows with the robot model held."""
    effects: list[Effect] = []
    values: list[np.ndarray] = []
    for effect, part in model.parts(x):
        if effect is maps:
            pieces = split_maps(maps.knots, part)
            if not keep:
                continue
            knots = tuple(kn if j in keep else np.empty(0) for j, (kn, _v) in enumerate(pieces))
            effects.append(JointMaps(knots, maps.taper))
            values.append(np.concatenate([v for j, (_k, v) in enumerate(pieces) if j in keep]))
        else:
            effects.append(effect)
            values.append(part)
    return _registration_refitted(model, x, effects, values, train, tau_tr, noise)


def _registration_refitted(
    model: Model,
    x: np.ndarray,
    effects: list[Effect],
    values: list[np.ndarray],
    train: Data,
    tau_tr: np.ndarray,
    noise: float,
) -> tuple[Model, np.ndarray]:
    """`model` with `effects` (their parameters `values`) in place of its own, and its
    registration refitted on the training rows with the robot model held: how a carried
    model is judged without one of its parts."""
    x_new = np.concatenate([x[: model.n_reg], *values])
    trial = Model(
        model.chain,
        model.position_only,
        effects,
        x_new,
        {},
        model.temperature_ref,
        model.time_ref,
        model.sessions,
        model.tools,
    )
    fixed = np.zeros(x_new.size, dtype=bool)
    fixed[trial.n_reg :] = True
    return trial, fit(trial, train, tau_tr, x_new, noise, fixed=fixed).x


def _repeatability_entry(data: Data) -> dict[str, Any] | None:
    """The data's repeatability from rows with equal joints. Only stop-and-measure data
    repeat a commanded pose: in motion data equal joints are the same angles passed at
    different times (with the delay's and the dynamics' errors in them), so what is found
    there is reported and not used as a floor."""
    rep = repeatability(data.q, data.p_ks)
    if rep is None:
        return None
    out = rep.as_dict()
    static = data.velocity is None
    out["used_as_floor"] = static
    if not static:
        out["note"] = (
            f"{rep.measurements} rows of motion at {rep.poses} joint positions passed more "
            f"than once scatter by {rep.rms_mm:.4f} mm RMS: the same angles reached at "
            "different times in motion, not repeats of one commanded pose, so not used as "
            "a floor"
        )
    return out


def describe_remaining(
    report: dict[str, Any],
    model: Model,
    x: np.ndarray,
    data: Data,
    uncertainty: TrackerUncertainty | None = None,
) -> None:
    """What the residual of `model` still correlates with, the floor a perfect model would
    reach on the held-out poses, and the verdict in words (called again when a later stage,
    the angle maps, changes the final model). `uncertainty`: the tracker's specification
    (None: the one this report already holds, else keo's assumed default)."""
    corr = correlations(model, x, data, model.chain.gravity_torques(data.q))
    report["correlations"] = corr[:10]
    if uncertainty is None:
        held = report.get("floor", {}).get("tracker_uncertainty")
        uncertainty = TrackerUncertainty(**held) if held else TrackerUncertainty()
    train_idx, val_idx = split_data(data)
    rep = report.get("repeatability")
    width = 3 if model.position_only or data.R_ks is None else 6
    report["floor"] = floor_report(
        None if data.sigma is None else data.sigma[val_idx],
        data.p_ks[val_idx],
        uncertainty,
        rep["rms_mm"] if rep and rep.get("used_as_floor") else None,
        int(x.size),
        width * int(train_idx.size),
    )
    final = report["final"]["validation"]["pos_rms_mm"]
    report["floor"]["ratio"] = final / report["floor"]["pos_rms_mm"]
    report["unexplained"] = _verdict(report, corr)
    if model.sessions > 1:
        session_report(report, model, x, data)


def _verdict(report: dict[str, Any], corr: list[dict[str, Any]]) -> str:
    """Within NOISE_RATIO x the floor and without structure: consistent with noise; else the
    excess over the floor in mm (sqrt(final^2 - floor^2), the part noise cannot explain) and
    where the correlations point."""
    strong = [c for c in corr if c["r2"] > max(0.15, 5 * c["chance"])]
    final = report["final"]["validation"]["pos_rms_mm"]
    floor = report["floor"]
    ratio = floor["ratio"]
    excess = float(np.sqrt(max(final**2 - floor["pos_rms_mm"] ** 2, 0.0)))
    against = f"{ratio:.2f}x the floor of {floor['pos_rms_mm']:.4f} mm (from the {floor['label']})"
    if strong:
        names = ", ".join(f"{c['variable']} (R^2 {c['r2']:.2f})" for c in strong[:4])
        return (
            f"structured residual remains ({final:.4f} mm RMS held out, {against}; "
            f"{excess:.4f} mm above the noise) that no effect in the library explains; it "
            f"correlates with {names}"
        )
    head = (
        f"the remaining {final:.4f} mm RMS held out is {against} and shows no structure "
        f"against the candidate variables (largest R^2 {corr[0]['r2']:.2f} with "
        f"{corr[0]['variable']})"
    )
    if ratio <= NOISE_RATIO:
        return f"{head}: consistent with noise"
    pointing = ", ".join(f"{c['variable']} (R^2 {c['r2']:.2f})" for c in corr[:3])
    return (
        f"{head}, yet it exceeds the noise by {excess:.4f} mm RMS: model error that none of "
        f"these variables explains alone; the largest correlations point at {pointing}"
    )
