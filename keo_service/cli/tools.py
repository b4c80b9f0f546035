"""The embedded default, a recording as a Rerun file, and the benchmarks: demo, view, bench."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from keo_service.cli import common
from keo_service.cli.live import add_viewer_options
from keo_service.core.errors import ConfigError
from keo_service.resources import demo_config_path


def cmd_view(args: argparse.Namespace) -> int:
    from keo_service.bench.view import view_recording

    if args.out.suffix != ".rrd":
        raise ConfigError("command line", "--out", f"a Rerun file ends in .rrd: {args.out}")
    result = view_recording(common.load(_view_config(args)), args.directory, args.out)
    for warning in result.warnings:
        print(f"warning: {warning}", file=sys.stderr)
    summary = {
        "out": str(result.out),
        "estimates": result.estimates,
        "held": result.held,
        "duration_s": result.duration_s,
        "path": result.path,
        "warnings": result.warnings,
    }
    if args.json:
        common.print_json(summary)
    else:
        print(
            f"wrote {result.out}: {result.estimates} estimates ({result.held} held) over "
            f"{result.duration_s:.1f} s [{result.path}]; open it with: rerun {result.out}"
        )
    return common.EXIT_OK


def _view_config(args: argparse.Namespace) -> str:
    """--config, else the one config file in the recording's folder, else the demo cell, said
    on stderr (the cell decides every number: never chosen in silence)."""
    if args.config is not None:
        return str(args.config)
    found = sorted(args.directory.glob("*.toml"))
    chosen = found[0] if len(found) == 1 else demo_config_path()
    print(
        f"keo view: no --config; using {chosen} "
        + ("(the one config in the folder)" if len(found) == 1 else "(the demo cell)")
        + ": give --config C for your cell",
        file=sys.stderr,
    )
    return str(chosen)


def cmd_bench(args: argparse.Namespace) -> int:
    from keo_service.bench.benchmarks import bench_table, run_bench

    if args.soak is not None:
        from keo_service.bench.benchmarks import soak

        if args.rounds is not None:
            raise ConfigError("command line", "--rounds", "a soak is one run; drop --rounds")

        result = soak(common.load(args.config), args.soak, rrd=args.rrd)
        if not args.json:
            keep = ("summary", "latency_ms", "lost", "recording")
            result = {k: result[k] for k in keep if k in result}
        common.print_json(result)
        return common.EXIT_OK
    if args.rrd:
        raise ConfigError("command line", "--rrd", "goes with --soak SECONDS")
    if args.rounds is not None and args.rounds < 1:
        raise ConfigError("command line", "--rounds", f"at least 1, got {args.rounds}")
    report = run_bench(common.load(args.config), quick=args.quick, rounds=args.rounds)
    if args.json:
        common.print_json(report)
    else:
        sys.stdout.write(bench_table(report))
    return common.EXIT_OK


def cmd_demo(args: argparse.Namespace) -> int:
    from keo_service.bench.demo import run_demo

    return run_demo(args)


def cmd_init(args: argparse.Namespace) -> int:
    from keo_service.io.init_config import InitOptions, write_init_config

    config = write_init_config(
        InitOptions(
            robot=args.robot,
            robot_protocol=args.robot_protocol,
            tracker_protocol=args.tracker_protocol,
            out=args.out,
            cell=args.cell,
            robot_host=args.robot_host,
            robot_port=args.robot_port,
            tracker_host=args.tracker_host,
            tracker_port=args.tracker_port,
            listen=args.listen,
            force=args.force,
        )
    )
    print(f"keo init: wrote {args.out} (robot model: {config.robot.urdf})")
    return common.EXIT_OK


def _register_init(add: common.AddCommand) -> None:
    # the protocol table, not init_config: that imports numpy, which every command's parser
    # would then load before the command can choose how (`cmd_estimate`)
    from keo_service.io.protocols import names as protocol_names

    p = add("init", cmd_init, "write a complete, commented config for a cell", config=False)
    p.add_argument("--robot", required=True, help="ur10, mh180 or a URDF file")
    p.add_argument("--robot-protocol", required=True, choices=protocol_names("robot"))
    p.add_argument("--tracker-protocol", required=True, choices=protocol_names("tracker"))
    p.add_argument("--out", type=Path, required=True, help="the config file to write")
    p.add_argument("--cell", default="cell1", help="the cell's name (default cell1)")
    p.add_argument("--robot-host", default="127.0.0.1", help="the controller's address")
    p.add_argument("--robot-port", type=int, default=0, help="default: the protocol's")
    p.add_argument("--tracker-host", default="127.0.0.1", help="the line-protocol tracker")
    p.add_argument("--tracker-port", type=int, default=5005)
    p.add_argument("--listen", default="tcp/127.0.0.1:7447", help="where keo run listens")
    p.add_argument("--force", action="store_true", help="overwrite FILE")


def cmd_selftest(args: argparse.Namespace) -> int:
    import dataclasses

    from keo_service.bench.fuzz import fuzz, fuzz_table

    if args.fuzz < 1:
        raise ConfigError(
            "command line", "--fuzz", f"at least 1 input per decoder, got {args.fuzz}"
        )
    reports = fuzz(args.fuzz, seed=args.seed, only=args.only)
    if not reports:
        raise ConfigError("command line", "--only", f"no decoder matches {args.only}")
    if args.json:
        common.print_json(
            {
                "n": args.fuzz,
                "seed": args.seed,
                "decoders": [dataclasses.asdict(r) for r in reports],
            }
        )
    else:
        sys.stdout.write(fuzz_table(reports, args.fuzz, args.seed))
    crashes = sum(r.crashes for r in reports)
    return common.EXIT_FAILURE if crashes else common.EXIT_OK


def _register_demo(add: common.AddCommand) -> None:
    p = add(
        "demo",
        cmd_demo,
        "mock devices, adapters and service on loopback; prints a summary",
        config=False,
    )
    p.add_argument(
        "--robot",
        choices=["mh180", "ur10"],
        default="mh180",
        help="mh180: MotoROS (the reference paper's cell); ur10: a UR10 over RTDE",
    )
    p.add_argument("--config", help="default: the demo cell of --robot")
    p.add_argument("--duration", type=float, default=18.0, help="seconds of scenario to play")
    p.add_argument("--rrd", type=Path, help="save a Rerun recording here")
    p.add_argument(
        "--listen",
        metavar="ENDPOINT",
        help="the service's Zenoh endpoint, e.g. tcp/127.0.0.1:7447, for your own client "
        "(default: a free loopback port; either way it is printed at the start)",
    )
    p.add_argument(
        "--logs",
        type=Path,
        metavar="DIR",
        help="keep the processes' logs here (default: a temporary folder, removed after a "
        "good run, kept and named after a failed one)",
    )
    p.add_argument("--json", action="store_true")
    p.add_argument("--seed", type=int, default=1)
    add_viewer_options(p, url=False)
    p.add_argument(
        "--compensate",
        action="store_true",
        help="close the loop: a UR10 (RTDE) follows a path plus keo's live correction; prints "
        "the true tool error along the path without and with it",
    )


def register(add: common.AddCommand) -> None:
    _register_init(add)
    p = add(
        "view",
        cmd_view,
        "a recording (interchange CSV or MCAP folder) as a Rerun file, estimates included",
        config=False,
    )
    p.add_argument(
        "--config",
        type=Path,
        help="the cell's config (default: the one .toml in DIR, else the demo cell; said so)",
    )
    p.add_argument("directory", type=Path, help="written by keo record (or keo simulate)")
    p.add_argument("--out", type=Path, required=True, help="the Rerun file (.rrd) to write")
    p.add_argument("--json", action="store_true")
    _register_demo(add)

    p = add(
        "selftest",
        cmd_selftest,
        "fuzz every decoder of outside bytes with a fixed budget; prints the counts",
        config=False,
    )
    p.add_argument(
        "--fuzz",
        type=int,
        required=True,
        metavar="N",
        help="generated inputs per decoder (mutated valid frames and random bytes); exit 1 on "
        "any crash",
    )
    p.add_argument("--seed", type=int, default=1, help="the generator's seed (reproducible runs)")
    p.add_argument(
        "--only", action="append", metavar="NAME", help="decoders whose name contains NAME"
    )
    p.add_argument("--json", action="store_true")

    p = add("bench", cmd_bench, "the benchmarks (numbers, no verdicts)", config=False)
    p.add_argument("--config", default=str(demo_config_path()))
    p.add_argument("--quick", action="store_true", help="under a minute; the CI smoke test")
    p.add_argument(
        "--rounds",
        type=int,
        metavar="N",
        help="end-to-end runs (service, relay, --rrd) N times in rotated order, each ratio "
        "taken within its round and the median printed (default 3; 1 with --quick)",
    )
    p.add_argument(
        "--soak",
        type=float,
        metavar="SECONDS",
        help="instead: a soak run at 1 kHz (e.g. 600), RSS and open files over time",
    )
    p.add_argument(
        "--rrd",
        action="store_true",
        help="with --soak: the service records to Rerun (its Rerun process listed apart)",
    )
    p.add_argument("--json", action="store_true")
