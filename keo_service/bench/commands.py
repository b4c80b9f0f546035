"""Recordings: `keo estimate`, `keo calibrate-delay` and `keo analyze` timed as commands
(wall and CPU time, peak memory) on a simulated recording, beside the in-process floor."""

from __future__ import annotations

import itertools
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from keo_service.bench.hot_path import floor_pass, khz_run
from keo_service.bench.machine import proc_mem_kb
from keo_service.core.errors import KeoError
from keo_service.io.cell import cell_from_config
from keo_service.io.config import Config, config_to_toml
from keo_service.sim.simulate import SimulatedRun, write_run


def _timed_command(args: list[str], log: Path) -> dict[str, float]:
    """Run a keo command as its own process: wall and CPU seconds, peak resident memory.

    The peak is the process's own high-water mark (VmHWM) read every few milliseconds while
    it runs: the rusage figure of a child counts the parent's size at the fork, which in the
    bench (a simulated recording in memory) is larger than the command's own peak."""
    argv = [sys.executable, "-m", "keo_service.cli", *args]
    peak_kb = [0]
    with log.open("w") as out:
        t0 = time.perf_counter()
        proc = subprocess.Popen(argv, stdout=out)
        watcher = threading.Thread(target=_watch_peak, args=(proc.pid, argv, peak_kb))
        watcher.start()
        _pid, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        watcher.join()
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise KeoError(f"keo {args[0]} exited {proc.returncode}: {log.read_text()[-500:]}")
    return {
        "wall_s": wall,
        "cpu_s": usage.ru_utime + usage.ru_stime,
        "peak_rss_mb": peak_kb[0] / 1024.0,
    }


def _watch_peak(pid: int, argv: list[str], peak_kb: list[int]) -> None:
    """The VmHWM of `pid` once it runs `argv` (before its exec it is still a copy of the
    bench), until it exits."""
    cmdline = ("\0".join(argv) + "\0").encode()
    while True:
        try:
            running = Path(f"/proc/{pid}/cmdline").read_bytes() == cmdline
            memory = proc_mem_kb(pid)
        except (OSError, ValueError):
            return  # reaped
        if "VmHWM" not in memory:
            return  # exited: a zombie has no memory left
        if running:
            peak_kb[0] = max(peak_kb[0], memory["VmHWM"])
        time.sleep(0.005)


