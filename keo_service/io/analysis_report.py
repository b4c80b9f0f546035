"""`keo analyze` files: read the interchange files, run the analysis, write report.json, a
readable report.md with plots, and model.toml (the config with every kept effect added)."""

from __future__ import annotations

import json
import math
import sys
import tomllib
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import pinocchio as pin
from scipy.spatial.transform import Rotation

from keo_service.core.chain import Chain
from keo_service.core.corrections import approach_directions, persist_directions
from keo_service.core.errors import KeoError
from keo_service.core.rules import DIRECTION_DEADBAND
from keo_service.core.timing import DelayModel
from keo_service.fit.analysis import (
    KEEP_MARGIN,
    Analysis,
    NotIdentifiableError,
    analyze,
    split,
    split_data,
)
from keo_service.fit.angle_maps import try_maps
from keo_service.fit.coupling import try_couplings
from keo_service.fit.diagnostics import repeatability, residual_components
from keo_service.fit.effects import JointMaps, config_fields, effect_from_config
from keo_service.fit.model import (
    Data,
    Model,
    fit,
    initial_registration,
    initial_registration_sessions,
    stats,
)
from keo_service.fit.sampling import MAX_ROWS, informative_rows, selection_report
from keo_service.fit.uncertainty import TrackerUncertainty, iso_path_figures, iso_pose_figures
from keo_service.io.cell import cell_from_config, delay_model, robot_from_config
from keo_service.io.config import Config, ModelConfig, config_to_toml
from keo_service.io.interchange import read_encoder, read_tracker

DELAY_SAMPLES = 60_000  # tracker samples the delay fit uses at most (evenly thinned)
SIGMA_COLUMNS = ("sx", "sy", "sz")  # optional tracker.csv columns: per-point std (m)


def tracker_uncertainty(config: Config) -> TrackerUncertainty:
    """The config's [tracker] uncertainty; assumed unless the config file states either key
    (a config built in code: assumed when both equal keo's defaults)."""
    t = config.tracker
    stated: bool | None = None
    source = Path(config.source) if config.source else None
    if source is not None and source.is_file():
        try:
            raw = tomllib.loads(source.read_text(encoding="utf-8")).get("tracker", {})
            stated = bool({"uncertainty_um", "uncertainty_um_per_m"} & set(raw))
        except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError):
            stated = None
    if stated is None:
        default = TrackerUncertainty()
        stated = (t.uncertainty_um, t.uncertainty_um_per_m) != (default.um, default.um_per_m)
    return TrackerUncertainty(t.uncertainty_um, t.uncertainty_um_per_m, assumed=not stated)


def load_data(
    config: Config,
    encoder_path: Path,
    tracker_path: Path,
    delay: DelayModel | None = None,
    max_rows: int = MAX_ROWS,
    info: dict[str, Any] | None = None,
) -> tuple[Data, bool]:
    """Pair each tracker row with the joints at its time minus the delay (the config's
    unless given); stop-and-measure data (an encoder row at every tracker t) uses none. Of a
    long motion recording at most `max_rows` informative rows are kept (fit.sampling);
    `info` gets how many were recorded and used, and how they were chosen."""
    robot = robot_from_config(config)
    enc = read_encoder(encoder_path, nq=robot.nq)
    trk = read_tracker(tracker_path)
    ok_e = np.isfinite(enc.t) & np.all(np.isfinite(enc.q), axis=1)
    enc_t, enc_q = enc.t[ok_e], enc.q[ok_e]
    order = np.argsort(enc_t)
    enc_t, enc_q = enc_t[order], enc_q[order]
    # stop-and-measure data has an encoder row at every tracker row's t: no delay applies
    static = bool(np.all(np.isin(trk.t[np.isfinite(trk.t)], enc_t)))
    if delay is None:
        timing = config.timing
        delay = delay_model(timing)
    target = trk.t.copy() if static else delay.encoder_times(trk.t)
    ok = np.isfinite(trk.t) & np.all(np.isfinite(trk.p), axis=1)
    ok &= (target >= enc_t[0]) & (target <= enc_t[-1])
    if trk.quat is not None:
        ok &= np.all(np.isfinite(trk.quat), axis=1)
    target = target[ok]
    q = np.column_stack([np.interp(target, enc_t, enc_q[:, j]) for j in range(robot.nq)])
    velocity = tool_speed = None
    if static:  # stop-and-measure: approach direction from the previous pose
        direction = approach_directions(q)
    else:
        h = 0.01
        ahead = np.column_stack(
            [np.interp(target + h, enc_t, enc_q[:, j]) for j in range(robot.nq)]
        )
        behind = np.column_stack(
            [np.interp(target - h, enc_t, enc_q[:, j]) for j in range(robot.nq)]
        )
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
        quat = trk.quat[ok]
        R = Rotation.from_quat(quat, scalar_first=True).as_matrix()
    extra = {k: v[ok] for k, v in trk.extra.items() if k not in SIGMA_COLUMNS}
    sigma = None
    if all(c in trk.extra for c in SIGMA_COLUMNS):
        sigma = np.column_stack([trk.extra[c][ok] for c in SIGMA_COLUMNS])
    if tool_speed is not None:
        extra["tool_speed_m_s"] = tool_speed
    data = Data(q, trk.p[ok], R, trk.t[ok], extra, direction, velocity, sigma)
    return data, trk.quat is None


