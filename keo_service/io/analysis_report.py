"""`keo analyze`'s files: report.json, a readable report.md with plots, and model.toml (the
config with the identified registration and every kept effect); the config's [model] section
read back as a fixed model, and the [tracker] uncertainty it states. The reading, pairing and
analysis are `keo_service.offline.analyze`'s."""

from __future__ import annotations

import json
import math
import tomllib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import pinocchio as pin

from keo_service.core.chain import Chain
from keo_service.core.errors import KeoError
from keo_service.core.model_corrections import MAP_TAPER_RAD
from keo_service.fit.accuracy import Accuracy, default_session_mm
from keo_service.fit.analysis import Analysis, split_data
from keo_service.fit.effects import JointMaps, JointRipple, config_fields, effect_from_config
from keo_service.fit.model import Data, Model
from keo_service.fit.uncertainty import TrackerUncertainty
from keo_service.io.config import Config, ModelConfig


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


def saved_accuracy(config: Config) -> Accuracy | None:
    """The accuracy a model.toml states (None: written before keo stated one)."""
    m = config.model
    if not m.accuracy_mm or not m.calibrated_q_min:
        return None
    # a model written before the between-session term states the bands' default
    session = m.accuracy_session_mm or default_session_mm(m.accuracy_mm, m.accuracy_outside_mm)
    return Accuracy(
        m.accuracy_mm,
        m.accuracy_outside_mm,
        np.asarray(m.calibrated_q_min, dtype=float),
        np.asarray(m.calibrated_q_max, dtype=float),
        m.map_taper_rad,
        session_mm=session,
        session_source=m.accuracy_session_source or "held-out bands",
    )


def model_config(result: Analysis, base: Config) -> Config:
    """The config with the identified registration and every kept effect."""
    model, x = result.model, result.x
    T_bk, T_ns, _corr = model.unpack(x)
    acc = result.report.get("accuracy", {})
    stated = (
        {
            "accuracy_mm": acc["inside_mm"],
            "accuracy_outside_mm": acc["outside_mm"],
            "accuracy_session_mm": acc["session_mm"],
            "accuracy_session_source": acc["session_source"],
            "calibrated_q_min": acc["lower_rad"],
            "calibrated_q_max": acc["upper_rad"],
        }
        if "inside_mm" in acc
        else {}
    )
    m = msgspec.convert(
        {
            **config_fields(model, x),
            **stated,
            "temperature_ref_c": model.temperature_ref,
            "time_ref_s": model.time_ref,
        },
        ModelConfig,
    )

    def xyz_rpy(T: np.ndarray) -> tuple[list[float], list[float]]:
        return T[:3, 3].tolist(), pin.rpy.matrixToRpy(T[:3, :3]).tolist()

    # the identified sensor mount is the probe, a measurement frame; [tool] stays the user's
    probe_xyz, probe_rpy = xyz_rpy(T_ns)
    trk_xyz, trk_rpy = xyz_rpy(T_bk)
    tracker = msgspec.structs.replace(
        base.tracker, xyz=trk_xyz, rpy=trk_rpy, probe_xyz=probe_xyz, probe_rpy=probe_rpy
    )
    return msgspec.structs.replace(base, tracker=tracker, model=m)


def _plots(
    out: Path, result: Analysis, data: Data, baseline_x: np.ndarray, baseline_model: Model
) -> list[str]:
    """The report's plots (file names, in the order report.md shows them): the joint maps,
    the residual's spectra, and the residual before and after against the variables."""
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
    files = _map_plots(plt, out, result.report)
    files += _spectrum_plots(plt, out, result.report)
    files.append(_histogram_plot(plt, out, before, after))
    files.append(_variables_plot(plt, out, data, before, after))
    files.append(_components_plot(plt, out, data, before, after, chain.robot.joint_names))
    return files


def _map_plots(plt: Any, out: Path, report: dict[str, Any]) -> list[str]:
    """Each joint map's angle error against its angle, with +/- 2 standard errors."""
    files = []
    maps_entry = next((e for e in report["effects"] if "maps" in e["parameters"]), None)
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
    return files