def recording(
    config: Config,
    seconds: float,
    streaming_too: bool = True,
    repeats: int = 3,
    analyze_seconds: float | None = None,
    analyze_whole: bool = False,
) -> dict[str, Any]:
    """`keo estimate` over `seconds` of a 1 kHz tracker and a 250 Hz robot (CSV in, CSV out,
    process start included) against the naive per-sample floor over the same tracker samples
    and, when asked, the same command on the per-sample streaming path; then `keo
    calibrate-delay` over the same files once.

    The command runs once to warm up (reported, not counted: on a VM the first command after
    the bench has written and freed a few hundred MB runs on memory the host has taken back,
    and pays for it page by page), then `repeats` times, each right after a floor pass over
    the whole recording in this process: a neighbour that slows the machine for a while slows
    both sides of a pair. The figure is the median of the per-pair ratios (command wall time
    over floor CPU time); the run with the median wall time and every run's wall time are
    beside it.

    `analyze_seconds`: `keo analyze` over the recording's first seconds too (every candidate
    effect fitted and judged on every pose). `analyze_whole`: and over the whole recording,
    the long-recording path (informative samples, fit.sampling), beside the same floor."""
    run = khz_run(config, seconds)
    cell = cell_from_config(config)
    out: dict[str, Any] = {
        "seconds": seconds,
        "tracker_samples": int(run.tracker.t.size),
        "encoder_samples": int(run.encoder.t.size),
    }
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        write_run(run, folder)
        cfg = folder / "keo.toml"
        cfg.write_text(config_to_toml(config))
        os.sync()  # the kernel writes our input files back now, not during the timed command
        args = ["estimate", "--config", str(cfg), "--encoder", str(folder / "encoder.csv")]
        args += ["--tracker", str(folder / "tracker.csv"), "--out", str(folder / "e.csv")]
        warmup = _timed_command(args, folder / "batch.log")
        runs, floors, floor_walls = [], [], []
        for _ in range(repeats):
            _n, floor_cpu, floor_wall = floor_pass(cell, run)
            floors.append(floor_cpu)
            floor_walls.append(floor_wall)
            runs.append(_timed_command(args, folder / "batch.log"))
        median = sorted(runs, key=lambda timing: timing["wall_s"])[len(runs) // 2]
        out.update(_pair_ratios(runs, floors, floor_walls))
        out["batch"] = {
            **median,
            "runs_wall_s": [r["wall_s"] for r in runs],  # in the order they ran
            "warmup_wall_s": warmup["wall_s"],
        }
        if streaming_too:
            out["streaming"] = _timed_command([*args, "--streaming"], folder / "streaming.log")
        # the delay fit over the same files: three rounds of kinematics over every sample
        fit = ["calibrate-delay", "--config", str(cfg), "--encoder", str(folder / "encoder.csv")]
        fit += ["--tracker", str(folder / "tracker.csv")]
        out["calibrate_delay"] = _timed_command(fit, folder / "delay.log")
        if analyze_seconds is not None:
            out["analyze"] = _analyze_head(run, folder, cfg, analyze_seconds)
        if analyze_whole:
            out["analyze_long"] = _analyze_whole(folder, cfg, out["floor_s"])
    return out


def _pair_ratios(
    runs: list[dict[str, float]], floor_cpu: list[float], floor_wall: list[float]
) -> dict[str, Any]:
    """The command against the floor pass run just before it, pair by pair: the time a user
    waits for each (wall over wall: on a busy machine both wait for a core alike; wall over
    the floor's CPU time, as measured before, charged the command with that wait and not the
    floor) and the CPU each takes."""
    walls = [r["wall_s"] / f for r, f in zip(runs, floor_wall, strict=True)]
    cpus = [r["cpu_s"] / f for r, f in zip(runs, floor_cpu, strict=True)]
    return {
        "floor_s": float(np.median(floor_cpu)),
        "floor_runs_s": floor_cpu,
        "floor_wall_s": float(np.median(floor_wall)),
        "floor_runs_wall_s": floor_wall,
        "over_floor": float(np.median(walls)),
        "over_floor_best": min(walls),
        "over_floor_worst": max(walls),
        "over_floor_runs": walls,  # in the order they ran
        "over_floor_cpu": float(np.median(cpus)),
        "over_floor_wall_over_cpu": float(
            np.median([r["wall_s"] / f for r, f in zip(runs, floor_cpu, strict=True)])
        ),
    }


def _analyze_whole(folder: Path, cfg: Path, floor_s: float) -> dict[str, Any]:
    """`keo analyze` over the whole recording: time, peak memory, its ratio to the floor of
    this run (the naive per-sample pass over the same tracker samples), the samples it kept
    and its held-out error."""
    args = ["analyze", "--config", str(cfg), "--encoder", str(folder / "encoder.csv")]
    args += ["--tracker", str(folder / "tracker.csv"), "--out", str(folder / "analysis")]
    timing = _timed_command(args, folder / "analyze_long.log")
    report = json.loads((folder / "analysis" / "report.json").read_text())
    return {
        **timing,
        "over_floor": timing["wall_s"] / floor_s,
        "samples": report.get("samples", {}),
        "held_out_pos_rms_mm": report["final"]["validation"]["pos_rms_mm"],
    }


def _analyze_head(run: SimulatedRun, folder: Path, cfg: Path, seconds: float) -> dict[str, Any]:
    """`keo analyze` over the rows of the recording's files stamped before `seconds`."""
    head, poses = head_files(run, folder, seconds)
    args = ["analyze", "--config", str(cfg), "--encoder", str(head / "encoder.csv")]
    args += ["--tracker", str(head / "tracker.csv"), "--out", str(head / "analysis")]
    timing = _timed_command(args, folder / "analyze.log")
    return {**timing, "seconds": seconds, "poses": poses}


def head_files(run: SimulatedRun, folder: Path, seconds: float) -> tuple[Path, int]:
    """`folder/head/`: `run`'s files in `folder` cut to their rows stamped before `seconds`
    (the simulator writes rows in time order); and the tracker rows kept."""
    head = folder / "head"
    head.mkdir(exist_ok=True)
    rows = {
        "encoder.csv": int(np.searchsorted(run.encoder.t, seconds)),
        "tracker.csv": int(np.searchsorted(run.tracker.t, seconds)),
    }
    for name, count in rows.items():
        with (folder / name).open() as src, (head / name).open("w") as dst:
            dst.writelines(itertools.islice(src, count + 1))  # the header, then the rows
    return head, rows["tracker.csv"]