def saved_model(config: Config, chain: Chain, position_only: bool) -> Model:
    """The effects in the config's [model] section, as a fixed Model (registration-only)."""
    m: ModelConfig = config.model
    nq = chain.nq
    section = msgspec.structs.asdict(m)
    effects, parts = [], []
    for name in m.effects:
        try:
            effect, values = effect_from_config(name, section)
        except KeyError:
            raise KeoError(
                f"{config.source}: key 'model.effects': unknown effect '{name}'"
            ) from None
        effects.append(effect)
        parts.append(values)
    n_reg = 9 if position_only else 12
    x = np.concatenate([np.zeros(n_reg), *parts]) if parts else np.zeros(n_reg)
    model = Model(chain, position_only, effects, x, {}, m.temperature_ref_c, m.time_ref_s)
    expected = n_reg + sum(model.sizes(nq))
    if x.size != expected:
        raise KeoError(
            f"{config.source}: key 'model': the saved effects have {x.size - n_reg} "
            f"numbers, expected {expected - n_reg}"
        )
    return model


def model_config(result: Analysis, base: Config) -> Config:
    """The config with the identified registration and every kept effect."""
    model, x = result.model, result.x
    T_bk, T_ns, _corr = model.unpack(x)
    m = msgspec.convert(
        {
            **config_fields(model, x),
            "temperature_ref_c": model.temperature_ref,
            "time_ref_s": model.time_ref,
        },
        ModelConfig,
    )

    def xyz_rpy(T: np.ndarray) -> tuple[list[float], list[float]]:
        return T[:3, 3].tolist(), pin.rpy.matrixToRpy(T[:3, :3]).tolist()

    tool_xyz, tool_rpy = xyz_rpy(T_ns)
    trk_xyz, trk_rpy = xyz_rpy(T_bk)
    tool = msgspec.structs.replace(base.tool, xyz=tool_xyz, rpy=tool_rpy)
    tracker = msgspec.structs.replace(base.tracker, xyz=trk_xyz, rpy=trk_rpy)
    return msgspec.structs.replace(base, tool=tool, tracker=tracker, model=m)


