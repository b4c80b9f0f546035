"""`keo bench`: hot path, end to end over real processes, capacity, accuracy, Rerun's cost.

Prints numbers, judges nothing: timing on shared machines is noisy, so ratios measured in one
run are what to compare. `--quick` (CI's smoke test) shortens every part.
"""

from __future__ import annotations

import dataclasses
import itertools
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import pinocchio as pin

from keo_service.bench.demo import loopback_config
from keo_service.bench.procs import process_group
from keo_service.core.errors import KeoError
from keo_service.core.estimator import Estimator
from keo_service.core.settings import EstimatorSettings
from keo_service.core.timing import DelayModel
from keo_service.fit.evaluate import estimate_error_rms, estimate_run
from keo_service.io.cell import cell_from_config, estimator_settings
from keo_service.io.config import Config, config_to_toml
from keo_service.live.bus import session_for_client
from keo_service.live.client import SyncClient
from keo_service.live.messages import EstimateMessage, decode, topic
from keo_service.sim.simulate import SimulatedRun, make_scenario, simulate, write_run

TICK = os.sysconf("SC_CLK_TCK")


def machine() -> dict[str, Any]:
    model = ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {
        "cpu": model or platform.processor(),
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "system": platform.platform(),
    }


# ---- 1. hot path -------------------------------------------------------------------------------


def _khz_run(config: Config, seconds: float) -> SimulatedRun:
    scen = make_scenario(
        "path",
        {
            "duration_s": repr(seconds),
            "tracker_rate_hz": "1000",
            "tracker_rate_std_hz": "50",
            "encoder_rate_hz": "250",
            "encoder_rate_std_hz": "10",
        },
    )
    return simulate(cell_from_config(config), scen, seed=1)


def _hot_path_pass(
    cell: Any, settings: EstimatorSettings, run: SimulatedRun, with_rerun: bool
) -> tuple[int, float]:
    """One pass over the run with a fresh estimator: (aligned samples, CPU seconds of this
    process). `with_rerun`: every estimate goes to a `RerunWorker` as in `keo run --rrd`
    (encoded and piped to a process of its own); its buffer holds the whole pass, so nothing
    is dropped (a drop costs less than a frame), and the Rerun process finishes its file after
    the pass."""
    est = Estimator(cell, settings)
    worker = None
    tmp = None
    if with_rerun:
        from keo_service.live.rerun_process import RerunWorker

        tmp = tempfile.TemporaryDirectory()
        worker = RerunWorker(cell, rrd=Path(tmp.name) / "bench.rrd", max_buffer=1 << 30)
        worker.start()
    # the samples as the service gets them from decoded messages: floats and lists of floats
    quat = run.tracker.quat
    assert quat is not None  # the benchmark scenario is a 6-DoF probe
    enc_t, enc_q = run.encoder.t.tolist(), run.encoder.q.tolist()
    trk_t, trk_p, trk_q = run.tracker.t.tolist(), run.tracker.p.tolist(), quat.tolist()
    n_enc = len(enc_t)
    cpu0 = time.process_time()
    n = 0
    i = 0
    for j, t in enumerate(trk_t):
        while i < n_enc and enc_t[i] <= t:
            est.on_encoder(enc_t[i], enc_q[i])
            i += 1
        for e in est.on_tracker(t, trk_p[j], trk_q[j]):
            n += 1
            if worker is not None:
                worker.submit(e)
    cpu = time.process_time() - cpu0
    if worker is not None:
        worker.close(timeout=120.0)  # the Rerun process finishes the recording
        if worker.failure is not None or worker.dropped:
            raise KeoError(
                f"the Rerun process did not log every estimate ({worker.dropped} dropped): "
                f"{worker.failure}"
            )
    if tmp is not None:
        tmp.cleanup()
    return n, cpu


def _rate_summary(rates: list[float], n: int) -> dict[str, float]:
    rate = float(np.median(rates))
    return {
        "samples": n,
        "repeats": len(rates),
        "samples_per_s": rate,
        "samples_per_s_best": max(rates),
        "samples_per_s_worst": min(rates),
        "us_per_sample": 1e6 / rate,
        "core_share_at_1kHz_pct": 100.0 * 1000.0 / rate,
    }


def hot_path(config: Config, seconds: float, with_rerun: bool, repeats: int = 5) -> dict[str, Any]:
    """Aligned samples per CPU second, `repeats` passes over the same run; the median is the
    figure (a shared machine's noise only ever slows a pass down), best and worst beside it.
    `with_rerun`: what `keo run --rrd` adds in the service's process (the Rerun process's own
    CPU is in the end-to-end `--rrd` run, where it works at the tracker's pace)."""
    run = _khz_run(config, seconds)
    cell = cell_from_config(config)
    settings = estimator_settings(config)
    rates = []
    n = 0
    for _ in range(repeats):
        n, cpu = _hot_path_pass(cell, settings, run, with_rerun)
        rates.append(n / cpu)
    summary: dict[str, Any] = _rate_summary(rates, n)
    if with_rerun:
        summary["rerun"] = "process"  # what the pass measured (earlier runs: "same thread")
    return summary


