"""`keo demo`: the embedded default. Mock robot, mock tracker, both adapters and the service,
each its own process, talking real TCP and Zenoh on loopback; this process subscribes to the
estimates like any client and compares the final one with the truth the simulator injected."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from keo_service.bench.procs import free_port, process_group
from keo_service.core.observer import noise_gain
from keo_service.io.cell import cell_from_config
from keo_service.io.config import Config, config_to_toml, load_config
from keo_service.live.client import Client, ClientError
from keo_service.live.messages import EstimateMessage, ServiceStatus
from keo_service.live.rerun_process import OpenedViewer, open_viewer
from keo_service.resources import configs_dir
from keo_service.sim.simulate import make_scenario, simulate

# per robot: the config it plays, the scenario, and what its mock controller adds
DEMO_ROBOTS = {
    "mh180": ("demo.toml", "paper-vertical", []),
    # a UR controller's own clock, 80 ppm fast, and delivery up to 6 ms late in bursts: the
    # adapter maps the controller's stamps onto the host clock
    "ur10": (
        "ur10_demo.toml",
        "paper-step",
        ["--clock-drift-ppm", "80", "--late-ms", "6", "--burst-every", "1"],
    ),
}
STARTUP_S = 4.0  # the children import numpy, Pinocchio and Zenoh before the scenario starts


def loopback_config(config: Config) -> Config:
    """The same cell on free loopback ports, so a demo never collides with anything."""
    robot = msgspec.structs.replace(config.robot, host="127.0.0.1", port=free_port())
    tracker = msgspec.structs.replace(config.tracker, host="127.0.0.1", port=free_port())
    bus = msgspec.structs.replace(
        config.bus, mode="peer", listen=[f"tcp/127.0.0.1:{free_port()}"], connect=[]
    )
    return msgspec.structs.replace(config, robot=robot, tracker=tracker, bus=bus)


async def _follow(config: Config, until: float) -> tuple[list[EstimateMessage], ServiceStatus]:
    """Subscribe like any user program: the estimates until `until` (wall clock), then the
    service's status."""
    out: list[EstimateMessage] = []
    async with Client.from_config(config, connect_timeout_s=20.0) as keo:

        async def gather() -> None:
            async for est in keo.estimates():
                out.append(est)

        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(gather(), timeout=max(0.0, until - time.time()))
        return out, await keo.status()


def run_demo(args: argparse.Namespace) -> int:
    config_name, scenario, robot_args = DEMO_ROBOTS[args.robot]
    base = load_config(args.config or configs_dir() / config_name)
    config = loopback_config(base)
    work = Path(tempfile.mkdtemp(prefix="keo-demo-"))
    cfg_path = work / "demo.toml"
    cfg_path.write_text(config_to_toml(config), encoding="utf-8")
    t0 = time.time() + STARTUP_S
    play = [
        "--scenario",
        scenario,
        "--seed",
        str(args.seed),
        "--t0",
        repr(t0),
        "--duration",
        repr(args.duration),
    ]
    status = None
    viewer = _open_viewer(args)
    with contextlib.ExitStack() as cleanup, process_group(work) as procs:
        if viewer is not None:
            cleanup.callback(viewer.close)  # after the cell, also on Ctrl-C
        rrd = ["--rrd", str(args.rrd.resolve())] if args.rrd is not None else []
        if viewer is not None:
            rrd += ["--viewer", viewer.grpc_url]
        if getattr(args, "viewer_window", None) is not None:
            rrd += ["--viewer-window", repr(args.viewer_window)]
        procs.start_cell(cfg_path, play, service=rrd, robot=robot_args)
        if not args.json:
            print(
                f"keo demo: 5 processes on loopback (logs in {work}); {args.robot} playing "
                f"{scenario} "
                f"for {args.duration:g} s from t0 + {STARTUP_S:g} s ...",
                flush=True,
            )
        try:
            estimates, status = asyncio.run(_follow(config, t0 + args.duration + 0.5))
        except ClientError:
            estimates = []
        codes = procs.close()
    summary = _summary(config, args, scenario, estimates, status, codes, t0, work)
    if args.rrd is not None:
        summary["rrd"] = str(args.rrd)
    if args.json:
        sys.stdout.write(json.dumps(summary, indent=2) + "\n")
    else:
        _print_summary(summary)
    return 0 if summary["estimates"] > 0 else 1