def _plots(
    out: Path, result: Analysis, data: Data, baseline_x: np.ndarray, baseline_model: Model
) -> list[str]:
    try:
        import matplotlib
    except ImportError:
        raise KeoError(
            "keo analyze draws its plots with matplotlib: pip install 'keo[plot]'"
        ) from None

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    chain = result.model.chain
    tau = chain.gravity_torques(data.q)
    width = 3 if result.model.position_only or data.R_ks is None else 6
    before = baseline_model.residuals(baseline_x, data, tau).reshape(-1, width)[:, :3] * 1e3
    after = result.model.residuals(result.x, data, tau).reshape(-1, width)[:, :3] * 1e3
    files = []
    maps_entry = next((e for e in result.report["effects"] if "maps" in e["parameters"]), None)
    for m in maps_entry["parameters"]["maps"] if maps_entry else []:
        knots, values, se = (
            np.asarray(m[k]) * 1e3 if k != "knots" else np.asarray(m[k])
            for k in ("knots", "values", "se")
        )
        fig, ax = plt.subplots(figsize=(6, 2.5))
        ax.fill_between(knots, values - 2 * se, values + 2 * se, alpha=0.3, label="+/- 2 se")
        ax.plot(knots, values, marker=".", label="angle error map")
        ax.set_xlabel(f"{m['joint']} angle (rad)")
        ax.set_ylabel("angle error (mrad)")
        ax.legend(loc="upper right", fontsize=7)
        fig.tight_layout()
        name = f"map_{m['joint']}.png"
        fig.savefig(out / name, dpi=110)
        plt.close(fig)
        files.append(name)
    fig, ax = plt.subplots(figsize=(6, 3.5))
    bins = np.linspace(0, max(np.linalg.norm(before, axis=1).max(), 1e-3), 50).tolist()
    ax.hist(np.linalg.norm(before, axis=1), bins=bins, alpha=0.6, label="nominal model")
    ax.hist(np.linalg.norm(after, axis=1), bins=bins, alpha=0.6, label="with kept effects")
    ax.set_xlabel("position residual (mm)")
    ax.set_ylabel("poses")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "residual_histogram.png", dpi=110)
    plt.close(fig)
    files.append("residual_histogram.png")
    variables = {f"q{j + 1} (rad)": data.q[:, j] for j in range(data.q.shape[1])}
    variables["time (s)"] = data.t
    for k, v in data.extra.items():
        variables[k] = v
    cols = 3
    rows = math.ceil(len(variables) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(12, 3 * rows), squeeze=False)
    for ax, (name, v) in zip(axes.ravel(), variables.items(), strict=False):
        ax.plot(v, np.linalg.norm(before, axis=1), ".", ms=2, alpha=0.4, label="nominal")
        ax.plot(v, np.linalg.norm(after, axis=1), ".", ms=2, alpha=0.4, label="with effects")
        ax.set_xlabel(name)
        ax.set_ylabel("|residual| (mm)")
    for ax in axes.ravel()[len(variables) :]:
        ax.axis("off")
    axes[0, 0].legend()
    fig.tight_layout()
    fig.savefig(out / "residual_vs_variables.png", dpi=90)
    plt.close(fig)
    files.append("residual_vs_variables.png")
    nq = data.q.shape[1]
    fig, axes = plt.subplots(3, nq, figsize=(2.6 * nq, 7), squeeze=False, sharey="row")
    for row, axis in enumerate("xyz"):
        for col in range(nq):
            ax = axes[row, col]
            ax.plot(data.q[:, col], before[:, row], ".", ms=2, alpha=0.3, label="nominal")
            ax.plot(data.q[:, col], after[:, row], ".", ms=2, alpha=0.4, label="identified")
            ax.axhline(0.0, color="grey", lw=0.5)
            if row == 2:
                ax.set_xlabel(f"{chain.robot.joint_names[col]} (rad)", fontsize=7)
            if col == 0:
                ax.set_ylabel(f"base {axis} residual (mm)")
    axes[0, 0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "residual_components_vs_joints.png", dpi=90)
    plt.close(fig)
    files.append("residual_components_vs_joints.png")
    return files


def _stats_line(s: dict[str, Any]) -> str:
    rot = "" if s["rot_rms_mrad"] is None else f", orientation {s['rot_rms_mrad']:.4f} mrad RMS"
    return (
        f"{s['n']} poses: position {s['pos_rms_mm']:.4f} mm RMS, {s['pos_max_mm']:.3f} mm max{rot}"
    )