def _spectrum_plots(plt: Any, out: Path, report: dict[str, Any]) -> list[str]:
    """Each joint's residual periodogram, the terms taken dashed."""
    files = []
    for spectra in report.get("spectra", {}).values():
        for joint, sp in spectra.items():
            fig, ax = plt.subplots(figsize=(6, 2.5))
            ax.plot(sp["periods_rad"], sp["amplitude_mrad"], lw=0.8)
            for term in sp["terms"]:
                ax.axvline(term["period_rad"], color="C3", lw=0.6, ls="--")
            ax.set_xscale("log")
            ax.set_xlabel(f"period in {joint} angle (rad)")
            ax.set_ylabel("amplitude (mrad)")
            ax.set_title("residual periodogram (dashed: terms taken)", fontsize=8)
            fig.tight_layout()
            name = f"spectrum_{joint}.png"
            fig.savefig(out / name, dpi=110)
            plt.close(fig)
            files.append(name)
    return files


def _histogram_plot(plt: Any, out: Path, before: np.ndarray, after: np.ndarray) -> str:
    """The position residual's length, nominal against identified."""
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
    return "residual_histogram.png"


def _variables_plot(plt: Any, out: Path, data: Data, before: np.ndarray, after: np.ndarray) -> str:
    """The residual's length against each joint, time and the tracker's extra columns."""
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
    return "residual_vs_variables.png"


def _components_plot(
    plt: Any,
    out: Path,
    data: Data,
    before: np.ndarray,
    after: np.ndarray,
    joint_names: Sequence[str],
) -> str:
    """Each base-frame component of the residual against each joint's angle."""
    nq = data.q.shape[1]
    fig, axes = plt.subplots(3, nq, figsize=(2.6 * nq, 7), squeeze=False, sharey="row")
    for row, axis in enumerate("xyz"):
        for col in range(nq):
            ax = axes[row, col]
            ax.plot(data.q[:, col], before[:, row], ".", ms=2, alpha=0.3, label="nominal")
            ax.plot(data.q[:, col], after[:, row], ".", ms=2, alpha=0.4, label="identified")
            ax.axhline(0.0, color="grey", lw=0.5)
            if row == 2:
                ax.set_xlabel(f"{joint_names[col]} (rad)", fontsize=7)
            if col == 0:
                ax.set_ylabel(f"base {axis} residual (mm)")
    axes[0, 0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "residual_components_vs_joints.png", dpi=90)
    plt.close(fig)
    return "residual_components_vs_joints.png"


def _stats_line(s: dict[str, Any]) -> str:
    rot = "" if s["rot_rms_mrad"] is None else f", orientation {s['rot_rms_mrad']:.4f} mrad RMS"
    return (
        f"{s['n']} poses: position {s['pos_rms_mm']:.4f} mm RMS, {s['pos_max_mm']:.3f} mm max{rot}"
    )


# complexity (C901): one section per optional part of the analysis
def markdown(report: dict[str, Any], plots: list[str]) -> str:  # noqa: C901
    lines = [
        "# keo analyze",
        "",
        "All numbers below are on held-out poses (never used to fit) unless marked.",
        "",
        f"- nominal model, registration fitted: {_stats_line(report['baseline']['validation'])}",
    ]
    previous_max = report["baseline"]["validation"]["pos_max_mm"]
    for e in report["effects"]:
        count = _parameter_count(e)
        line = (
            f"- + {e['name']} ({e['description']}): {_stats_line(e['validation'])} "
            f"({e['held_out_improvement_pct']:+.1f} %, {count} parameters)"
        )
        new_max = e["validation"]["pos_max_mm"]
        if new_max > previous_max:
            line += f"; **the held-out maximum rose** from {previous_max:.3f} to {new_max:.3f} mm"
        previous_max = new_max
        lines.append(line)
    lines += _carried_markdown(report)
    lines += _transfer_line(report)
    lines.append(f"- final: {_stats_line(report['final']['validation'])}")
    lines.append(f"- (final on the fitted poses: {_stats_line(report['final']['train'])})")
    lines += _leave_out_markdown(report.get("leave_one_session_out"))
    if report.get("sessions"):
        lines += ["", "Sessions (one tracker registration each, one robot model):", ""]
        for entry in report["sessions"]:
            t = np.array(entry["T_bk"])[:3, 3]
            lines.append(
                f"- session {entry['session'] + 1}: held out {_stats_line(entry['validation'])}"
                f"; tracker at [{t[0]:.4f}, {t[1]:.4f}, {t[2]:.4f}] m in the base frame"
            )
        lines += _mounts_markdown(report["registration"])
    lines += _accuracy_markdown(report)
    lines += _registration_markdown(report)
    if report["rejected"]:
        lines += ["", "Tried and not kept, with the reason:", ""]
        for e in report["rejected"]:
            lines.append(f"- {e['name']}: {_rejection_reason(e)}")
    lines += _outliers_markdown(report)
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
    lines += _parameters_markdown(report["effects"])
    lines += ["## Plots", ""] + [f"![{p}]({p})" for p in plots]
    return "\n".join(lines) + "\n"


