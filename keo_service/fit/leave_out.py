"""Leave one session out: how a model fitted on some recordings does on a recording it never
saw, with only the tracker registration and the sensor mount fitted there (as
`keo analyze --registration-only` does on a new session). No I/O.

Why: the held-out blocks of a recording are interpolation (their neighbours were fitted); a
user calibrates once and then runs on other days, from other tracker stations, in other parts
of the workspace. With several recordings the honest figure for that is to fit on all but
one and judge on the one left out, each in turn. And pooling recordings must earn its place:
for every recording left out, the model of the others pooled is compared with each other
recording's model alone; where pooling did worse than the best single recording, the report
says so (a recording that teaches the model something false about the others' workspace).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from keo_service.core.kinematics import RobotModel
from keo_service.fit.accuracy import (
    Accuracy,
    coverage,
    predicted_position_sigma,
    session_term,
    stated_accuracy,
)
from keo_service.fit.analysis import (
    CANDIDATES,
    KEEP_MARGIN,
    Analysis,
    analyze,
    sessions_of,
    split_data,
)
from keo_service.fit.angle_maps import try_maps
from keo_service.fit.coupling import try_couplings
from keo_service.fit.model import Data, Model, NotIdentifiableError
from keo_service.fit.uncertainty import TrackerUncertainty

# pooling is "worse" than a single recording when its error on the recording left out is
# this much above the best single one's (the keep margin of every other choice) and beyond
# the held-out poses' scatter (pooled_worse)
POOLED_MARGIN = KEEP_MARGIN


def fit_full(
    robot: RobotModel,
    data: Data,
    position_only: bool,
    uncertainty: TrackerUncertainty | None = None,
    say: Callable[[str], None] | None = None,
    candidates: tuple[str, ...] = CANDIDATES,
    on_top: bool = True,
) -> Analysis:
    """The whole identification of `keo analyze` on `data` (one recording or several): the
    effects (`candidates`), then (`on_top`) the joint maps and the couplings on top."""
    result = analyze(
        robot, data, position_only, progress=say, candidates=candidates, uncertainty=uncertainty
    )
    if not on_top:
        return result
    train_idx, val_idx = split_data(data)
    names = robot.joint_names
    try_maps(result, data, train_idx, val_idx, KEEP_MARGIN, names, say)
    try_couplings(result, data, train_idx, val_idx, KEEP_MARGIN, names, say)
    return result


def fitted(result: Analysis) -> Model:
    """The analysis' model holding its fitted parameters (an Analysis keeps them beside the
    model, whose own x is where its last fit started)."""
    return dataclasses.replace(result.model, x=result.x)


def sessions_subset(data: Data, sessions: Sequence[int]) -> Data:
    """The rows of `sessions`, relabelled 0..k-1 and weighted so each counts equally (one
    session: unlabelled and unweighted, as a recording analysed alone)."""
    assert data.session is not None
    rows = np.flatnonzero(np.isin(data.session, list(sessions)))
    sub = data.subset(rows)
    if len(sessions) == 1:
        return dataclasses.replace(sub, session=None, weight=None)
    assert sub.session is not None
    label = np.searchsorted(np.sort(np.asarray(sessions)), sub.session)
    counts = np.bincount(label, minlength=len(sessions)).astype(float)
    weight = sub.n / (len(sessions) * counts[label])
    return dataclasses.replace(sub, session=label, weight=weight)


def stated(result: Analysis, data: Data) -> Accuracy:
    """The accuracy the model of `result` (fitted on `data`) states, as `keo analyze` writes
    it to model.toml: its calibrated ranges those of the training rows (split_data), the
    poses the model was fitted on."""
    train_idx, _val_idx = split_data(data)
    return stated_accuracy(result.report, data.q[train_idx])


def held_out_errors(result: Analysis, data: Data) -> tuple[np.ndarray, np.ndarray]:
    """The held-out poses' joints and position error lengths (mm) under `result`'s model."""
    _train, val_idx = split_data(data)
    val = data.subset(val_idx)
    model = result.model
    r = model.residuals(result.x, val, model.chain.gravity_torques(val.q))
    width = 3 if model.position_only or data.R_ks is None else 6
    return val.q, np.linalg.norm(r.reshape(-1, width)[:, :3], axis=1) * 1e3


def carried(
    robot: RobotModel,
    model: Model,
    data: Data,
    position_only: bool,
    accuracy: Accuracy | None = None,
) -> dict[str, Any]:
    """`model` carried to one recording: the registration (and the mount) refitted on its
    training rows, the robot model as it is (carried maps judged per joint, as with
    --registration-only); its held-out numbers, and the nominal robot's there. With the
    model's stated `accuracy`: how it covered the held-out poses, as stated within its own
    session (`stated_within`) and with its between-session term (`stated_off_session`)."""
    result = analyze(robot, data, position_only, fixed_model=model)
    rep = result.report
    out: dict[str, Any] = {
        "held_out_poses": rep["final"]["validation"]["n"],
        "held_out_pos_rms_mm": rep["final"]["validation"]["pos_rms_mm"],
        "held_out_pos_max_mm": rep["final"]["validation"]["pos_max_mm"],
        "nominal_pos_rms_mm": rep["baseline"]["validation"]["pos_rms_mm"],
    }
    if "carried_maps" in rep:
        out["maps_kept"] = rep["carried_maps"]["kept"]
    if accuracy is not None:
        q, error_mm = held_out_errors(result, data)
        out["stated_within"] = coverage(predicted_position_sigma(accuracy, q), error_mm)
        out["stated_off_session"] = {
            **coverage(predicted_position_sigma(accuracy, q, off_session=True), error_mm),
            "session_mm": accuracy.session_mm,
            "session_source": accuracy.session_source,
        }
    return out


def leave_one_session_out(
    robot: RobotModel,
    data: Data,
    position_only: bool,
    pooled: Analysis,
    uncertainty: TrackerUncertainty | None = None,
    say: Callable[[str], None] | None = None,
    candidates: tuple[str, ...] = CANDIDATES,
    on_top: bool = True,
) -> dict[str, Any]:
    """Each recording left out in turn: the model of the others (pooled when there are
    several) carried to it, beside its within-session held-out figure from the pooled model
    (`pooled`: the analysis of all recordings) and its own model's. With three or more
    recordings, each other recording's model alone is carried to it too, and where the pooled
    one did worse than the best of them (pooled_worse) the entry and the summary say so.
    `candidates`, `on_top`: as fit_full (the pooled analysis' own choices)."""
    say = say or (lambda _m: None)
    n = sessions_of(data)
    own: dict[int, Analysis] = {}
    for s in range(n):
        say(f"leave one session out: session {s + 1}'s model alone")
        own[s] = fit_full(
            robot, sessions_subset(data, [s]), position_only, uncertainty, None, candidates, on_top
        )
    within = {e["session"]: e["validation"]["pos_rms_mm"] for e in pooled.report["sessions"]}
    entries: list[dict[str, Any]] = []
    for s in range(n):
        others = [o for o in range(n) if o != s]
        alone = sessions_subset(data, [s])
        if len(others) == 1:
            model = fitted(own[others[0]])
            accuracy = stated(own[others[0]], sessions_subset(data, others))
        else:
            say(f"leave one session out: sessions {_names(others)} pooled, session {s + 1} out")
            try:
                part = sessions_subset(data, others)
                part_fit = fit_full(
                    robot, part, position_only, uncertainty, None, candidates, on_top
                )
            except NotIdentifiableError as exc:
                entries.append({"session": s, "fitted_on": others, "error": str(exc)})
                continue
            model, accuracy = fitted(part_fit), stated(part_fit, part)
        entry: dict[str, Any] = {
            "session": s,
            "fitted_on": others,
            **carried(robot, model, alone, position_only, accuracy),
            "within_session_pooled_pos_rms_mm": within[s],
            "within_session_own_pos_rms_mm": own[s].report["final"]["validation"]["pos_rms_mm"],
        }
        if len(others) > 1:
            singles = {o: carried(robot, fitted(own[o]), alone, position_only) for o in others}
            best = min(others, key=lambda o: singles[o]["held_out_pos_rms_mm"])
            best_mm = singles[best]["held_out_pos_rms_mm"]
            entry["single_sessions"] = [{"fitted_on": o, **singles[o]} for o in others]
            entry["best_single"] = {"fitted_on": best, "held_out_pos_rms_mm": best_mm}
            entry["pooled_worse_than_best_single"] = pooled_worse(
                entry["held_out_pos_rms_mm"], best_mm, int(entry["held_out_poses"])
            )
        entries.append(entry)
        say(
            f"session {s + 1} left out: {entry['held_out_pos_rms_mm']:.4f} mm held out "
            f"(nominal {entry['nominal_pos_rms_mm']:.4f}, within the session "
            f"{within[s]:.4f})"
        )
    out: dict[str, Any] = {
        "kind": "leave one session out",
        "entries": entries,
        "summary": _summary(entries),
    }
    term = _session_term(entries)
    if term is not None:
        out["session_term"] = term
    return out


def _session_term(entries: list[dict[str, Any]]) -> dict[str, Any] | None:
    """What the carried models missed beyond their within-session statement, over the
    recordings left out (fit.accuracy.session_term); None when none was judged."""
    judged = [e for e in entries if "stated_within" in e]
    if not judged:
        return None
    measured = [e["held_out_pos_rms_mm"] for e in judged]
    stated = [e["stated_within"]["predicted_rms_mm"] for e in judged]
    return {"session_mm": session_term(measured, stated), "sessions": len(judged)}


def pooled_worse(pooled_mm: float, single_mm: float, poses: int) -> bool:
    """Pooling did worse than a single recording on the recording left out: its held-out RMS
    is POOLED_MARGIN above the single one's and the difference is beyond what the held-out
    poses' own scatter allows (two standard errors of the difference of two RMS over `poses`
    3-D errors, each RMS / sqrt(6 x poses)): with a few dozen held-out poses at the noise,
    5 % is chance."""
    se = np.hypot(pooled_mm, single_mm) / np.sqrt(6.0 * max(poses, 1))
    return bool(pooled_mm - single_mm > max(POOLED_MARGIN * single_mm, 2.0 * se))


def _names(sessions: Sequence[int]) -> str:
    return "+".join(str(s + 1) for s in sessions)


def _summary(entries: list[dict[str, Any]]) -> dict[str, Any]:
    """The transfer headline: RMS over the recordings left out (each counted once), beside the
    within-session figure over the same recordings, and the pooling verdict in words."""
    ok = [e for e in entries if "held_out_pos_rms_mm" in e]
    if not ok:
        return {"verdict": "no recording could be left out (the others cannot be fitted)"}
    out: dict[str, Any] = {
        "left_out_pos_rms_mm": float(np.sqrt(np.mean([e["held_out_pos_rms_mm"] ** 2 for e in ok]))),
        "within_session_pos_rms_mm": float(
            np.sqrt(np.mean([e["within_session_pooled_pos_rms_mm"] ** 2 for e in ok]))
        ),
        "nominal_pos_rms_mm": float(np.sqrt(np.mean([e["nominal_pos_rms_mm"] ** 2 for e in ok]))),
    }
    compared = [e for e in ok if "best_single" in e]
    worse = [e for e in compared if e["pooled_worse_than_best_single"]]
    if not compared:
        out["verdict"] = (
            "two recordings: each left out is judged by the other's model alone, so pooling "
            "is not compared with a single recording on a recording left out (that takes three "
            "or more)"
        )
    elif not worse:
        out["verdict"] = (
            f"pooling the others did no worse than the best single recording on every "
            f"recording left out ({len(compared)} compared)"
        )
    else:
        parts = [
            f"session {e['session'] + 1}: pooled {e['held_out_pos_rms_mm']:.4f} mm, session "
            f"{e['best_single']['fitted_on'] + 1} alone "
            f"{e['best_single']['held_out_pos_rms_mm']:.4f} mm"
            for e in worse
        ]
        out["verdict"] = (
            "pooling did worse than a single recording on a recording left out ("
            + "; ".join(parts)
            + "): the pooled model is written, but on a new session like those it is not the "
            "best choice; compare the recordings (a station, a mount or a workspace that "
            "differs) before relying on it"
        )
    out["pooled_worse_than_best_single"] = [e["session"] for e in worse]
    return out
