"""`keo analyze`: read each recording once, pair its streams, run the analysis (the delay from
the motion, the effects, the joint maps and couplings, the diagnostics) and hand the result to
`io.analysis_report`, which writes report.json, report.md, the plots and model.toml."""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.spatial.transform import Rotation

from keo_service.core.chain import Chain
from keo_service.core.errors import KeoError
from keo_service.core.model_corrections import approach_directions, persist_directions
from keo_service.core.rules import DIRECTION_DEADBAND
from keo_service.core.timing import DelayModel
from keo_service.fit.accuracy import (
    coverage,
    distance_outside,
    predicted_position_sigma,
)
from keo_service.fit.analysis import (
    KEEP_MARGIN,
    Analysis,
    NotIdentifiableError,
    analyze,
    split_data,
)
from keo_service.fit.angle_maps import try_maps
from keo_service.fit.coupling import try_couplings
from keo_service.fit.diagnostics import repeatability, residual_components
from keo_service.fit.leave_out import leave_one_session_out, stated
from keo_service.fit.model import Data, Model, fit, initial_registration_sessions
from keo_service.fit.sampling import MAX_ROWS, informative_rows, selection_report
from keo_service.fit.uncertainty import iso_path_figures, iso_pose_figures
from keo_service.io.analysis_report import (
    model_config,
    saved_accuracy,
    saved_model,
    tracker_uncertainty,
    with_delay,
    write_analysis,
)
from keo_service.io.cell import delay_model, robot_from_config
from keo_service.offline.recording import Recording, read_recording

if TYPE_CHECKING:
    from keo_service.core.kinematics import RobotModel
    from keo_service.io.config import Config

SIGMA_COLUMNS = ("sx", "sy", "sz")  # optional tracker.csv columns: per-point std (m)
SPEED_STEP_S = 0.01  # s either side of a tracker sample for the joints' speed
OUTLIER_FACTOR = 4.0  # a pose whose position error exceeds this x the held-out RMS is listed
OUTLIER_RUN = 3  # this many consecutive listed poses are reported as a run


def is_static(recording: Recording) -> bool:
    """Stop-and-measure data: an encoder row at every tracker row's t (no delay applies)."""
    trk_t = recording.tracker.t
    return bool(np.all(np.isin(trk_t[np.isfinite(trk_t)], recording.encoder.t)))


def pair_streams(
    robot: RobotModel,
    recording: Recording,
    delay: DelayModel,
    max_rows: int = MAX_ROWS,
    info: dict[str, Any] | None = None,
) -> tuple[Data, bool]:
    """Each tracker row with the joints at its time minus the delay; stop-and-measure data
    use none. Of a long motion recording at most `max_rows` informative rows are kept
    (fit.sampling); `info` gets how many were recorded and used, and how they were chosen.
    Returns the data and whether the tracker measured positions only."""
    enc, trk = recording.encoder, recording.tracker
    ok_e = np.isfinite(enc.t) & np.all(np.isfinite(enc.q), axis=1)
    enc_t, enc_q = enc.t[ok_e], enc.q[ok_e]
    order = np.argsort(enc_t)
    enc_t, enc_q = enc_t[order], enc_q[order]
    static = bool(np.all(np.isin(trk.t[np.isfinite(trk.t)], enc_t)))
    target = trk.t.copy() if static else delay.encoder_times(trk.t)
    ok = np.isfinite(trk.t) & np.all(np.isfinite(trk.p), axis=1)
    ok &= (target >= enc_t[0]) & (target <= enc_t[-1])
    if trk.quat is not None:
        ok &= np.all(np.isfinite(trk.quat), axis=1)
    target = target[ok]

    def joints_at(times: np.ndarray) -> np.ndarray:
        return np.column_stack([np.interp(times, enc_t, enc_q[:, j]) for j in range(robot.nq)])

    q = joints_at(target)
    velocity = tool_speed = None
    if static:  # stop-and-measure: approach direction from the previous pose
        direction = approach_directions(q)
    else:
        h = SPEED_STEP_S
        ahead, behind = joints_at(target + h), joints_at(target - h)
        velocity = (ahead - behind) / (2 * h)
        moving = np.where(np.abs(velocity) > DIRECTION_DEADBAND, np.sign(velocity), 0.0)
        direction = persist_directions(moving)
        rows = informative_rows(q, direction, max_rows)
        if info is not None:
            info.update(selection_report(q.shape[0], rows))
        if rows.size < q.shape[0]:
            keep = np.zeros(ok.size, dtype=bool)
            keep[np.flatnonzero(ok)[rows]] = True
            ok = keep
            q, velocity, direction = q[rows], velocity[rows], direction[rows]
            ahead, behind = ahead[rows], behind[rows]
        chain = Chain(robot)
        moved = chain.flange_poses(ahead)[:, :3, 3] - chain.flange_poses(behind)[:, :3, 3]
        tool_speed = np.linalg.norm(moved, axis=1) / (2 * h)
    R = None
    if trk.quat is not None:
        R = Rotation.from_quat(trk.quat[ok], scalar_first=True).as_matrix()
    extra = {k: v[ok] for k, v in trk.extra.items() if k not in SIGMA_COLUMNS}
    sigma = None
    if all(c in trk.extra for c in SIGMA_COLUMNS):
        sigma = np.column_stack([trk.extra[c][ok] for c in SIGMA_COLUMNS])
    if tool_speed is not None:
        extra["tool_speed_m_s"] = tool_speed
    data = Data(q, trk.p[ok], R, trk.t[ok], extra, direction, velocity, sigma)
    return data, trk.quat is None