def _open_viewer(args: argparse.Namespace) -> OpenedViewer | None:
    """`--viewer`: Rerun's viewer, opened before the cell starts, its URL printed."""
    kind = getattr(args, "viewer", None)
    if kind is None:
        return None
    viewer = open_viewer(kind, args.viewer_port, args.web_port, args.viewer_bind)
    where = "open" if viewer.kind == "web" else "native viewer on"
    print(f"keo demo: Rerun {where} {viewer.url}", file=sys.stderr, flush=True)
    return viewer


def _summary(
    config: Config,
    args: argparse.Namespace,
    scenario: str,
    estimates: list[EstimateMessage],
    status: ServiceStatus | None,
    codes: dict[str, int | None],
    t0: float,
    work: Path,
) -> dict[str, Any]:
    run = simulate(
        cell_from_config(config),
        make_scenario(scenario, {"duration_s": repr(args.duration)}),
        seed=args.seed,
    )
    good = [e for e in estimates if e.measured is not None]
    out: dict[str, Any] = {
        "robot": args.robot,
        "scenario": scenario,
        "duration_s": args.duration,
        "estimates": len(estimates),
        "held": len(estimates) - len(good),
        "exit_codes": codes,
        "logs": str(work),
    }
    if status is not None:
        out["rates_hz"] = status.rates_hz
        out["delay_s"] = status.delay_s
        out["counters"] = status.counters
    if good:
        last = good[-1]
        truth = np.array(
            [
                np.interp(last.stamp - t0, run.truth_t, run.truth[:, k])
                for k in range(run.truth.shape[1])
            ]
        )
        err = np.asarray(last.estimate) - truth
        period = float(np.mean(np.diff([e.stamp for e in good]))) if len(good) > 1 else 0.01
        band = noise_gain(config.observer.gain[0], period)
        out.update(
            {
                "channels": last.channels,
                "final_estimate": last.estimate,
                "injected_truth": truth.tolist(),
                "final_error_pos_mm": float(np.linalg.norm(err[:3]) * 1e3),
                "final_error_rot_mrad": float(np.linalg.norm(err[3:]) * 1e3)
                if err.size > 3
                else None,
                "predicted_noise_pos_mm": float(band * run.scenario.position_noise_m * 1e3),
            }
        )
    return out


def _print_summary(s: dict[str, Any]) -> None:
    print(f"estimates received: {s['estimates']} ({s['held']} held)")
    if "rates_hz" in s:
        rates = ", ".join(f"{k} {v:.1f} Hz" for k, v in s["rates_hz"].items())
        print(f"rates seen by the service (at the end): {rates}")
        print(f"delay in use: {s['delay_s'] * 1e3:.1f} ms")
    if "final_estimate" in s:
        names = s["channels"]
        scale = [1e3] * len(names)
        print(f"{'channel':>8} {'estimate':>10} {'truth':>10}   (mm / mrad)")
        for name, e, t, k in zip(
            names, s["final_estimate"], s["injected_truth"], scale, strict=True
        ):
            print(f"{name:>8} {e * k:>10.4f} {t * k:>10.4f}")
        rot = s["final_error_rot_mrad"]
        rot_text = f", {rot:.4f} mrad" if rot is not None else ""
        print(
            f"final estimate vs injected truth: {s['final_error_pos_mm']:.4f} mm{rot_text} "
            f"(white-noise band 1 sigma: {s['predicted_noise_pos_mm']:.4f} mm per axis)"
        )
    print(f"process exit codes: {s['exit_codes']}")