def markdown(report: dict[str, Any], plots: list[str]) -> str:
    lines = [
        "# keo analyze",
        "",
        "All numbers below are on held-out poses (never used to fit) unless marked.",
        "",
        f"- nominal model, registration fitted: {_stats_line(report['baseline']['validation'])}",
    ]
    for e in report["effects"]:
        count = _parameter_count(e)
        lines.append(
            f"- + {e['name']} ({e['description']}): {_stats_line(e['validation'])} "
            f"({e['held_out_improvement_pct']:+.1f} %, {count} parameters)"
        )
    carried = report.get("carried_maps")
    if carried:
        lines.append(
            f"- carried {JointMaps.name} (registration refitted): held out "
            f"{carried['held_out_pos_rms_mm_with']:.4f} mm with them, "
            f"{carried['held_out_pos_rms_mm_without']:.4f} mm without: "
            + ("kept" if carried["kept"] else "dropped, the model is written without them")
            + f"; {carried['poses_outside_calibrated_range_pct']:.0f} % of these poses lie "
            "outside the angles the maps were calibrated on (there a map holds its edge value)"
        )
    lines.append(f"- final: {_stats_line(report['final']['validation'])}")
    lines.append(f"- (final on the fitted poses: {_stats_line(report['final']['train'])})")
    if report.get("sessions"):
        lines += ["", "Sessions (one tracker registration each, one robot model):", ""]
        for entry in report["sessions"]:
            t = np.array(entry["T_bk"])[:3, 3]
            lines.append(
                f"- session {entry['session'] + 1}: held out {_stats_line(entry['validation'])}"
                f"; tracker at [{t[0]:.4f}, {t[1]:.4f}, {t[2]:.4f}] m in the base frame"
            )
    if report["rejected"]:
        lines += ["", "Tried and not kept (held-out change below 5 %):", ""]
        for e in report["rejected"]:
            lines.append(f"- {e['name']}: {e['held_out_improvement_pct']:+.1f} %")
    lines += ["", "## What remains", ""]
    lines += _floor_markdown(report)
    if "against_repeatability" in report:
        lines += [report["against_repeatability"], ""]
    lines += _iso_markdown(report.get("iso9283"))
    comps = report.get("residual_components_mm")
    if comps:
        lines += [
            "| signed position residual, base frame (RMS, mm) | x | y | z |",
            "|---|---|---|---|",
        ]
        for label, key in (
            ("nominal model (all poses)", "nominal_all_poses"),
            ("identified model (held out)", "final_held_out"),
        ):
            c = comps[key]
            lines.append(f"| {label} | {c['x']:.4f} | {c['y']:.4f} | {c['z']:.4f} |")
        lines += ["", "(against each joint: residual_components_vs_joints.png)", ""]
    lines += [
        report["unexplained"],
        "",
        "| variable | R^2 of the residual | by chance |",
        "|---|---|---|",
    ]
    for c in report["correlations"]:
        lines.append(f"| {c['variable']} | {c['r2']:.3f} | {c['chance']:.3f} |")
    lines += ["", "## Parameters (value +/- standard error)", ""]
    for e in report["effects"]:
        p = e["parameters"]
        if "maps" in p:
            lines += _maps_markdown(e)
            continue
        head = f"### {e['name']}"
        if "identifiable" in p:
            head += f" ({p['identifiable']} of {p['of']} combinations identifiable)"
        if p.get("records"):
            lines += [head, ""]
            lines += [_record_line(rec) for rec in p["records"]]
            lines.append("")
            lines += [f"- {text}" for text in p.get("couplings", [])]
            if p.get("couplings"):
                lines.append("")
            if p.get("unidentifiable"):
                lines += ["What these poses cannot tell apart:", ""]
                lines += [f"- {u['text']}" for u in p["unidentifiable"]]
                lines.append("")
            continue
        if "values" in p:
            body = ", ".join(
                f"{v:.3g} +/- {s:.2g}" for v, s in zip(p["values"], p["se"], strict=True)
            )
        else:
            body = ", ".join(
                f"{k} = {v:.6g}" if isinstance(v, float) else f"{k} = {v}" for k, v in p.items()
            )
        lines += [head, "", body, ""]
    lines += ["## Plots", ""] + [f"![{p}]({p})" for p in plots]
    return "\n".join(lines) + "\n"


