"""Build README.md from docs/README.template.md and generated results.

    python docs/build_readme.py --paper docs/results/paper.md --delay docs/results/delay.md \
        --bench docs/results/bench.json --ur10 docs/results/ur10 \
        --notes docs/results/ur10_notes.md \
        --soak docs/results/soak.json docs/results/soak_rrd.json \
        --rtde docs/results/rtde_clock.json

DIR holds analyses of the shared UR10 data: A/an.json, B/an.json (full analyses) and
A/reg.json, B/reg.json (registration-only with the other series' model.toml).
"""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

from keo_service.bench.benchmarks import bench_table

HERE = Path(__file__).resolve().parent


def stats(s: dict) -> str:
    rot = "–" if s["rot_rms_mrad"] is None else f"{s['rot_rms_mrad']:.3f}"
    return f"{s['pos_rms_mm']:.3f} | {s['pos_max_mm']:.2f} | {rot}"


# complexity (C901): one row per kind of result, each optional
def ur10_table(folder: Path) -> str:  # noqa: C901
    lines = [
        "| data | model | held-out poses | position RMS (mm) | position max (mm) | "
        "orientation RMS (mrad) |",
        "|---|---|---|---|---|---|",
    ]
    for series in ("A", "B"):
        r = json.loads((folder / series / "an.json").read_text())
        label = f"Series {series}"
        lines.append(
            f"| {label} | nominal, registration fitted | {r['baseline']['validation']['n']} "
            f"| {stats(r['baseline']['validation'])} |"
        )
        for e in r["effects"]:
            ident = e["parameters"].get("identifiable") or e.get("parameter_count")
            extra = f" ({ident} parameters)" if ident else ""
            lines.append(
                f"| {label} | + {e['name']}{extra} | {e['validation']['n']} | "
                f"{stats(e['validation'])} |"
            )
        lines.append(
            f"| {label} | final (same poses, fitted) | {r['final']['train']['n']} | "
            f"{stats(r['final']['train'])} |"
        )
        rejected = ", ".join(
            f"{e['name']} {e['held_out_improvement_pct']:+.1f} %" for e in r["rejected"]
        )
        lines.append(f"| {label} | not kept: {rejected} | | | | |")
    for fit_on, reg_on in (("A", "B"), ("B", "A")):
        r = json.loads((folder / reg_on / "reg.json").read_text())
        carried = r.get("carried_maps")
        if carried:
            lines.append(
                f"| Series {reg_on} | model of Series {fit_on} without its maps, registration "
                f"only | {r['final']['validation']['n']} | "
                f"{carried['held_out_pos_rms_mm_without']:.3f} | | |"
            )
        lines.append(
            f"| Series {reg_on} | model of Series {fit_on}"
            + (
                " with its maps and periodic terms (per joint, as its registration poses "
                "confirm them)"
                if carried and carried["kept"]
                else ""
            )
            + f", registration only | {r['final']['validation']['n']} | "
            f"{stats(r['final']['validation'])} |"
        )
    lines.append("")
    for series in ("A", "B"):
        r = json.loads((folder / series / "an.json").read_text())
        lines += [f"What is left (Series {series}): {r['unexplained']}.", ""]
        if r.get("against_repeatability"):
            lines += [f"Against the data's own repeatability: {r['against_repeatability']}.", ""]
    for fit_on, reg_on in (("A", "B"), ("B", "A")):
        carried = json.loads((folder / reg_on / "reg.json").read_text()).get("carried_maps")
        if carried:
            lines += [
                f"Series {fit_on}'s maps on Series {reg_on}: "
                f"{carried['poses_outside_calibrated_range_pct']:.0f} % of its poses lie outside "
                "the angles they were calibrated on, on some joint (there that joint's map "
                f"fades to zero over {carried.get('taper_rad', 0.1):g} rad; the other joints' "
                "maps apply).",
                "",
            ]
    for series in ("A", "B"):
        plots = sorted((folder / series / "maps").glob("map_*.png"))
        if plots:
            lines += [f"Joint-angle error maps, Series {series} (each with its +/- 2 se band):", ""]
            lines += [
                f"![{p.stem} Series {series}]({p.resolve().relative_to(HERE.parent).as_posix()})"
                for p in plots
            ]
            lines.append("")
    return "\n".join(lines) + "\n"