# complexity (C901): per effect its maps, spectra, records and combinations, each optional
def _parameters_markdown(effects: list[dict[str, Any]]) -> list[str]:  # noqa: C901
    """Each kept effect's parameters (value +/- standard error), combinations the poses
    see only together once, and what the poses cannot tell apart."""
    lines: list[str] = []
    lines += ["", "## Parameters (value +/- standard error)", ""]
    for e in effects:
        p = e["parameters"]
        if "maps" in p:
            lines += _maps_markdown(e)
            continue
        head = f"### {e['name']}"
        if e.get("spectra"):
            lines += _spectra_markdown(e)
        if "identifiable" in p:
            head += f" ({p['identifiable']} of {p['of']} combinations identifiable)"
        if p.get("records"):
            lines += [head, ""]
            lines += [_record_line(rec) for rec in p["records"] if "combination" not in rec]
            lines.append("")
            for c in p.get("combinations", []):
                scale, unit = _DISPLAY.get(c["unit"], (1.0, c["unit"]))
                members = " + ".join(
                    f"{m['ratio']:.3g} x {m['joint']} {m['parameter']}" for m in c["members"]
                )
                lines.append(
                    f"    only their combination is identified: {members} (each at "
                    f"{c['value'] * scale:+.4g} +/- {c['se'] * scale:.2g} {unit} times its "
                    "ratio; any other split fits alike)"
                )
            if p.get("combinations"):
                lines.append("")
            small = [
                r
                for r in p["records"]
                if "combination" not in r and not r.get("held") and abs(r["value"]) < r["se"]
            ]
            if small:
                lines.append(
                    f"{len(small)} of these values are smaller than their standard error: "
                    "not distinguishable from zero on their own; kept because the effect as a "
                    "whole lowered the held-out error (above)"
                )
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
    return lines


_DISPLAY = {
    "m": (1e3, "mm"),
    "rad": (1e3, "mrad"),
    "m/C": (1e6, "um/C"),
    "m/s": (1e6, "um/s"),
    "rad/rad": (1e3, "mrad/rad"),
}


def _carried_markdown(report: dict[str, Any]) -> list[str]:
    """--registration-only: what became of the carried maps, and what the model predicted
    for this session beside what it measured."""
    lines: list[str] = []
    carried = report.get("carried_maps")
    if carried:
        lines.append(
            f"- carried {JointMaps.name} (registration refitted): held out "
            f"{carried['held_out_pos_rms_mm_with']:.4f} mm with them, "
            f"{carried['held_out_pos_rms_mm_without']:.4f} mm without: "
            + ("kept" if carried["kept"] else "dropped, the model is written without them")
            + f"; {carried['poses_outside_calibrated_range_pct']:.0f} % of these poses lie "
            "outside the angles the maps were calibrated on, on some joint (there that joint's "
            f"map fades to zero over {carried.get('taper_rad', MAP_TAPER_RAD):g} rad; the other "
            "joints' maps apply)"
            + (
                "; maps of "
                + ", ".join(d["joint"] for d in carried.get("joints_dropped", []))
                + " dropped (they raised the error on this session's registration poses)"
                if carried.get("joints_dropped")
                else ""
            )
        )
    ripple = report.get("carried_ripple")
    if ripple and ripple["joints_dropped"]:
        lines.append(
            f"- carried {JointRipple.name} terms of "
            + ", ".join(d["joint"] for d in ripple["joints_dropped"])
            + " dropped (they raised the error on this session's registration poses)"
        )
    predicted = report.get("predicted_vs_measured")
    if predicted:
        lines.append(
            f"- the model predicted {predicted['predicted_rms_mm']:.4f} mm RMS on these "
            f"held-out poses ({predicted['outside_calibrated_range_pct']:.0f} % outside its "
            f"calibrated joint ranges) and measured {predicted['measured_rms_mm']:.4f} mm; "
            f"{predicted['within_95_pct']:.0f} % of the poses lie within its 95 % band"
            + (
                f" (its between-session term {predicted['session_mm']:.4f} mm, from the "
                f"{predicted['session_source']}, added in quadrature; without it "
                f"{predicted['within_session_band']['within_95_pct']:.0f} %)"
                if "session_mm" in predicted
                else ""
            )
        )
    return lines