_DISPLAY = {
    "m": (1e3, "mm"),
    "rad": (1e3, "mrad"),
    "m/C": (1e6, "um/C"),
    "m/s": (1e6, "um/s"),
    "rad/rad": (1e3, "mrad/rad"),
}


def _record_line(rec: dict[str, Any]) -> str:
    """`shoulder_lift_joint  link x  +0.300 +/- 0.070 mm` (display units); a parameter the
    poses cannot see is listed as held, without a value."""
    scale, unit = _DISPLAY.get(rec["unit"], (1.0, rec["unit"]))
    if rec.get("held"):
        return f"    {rec['joint']:<22} {rec['parameter']:<18} held at zero (not identifiable here)"
    return (
        f"    {rec['joint']:<22} {rec['parameter']:<18} {rec['value'] * scale:+.4g} +/- "
        f"{rec['se'] * scale:.2g} {unit}"
    )


def _floor_markdown(report: dict[str, Any]) -> list[str]:
    floor = report.get("floor")
    if not floor:
        return []
    lines = [
        f"Floor (the held-out RMS a perfect model would reach on these {floor['held_out_poses']} "
        f"held-out poses, {floor['parameters']} parameters fitted): "
        f"**{floor['pos_rms_mm']:.4f} mm**, from the {floor['source']}"
        + (" (assumed)" if floor["assumed"] else "")
        + f"; the final model is at **{floor['ratio']:.2f}x** the floor "
        "(consistent with noise only within 1.2x).",
        "",
    ]
    others = floor["sources"][1:]
    if others:
        lines += [
            "Other estimates of the floor: "
            + "; ".join(
                f"{o['floor_mm']:.4f} mm from the {o['source']}"
                + (" (assumed)" if o["assumed"] else "")
                for o in others
            ),
            "",
        ]
    return lines


def _iso_markdown(iso: dict[str, Any] | None) -> list[str]:
    if not iso:
        return []
    lines = ["ISO 9283 figures (mm; before: nominal model, after: identified model):", ""]
    pose = iso.get("pose")
    if pose:
        ap = pose["AP_mm"]
        lines += [
            "| figure | before (mean / max) | after (mean / max) |",
            "|---|---|---|",
            f"| AP, pose accuracy ({pose['poses']} repeated poses, median "
            f"{pose['cycles_median']:g} cycles) | {ap['before']['mean']:.4f} / "
            f"{ap['before']['max']:.4f} | {ap['after']['mean']:.4f} / {ap['after']['max']:.4f} |",
            f"| RP, pose repeatability | {pose['RP_mm']['mean']:.4f} / "
            f"{pose['RP_mm']['max']:.4f} | (the same: the model does not change it) |",
            "",
            "(AP after is on poses the fit used; ISO 9283 asks for 30 cycles per pose, fewer "
            "make these figures indicative.)",
            "",
        ]
    path = iso.get("path")
    if path:
        at = path["AT_mm"]
        lines += [
            f"AT, path accuracy over the held-out motion (one pass): {at['before']:.4f} mm "
            f"before, {at['after']:.4f} mm after.",
            "",
        ]
    if iso.get("pose_note"):
        lines += [f"({iso['pose_note']}.)", ""]
    return lines


def _parameter_count(entry: dict[str, Any]) -> int:
    if "parameter_count" in entry:
        return int(entry["parameter_count"])
    p = entry["parameters"]
    if "identifiable" in p:
        return int(p["identifiable"])
    return len(p.get("values", [])) or len(p)