def load_data(
    config: Config,
    encoder_path: Path,
    tracker_path: Path,
    delay: DelayModel | None = None,
    max_rows: int = MAX_ROWS,
    info: dict[str, Any] | None = None,
) -> tuple[Data, bool]:
    """One recording read and paired with the config's delay (unless given)."""
    recording = read_recording(config, encoder_path, tracker_path, mcap=False)
    if delay is None:
        delay = delay_model(config.timing)
    return pair_streams(robot_from_config(config), recording, delay, max_rows, info)


def pooled(parts: list[Data]) -> Data:
    """Several recordings as one Data with session labels (columns all share, else none)."""

    def stack(arrays: list[np.ndarray | None]) -> np.ndarray | None:
        if any(a is None for a in arrays):
            return None
        return np.concatenate([a for a in arrays if a is not None])

    extra_keys = set.intersection(*(set(d.extra) for d in parts))
    return Data(
        np.concatenate([d.q for d in parts]),
        np.concatenate([d.p_ks for d in parts]),
        stack([d.R_ks for d in parts]),
        np.concatenate([d.t for d in parts]),
        {k: np.concatenate([d.extra[k] for d in parts]) for k in sorted(extra_keys)},
        stack([d.direction for d in parts]),
        stack([d.velocity for d in parts]),
        stack([d.sigma for d in parts]),
        np.concatenate([np.full(d.n, s) for s, d in enumerate(parts)]),
        session_weights([d.n for d in parts]),
    )


def session_weights(rows: list[int]) -> np.ndarray:
    """Per row, total / (sessions x its session's rows): each session counts equally in the
    fit and the held-out judgement (mean weight 1), however many poses it has."""
    total = sum(rows)
    return np.concatenate([np.full(n, total / (len(rows) * n)) for n in rows])


def time_delay_effect(
    config: Config,
    robot: RobotModel,
    recording: Recording,
    data: Data,
    position_only: bool,
    say: Callable[[str], None],
) -> tuple[Data, dict[str, Any] | None]:
    """Motion data: the delay (and drift) from the motion itself, kept if pairing the streams
    with it lowers the held-out error of the registered nominal model by 5 %."""
    from keo_service.fit.delay import DelayNotIdentifiableError
    from keo_service.fit.delay_effect import fit_recording_delay, judge_delay

    say("trying time_delay (the delay between the streams, from the motion)")
    try:
        found = fit_recording_delay(
            recording.cell, *recording.streams(), initial=config.timing.delay_s
        )
    except DelayNotIdentifiableError as exc:
        say(f"time_delay: not identifiable ({exc})")
        return data, None
    model_delay = DelayModel(found.delay_s, found.drift, found.t_ref)
    new_data, _ = pair_streams(robot, recording, model_delay)
    entry = judge_delay(Chain(recording.cell.robot), found, data, new_data, position_only)
    say(
        f"time_delay: {found.delay_s * 1e3:.2f} +/- {found.delay_se_s * 1e3:.2f} ms, held-out "
        f"change {entry['held_out_improvement_pct']:+.1f} %"
    )
    return (new_data if entry["kept"] else data), entry