def _transfer_line(report: dict[str, Any]) -> list[str]:
    """The transfer headline: leave-one-session-out with several recordings, the held-out
    extrapolation bands with one."""
    transfer = report.get("transfer")
    if not transfer or report.get("registration_only"):
        return []
    if "left_out_pos_rms_mm" in transfer:
        return [
            "- **transfer** (leave one session out: the model of the other recordings, only "
            "the registration fitted on the one left out, its held-out poses): "
            f"{transfer['left_out_pos_rms_mm']:.4f} mm RMS over the recordings left out, "
            f"against {transfer['within_session_pos_rms_mm']:.4f} mm within the sessions "
            f"and the nominal {transfer['nominal_pos_rms_mm']:.4f} mm (table below)"
        ]
    return [
        "- extrapolation (standing in for a session not seen: held-out bands at the ends "
        "of each joint's range, linearized, physical effects only; the maps fade there): "
        f"{transfer['model_bands_pos_rms_mm']:.4f} mm RMS against the nominal "
        f"{transfer['nominal_bands_pos_rms_mm']:.4f} mm"
    ]


def _leave_out_markdown(loso: dict[str, Any] | None) -> list[str]:
    """Several recordings: each one left out, the others' model carried to it."""
    if not loso:
        return []
    lines = [
        "",
        "Leave one session out (fitted on the others, only the registration and the mount "
        "fitted on the one left out; position RMS on its held-out poses, mm):",
        "",
        "| left out | fitted on | held out (max) | nominal there | within the session, "
        "pooled model | its own model | best single other |",
        "|---|---|---|---|---|---|---|",
    ]
    for e in loso["entries"]:
        fitted = "+".join(str(o + 1) for o in e["fitted_on"])
        if "error" in e:
            lines.append(f"| {e['session'] + 1} | {fitted} | {e['error']} | | | | |")
            continue
        best = e.get("best_single")
        best_text = (
            f"{best['held_out_pos_rms_mm']:.4f} (session {best['fitted_on'] + 1})"
            + (" **better than pooled**" if e["pooled_worse_than_best_single"] else "")
            if best
            else "-"
        )
        lines.append(
            f"| {e['session'] + 1} | {fitted} | {e['held_out_pos_rms_mm']:.4f} "
            f"({e['held_out_pos_max_mm']:.3f}) | {e['nominal_pos_rms_mm']:.4f} | "
            f"{e['within_session_pooled_pos_rms_mm']:.4f} | "
            f"{e['within_session_own_pos_rms_mm']:.4f} | {best_text} |"
        )
    lines += ["", loso["summary"]["verdict"]]
    lines += _left_out_coverage(loso)
    return lines


def _left_out_coverage(loso: dict[str, Any]) -> list[str]:
    """How the carried models' stated accuracy covered the sessions left out, and the
    between-session term this model states from them."""
    judged = [e for e in loso["entries"] if "stated_off_session" in e]
    if not judged:
        return []
    lines = ["", "Stated accuracy on the session left out (fraction within the 95 % band):", ""]
    for e in judged:
        off, own = e["stated_off_session"], e["stated_within"]
        lines.append(
            f"- session {e['session'] + 1}: {off['within_95_pct']:.1f} % with the carried "
            f"model's between-session term ({off['session_mm']:.4f} mm, from the "
            f"{off['session_source']}; predicted {off['predicted_rms_mm']:.4f} mm RMS, measured "
            f"{off['measured_rms_mm']:.4f}), {own['within_95_pct']:.1f} % with its "
            "within-session figure alone"
        )
    term = loso.get("session_term")
    if term:
        lines += [
            "",
            f"Between-session term this model states (what the carried models missed beyond "
            f"their within-session figure, over {term['sessions']} sessions left out): "
            f"{term['session_mm']:.4f} mm, added in quadrature off-session.",
        ]
    return lines


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