def soak_text(d: dict) -> str:
    s = d["summary"]
    lat = d["latency_ms"]
    names = {
        "service": "service",
        "adapter-encoder": "encoder adapter",
        "adapter-tracker": "tracker adapter",
    }
    rss = ", ".join(
        f"{label} {s[n]['rss_first_mb']:.1f} → {s[n]['rss_last_mb']:.1f} MB"
        for n, label in names.items()
    )
    fds = ", ".join(
        f"{label} {s[n]['fds_first']} → {s[n]['fds_last']}" for n, label in names.items()
    )
    rrd = d.get("rrd", False)
    command = f"keo bench --soak {d['seconds']:.0f}" + (" --rrd" if rrd else "")
    rerun = ""
    if "rerun-process" in s:
        r, rec = s["rerun-process"], d["recording"]
        trace = [(x["t_s"], x["rss_mb"]["rerun-process"]) for x in d["trace"]]
        drop = min(itertools.pairwise(trace), key=lambda pair: pair[1][1] - pair[0][1])
        (t_before, before), (t_after, after) = drop
        rerun = (
            f" The Rerun process (the service's child) {r['rss_first_mb']:.1f} → "
            f"{r['rss_last_mb']:.1f} MB, at most {r['rss_max_mb']:.1f} MB ({before:.1f} MB "
            f"at {t_before:.0f} s into the run, {after:.1f} MB at {t_after:.0f} s: the "
            f"recording rolled to its next file); {rec['files']} files "
            f"({', '.join(f'{mb:.0f}' for mb in rec['mb'])} MB)."
        )
    return (
        f"Soak (`{command}`, 1 kHz tracker, 250 Hz robot, every "
        f"process its own{', the service recording to Rerun' if rrd else ''}): resident "
        f"memory from a third of the run to its end: {rss}; "
        f"open files: {fds}; {d['estimates_received']} estimates for "
        f"{d['tracker_samples_sent']} tracker samples; latency p50 {lat['p50']:.2f} ms, "
        f"p99 {lat['p99']:.2f} ms, max {lat['max']:.1f} ms.{rerun} Queues are bounded by "
        "construction (deques with a maximum length everywhere).\n"
    )


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--paper", type=Path, required=True)
    p.add_argument("--delay", type=Path, required=True)
    p.add_argument("--bench", type=Path, required=True)
    p.add_argument("--ur10", type=Path, required=True)
    p.add_argument("--notes", type=Path, help="markdown appended after the UR10 table")
    p.add_argument(
        "--soak", type=Path, nargs="+", required=True, help="keo bench --soak 600 [--rrd] --json"
    )
    p.add_argument("--rtde", type=Path, required=True, help="clock numbers of tests/test_rtde.py")
    args = p.parse_args()
    text = (HERE / "README.template.md").read_text()
    text = text.replace("@PAPER@", args.paper.read_text())
    text = text.replace("@DELAY@", args.delay.read_text())
    text = text.replace("@BENCH@", bench_table(json.loads(args.bench.read_text())))
    ur10 = ur10_table(args.ur10)
    if args.notes:
        ur10 += "\n" + args.notes.read_text()
    text = text.replace("@UR10@", ur10)
    soaks = [soak_text(json.loads(path.read_text())) for path in args.soak]
    text = text.replace("@SOAK@", "\n".join(soaks))
    clock = json.loads(args.rtde.read_text())
    text = text.replace("@RTDE_RECEIPT@", f"{clock['receipt_jitter_p99_ms']:.2f}")
    text = text.replace("@RTDE_MAPPED@", f"{clock['mapped_jitter_p99_ms']:.3f}")
    text = text.replace("@RTDE_DRIFT@", f"{clock['mapped_drift_ppm']:+.1f}")
    text = text.replace("@RTDE_EST@", f"{clock['clock']['drift_ppm']:+.1f}")
    (HERE.parent / "README.md").write_text(text)


if __name__ == "__main__":
    main()
