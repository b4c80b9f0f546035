"""`keo demo`: the embedded default. Mock robot, mock tracker, both adapters and the service,
each its own process, talking real TCP and Zenoh on loopback; this process subscribes to the
estimates like any client and compares the final one with the truth the simulator injected."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import re
import shutil
import socket
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from keo_service.bench.procs import ProcessGroup, free_port, process_group
from keo_service.core.errors import ConfigError
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

# why an estimate's step was held, in a user's words (the flag is the estimate's only flag)
HELD_WHY = {
    "encoder_stale": "no encoder sample yet at the tracker sample's time minus the delay (the "
    "streams' first moments, or the encoder stream stopped)",
    "encoder_too_old": "the tracker sample's time minus the delay lies before the oldest "
    "encoder sample there is (before the encoder stream began, or older than timing.buffer_s)",
    "encoder_gap": "the encoder samples around its time are further apart than timing.max_gap_s",
    "tracker_gap": "the tracker sent no valid pose (a status other than ok, e.g. beam broken)",
    "tracker_stale": "the newest tracker pose is older than timing.stale_after_s",
}


def loopback_config(config: Config, listen: str | None = None) -> Config:
    """The same cell on free loopback ports, so a demo never collides with anything; the
    service listens on `listen` when given (`keo demo --listen`)."""
    robot = msgspec.structs.replace(config.robot, host="127.0.0.1", port=free_port())
    tracker = msgspec.structs.replace(config.tracker, host="127.0.0.1", port=free_port())
    endpoint = listen or f"tcp/127.0.0.1:{free_port()}"
    bus = msgspec.structs.replace(config.bus, mode="peer", listen=[endpoint], connect=[])
    return msgspec.structs.replace(config, robot=robot, tracker=tracker, bus=bus)


def check_listen(endpoint: str) -> str:
    """`--listen`: a Zenoh endpoint `tcp/HOST:PORT` whose port is free (else exit 2, saying
    so, instead of a service that dies in its log while the demo waits for it)."""
    match = re.fullmatch(r"tcp/(\[[0-9a-fA-F:.]+\]|[^:/\s]+):(\d{1,5})", endpoint)
    if match is None:
        raise ConfigError("--listen", "listen", f"{endpoint!r} is not tcp/HOST:PORT")
    host, port = match.group(1).strip("[]"), int(match.group(2))
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        try:
            probe.bind((host, port))
        except OSError as exc:
            raise ConfigError(
                "--listen",
                "listen",
                f"cannot listen on {endpoint}: {exc.strerror} (another keo demo or keo run "
                "there? pick another port)",
            ) from None
    return endpoint


def _work_dir(args: argparse.Namespace) -> tuple[Path, bool]:
    """Where the children's logs go, and whether they stay: `--logs DIR` keeps them there;
    by default a temporary folder removed at the end unless something failed."""
    logs = getattr(args, "logs", None)
    if logs is not None:
        logs.mkdir(parents=True, exist_ok=True)
        return logs.resolve(), True
    return Path(tempfile.mkdtemp(prefix="keo-demo-")), False


def _finish_logs(work: Path, keep: bool, failed: bool) -> str | None:
    """Remove the temporary log folder after a good run; keep and name it otherwise."""
    if keep or failed:
        return str(work)
    shutil.rmtree(work, ignore_errors=True)
    return None


def _seconds_until_listening(endpoint: str, procs: ProcessGroup, limit: float = 60.0) -> float:
    """How long the service took to listen: the mocks, started next, import as much and
    compute their scenario besides, so their start is given four times this (on a heavily
    loaded machine a fixed lead let the scenario end before the mocks were up, and the demo
    saw no estimate: docs/performance.md)."""
    started = time.monotonic()
    host, _, port = endpoint.removeprefix("tcp/").rpartition(":")
    while time.monotonic() - started < limit and procs.procs["service"].poll() is None:
        with (
            contextlib.suppress(OSError),
            socket.create_connection((host.strip("[]"), int(port)), 0.2),
        ):
            break
        time.sleep(0.1)
    return time.monotonic() - started


def _say_endpoint(config: Config, to_stderr: bool) -> None:
    endpoint = config.bus.listen[0]
    print(
        f"keo demo: the service listens on {endpoint} (cell {config.cell!r}); from another "
        f'terminal: Client("{endpoint}", cell="{config.cell}"), or keo echo '
        f"'keo/{config.cell}/estimate' with [bus] connect = [\"{endpoint}\"]",
        file=sys.stderr if to_stderr else sys.stdout,
        flush=True,
    )


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
    if getattr(args, "compensate", False):
        return run_compensated_demo(args)
    config_name, scenario, robot_args = DEMO_ROBOTS[args.robot]
    base = load_config(args.config or configs_dir() / config_name)
    listen = getattr(args, "listen", None)
    config = loopback_config(base, check_listen(listen) if listen else None)
    work, keep = _work_dir(args)
    cfg_path = work / "demo.toml"
    cfg_path.write_text(config_to_toml(config), encoding="utf-8")
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
        cfg = ["--config", str(cfg_path)]
        procs.start("service", ["run", *cfg, *rrd])
        _say_endpoint(config, to_stderr=args.json)
        lead = max(STARTUP_S, 4.0 * _seconds_until_listening(config.bus.listen[0], procs))
        t0 = time.time() + lead
        play = ["--scenario", scenario, "--seed", str(args.seed), "--t0", repr(t0)]
        play += ["--duration", repr(args.duration)]
        procs.start("mock-robot", ["mock", "robot", *cfg, *play, *robot_args])
        procs.start("mock-tracker", ["mock", "tracker", *cfg, *play])
        procs.start("adapter-encoder", ["adapter", "encoder", *cfg])
        procs.start("adapter-tracker", ["adapter", "tracker", *cfg])
        if not args.json:
            print(
                f"keo demo: 5 processes on loopback; {args.robot} playing {scenario} "
                f"for {args.duration:g} s, starting in {lead:.0f} s ...",
                flush=True,
            )
        try:
            estimates, status = asyncio.run(_follow(config, t0 + args.duration + 0.5))
        except ClientError:
            estimates = []
        codes = procs.close()
    summary = _summary(config, args, scenario, estimates, status, codes, t0)
    failed = summary["estimates"] == 0 or any(code not in (0, None) for code in codes.values())
    summary["logs"] = _finish_logs(work, keep, failed)
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
        "endpoint": config.bus.listen[0],
        "estimates": len(estimates),
        "held": len(estimates) - len(good),
        # why each held step was held: its flag (the reason) and how often
        "held_reasons": dict(
            Counter("|".join(e.flags) or "unknown" for e in estimates if e.measured is None)
        ),
        "exit_codes": codes,
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
    for reason, count in s["held_reasons"].items():
        why = HELD_WHY.get(reason, "see the flag in docs/topics-and-files.md")
        print(f"  held {count}x {reason}: {why}; the observer kept its state")
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
    if s["logs"] is not None:
        print(f"the processes' logs: {s['logs']}")


# ---- keo demo --compensate -------------------------------------------------------------------

# a UR10 (RTDE, 125 Hz) whose real arm differs from the nominal one (the simulator's perturbed
# geometry and joint offsets, and a tool off by 1.97 mm / 1.97 mrad), strokes of 0.25 m down
# at 0.1 m/s with 1 s dwells
COMPENSATED_PATH = ["--set", "stroke_m=0.25", "--set", "dwell_s=1.0", "--set", "speed_m_s=0.1"]
COMPENSATED_TOOL_ERROR = "0.0012,-0.001,0.0012,0.0012,0.001,-0.0012"  # 1.97 mm / 1.97 mrad


def run_compensated_demo(args: argparse.Namespace) -> int:
    """The whole loop as processes: keo run, the RTDE adapter writing the correction to the
    controller's input registers, the tracker adapter, and the mock UR following its path plus
    the registers (with the tracker that sees its arm). The mock knows the true tool error at
    every controller cycle, with the correction and (the same path) without it."""
    base = load_config(args.config or configs_dir() / "ur10_demo.toml")
    listen = getattr(args, "listen", None)
    config = loopback_config(base, check_listen(listen) if listen else None)
    robot = msgspec.structs.replace(config.robot, correction="rtde_registers", frequency_hz=125.0)
    config = msgspec.structs.replace(config, robot=robot)
    work, keep = _work_dir(args)
    cfg_path = work / "demo.toml"
    cfg_path.write_text(config_to_toml(config), encoding="utf-8")
    summary_path = work / "errors.json"
    t0 = time.time() + STARTUP_S + 2.0  # the clock mappings settle before the path moves
    duration = args.duration
    cfg = ["--config", str(cfg_path)]
    mock = [
        *("mock", "robot", *cfg, "--scenario", "paper-vertical", *COMPENSATED_PATH),
        *("--set", f"duration_s={duration!r}", "--seed", str(args.seed), "--t0", repr(t0)),
        *("--max-hz", "125", "--follow-corrections", "--tool-error", COMPENSATED_TOOL_ERROR),
        *("--summary", str(summary_path)),
    ]
    if not args.json:
        print(
            f"keo demo --compensate: 4 processes on loopback; a UR10 follows "
            f"0.25 m strokes at 0.1 m/s plus keo's correction for {duration:g} s ...",
            flush=True,
        )
    _say_endpoint(config, to_stderr=args.json)
    with process_group(work) as procs:
        procs.start("service", ["run", *cfg])
        procs.start("mock-robot", mock)
        procs.start("adapter-encoder", ["adapter", "encoder", *cfg])
        procs.start("adapter-tracker", ["adapter", "tracker", *cfg])
        time.sleep(max(0.0, t0 + duration + 0.5 - time.time()))
        codes = procs.close()
    if not summary_path.exists():
        print(f"keo demo: the mock robot wrote no errors (logs in {work})", file=sys.stderr)
        return 1
    doc = json.loads(summary_path.read_text(encoding="utf-8"))
    closed = doc["summary"].get("loop_closed_at_s") is not None
    logs = _finish_logs(work, keep, not closed)
    out = {"exit_codes": codes, "logs": logs, **doc["summary"], "along_path": _bins(doc)}
    if args.json:
        sys.stdout.write(json.dumps(out, indent=2) + "\n")
    else:
        _print_compensated(out)
    return 0 if closed else 1


def _bins(doc: dict[str, Any], width_s: float = 0.5) -> list[dict[str, float]]:
    """The true error along the path in bins of `width_s` (RMS over the controller cycles)."""
    series = doc["series"]
    t = np.asarray(series["t"])
    rows = []
    for start in np.arange(0.0, float(t.max()) if t.size else 0.0, width_s):
        m = (t >= start) & (t < start + width_s)
        if not m.any():
            continue

        def rms(name: str, m: np.ndarray = m) -> float:
            return float(np.sqrt(np.mean(np.square(np.asarray(series[name])[m]))))

        rows.append(
            {
                "t": float(start),
                "without_mm": rms("pos_uncompensated_mm"),
                "without_mrad": rms("rot_uncompensated_mrad"),
                "with_mm": rms("pos_mm"),
                "with_mrad": rms("rot_mrad"),
            }
        )
    return rows


def _print_compensated(s: dict[str, Any]) -> None:
    print("true tool error along the path (RMS per 0.5 s), without and with compensation:")
    print(f"{'t [s]':>6} {'without mm':>11} {'mrad':>7} {'with mm':>9} {'mrad':>7}")
    for r in s["along_path"]:
        print(
            f"{r['t']:>6.1f} {r['without_mm']:>11.4f} {r['without_mrad']:>7.4f} "
            f"{r['with_mm']:>9.4f} {r['with_mrad']:>7.4f}"
        )
    closed = s.get("loop_closed_at_s")
    if closed is None:
        print("the loop never closed (no correction reached the controller)")
    else:
        print(
            f"loop closed at {closed:.2f} s; from 5 s later: {s['compensated_pos_rms_mm']:.4f} mm "
            f"/ {s['compensated_rot_rms_mrad']:.4f} mrad RMS (max {s['compensated_pos_max_mm']:.4f}"
            f" mm); without: {s['uncompensated_pos_rms_mm']:.4f} mm / "
            f"{s['uncompensated_rot_rms_mrad']:.4f} mrad RMS"
        )
    print(f"process exit codes: {s['exit_codes']}")
    if s["logs"] is not None:
        print(f"the processes' logs: {s['logs']}")