def _spectra_markdown(entry: dict[str, Any]) -> list[str]:
    """The periodic terms found in each joint's residual spectrum (plots: spectrum_*.png)."""
    lines = [
        f"### {entry['name']}: the residual's spectrum against each joint's angle",
        "",
        "| joint | period (rad) | per revolution | explained / residual variance |",
        "|---|---|---|---|",
    ]
    for joint, sp in entry["spectra"].items():
        for t in sp["terms"]:
            lines.append(
                f"| {joint} | {t['period_rad']:.4f} | {t['per_revolution']:.2f} | "
                f"{t['explained_variance_ratio']:.0f} |"
            )
    return [*lines, ""]


def _rejection_reason(entry: dict[str, Any]) -> str:
    """The actual reason an effect was not kept, in words."""
    if entry.get("reason"):
        return str(entry["reason"])
    gain = entry.get("held_out_improvement_pct", 0.0)
    band = entry.get("band_split")
    if band is not None and gain >= 5.0:
        return (
            f"held-out change {gain:+.1f} %, but on the held-out band of "
            f"{band.get('joint', 'a joint')}'s angle {band['improvement_pct']:+.1f} % "
            "(needs 5 % on both)"
        )
    if band is not None:
        return (
            f"held-out change {gain:+.1f} % (band {band['improvement_pct']:+.1f} %), below "
            "the 5 % needed"
        )
    return f"held-out change {gain:+.1f} %, below the 5 % needed"


def _xyz_rpy_text(T: Any) -> str:
    M = np.asarray(T)
    xyz = M[:3, 3] * 1e3
    rpy = pin.rpy.matrixToRpy(M[:3, :3]) * 1e3
    return (
        f"xyz [{xyz[0]:+.3f}, {xyz[1]:+.3f}, {xyz[2]:+.3f}] mm, "
        f"rpy [{rpy[0]:+.3f}, {rpy[1]:+.3f}, {rpy[2]:+.3f}] mrad"
    )


def _registration_markdown(report: dict[str, Any]) -> list[str]:
    """The tracker in the base frame and the probe mount in the flange frame (model.toml
    writes the probe to [tool] as the measured frame)."""
    reg = report.get("registration")
    if not reg:
        return []
    return [
        "",
        "Registration (identified with the model; the frames the numbers above are in):",
        "",
        f"- tracker in the robot base frame (T_bk): {_xyz_rpy_text(reg['T_bk'])}",
        f"- probe mount in the flange frame (T_ns): {_xyz_rpy_text(reg['T_ns'])}",
        "- noise of the nominal registration's residuals (robust estimate): "
        f"{reg['noise_estimate_mm']:.4f} mm",
    ]


def _accuracy_markdown(report: dict[str, Any]) -> list[str]:
    acc = report.get("accuracy")
    if not acc:
        return []
    lines = [
        "",
        f"Stated accuracy (model.toml; `predicted_position_sigma`): {acc['inside_mm']:.4f} mm "
        f"RMS within the calibrated joint ranges, {acc['outside_mm']:.4f} mm at "
        f"{acc['taper_rad']:g} rad or more outside (the extrapolation bands' figure)"
        + (
            f"; in another session {acc['session_mm']:.4f} mm more in quadrature (the "
            f"between-session term, from the {acc['session_source']})."
            if "session_mm" in acc
            else "."
        ),
    ]
    cov = acc.get("held_out_coverage")
    if cov and cov.get("n"):
        lines.append(
            f"On the held-out poses it predicted {cov['predicted_rms_mm']:.4f} mm RMS, measured "
            f"{cov['measured_rms_mm']:.4f} mm; {cov['within_95_pct']:.1f} % of them lie within "
            "its 95 % band."
        )
    return lines