def _read_all(
    config: Config, encoders: list[Path], trackers: list[Path], registration_only: bool
) -> list[Recording]:
    """Every recording, each file read once (the pairs checked first)."""
    if len(encoders) != len(trackers):
        raise KeoError(
            f"--encoder and --tracker come in pairs (one of each per recording): got "
            f"{len(encoders)} and {len(trackers)}"
        )
    if registration_only and len(encoders) > 1:
        raise KeoError("--registration-only takes one recording (one --encoder/--tracker pair)")
    pairs = zip(encoders, trackers, strict=True)
    return [read_recording(config, e, t, mcap=False) for e, t in pairs]


def _load_sessions(
    robot: RobotModel, recordings: list[Recording], delay: DelayModel
) -> tuple[Data, bool]:
    loaded = [pair_streams(robot, r, delay) for r in recordings]
    if len({p for _d, p in loaded}) > 1:
        raise KeoError("the recordings mix a 6-DoF probe and a single reflector")
    return pooled([d for d, _p in loaded]), loaded[0][1]


def run_analysis(
    config: Config,
    encoder: Path | list[Path],
    tracker: Path | list[Path],
    out: Path,
    registration_only: bool,
    recordings: list[Recording] | None = None,
) -> dict[str, Any]:
    """`keo analyze`: one recording, or several (repeated --encoder/--tracker pairs: each with
    its own tracker registration, one robot model; the delay is the config's for each). Each
    file is read once (`recordings`: already read, e.g. by the library's `analyze`)."""

    def progress(msg: str) -> None:
        print(f"[analyze] {msg}", file=sys.stderr, flush=True)

    samples: dict[str, Any] = {}
    encoders = encoder if isinstance(encoder, list) else [encoder]
    trackers = tracker if isinstance(tracker, list) else [tracker]
    recordings = recordings or _read_all(config, encoders, trackers, registration_only)
    robot = robot_from_config(config)
    delay = delay_model(config.timing)
    delay_entry = None
    if len(recordings) == 1:
        recording = recordings[0]
        data, position_only = pair_streams(robot, recording, delay, info=samples)
        if not registration_only and not is_static(recording):
            data, delay_entry = time_delay_effect(
                config, robot, recording, data, position_only, progress
            )
    else:
        data, position_only = _load_sessions(robot, recordings, delay)
        progress(f"{len(recordings)} recordings, one tracker registration each, one robot model")

    chain = Chain(robot)
    fixed = saved_model(config, chain, position_only) if registration_only else None
    try:
        result = analyze(
            robot,
            data,
            position_only,
            fixed_model=fixed,
            progress=progress,
            uncertainty=tracker_uncertainty(config),
        )
    except NotIdentifiableError as exc:
        raise KeoError(f"cannot analyze these data: {exc}") from None
    if fixed is None:
        _on_top(result, robot, data, position_only, config, len(recordings), progress)
    _state_accuracy(result, data, config if fixed is not None else None, progress)
    sessions, tools = result.model.sessions, result.model.tools
    baseline = Model(
        chain, position_only, [], result.x[: result.model.n_reg], {}, 0.0, 0.0, sessions, tools
    )
    tau = chain.gravity_torques(data.q)
    base_x = fit(
        baseline,
        data,
        tau,
        initial_registration_sessions(chain, data, position_only, sessions, tools),
        result.report["registration"]["noise_estimate_mm"] * 1e-3,
    ).x
    report = result.report
    add_diagnostics(report, result, data, base_x, baseline)
    improved = model_config(result, config)
    if delay_entry is not None:
        if delay_entry.pop("kept"):
            report["baseline"] = delay_entry.pop("baseline")
            report["effects"].insert(0, delay_entry)
            improved = with_delay(improved, delay_entry["parameters"])
        else:
            delay_entry.pop("baseline")
            report["rejected"].insert(0, delay_entry)
    report["position_only"] = position_only
    report["registration_only"] = registration_only
    if samples:
        report["samples"] = samples
    write_analysis(out, report, result, data, base_x, baseline, improved)
    return report


def _on_top(
    result: Analysis,
    robot: RobotModel,
    data: Data,
    position_only: bool,
    config: Config,
    recordings: int,
    say: Callable[[str], None],
) -> None:
    """A new model: the joint maps and the couplings on top of the effects; with several
    recordings, each left out in turn."""
    train_idx, val_idx = split_data(data)
    try_maps(result, data, train_idx, val_idx, KEEP_MARGIN, robot.joint_names, say)
    try_couplings(result, data, train_idx, val_idx, KEEP_MARGIN, robot.joint_names, say)
    if recordings > 1:
        _leave_one_out(result, robot, data, position_only, config, say)