def _maps_markdown(entry: dict[str, Any]) -> list[str]:
    band = entry["band_split"]
    lines = [
        f"### {JointMaps.name}: knots every {entry['knot_spacing_rad']:g} rad, smoothing "
        f"{entry['smoothing']:g} (chosen by cross-validation), {entry['parameter_count']} values",
        "",
        "Outside its calibrated range a map holds its edge value and `keo run` flags the "
        "estimate `outside_calibrated_range`.",
        "",
        "| joint | calibrated range (rad) | knots | peak (mrad) | median se (mrad) |",
        "|---|---|---|---|---|",
    ]
    for m in entry["parameters"]["maps"]:
        lo, hi = m["range_rad"]
        lines.append(
            f"| {m['joint']} | {lo:+.3f} .. {hi:+.3f} | {len(m['knots'])} | "
            f"{m['peak_mrad']:.3f} | {float(np.median(m['se'])) * 1e3:.4f} |"
        )
    lines += [
        "",
        f"Second split, a band of {band['joint']} held out ({band['held_out_poses']} poses): "
        f"{band['pos_rms_mm_before']:.4f} -> {band['pos_rms_mm_after']:.4f} mm "
        f"({band['improvement_pct']:+.1f} %).",
        "",
        "Learning curve (held-out position RMS against training poses): "
        + ", ".join(
            f"{c['train_poses']}: {c['held_out_pos_rms_mm']:.4f} mm"
            for c in entry["learning_curve"]
        ),
        "",
    ]
    return lines