def _outliers_markdown(report: dict[str, Any]) -> list[str]:
    out = report.get("outliers")
    if not out:
        return []
    lines = ["", f"Outliers (position error above {out['threshold_mm']:.3f} mm, 4x the RMS):", ""]
    for label in ("fitted", "held_out"):
        rows = out.get(label, [])
        if not rows:
            lines.append(f"- {label.replace('_', ' ')} poses: none")
            continue
        text = ", ".join(f"row {r['row']} ({r['pos_mm']:.3f} mm)" for r in rows[:10])
        more = f" and {len(rows) - 10} more" if len(rows) > 10 else ""
        far = sum("outside_fitted_rad" in r for r in rows)
        where = f"; {far} outside the joint angles the fit saw" if far else ""
        lines.append(f"- {label.replace('_', ' ')} poses: {len(rows)}{where}: {text}{more}")
    for run in out.get("runs", []):
        far = run["outside_fitted_rad"]
        why = (
            "outside the joint angles the fit saw ("
            + ", ".join(f"{name} by up to {d:.3f} rad" for name, d in far.items())
            + f", {run['outside_fitted']} of the {run['poses']} poses): the model "
            "extrapolates there"
            if far
            else "inside the joint angles the fit saw: look at the measurement"
        )
        lines.append(
            f"- run of {run['poses']} consecutive {run['set'].replace('_', ' ')} poses, rows "
            f"{run['first_row']}-{run['last_row']} ({run['pos_mm_min']:.3f}-"
            f"{run['pos_mm_max']:.3f} mm), {why}; not rejected"
        )
    return lines


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
        f"Outside its calibrated range each joint's map fades to zero over "
        f"{entry.get('taper', {}).get('taper_rad', MAP_TAPER_RAD):g} rad (chosen on held-out "
        "bands at the ends of each joint's range; the other joints' maps still apply) and "
        "`keo run` flags the estimate "
        "`outside_calibrated_range`. A map whose peak is below its median standard error is "
        "marked: its shape is not resolved by these poses.",
        "",
        "| joint | calibrated range (rad) | knots | peak (mrad) | median se (mrad) |",
        "|---|---|---|---|---|",
    ]
    for m in entry["parameters"]["maps"]:
        lo, hi = m["range_rad"]
        median_se = float(np.median(m["se"])) * 1e3
        mark = " (below its se)" if m["peak_mrad"] < median_se else ""
        lines.append(
            f"| {m['joint']} | {lo:+.3f} .. {hi:+.3f} | {len(m['knots'])} | "
            f"{m['peak_mrad']:.3f}{mark} | {median_se:.4f} |"
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


def with_delay(config: Config, parameters: dict[str, Any]) -> Config:
    """The config with the delay (and drift) of a kept time_delay entry."""
    timing = msgspec.structs.replace(
        config.timing,
        delay_s=parameters["delay_s"],
        drift_ppm=parameters["drift_ppm"],
        drift_ref_s=parameters["t_ref_s"] if parameters["drift_ppm"] else 0.0,
    )
    return msgspec.structs.replace(config, timing=timing)


def write_analysis(
    out: Path,
    report: dict[str, Any],
    result: Analysis,
    data: Data,
    base_x: np.ndarray,
    baseline: Model,
    improved: Config,
) -> None:
    """report.json, the plots, report.md and model.toml into `out` (created)."""
    from keo_service.io import model_file  # model.toml: frames pinned, region, travel

    out.mkdir(parents=True, exist_ok=True)
    final = report["final"]["validation"]
    train_idx, _val_idx = split_data(data)
    improved = model_file.pinned_config(
        improved,
        data.q,
        result.model.position_only or data.R_ks is None,
        final["pos_rms_mm"],
        final.get("rot_rms_mrad") or 0.0,
        calibrated_q=data.q[train_idx],
    )
    report["calibrated_region"] = model_file.region_report(improved)
    plots = _plots(out, result, data, base_x, baseline)
    (out / "report.json").write_text(json.dumps(report, indent=2, allow_nan=False, default=float))
    text = markdown(report, plots)
    (out / "report.md").write_text(text + "\n" + "\n".join(model_file.region_markdown(improved)))
    model_file.write_model_toml(improved, out)


def _mounts_markdown(registration: dict[str, Any]) -> list[str]:
    """Several sessions: one sensor mount or one each, and the held-out numbers that chose."""
    judged = registration.get("tools", {}).get("with_effects_and_maps")
    if judged is None:
        return []
    pair = ", ".join(
        f"{a:.4f} -> {b:.4f}"
        for a, b in zip(
            judged["held_out_pos_rms_mm_shared"],
            judged["held_out_pos_rms_mm_per_session"],
            strict=True,
        )
    )
    if not judged["per_session"]:
        return [f"- sensor mount: one for all sessions (one each: held out {pair} mm, not kept)"]
    mounts = [np.array(T)[:3, 3] * 1e3 for T in registration["T_ns_sessions"]]
    moved = "; ".join(
        f"session {s + 1} [{m[0] - mounts[0][0]:+.3f}, {m[1] - mounts[0][1]:+.3f}, "
        f"{m[2] - mounts[0][2]:+.3f}] mm"
        for s, m in enumerate(mounts[1:], start=1)
    )
    return [
        f"- sensor mount: each session its own (held out {pair} mm with the effects and maps); "
        f"from session 1's: {moved}"
    ]
