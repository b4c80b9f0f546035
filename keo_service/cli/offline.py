"""Offline commands: gain, simulate, estimate, calibrate-delay, delay-study, import, paper,
analyze, compensate."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Any

from keo_service.cli import common
from keo_service.core.errors import ConfigError
from keo_service.resources import demo_config_path


# complexity (C901): one check per argument, each with its own error message
def cmd_gain(args: argparse.Namespace) -> int:  # noqa: C901
    from keo_service.core import observer as ob

    if args.rate <= 0:
        raise ConfigError("--rate", "rate", "must be > 0 (Hz)")
    rows: list[dict[str, Any]] = []
    gains = list(args.gain or [])
    best = None
    if args.noise is not None or args.drift is not None:
        if args.noise is None or args.drift is None:
            raise ConfigError("--noise/--drift", "noise", "give both --noise and --drift")
        if args.noise <= 0 or args.drift <= 0:
            raise ConfigError("--noise/--drift", "noise", "both must be > 0")
        best = ob.best_gain(args.noise, args.drift, args.rate)
        gains.append(best)
    if not gains:
        raise ConfigError("--gain", "gain", "give --gain L [L ...] and/or --noise N --drift D")
    for gain in gains:
        if not gain > 0:
            raise ConfigError("--gain", "gain", f"{gain} is not > 0")
        rep = ob.describe_gain(gain, args.rate)
        row: dict[str, Any] = {
            "gain": gain,
            "rate_hz": args.rate,
            "time_constant_s": rep.time_constant_s,
            "settling_time_s": rep.settling_time_s,
            "settling_time_sampled_s": rep.discrete_settling_time_s,
            "step_alpha": rep.step_alpha,
            "noise_gain": rep.noise_gain,
        }
        if args.noise is not None and args.drift is not None:
            mse = ob.steady_state_mse(rep.step_alpha, args.noise, args.drift, 1.0 / args.rate)
            row["rms_error"] = mse**0.5
            row["best"] = gain == best
        rows.append(row)
    if args.json:
        common.print_json({"gains": rows})
        return common.EXIT_OK
    head = (
        f"{'L [1/s]':>10} {'tau [s]':>9} {'2% settle [s]':>14} {'at rate [s]':>12} "
        f"{'noise gain':>11}"
    )
    if args.noise is not None:
        head += f" {'rms error':>11}"
    print(f"rate {args.rate:g} Hz; noise gain = estimate std / measurement noise std")
    print(head)
    for r in rows:
        line = (
            f"{r['gain']:>10.4g} {r['time_constant_s']:>9.4g} {r['settling_time_s']:>14.4g} "
            f"{r['settling_time_sampled_s']:>12.4g} {r['noise_gain']:>11.4g}"
        )
        if "rms_error" in r:
            line += f" {r['rms_error']:>11.4g}" + (
                "  <- best (steady-state Kalman)" if r["best"] else ""
            )
        print(line)
    return common.EXIT_OK


def cmd_simulate(args: argparse.Namespace) -> int:
    from keo_service.io.cell import cell_from_config
    from keo_service.sim.simulate import make_scenario, simulate, write_run

    config = common.load(args.config)
    overrides = common.parse_sets(args.set)
    if args.position_only:
        overrides["position_only"] = "true"
    scenario = make_scenario(args.scenario, overrides)
    run = simulate(cell_from_config(config), scenario, seed=args.seed)
    write_run(run, args.out)
    summary = {
        "out": str(args.out),
        "scenario": scenario.name,
        "seed": args.seed,
        "encoder_rows": int(run.encoder.t.size),
        "tracker_rows": int(run.tracker.t.size),
        "duration_s": float(run.truth_t[-1]) if run.truth_t.size else 0.0,
        "channels": list(run.channels),
    }
    if args.json:
        common.print_json(summary)
    else:
        print(
            f"wrote {args.out}/encoder.csv ({summary['encoder_rows']} rows), tracker.csv "
            f"({summary['tracker_rows']} rows), truth.csv; "
            f"scenario {scenario.name}, seed {args.seed}"
        )
    return common.EXIT_OK


# what OpenBLAS reads for its thread count, in its order: any of them set is the user's choice
USER_BLAS_THREADS = ("OPENBLAS_NUM_THREADS", "GOTO_NUM_THREADS", "OMP_NUM_THREADS")


def _blas_on_one_thread() -> None:
    """BLAS on one thread for the rest of this process, unless the user chose: numpy's
    OpenBLAS starts a thread per core when it loads, which spins between calls, and in `keo
    estimate` it only took a core from the CSV parser's and the batch's own threads
    (docs/performance.md). Only before numpy loads: OpenBLAS reads the variable then."""
    chosen = any(name in os.environ for name in USER_BLAS_THREADS)
    if "numpy" not in sys.modules and not chosen:
        os.environ["OPENBLAS_NUM_THREADS"] = "1"


@common.collector_paused
def cmd_estimate(args: argparse.Namespace) -> int:
    _blas_on_one_thread()
    from keo_service.offline.library import estimate

    result = estimate(args.config, args.encoder, args.tracker, args.out, streaming=args.streaming)
    if args.json:
        common.print_json(result.summary())
    else:
        size = result.stamp.size
        print(f"wrote {size} estimates ({result.held} held) to {args.out} [{result.path}]")
        skipped = {
            k: v
            for k, v in result.counters.items()
            if k.startswith(("encoder_", "tracker_")) and not k.endswith("samples")
        }
        if skipped:
            print("skipped rows: " + ", ".join(f"{k}={v}" for k, v in sorted(skipped.items())))
            for m in result.messages[-5:]:
                print(f"  {m}")
    return common.EXIT_OK


def cmd_paper(args: argparse.Namespace) -> int:
    from keo_service.sim.paper import paper_markdown, paper_report

    config = common.load(args.config)
    report = paper_report(config, seed=args.seed)
    if args.json:
        common.print_json(report)
    else:
        sys.stdout.write(paper_markdown(report))
    return common.EXIT_OK


@common.collector_paused
def cmd_calibrate_delay(args: argparse.Namespace) -> int:
    from keo_service.fit.delay import DelayNotIdentifiableError
    from keo_service.offline.library import calibrate_delay

    try:
        result = calibrate_delay(args.config, args.encoder, args.tracker, drift=not args.no_drift)
    except DelayNotIdentifiableError as exc:
        if args.json:
            common.print_json({"verdict": "refused", "reason": str(exc)})
        print(f"keo calibrate-delay: refused: {exc}", file=sys.stderr)
        return common.EXIT_FAILURE
    if args.json:
        common.print_json(result.document())
    else:
        print("\n".join(result.lines()))
    if not result.explained:
        print(
            "keo calibrate-delay: the number above is not to be trusted: "
            + "; ".join(result.notes),
            file=sys.stderr,
        )
        return common.EXIT_FAILURE
    return common.EXIT_OK


def cmd_delay_study(args: argparse.Namespace) -> int:
    from keo_service.sim.delay_study import as_jsonable, delay_markdown, delay_study

    rows = delay_study(common.load(args.config), seed=args.seed)
    if args.json:
        common.print_json(as_jsonable(rows))
    else:
        sys.stdout.write(delay_markdown(rows))
    return common.EXIT_OK


def cmd_import(args: argparse.Namespace) -> int:
    from keo_service.io.importers import import_dataset

    info = import_dataset(args.kind, args.source, args.out)
    if args.json:
        common.print_json(info)
    else:
        print(f"wrote {args.out}/encoder.csv and tracker.csv: {info['rows']} poses; {info['time']}")
    return common.EXIT_OK


def cmd_analyze(args: argparse.Namespace) -> int:
    from keo_service.offline.library import analyze

    result = analyze(
        args.config, args.encoder, args.tracker, args.out, registration_only=args.registration_only
    )
    if args.json:
        common.print_json(result.report)
    else:
        print(result.report_path.read_text())
        print(f"wrote {args.out}/report.json, report.md, plots and model.toml")
        for warning in result.warnings:  # again at the end, where the eye lands
            print(f"warning: {warning}", file=sys.stderr)
    return common.EXIT_OK


@common.collector_paused
def cmd_compensate(args: argparse.Namespace) -> int:
    from keo_service.offline.compensate import compensate

    summary = compensate(
        common.load(args.config), args.targets, args.out, accuracy_columns=args.accuracy
    ).summary
    if args.json:
        common.print_json(summary)
        return common.EXIT_OK
    flags = ", ".join(f"{k} {v}" for k, v in summary["flags"].items() if v) or "no flags"
    tool = summary["tool_frame"]
    print(
        f"targets: the TCP [tool] xyz {tool['xyz']} m, rpy {tool['rpy']} rad, in the robot "
        "base frame"
    )
    region = summary["calibrated_region"]
    if region is None:
        print("calibrated region: not stated in this model (re-run keo analyze to write it)")
    else:
        joints = ", ".join(
            f"{n} {lo:+.3f}..{hi:+.3f}" for n, (lo, hi) in region["joints_rad"].items()
        )
        print(f"calibrated region: joints (rad) {joints}")
        for b in region["tool_boxes_m"]:
            lo, hi = b["lower"], b["upper"]
            print(
                f"  tool {b['band']} ({b['poses']} poses): x {lo[0]:+.3f}..{hi[0]:+.3f}, "
                f"y {lo[1]:+.3f}..{hi[1]:+.3f}, z {lo[2]:+.3f}..{hi[2]:+.3f} m"
            )
    outside = summary["outside_region"]
    if outside and outside["targets"]:
        far = outside["max_mm"]
        print(
            f"{outside['targets']} target(s) outside the calibrated region"
            + (f" (farthest {far:.1f} mm)" if far is not None else "")
            + (
                f", {outside['unseen_orientation']} with a tool orientation no calibration pose had"
                if outside["unseen_orientation"]
                else ""
            )
            + ": the accuracy stated there (--accuracy) is the model's extrapolation figure, "
            "none for an orientation not seen (outside_region_mm)"
        )
    acc = summary["model_accuracy_mm"]
    later = summary["accuracy_mm_rms"]
    session = summary["accuracy_session_mm"]
    print(
        f"wrote {summary['out']}: {summary['targets']} targets ({summary['form']}); "
        f"correction {summary['correction_mm']['rms']:.4f} mm RMS, "
        f"{summary['correction_mm']['max']:.4f} mm max, "
        f"{summary['correction_mrad']['rms']:.4f} mrad RMS"
        + (f"; model accuracy {acc:.4f} mm RMS (held out)" if acc else "")
        + (
            f", {later:.4f} mm RMS at these targets in a later session (between sessions "
            f"{session:.4f} mm, from {summary['accuracy_session_source'] or 'the model file'})"
            if acc and later is not None and session
            else ""
        )
        + f"; {flags}"
    )
    return common.EXIT_OK


def register(add: common.AddCommand) -> None:
    p = add(
        "gain",
        cmd_gain,
        "time constant, 2%% settling time and noise gain of observer gains",
        config=False,
    )
    p.add_argument("--gain", type=float, nargs="+", metavar="L", help="gains in 1/s")
    p.add_argument("--rate", type=float, required=True, help="sample rate in Hz")
    p.add_argument("--noise", type=float, help="measurement noise std (m or rad)")
    p.add_argument(
        "--drift",
        type=float,
        help="random-walk drift of the true error: std of its change over 1 s (per sqrt(s))",
    )
    p.add_argument("--json", action="store_true")

    p = add("simulate", cmd_simulate, "write encoder.csv, tracker.csv and truth.csv for a scenario")
    p.add_argument("--scenario", required=True)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--set", action="append", metavar="KEY=VALUE", help="override a scenario parameter"
    )
    p.add_argument("--position-only", action="store_true", help="a single-reflector tracker")
    p.add_argument("--json", action="store_true")

    p = add("estimate", cmd_estimate, "the service's alignment and observer over recorded files")
    p.add_argument("--encoder", type=Path, required=True)
    p.add_argument("--tracker", type=Path, required=True)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument(
        "--streaming",
        action="store_true",
        help="feed the samples one at a time through the live estimator (a cross-check of "
        "the default batch path; the same output, 10x slower)",
    )
    p.add_argument("--json", action="store_true")

    p = add(
        "calibrate-delay",
        cmd_calibrate_delay,
        "the delay (and clock drift) between the streams, from any motion",
    )
    p.add_argument("--encoder", type=Path, required=True)
    p.add_argument("--tracker", type=Path, required=True)
    p.add_argument("--no-drift", action="store_true", help="fit a constant delay only")
    p.add_argument("--json", action="store_true")

    p = add(
        "delay-study",
        cmd_delay_study,
        "true vs found delay on simulated scenarios (README table)",
        config=False,
    )
    p.add_argument("--config", default=str(demo_config_path()))
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--json", action="store_true")

    p = add("import", cmd_import, "an outside data set to the interchange files", config=False)
    p.add_argument("kind", choices=["ur10-lasertracker"])
    p.add_argument("source", type=Path, help="e.g. Series_A/measurements_grid.csv")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--json", action="store_true")

    p = add(
        "paper",
        cmd_paper,
        "the reference paper's experiments reproduced in simulation",
        config=False,
    )
    p.add_argument("--config", default=str(demo_config_path()))
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--json", action="store_true")
    _register_model(add)


def _register_model(add: common.AddCommand) -> None:
    """The identified model's two commands: `analyze` writes it, `compensate` uses it."""
    p = add("analyze", cmd_analyze, "what the model still gets wrong, effects added and judged")
    p.add_argument(
        "--encoder",
        type=Path,
        required=True,
        action="append",
        help="repeat with --tracker for several recordings of one robot",
    )
    p.add_argument("--tracker", type=Path, required=True, action="append")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument(
        "--registration-only",
        action="store_true",
        help="keep the effects in the config; re-identify tracker and tool only",
    )
    p.add_argument("--json", action="store_true")

    p = add(
        "compensate",
        cmd_compensate,
        "the joints (and the nominal-model pose to command) that put the tool on each target "
        "under the identified model (--config: the model.toml of keo analyze); targets are "
        "the TCP ([tool]) in the robot base frame",
    )
    p.add_argument("--targets", type=Path, required=True, help="targets CSV")
    p.add_argument("--out", type=Path, required=True, help="compensated targets CSV")
    p.add_argument(
        "--accuracy",
        action="store_true",
        help="add the columns predicted_mm, predicted_mrad (the model's deviation from the "
        "nominal robot at each target), accuracy_mm (its predicted accuracy there in a later "
        "session) and accuracy_same_session_mm (in the calibration session)",
    )
    p.add_argument("--json", action="store_true")