def _add_diagnostics(
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
    report["iso9283"] = _iso_figures(result, data, base_x, baseline, val_idx)


def _iso_figures(
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


def _is_static(config: Config, encoder: Path, tracker: Path) -> bool:
    enc = read_encoder(encoder)
    trk = read_tracker(tracker)
    return bool(np.all(np.isin(trk.t[np.isfinite(trk.t)], enc.t)))


def _time_delay_effect(
    config: Config, encoder: Path, tracker: Path, data: Data, position_only: bool, say: Any
) -> tuple[Data, dict[str, Any] | None]:
    """Motion data: the delay (and drift) from the motion itself, kept if pairing the
    streams with it lowers the held-out error of the registered nominal model by 5 %."""
    from keo_service.fit.delay import DelayNotIdentifiableError, fit_delay

    cell = cell_from_config(config)
    enc = read_encoder(encoder, nq=cell.robot.nq)
    trk = read_tracker(tracker)
    say("trying time_delay (the delay between the streams, from the motion)")
    # a long recording: every k-th tracker sample is plenty for one delay and one drift
    k = max(1, trk.t.size // DELAY_SAMPLES)
    quat = None if trk.quat is None else trk.quat[::k]
    try:
        found = fit_delay(
            cell, enc.t, enc.q, trk.t[::k], trk.p[::k], quat, initial=config.timing.delay_s
        )
    except DelayNotIdentifiableError as exc:
        say(f"time_delay: not identifiable ({exc})")
        return data, None
    model_delay = DelayModel(found.delay_s, found.drift, found.t_ref)
    new_data, _ = load_data(config, encoder, tracker, model_delay)
    chain = Chain(cell.robot)

    def held_out(d: Data) -> tuple[dict[str, Any], dict[str, Any]]:
        tr, va = split(d.n)
        train, val = d.subset(tr), d.subset(va)
        tau_tr, tau_va = chain.gravity_torques(train.q), chain.gravity_torques(val.q)
        model = Model(
            chain, position_only, [], initial_registration(chain, train, None, position_only)
        )
        x = fit(model, train, tau_tr, model.x, 50e-6).x
        return stats(model, x, train, tau_tr).as_dict(), stats(model, x, val, tau_va).as_dict()

    old_train, old_val = held_out(data)
    new_train, new_val = held_out(new_data)
    gain = 1 - new_val["pos_rms_mm"] / old_val["pos_rms_mm"]
    entry = {
        "name": "time_delay",
        "description": "delay (and clock drift) between the streams",
        "parameters": {
            "delay_s": found.delay_s,
            "se_s": found.delay_se_s,
            "drift_ppm": found.drift * 1e6,
            "drift_se_ppm": found.drift_se * 1e6,
            "t_ref_s": found.t_ref,
            "explained": found.explained,
        },
        "train": new_train,
        "validation": new_val,
        "held_out_improvement_pct": 100 * gain,
        "kept": gain >= KEEP_MARGIN,
        "baseline": {"train": old_train, "validation": old_val},
    }
    say(
        f"time_delay: {found.delay_s * 1e3:.2f} +/- {found.delay_se_s * 1e3:.2f} ms, held-out "
        f"change {100 * gain:+.1f} %"
    )
    return (new_data if entry["kept"] else data), entry


def _pooled(parts: list[Data]) -> Data:
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
    )


def _load_sessions(
    config: Config, encoders: list[Path], trackers: list[Path], registration_only: bool
) -> tuple[Data, bool]:
    if len(encoders) != len(trackers):
        raise KeoError(
            f"--encoder and --tracker come in pairs (one of each per recording): got "
            f"{len(encoders)} and {len(trackers)}"
        )
    if registration_only:
        raise KeoError("--registration-only takes one recording (one --encoder/--tracker pair)")
    loaded = [load_data(config, e, t) for e, t in zip(encoders, trackers, strict=True)]
    if len({p for _d, p in loaded}) > 1:
        raise KeoError("the recordings mix a 6-DoF probe and a single reflector")
    return _pooled([d for d, _p in loaded]), loaded[0][1]


def run_analysis(
    config: Config,
    encoder: Path | list[Path],
    tracker: Path | list[Path],
    out: Path,
    registration_only: bool,
) -> dict[str, Any]:
    """`keo analyze`: one recording, or several (repeated --encoder/--tracker pairs: each with
    its own tracker registration, one robot model; the delay is the config's for each)."""

    def progress(msg: str) -> None:
        print(f"[analyze] {msg}", file=sys.stderr, flush=True)

    samples: dict[str, Any] = {}
    encoders = encoder if isinstance(encoder, list) else [encoder]
    trackers = tracker if isinstance(tracker, list) else [tracker]
    delay_entry = None
    if len(encoders) == 1 and len(trackers) == 1:
        encoder, tracker = encoders[0], trackers[0]
        data, position_only = load_data(config, encoder, tracker, info=samples)
        if not registration_only and not _is_static(config, encoder, tracker):
            data, delay_entry = _time_delay_effect(
                config, encoder, tracker, data, position_only, progress
            )
    else:
        data, position_only = _load_sessions(config, encoders, trackers, registration_only)
        progress(f"{len(encoders)} recordings, one tracker registration each, one robot model")

    robot = robot_from_config(config)
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
        train_idx, val_idx = split_data(data)
        try_maps(result, data, train_idx, val_idx, KEEP_MARGIN, robot.joint_names, progress)
        try_couplings(result, data, train_idx, val_idx, KEEP_MARGIN, robot.joint_names, progress)
    out.mkdir(parents=True, exist_ok=True)
    sessions = result.model.sessions
    baseline = Model(
        chain, position_only, [], result.x[: result.model.n_reg], {}, 0.0, 0.0, sessions
    )
    tau = chain.gravity_torques(data.q)
    base_x = fit(
        baseline,
        data,
        tau,
        initial_registration_sessions(chain, data, position_only, sessions),
        result.report["registration"]["noise_estimate_mm"] * 1e-3,
    ).x
    plots = _plots(out, result, data, base_x, baseline)
    report = result.report
    _add_diagnostics(report, result, data, base_x, baseline)
    if delay_entry is not None:
        if delay_entry.pop("kept"):
            report["baseline"] = delay_entry.pop("baseline")
            report["effects"].insert(0, delay_entry)
        else:
            delay_entry.pop("baseline")
            report["rejected"].insert(0, delay_entry)
    report["position_only"] = position_only
    report["registration_only"] = registration_only
    if samples:
        report["samples"] = samples
    (out / "report.json").write_text(json.dumps(report, indent=2, allow_nan=False, default=float))
    (out / "report.md").write_text(markdown(report, plots))
    improved = model_config(result, config)
    kept_delay = delay_entry if any(e is delay_entry for e in report["effects"]) else None
    if kept_delay is not None:
        p = kept_delay["parameters"]
        timing = msgspec.structs.replace(
            improved.timing,
            delay_s=p["delay_s"],
            drift_ppm=p["drift_ppm"],
            drift_ref_s=p["t_ref_s"] if p["drift_ppm"] else 0.0,
        )
        improved = msgspec.structs.replace(improved, timing=timing)
    (out / "model.toml").write_text(config_to_toml(improved))
    return report