def _leave_one_out(
    result: Analysis,
    robot: RobotModel,
    data: Data,
    position_only: bool,
    config: Config,
    say: Callable[[str], None],
) -> None:
    """Several recordings: leave-one-session-out (fit.leave_out) is the transfer figure, the
    report's headline beside the within-session one."""
    loso = leave_one_session_out(
        robot, data, position_only, result, tracker_uncertainty(config), say
    )
    report = result.report
    report["leave_one_session_out"] = loso
    summary = loso["summary"]
    if "left_out_pos_rms_mm" in summary:
        report["transfer"] = {
            "kind": "leave one session out (fit on the others, registration only on the one "
            "left out)",
            "left_out_pos_rms_mm": summary["left_out_pos_rms_mm"],
            "within_session_pos_rms_mm": summary["within_session_pos_rms_mm"],
            "nominal_pos_rms_mm": summary["nominal_pos_rms_mm"],
        }
    say(summary["verdict"])


def _state_accuracy(
    result: Analysis, data: Data, carried: Config | None, say: Callable[[str], None]
) -> None:
    """The model's stated accuracy (fit.accuracy) and how it covers the held-out poses: a new
    model states its own from this analysis; a carried one (`carried`: its config,
    --registration-only) is judged on this session against what it stated."""
    report = result.report
    train_idx, val_idx = split_data(data)
    val = data.subset(val_idx)
    chain = result.model.chain
    width = 3 if result.model.position_only or data.R_ks is None else 6
    r = result.model.residuals(result.x, data, chain.gravity_torques(data.q)).reshape(-1, width)
    all_mm = np.linalg.norm(r[:, :3], axis=1) * 1e3
    error_mm = all_mm[val_idx]
    report["outliers"] = outlier_poses(
        all_mm, error_mm, data, train_idx, val_idx, chain.robot.joint_names
    )
    if carried is None:
        acc = stated(result, data)  # its ranges from the training rows
        report["accuracy"] = acc.as_dict()
        report["accuracy"]["held_out_coverage"] = coverage(
            predicted_position_sigma(acc, val.q), error_mm
        )
        return
    saved = saved_accuracy(carried)
    if saved is None:
        say("the model states no accuracy (written by an older keo): nothing to compare")
        return
    # a new session: the stated accuracy with its between-session term (fit.accuracy)
    cov = coverage(predicted_position_sigma(saved, val.q, off_session=True), error_mm)
    outside = distance_outside(val.q, saved.lower, saved.upper) > 0
    cov["outside_calibrated_range_pct"] = 100.0 * float(np.mean(outside))
    cov["session_mm"] = saved.session_mm
    cov["session_source"] = saved.session_source
    cov["within_session_band"] = coverage(predicted_position_sigma(saved, val.q), error_mm)
    report["predicted_vs_measured"] = cov
    say(
        f"the model predicted {cov['predicted_rms_mm']:.4f} mm RMS on this session's "
        f"held-out poses ({cov['outside_calibrated_range_pct']:.0f} % outside its calibrated "
        f"joint ranges, {saved.session_mm:.4f} mm between sessions); measured "
        f"{cov['measured_rms_mm']:.4f} mm, {cov['within_95_pct']:.0f} % of the poses within "
        "its 95 % band"
    )