def _floor_pass(cell: Any, run: SimulatedRun) -> tuple[int, float]:
    """The per-sample floor of Python over Pinocchio: for each tracker sample only what the
    math needs (forward kinematics on preallocated data, the tool and sensor poses, the
    error transform and its log3), joints from the newest encoder sample, no validation, no
    interpolation, no observer: (samples, CPU seconds)."""
    model, data = cell.robot.model, cell.robot.create_data()
    flange, T_nt, T_bk = cell.robot.flange_frame_id, cell.T_nt, cell.T_bk
    quat = run.tracker.quat
    assert quat is not None
    xyzquat = np.hstack([run.tracker.p, quat[:, 1:], quat[:, :1]])  # pin's x y z qx qy qz qw
    enc_index = np.searchsorted(run.encoder.t, run.tracker.t, side="right") - 1
    cpu0 = time.process_time()
    n = 0
    for j in range(run.tracker.t.size):
        i = enc_index[j]
        if i < 0:
            continue
        pin.framesForwardKinematics(model, data, run.encoder.q[i])
        T_bt = data.oMf[flange] * T_nt
        T_bs = T_bk * pin.XYZQUATToSE3(xyzquat[j])
        err = T_bt.actInv(T_bs)
        pin.log3(err.rotation)
        n += 1
    return n, time.process_time() - cpu0


def hot_path_and_floor(
    config: Config, seconds: float, repeats: int = 7
) -> tuple[dict[str, float], dict[str, float]]:
    """keo's hot path and the naive floor in alternating passes over the same run, so that a
    noisy neighbour slows both alike; the ratio is the median of the per-pair ratios."""
    run = _khz_run(config, seconds)
    cell = cell_from_config(config)
    settings = estimator_settings(config)
    hot, floor, ratios = [], [], []
    n_hot = n_floor = 0
    for _ in range(repeats):
        n_floor, cpu_floor = _floor_pass(cell, run)
        n_hot, cpu_hot = _hot_path_pass(cell, settings, run, False)
        floor.append(n_floor / cpu_floor)
        hot.append(n_hot / cpu_hot)
        ratios.append(hot[-1] / floor[-1])
    hot_summary = _rate_summary(hot, n_hot)
    hot_summary["over_floor"] = float(np.median(ratios))
    hot_summary["over_floor_best"] = max(ratios)
    hot_summary["over_floor_worst"] = min(ratios)
    return hot_summary, _rate_summary(floor, n_floor)