def outlier_poses(
    all_mm: np.ndarray,
    error_mm: np.ndarray,
    data: Data,
    train_idx: np.ndarray,
    val_idx: np.ndarray,
    joint_names: list[str] | tuple[str, ...],
) -> dict[str, Any]:
    """The poses whose position error exceeds OUTLIER_FACTOR x the held-out RMS, fitted and
    held out, each with the joints on which it lies outside the angles the fit saw (rad), and
    the runs of consecutive such poses. Nothing is rejected: a run outside the fitted angles is
    the model extrapolating (a fault of the measurement would show inside them as well; UR10
    Series A's rows 9965-9975 are such a run, docs/analyze.md), and the listing lets the
    reader tell the two apart."""
    threshold = OUTLIER_FACTOR * float(np.sqrt(np.mean(error_mm**2)))
    lo, hi = data.q[train_idx].min(axis=0), data.q[train_idx].max(axis=0)
    out: dict[str, Any] = {"threshold_mm": threshold}
    runs: list[dict[str, Any]] = []

    def outside(i: int) -> dict[str, float]:
        d = np.maximum(lo - data.q[i], 0.0) + np.maximum(data.q[i] - hi, 0.0)
        return {str(joint_names[j]): float(d[j]) for j in np.flatnonzero(d > 0)}

    for label, idx in (("fitted", train_idx), ("held_out", val_idx)):
        rows = np.sort(idx[all_mm[idx] > threshold])
        entries: dict[int, dict[str, Any]] = {
            int(i): {"row": int(i), "t": float(data.t[i]), "pos_mm": float(all_mm[i])}
            | ({"outside_fitted_rad": o} if (o := outside(int(i))) else {})
            for i in rows
        }
        out[label] = [entries[int(i)] for i in rows[np.argsort(-all_mm[rows], kind="stable")]]
        for run in np.split(rows, np.flatnonzero(np.diff(rows) > 1) + 1):
            if run.size < OUTLIER_RUN:
                continue
            far: dict[str, float] = {}
            for i in run:
                for name, d in entries[int(i)].get("outside_fitted_rad", {}).items():
                    far[name] = max(far.get(name, 0.0), d)
            runs.append(
                {
                    "set": label,
                    "first_row": int(run[0]),
                    "last_row": int(run[-1]),
                    "poses": int(run.size),
                    "outside_fitted": sum("outside_fitted_rad" in entries[int(i)] for i in run),
                    "pos_mm_min": float(all_mm[run].min()),
                    "pos_mm_max": float(all_mm[run].max()),
                    "outside_fitted_rad": far,
                }
            )
    out["runs"] = runs
    return out


def add_diagnostics(
    report: dict[str, Any], result: Analysis, data: Data, base_x: np.ndarray, baseline: Model
) -> None:
    """The data's own repeatability against what remains, and the residual per base-frame
    component: held out for the identified model, all rows for the nominal one."""
    rep = report.get("repeatability")
    chain = result.model.chain
    _train_idx, val_idx = split_data(data)
    val = data.subset(val_idx)
    width = 3 if result.model.position_only or data.R_ks is None else 6
    after = result.model.residuals(result.x, val, chain.gravity_torques(val.q))
    before = baseline.residuals(base_x, data, chain.gravity_torques(data.q))
    report["residual_components_mm"] = {
        "nominal_all_poses": residual_components(before.reshape(-1, width)[:, :3] * 1e3),
        "final_held_out": residual_components(after.reshape(-1, width)[:, :3] * 1e3),
    }
    final = report["final"]["validation"]["pos_rms_mm"]
    if rep is None:
        report["against_repeatability"] = (
            f"{final:.3f} mm RMS held out; these data repeat fewer than 5 poses, so their "
            "repeatability is not measured here"
        )
    elif not rep.get("used_as_floor", True):
        report["against_repeatability"] = f"{final:.3f} mm RMS held out; {rep['note']}"
    else:
        report["against_repeatability"] = (
            f"{final:.3f} mm RMS held out, {final / rep['rms_mm']:.1f}x the repeatability "
            f"measured in this data ({rep['rms_mm']:.4f} mm RMS over {rep['measurements']} "
            f"measurements of {rep['poses']} repeated poses"
            + (
                f"; {rep['left_out_poses']} poses with equal joints but a scatter over 5x the "
                "median's left out as no repeat)"
                if rep["left_out_poses"]
                else ")"
            )
        )
    report["iso9283"] = iso_figures(result, data, base_x, baseline, val_idx)


def iso_figures(
    result: Analysis, data: Data, base_x: np.ndarray, baseline: Model, val_idx: np.ndarray
) -> dict[str, Any]:
    """ISO 9283 figures the data allow, for the nominal model (registration fitted) and the
    identified one: AP and RP from repeated stop-and-measure poses, AT from motion."""
    chain = result.model.chain
    width = 3 if result.model.position_only or data.R_ks is None else 6
    tau = chain.gravity_torques(data.q)

    def residual(model: Model, x: np.ndarray) -> np.ndarray:
        return model.residuals(x, data, tau).reshape(-1, width)[:, :3]

    both = {"before": residual(baseline, base_x), "after": residual(result.model, result.x)}
    out: dict[str, Any] = {}
    if data.velocity is None:
        rep = repeatability(data.q, data.p_ks)
        pose = None if rep is None else iso_pose_figures(rep.groups, data.p_ks, both)
        if pose is not None:
            out["pose"] = pose
        else:
            out["pose_note"] = "no repeated poses: AP and RP need poses measured repeatedly"
    else:
        out["path"] = iso_path_figures({k: r[val_idx] for k, r in both.items()})
        out["pose_note"] = "motion data: AP and RP need repeated stop-and-measure poses"
    return out