# ---- recordings: keo estimate as a command ----------------------------------------------------


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
            memory = _proc_mem_kb(pid)
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
    effect fitted and judged: minutes, not seconds, so not over the whole recording)."""
    run = _khz_run(config, seconds)
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
        runs, floors = [], []
        for _ in range(repeats):
            floors.append(_floor_pass(cell, run)[1])
            runs.append(_timed_command(args, folder / "batch.log"))
        median = sorted(runs, key=lambda timing: timing["wall_s"])[len(runs) // 2]
        ratios = [r["wall_s"] / f for r, f in zip(runs, floors, strict=True)]
        out["floor_s"] = float(np.median(floors))
        out["floor_runs_s"] = floors
        out["over_floor"] = float(np.median(ratios))
        out["over_floor_best"] = min(ratios)
        out["over_floor_worst"] = max(ratios)
        out["over_floor_runs"] = ratios  # in the order they ran
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
    return out


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


# ---- 2./3. end to end --------------------------------------------------------------------------


def _stat_fields(pid: int | str) -> list[str]:
    """/proc/<pid>/stat after the command name (which may hold spaces): state, ppid, ..."""
    return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()


def machine_ticks() -> dict[str, int]:
    """The machine's CPU time so far by kind, all cores, in clock ticks (/proc/stat's first
    line: user nice system idle iowait irq softirq steal ...)."""
    with open("/proc/stat", encoding="ascii") as f:
        values = [int(v) for v in f.readline().split()[1:9]]
    return {"busy": sum(values[:3]) + sum(values[5:7]), "steal": values[7], "all": sum(values)}


def machine_share(before: dict[str, int], after: dict[str, int]) -> dict[str, float]:
    """Busy and stolen time between two `machine_ticks`, in % of all cores' time (stolen: the
    hypervisor ran something else while these cores had work)."""
    span = max(1, after["all"] - before["all"])
    return {
        "busy_pct": 100.0 * (after["busy"] - before["busy"]) / span,
        "steal_pct": 100.0 * (after["steal"] - before["steal"]) / span,
    }


def _proc_cpu_s(pid: int) -> float:
    fields = _stat_fields(pid)
    return (int(fields[11]) + int(fields[12])) / TICK


def _proc_mem_kb(pid: int) -> dict[str, int]:
    out = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(("VmRSS", "VmHWM")):
            key, value = line.split(":", 1)
            out[key] = int(value.split()[0])
    return out


class _Collector:
    """The subscriber at the end of the chain. It is the measuring instrument, so its callback
    keeps only an arrival time and the raw bytes (no object the garbage collector tracks: a
    growing list of decoded messages cost a 30 ms gen-2 pause mid-run) and decodes afterwards."""

    def __init__(self, config: Config) -> None:
        self.session = session_for_client(config, retry_for=30)
        self._arrived: list[float] = []
        self._payloads: list[bytes] = []
        self._lock = threading.Lock()
        self.sub = self.session.declare_subscriber(topic(config.cell, "estimate"), self._on)

    def _on(self, sample: Any) -> None:
        arrived = time.time()
        payload = sample.payload.to_bytes()
        with self._lock:
            self._arrived.append(arrived)
            self._payloads.append(payload)

    def close(self) -> list[tuple[float, EstimateMessage]]:
        self.sub.undeclare()
        self.session.close()
        with self._lock:
            pairs = list(zip(self._arrived, self._payloads, strict=True))
        out = []
        for arrived, payload in pairs:
            msg = decode(payload)
            if isinstance(msg, EstimateMessage):
                out.append((arrived, msg))
        return out


def _service_counters(config: Config) -> dict[str, int]:
    try:
        with SyncClient.from_config(config, connect_timeout_s=5.0) as keo:
            return dict(keo.status(timeout=3.0).counters)
    except KeoError:
        return {}


def _children(pid: int) -> list[int]:
    """The processes whose parent is `pid`."""
    out = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = _stat_fields(entry.name)
        except OSError:
            continue  # gone meanwhile
        if int(fields[1]) == pid:
            out.append(int(entry.name))
    return out


def _open_fds(pid: int) -> int:
    return len(os.listdir(f"/proc/{pid}/fd"))


def end_to_end(
    config: Config,
    seconds: float,
    tracker_hz: float = 1000.0,
    encoder_hz: float = 250.0,
    rrd: bool = False,
    sample_every: float | None = None,
    relay_only: bool = False,
) -> dict[str, Any]:
    """Each component its own process; latency from the tracker line leaving the mock to the
    estimate arriving at a subscriber, split at the service's publish stamp. `relay_only`: the
    transport floor, with a pass-through relay in the service's place.

    The processes' logs (and the recording) go to a fresh folder, removed after the run; kept,
    and named in the error, when the run fails."""
    work = Path(tempfile.mkdtemp(prefix="keo-bench-"))
    try:
        res = _end_to_end(
            work,
            config,
            seconds,
            tracker_hz=tracker_hz,
            encoder_hz=encoder_hz,
            rrd=rrd,
            sample_every=sample_every,
            relay_only=relay_only,
        )
    except BaseException as exc:
        exc.add_note(f"the processes' logs: {work}")
        raise
    shutil.rmtree(work, ignore_errors=True)
    return res


def _end_to_end(
    work: Path,
    config: Config,
    seconds: float,
    *,
    tracker_hz: float,
    encoder_hz: float,
    rrd: bool,
    sample_every: float | None,
    relay_only: bool,
) -> dict[str, Any]:
    cfg = work / "bench.toml"
    cfg.write_text(config_to_toml(config))
    sets = [
        f"tracker_rate_hz={tracker_hz}",
        "tracker_rate_std_hz=0",
        f"encoder_rate_hz={encoder_hz}",
        "encoder_rate_std_hz=0",
        "drop_probability=0",
        f"duration_s={seconds}",
    ]
    set_args = [a for s in sets for a in ("--set", s)]
    # the mocks simulate the whole scenario before they listen (about 2 % of its length at
    # 1 kHz): start the play late enough that no device data is skipped
    startup = 5.0 + 0.04 * seconds * tracker_hz / 1000.0
    t0 = time.time() + startup
    play = ["--scenario", "path", "--seed", "1", "--t0", repr(t0), *set_args]
    names = ["service", "mock-robot", "mock-tracker", "adapter-encoder", "adapter-tracker"]
    with process_group(work) as procs:
        recording = work / "bench.rrd"
        extra = ["--rrd", str(recording)] if rrd else []
        procs.start_cell(
            cfg, play, service=extra, tracker=["--wall-clock-device-time"], relay_only=relay_only
        )
        collector = _Collector(config)
        pids = {n: procs.procs[n].pid for n in names}
        time.sleep(max(0.0, t0 + 0.5 - time.time()))
        rerun_process = _children(pids["service"]) if rrd else []
        if rerun_process:  # the service's only child, started by then
            pids["rerun-process"] = rerun_process[0]
        warm_cpu = {n: _proc_cpu_s(p) for n, p in pids.items()}
        warm_machine = machine_ticks()
        time.sleep(max(0.0, seconds / 3))
        warm_mem = {n: _proc_mem_kb(p) for n, p in pids.items()}
        trace = []
        while sample_every is not None and time.time() + sample_every < t0 + seconds:
            time.sleep(sample_every)
            trace.append(
                {
                    "t_s": round(time.time() - t0, 1),
                    "rss_mb": {n: _proc_mem_kb(p).get("VmRSS", 0) / 1024 for n, p in pids.items()},
                    "open_fds": {n: _open_fds(p) for n, p in pids.items()},
                }
            )
        time.sleep(max(0.0, t0 + seconds - time.time()))
        end_cpu = {n: _proc_cpu_s(p) for n, p in pids.items()}
        end_machine = machine_ticks()
        end_mem = {n: _proc_mem_kb(p) for n, p in pids.items()}
        time.sleep(1.5)  # the last samples: encoder coverage, or the quiet-time flush
        items = collector.close()
        counters = {} if relay_only else _service_counters(config)
    run_s = seconds - 0.5
    played = simulate(
        cell_from_config(config), make_scenario("path", dict(s.split("=", 1) for s in sets)), seed=1
    )
    sent = int(played.tracker.t.size)
    # latency after a warm-up of 0.5 s (connections settle, the first samples wait for encoder
    # data that predates the subscription)
    # good estimates only: the held ones at the very end (tracker samples stamped after the
    # last encoder sample, answered by the quiet-time flush) say nothing about latency
    in_window = [
        (a, m)
        for a, m in items
        if m.tracker_device_t is not None and m.tracker_device_t > t0 + 0.5 and not m.flags
    ]
    device_t = np.array([m.tracker_device_t for _a, m in in_window], dtype=float)
    lat = (np.array([a for a, _m in in_window]) - device_t) * 1e3
    to_publish = (np.array([m.host_ns * 1e-9 for _a, m in in_window]) - device_t) * 1e3
    to_subscriber = np.array([a - m.host_ns * 1e-9 for a, m in in_window]) * 1e3
    held = sum(1 for _a, m in items if m.measured is None)
    procs_out = {
        n: {
            "cpu_pct": 100.0 * (end_cpu[n] - warm_cpu[n]) / run_s,
            "peak_rss_mb": end_mem[n].get("VmHWM", 0) / 1024,
            "rss_growth_mb": (end_mem[n].get("VmRSS", 0) - warm_mem[n].get("VmRSS", 0)) / 1024,
        }
        for n in pids
    }
    out: dict[str, Any] = {
        "tracker_hz": tracker_hz,
        "encoder_hz": encoder_hz,
        "seconds": seconds,
        "tracker_samples_sent": sent,
        "estimates_received": len(items),
        "held": held,
        "lost": max(0, sent - len(items)),
        "latency_ms": _percentiles(lat),
        "latency_to_service_publish_ms": _percentiles(to_publish),
        "latency_publish_to_subscriber_ms": _percentiles(to_subscriber),
        "processes": procs_out,
        "machine": machine_share(warm_machine, end_machine),
        "trace": trace,
        "rerun_dropped": counters.get("rerun_dropped", 0),
        "service_counters": counters,
    }
    if rrd:  # the recording rolls every 10 minutes: its files in the sink's own order
        from keo_service.live.rerun_sink import rolled_path  # imports Rerun: only here

        files = list(
            itertools.takewhile(Path.exists, (rolled_path(recording, i) for i in itertools.count()))
        )
        out["recording"] = {
            "files": len(files),
            "mb": [round(f.stat().st_size / 2**20, 1) for f in files],
        }
    return out


def _percentiles(ms: np.ndarray) -> dict[str, float | None]:
    if not ms.size:
        return {"p50": None, "p99": None, "max": None}
    return {
        "p50": float(np.percentile(ms, 50)),
        "p99": float(np.percentile(ms, 99)),
        "max": float(ms.max()),
    }


# the end-to-end kinds a round runs, and how `end_to_end` runs each
E2E_KINDS: dict[str, dict[str, bool]] = {
    "end_to_end": {},
    "transport_floor": {"relay_only": True},
    "end_to_end_rerun": {"rrd": True},
}


def end_to_end_rounds(
    config: Config, seconds: float, rounds: int, with_rerun: bool
) -> list[dict[str, Any]]:
    """`rounds` runs of each end-to-end kind, the order rotated every round so that no kind
    always runs first (a machine's load drifts over minutes; one run's p99 moves 1-5 ms)."""
    kinds = [k for k in E2E_KINDS if with_rerun or k != "end_to_end_rerun"]
    out = []
    for i in range(rounds):
        order = kinds[i % len(kinds) :] + kinds[: i % len(kinds)]
        done: dict[str, Any] = {"order": order}
        for kind in order:
            done[kind] = end_to_end(loopback_config(config), seconds, **E2E_KINDS[kind])
        out.append(done)
    return out


def _spread_of(values: list[float]) -> dict[str, Any]:
    return {
        "median": float(np.median(values)),
        "min": min(values),
        "max": max(values),
        "each": values,
    }


def _at(run: dict[str, Any], path: tuple[str, ...]) -> Any:
    for key in path:
        run = run[key]
    return run


def round_ratios(rounds: list[dict[str, Any]]) -> dict[str, Any]:
    """The service against its references, each ratio within one round (runs minutes apart,
    not a median run against another run's median)."""

    def ratio(over: str, under: str, *path: str) -> dict[str, Any] | None:
        pairs = [
            (_at(r[over], path), _at(r[under], path)) for r in rounds if over in r and under in r
        ]
        values = [a / b for a, b in pairs if a is not None and b]
        return _spread_of(values) if values else None

    cpu = ("processes", "service", "cpu_pct")
    found = {
        "service_cpu_over_relay": ratio("end_to_end", "transport_floor", *cpu),
        "p50_over_relay": ratio("end_to_end", "transport_floor", "latency_ms", "p50"),
        "p99_over_relay": ratio("end_to_end", "transport_floor", "latency_ms", "p99"),
        "rrd_p50_over_plain": ratio("end_to_end_rerun", "end_to_end", "latency_ms", "p50"),
        "rrd_p99_over_plain": ratio("end_to_end_rerun", "end_to_end", "latency_ms", "p99"),
    }
    return {name: spread for name, spread in found.items() if spread is not None}


def capacity(config: Config, rates: list[float], seconds: float) -> dict[str, Any]:
    steps = []
    best = 0.0
    for rate in rates:
        res = end_to_end(config, seconds, tracker_hz=rate, encoder_hz=250.0)
        ok = res["lost"] == 0
        steps.append(
            {
                "tracker_hz": rate,
                "sent": res["tracker_samples_sent"],
                "received": res["estimates_received"],
                "lost": res["lost"],
                "p99_ms": res["latency_ms"]["p99"],
            }
        )
        if not ok:
            break
        best = rate
    return {"highest_rate_without_drops_hz": best, "steps": steps}


# ---- 4. accuracy -------------------------------------------------------------------------------


def accuracy(config: Config, seed: int = 1) -> dict[str, Any]:
    cell = cell_from_config(config)
    run = simulate(
        cell, make_scenario("paper-vertical", {"error_drift_m_per_s": "2e-5"}), seed=seed
    )
    base = dataclasses.replace(estimator_settings(config), delay=DelayModel(run.scenario.delay_s))

    def rms_for(**changes: Any) -> tuple[float, float]:
        settings = dataclasses.replace(base, **changes)
        series = estimate_run(cell, settings, run)
        mask = series.t > series.t[0] + 5.0
        return estimate_error_rms(series, run.truth_t, run.truth, mask)

    configured = base.gains[0]
    gains = [0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0]
    sweep = {g: rms_for(gains=(g,) * 6)[0] for g in gains}
    best = min(sweep, key=lambda g: sweep[g])
    interp = rms_for()
    latest = rms_for(alignment="latest")
    ref_best = rms_for(alignment="latest", gains=(best,) * 6)
    return {
        "scenario": "paper-vertical with 20 um/s drift of the true error",
        "configured_gain": configured,
        "best_gain": best,
        "interpolate_pos_mm": interp[0] * 1e3,
        "interpolate_rot_mrad": interp[1] * 1e3,
        "latest_pos_mm": latest[0] * 1e3,
        "latest_rot_mrad": latest[1] * 1e3,
        "best_gain_interpolate_pos_mm": sweep[best] * 1e3,
        "best_gain_latest_pos_mm": ref_best[0] * 1e3,
        "reference_over_keo": latest[0] / sweep[best],
        "gain_sweep_pos_mm": {str(g): v * 1e3 for g, v in sweep.items()},
    }


# ---- all ---------------------------------------------------------------------------------------


def soak(
    config: Config, seconds: float, rrd: bool = False, sample_every: float = 10.0
) -> dict[str, Any]:
    """A long run at 1 kHz: RSS and open files sampled every `sample_every` seconds, per
    process. `rrd`: the service records to Rerun as `keo run --rrd` does (its Rerun process
    listed apart; over 10 minutes the recording rolls to a new file)."""
    res = end_to_end(loopback_config(config), seconds, rrd=rrd, sample_every=sample_every)
    res["rrd"] = rrd
    summary = {}
    for name in res["processes"]:
        rss = [s["rss_mb"][name] for s in res["trace"]]
        fds = [s["open_fds"][name] for s in res["trace"]]
        if rss:
            summary[name] = {
                "rss_first_mb": rss[0],
                "rss_last_mb": rss[-1],
                "rss_max_mb": max(rss),
                "fds_first": fds[0],
                "fds_last": fds[-1],
            }
    res["summary"] = summary
    return res


def run_bench(config: Config, quick: bool, rounds: int | None = None) -> dict[str, Any]:
    """Everything once, the end-to-end runs `rounds` times (default: 1 quick, else 3)."""
    config = loopback_config(config)
    hp_seconds = 5.0 if quick else 30.0
    e2e_seconds = 5.0 if quick else 30.0
    rounds = rounds if rounds is not None else (1 if quick else 3)
    out: dict[str, Any] = {"machine": machine(), "quick": quick}
    out["hot_path"], out["naive_floor"] = hot_path_and_floor(config, hp_seconds)
    out["hot_path_rerun"] = hot_path(config, hp_seconds, with_rerun=True)
    out["recording"] = recording(
        config,
        60.0 if quick else 600.0,
        # five pairs in a full run: one busy minute on the VM then moves the median less
        repeats=3 if quick else 5,
        analyze_seconds=None if quick else 10.0,
    )
    done = end_to_end_rounds(config, e2e_seconds, rounds, with_rerun=not quick)
    for kind in E2E_KINDS:  # the first round's runs in full, as before rounds
        if kind in done[0]:
            out[kind] = done[0][kind]
    out["end_to_end_rounds"] = done
    out["round_ratios"] = round_ratios(done)
    rates = [1000.0, 2000.0] if quick else [1000.0, 2000.0, 4000.0, 8000.0]
    out["capacity"] = capacity(loopback_config(config), rates, 3.0 if quick else 8.0)
    out["accuracy"] = accuracy(config)
    return out


def _spread(hp: dict[str, Any]) -> str:
    if "repeats" not in hp:
        return ""
    return (
        f" (median of {hp['repeats']} passes; best {hp['samples_per_s_best']:,.0f}, "
        f"worst {hp['samples_per_s_worst']:,.0f})"
    )


def _over_floor(hp: dict[str, Any], floor: dict[str, Any]) -> str:
    if "over_floor" not in hp:  # runs before the passes alternated
        return f"{hp['samples_per_s'] / floor['samples_per_s']:.2f}"
    return (
        f"{hp['over_floor']:.2f} (median of {hp['repeats']} alternating pairs; "
        f"{hp['over_floor_worst']:.2f} to {hp['over_floor_best']:.2f})"
    )


def _rerun_row(hp: dict[str, Any], hpr: dict[str, Any]) -> str:
    cost = (
        f"{hpr['samples_per_s']:,.0f} (x{hp['samples_per_s'] / hpr['samples_per_s']:.2f} the cost)"
    )
    if hpr.get("rerun") != "process":  # runs from before: the sink in the same thread
        return f"| hot path with the Rerun sink in the same thread | {cost} |"
    return (
        "| hot path with `--rrd`'s Rerun worker (each estimate encoded and piped to the Rerun "
        f"process; that process's own CPU: the end-to-end `--rrd` run below) | {cost} |"
    )


def _runs(command: dict[str, Any]) -> str:
    walls = command.get("runs_wall_s", [])
    if len(walls) < 2:
        return ""
    warmup = command.get("warmup_wall_s")
    after = "" if warmup is None else f" after a warm-up run of {warmup:.2f} s"
    return f" (median of {len(walls)} runs{after}, {min(walls):.2f} to {max(walls):.2f} s wall)"


def _command_over_floor(rec: dict[str, Any]) -> str:
    b = rec["batch"]
    if "over_floor" not in rec:  # runs before the floor passes alternated with the command
        return f"{b['wall_s'] / rec['floor_s']:.2f}"
    return (
        f"{rec['over_floor']:.2f} (median of {len(b['runs_wall_s'])} pairs of a floor pass "
        f"and a command run; {rec['over_floor_best']:.2f} to {rec['over_floor_worst']:.2f})"
    )


def _ratio(spread: dict[str, Any] | None) -> str:
    if spread is None:
        return "not measured"
    each = ", ".join(f"{v:.2f}" for v in spread["each"])
    if len(spread["each"]) == 1:
        return f"x{each}"
    return f"x{spread['median']:.2f} (median; each round: {each})"


def _round_rows(r: dict[str, Any]) -> list[str]:
    rounds, ratios = r["end_to_end_rounds"], r["round_ratios"]
    n = len(rounds)
    label = (
        "same run"
        if n == 1
        else f"{n} rounds of the runs above, each ratio within its round, the order rotated"
    )
    lines = [
        f"| keo over the transport floor, {label} | "
        f"CPU {_ratio(ratios.get('service_cpu_over_relay'))}; "
        f"p50 {_ratio(ratios.get('p50_over_relay'))}; p99 {_ratio(ratios.get('p99_over_relay'))} |"
    ]
    if n > 1:
        names = {"end_to_end": "service", "transport_floor": "relay", "end_to_end_rerun": "--rrd"}

        def each_run(path: tuple[str, ...], digits: int) -> str:
            """A value of every run, kind by kind (a p99 of no samples is None: nan)."""
            values = {k: [_at(x[k], path) for x in rounds] for k in names if k in rounds[0]}
            return "; ".join(
                f"{names[k]} "
                + ", ".join(f"{float('nan') if v is None else v:.{digits}f}" for v in vs)
                for k, vs in values.items()
            )

        lines.append(f"| p99 in each round (ms) | {each_run(('latency_ms', 'p99'), 2)} |")
        if all("machine" in x[kind] for x in rounds for kind in names if kind in x):
            lines.append(
                "| CPU time the hypervisor took in each run (% of all cores) | "
                f"{each_run(('machine', 'steal_pct'), 1)} |"
            )
    if "rrd_p99_over_plain" in ratios:
        drops = [x["end_to_end_rerun"].get("rerun_dropped", 0) for x in rounds]
        lines.append(
            f"| --rrd over the plain run, {'same bench' if n == 1 else f'{n} rounds'} | "
            f"p50 {_ratio(ratios.get('rrd_p50_over_plain'))}; "
            f"p99 {_ratio(ratios['rrd_p99_over_plain'])}; Rerun queue drops "
            f"{sum(drops)} |"
        )
    return lines


def bench_table(r: dict[str, Any]) -> str:
    m = r["machine"]
    lines = [
        f"machine: {m['cpu']}, {m['cores']} cores, Python {m['python']}"
        + (" (quick run)" if r["quick"] else ""),
        "",
    ]
    hp, hpr = r["hot_path"], r["hot_path_rerun"]
    lines += [
        "| measure | value |",
        "|---|---|",
        f"| hot path: aligned samples/s, one core{_spread(hp)} | {hp['samples_per_s']:,.0f} "
        f"({hp['us_per_sample']:.1f} us each; a 1 kHz tracker costs "
        f"{hp['core_share_at_1kHz_pct']:.1f} % of a core) |",
        f"| naive per-sample floor (FK, two SE3 products, log3; same run) | "
        f"{r['naive_floor']['samples_per_s']:,.0f} ({r['naive_floor']['us_per_sample']:.1f} us "
        f"each); hot path / floor = {_over_floor(hp, r['naive_floor'])} |"
        if "naive_floor" in r
        else "| naive per-sample floor | not measured in this run |",
        _rerun_row(hp, hpr),
    ]

    if "recording" in r:
        rec = r["recording"]
        b = rec["batch"]
        lines.append(
            f"| keo estimate, {rec['seconds']:.0f} s at 1 kHz ({rec['tracker_samples']:,} tracker, "
            f"{rec['encoder_samples']:,} encoder rows; CSV in and out, process start included) | "
            f"{b['wall_s']:.2f} s wall, {b['cpu_s']:.2f} s CPU, "
            f"peak RSS {b['peak_rss_mb']:.0f} MB{_runs(b)}; "
            f"naive floor over the same samples {rec['floor_s']:.2f} s CPU; command / floor = "
            f"{_command_over_floor(rec)} (wall), {b['cpu_s'] / rec['floor_s']:.2f} (CPU) |"
        )
        if "streaming" in rec:
            st = rec["streaming"]
            lines.append(
                f"| keo estimate --streaming (per-sample path), same files | {st['wall_s']:.2f} s "
                f"wall, {st['cpu_s']:.2f} s CPU, peak RSS {st['peak_rss_mb']:.0f} MB; batch is "
                f"x{st['wall_s'] / b['wall_s']:.1f} faster |"
            )
        if "calibrate_delay" in rec:
            cd = rec["calibrate_delay"]
            lines.append(
                f"| keo calibrate-delay, same files (delay and drift, Gauss-Newton to 0.1 us) | "
                f"{cd['wall_s']:.2f} s wall, {cd['cpu_s']:.2f} s CPU, "
                f"peak RSS {cd['peak_rss_mb']:.0f} MB |"
            )
        if "analyze" in rec:
            an = rec["analyze"]
            lines.append(
                f"| keo analyze, the first {an['seconds']:.0f} s of the same files "
                f"({an['poses']:,} poses; registration, then every candidate effect fitted and "
                f"judged on held-out poses) | {an['wall_s']:.1f} s wall, {an['cpu_s']:.1f} s CPU, "
                f"peak RSS {an['peak_rss_mb']:.0f} MB |"
            )

    def ms(d: dict[str, float | None]) -> str:
        return ", ".join(f"{k} {v:.2f} ms" for k, v in d.items() if v is not None)

    rows = (
        ("end_to_end", "end to end"),
        ("transport_floor", "transport floor (pass-through relay in the service's place)"),
        ("end_to_end_rerun", "end to end, --rrd"),
    )
    first_of = len(r.get("end_to_end_rounds", []))
    for key, kind in rows:
        if key not in r:
            continue
        e = r[key]
        label = kind + (f" (round 1 of {first_of})" if first_of > 1 else "")
        lines.append(
            f"| {label}: tracker {e['tracker_hz']:.0f} Hz, robot {e['encoder_hz']:.0f} Hz, "
            f"{e['seconds']:.0f} s | latency {ms(e['latency_ms'])}; "
            f"{e['estimates_received']} estimates for {e['tracker_samples_sent']} samples"
            + (
                f"; the machine {e['machine']['busy_pct']:.0f} % busy, "
                f"{e['machine']['steal_pct']:.1f} % stolen |"
                if "machine" in e
                else " |"
            )
        )
        if "latency_to_service_publish_ms" in e:
            lines.append(
                f"| {label}: tracker line -> service publish / publish -> subscriber | "
                f"{ms(e['latency_to_service_publish_ms'])} / "
                f"{ms(e['latency_publish_to_subscriber_ms'])} |"
            )
        for name, p in e["processes"].items():
            lines.append(
                f"| {label}: {name} | CPU {p['cpu_pct']:.1f} %, peak RSS "
                f"{p['peak_rss_mb']:.0f} MB, RSS growth after warm-up "
                f"{p['rss_growth_mb']:+.1f} MB |"
            )
    if "round_ratios" in r:
        lines += _round_rows(r)
    elif "transport_floor" in r:  # runs before rounds: the one pair
        keo, floor = r["end_to_end"]["latency_ms"], r["transport_floor"]["latency_ms"]
        if keo["p99"] and floor["p99"]:
            lines.append(
                f"| keo over the transport floor, same run | p50 x{keo['p50'] / floor['p50']:.2f}, "
                f"p99 x{keo['p99'] / floor['p99']:.2f} |"
            )
    if "end_to_end_rerun" in r and "round_ratios" not in r:
        plain, rrd = r["end_to_end"]["latency_ms"], r["end_to_end_rerun"]["latency_ms"]
        if plain["p99"] and rrd["p99"]:
            lines.append(
                f"| --rrd over the plain run, same bench | p50 x{rrd['p50'] / plain['p50']:.2f}, "
                f"p99 x{rrd['p99'] / plain['p99']:.2f}; Rerun queue drops "
                f"{r['end_to_end_rerun'].get('rerun_dropped', 0)} |"
            )
    c = r["capacity"]
    steps = ", ".join(f"{s['tracker_hz']:.0f} Hz: {s['received']}/{s['sent']}" for s in c["steps"])
    lines.append(
        f"| capacity: highest tracker rate with no drops | "
        f"{c['highest_rate_without_drops_hz']:.0f} Hz ({steps}) |"
    )
    a = r["accuracy"]
    lines.append(
        f"| accuracy ({a['scenario']}), RMS position error after 5 s | keo interpolate "
        f"L={a['configured_gain']:g}: {a['interpolate_pos_mm']:.4f} mm; reference latest: "
        f"{a['latest_pos_mm']:.4f} mm; keo at best gain L={a['best_gain']:g}: "
        f"{a['best_gain_interpolate_pos_mm']:.4f} mm; reference / keo-best = "
        f"{a['reference_over_keo']:.1f} |"
    )
    return "\n".join(lines) + "\n"


def dumps(r: dict[str, Any]) -> str:
    return msgspec.json.encode(r).decode()
