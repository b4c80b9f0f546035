"""End to end over real processes: mock devices, adapters, the service and a subscriber on
one machine; latency percentiles, each process's CPU and memory, the machine's share; the
rounds that rotate the kinds of run, and capacity at rising rates."""

from __future__ import annotations

import functools
import itertools
import os
import shutil
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from keo_service.bench.demo import loopback_config
from keo_service.bench.machine import (
    children,
    cmdline,
    machine_share,
    machine_ticks,
    open_fds,
    proc_cpu_s,
    proc_mem_kb,
    stat_fields,
    thread_cpu_s,
)
from keo_service.bench.procs import process_group
from keo_service.core.errors import KeoError
from keo_service.io.cell import cell_from_config
from keo_service.io.config import Config, config_to_toml
from keo_service.live.bus import session_for_client
from keo_service.live.client import SyncClient
from keo_service.live.messages import CorrectionMessage, EstimateMessage, decode, topic
from keo_service.sim.simulate import make_scenario, simulate

# the bench's correction output: the service publishes the corrections an RTDE adapter would
# write to the controller's registers (the mock controller here speaks MotoROS: nothing reads
# them but the bench's subscriber)
CORRECTION_OUTPUT = "rtde_registers"


class _Collector:
    """The subscriber at the end of the chain. It is the measuring instrument, so its callback
    keeps only an arrival time and the raw bytes (no object the garbage collector tracks: a
    growing list of decoded messages cost a long gen-2 pause mid-run, docs/performance.md)
    and decodes afterwards.
    It takes the estimates and, from a service with a correction output, the corrections."""

    def __init__(self, config: Config) -> None:
        self.session = session_for_client(config, retry_for=30)
        self._arrived: dict[str, list[float]] = {"estimate": [], "correction": []}
        self._payloads: dict[str, list[bytes]] = {"estimate": [], "correction": []}
        self._lock = threading.Lock()
        self.subs = [
            self.session.declare_subscriber(
                topic(config.cell, name), functools.partial(self._on, name)
            )
            for name in self._arrived
        ]

    def _on(self, name: str, sample: Any) -> None:
        arrived = time.time()
        payload = sample.payload.to_bytes()
        with self._lock:
            self._arrived[name].append(arrived)
            self._payloads[name].append(payload)

    def close(self) -> tuple[list[tuple[float, EstimateMessage]], list[tuple[float, Any]]]:
        """(arrival, estimate) and (arrival, correction) pairs, in arrival order."""
        for sub in self.subs:
            sub.undeclare()
        self.session.close()
        out: dict[str, list[tuple[float, Any]]] = {}
        for name, kind in (("estimate", EstimateMessage), ("correction", CorrectionMessage)):
            with self._lock:
                pairs = list(zip(self._arrived[name], self._payloads[name], strict=True))
            out[name] = []
            for arrived, payload in pairs:
                msg = decode(payload)
                if isinstance(msg, kind):
                    out[name].append((arrived, msg))
        return out["estimate"], out["correction"]


def correction_latency(
    estimates: list[tuple[float, EstimateMessage]], corrections: list[tuple[float, Any]]
) -> tuple[np.ndarray, np.ndarray]:
    """The correction path's latency (ms), from the tracker line leaving the mock to the
    correction arriving at a subscriber, and to the service's publish stamp: each estimate's
    first correction (lowest `seq` of its stream time; later ones are the cycle's renewals)
    joined to the estimate by stream time, which carries the tracker's device stamp."""
    device = {m.stamp: m.device_stamp for _a, m in estimates if m.device_stamp is not None}
    first: dict[float, tuple[int, float, int]] = {}
    for at, c in corrections:
        if c.stamp in device and c.valid and (c.stamp not in first or c.seq < first[c.stamp][0]):
            first[c.stamp] = (c.seq, at, c.host_ns)
    stamps = list(first)
    sent = np.array([device[s] for s in stamps], dtype=float)
    arrived = np.array([first[s][1] for s in stamps], dtype=float)
    published = np.array([first[s][2] * 1e-9 for s in stamps], dtype=float)
    return (arrived - sent) * 1e3, (published - sent) * 1e3


def _service_counters(config: Config) -> dict[str, int]:
    try:
        with SyncClient.from_config(config, connect_timeout_s=5.0) as keo:
            return dict(keo.status(timeout=3.0).counters)
    except KeoError:
        return {}


def end_to_end(
    config: Config,
    seconds: float,
    tracker_hz: float = 1000.0,
    encoder_hz: float = 250.0,
    rrd: bool = False,
    sample_every: float | None = None,
    relay_only: bool = False,
    correction: bool = False,
    service_python: Sequence[str] = (),
    relay_math: bool = False,
) -> dict[str, Any]:
    """Each component its own process; latency from the tracker line leaving the mock to the
    estimate arriving at a subscriber, split at the service's publish stamp. `relay_only`: the
    transport floor, with a pass-through relay in the service's place; `relay_math`: that
    relay doing the naive floor's math per tracker pose too (what any estimator in this
    stack must do per sample: a bound from below for the service). `correction`: the
    service with a correction output configured (`robot.correction`, no controller reading
    it), and the correction path's latency measured. `service_python`: interpreter arguments
    for the service (a profiler).

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
            relay_only=relay_only or relay_math,
            correction=correction,
            service_python=service_python,
            relay_math=relay_math,
        )
    except BaseException as exc:
        exc.add_note(f"the processes' logs: {work}")
        raise
    shutil.rmtree(work, ignore_errors=True)
    return res


# the processes of the chain whose CPU and memory every run reports
CHAIN = ("service", "mock-robot", "mock-tracker", "adapter-encoder", "adapter-tracker")


def _chain_settings(tracker_hz: float, encoder_hz: float, seconds: float) -> list[str]:
    """The mocks' scenario settings: steady rates, no drops, `seconds` long."""
    return [
        f"tracker_rate_hz={tracker_hz}",
        "tracker_rate_std_hz=0",
        f"encoder_rate_hz={encoder_hz}",
        "encoder_rate_std_hz=0",
        "drop_probability=0",
        f"duration_s={seconds}",
    ]


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
    correction: bool = False,
    service_python: Sequence[str] = (),
    relay_math: bool = False,
) -> dict[str, Any]:
    if correction:  # the correction path runs only with an output configured
        robot = msgspec.structs.replace(config.robot, correction=CORRECTION_OUTPUT)
        config = msgspec.structs.replace(config, robot=robot)
    cfg = work / "bench.toml"
    cfg.write_text(config_to_toml(config))
    sets = _chain_settings(tracker_hz, encoder_hz, seconds)
    # the mocks simulate the whole scenario before they listen (a few % of its length at
    # 1 kHz) after their imports, which take many times as long on a loaded machine (a fixed
    # lead lost most of each run's samples there, docs/performance.md): start the play late
    # enough that no device data is skipped
    startup = startup_s() + 0.04 * seconds * tracker_hz / 1000.0
    t0 = time.time() + startup
    play = ["--scenario", "path", "--seed", "1", "--t0", repr(t0)]
    play += [a for s in sets for a in ("--set", s)]
    recording = work / "bench.rrd"
    with process_group(work) as procs:
        procs.start_cell(
            cfg,
            play,
            service=["--rrd", str(recording)] if rrd else [],
            tracker=["--wall-clock-device-time"],
            relay_only=relay_only,
            service_python=service_python,
            relay_math=relay_math,
        )
        collector = _Collector(config)
        pids = {n: procs.procs[n].pid for n in CHAIN}
        time.sleep(max(0.0, t0 + 0.5 - time.time()))
        pids.update(_service_children(pids["service"]))
        measured = _fold_service_workers(_measure_run(pids, t0, seconds, sample_every))
        time.sleep(1.5)  # the last samples: encoder coverage, or the quiet-time flush
        items, corrections = collector.close()
        counters = {} if relay_only else _service_counters(config)
    played = simulate(
        cell_from_config(config), make_scenario("path", dict(s.split("=", 1) for s in sets)), seed=1
    )
    out: dict[str, Any] = {
        "tracker_hz": tracker_hz,
        "encoder_hz": encoder_hz,
        "seconds": seconds,
        **_results(items, corrections, int(played.tracker.t.size), t0, measured),
        "rerun_dropped": counters.get("rerun_dropped", 0),
        "service_counters": counters,
    }
    if correction:
        out["correction"] = config.robot.correction
        out.update(_correction_results(items, corrections, t0))
    if rrd:  # the recording rolls every 10 minutes: its files in the sink's own order
        out["recording"] = _recording_files(recording)
    return out


# the service's child processes whose CPU is the service's own work: its delay fits' worker
# and the standard library's helper for that worker (the Rerun process is listed apart)
SERVICE_WORKERS = {
    "service-fit-worker": "multiprocessing.spawn",
    "service-mp-helper": "multiprocessing.resource_tracker",
}


def _service_children(service: int) -> dict[str, int]:
    """The service's child processes by name (started by then: at the service's start, or,
    for the Rerun process, when it is asked for)."""
    found = {}
    for pid in children(service):
        line = cmdline(pid)
        if "keo_service.live.rerun_process" in line:
            found["rerun-process"] = pid
            continue
        for name, marker in SERVICE_WORKERS.items():
            if marker in line and name not in found:
                found[name] = pid
    return found


def _fold_service_workers(measured: dict[str, Any]) -> dict[str, Any]:
    """The service's CPU with its workers' in it (`cpu_pct`; its own process alone in
    `own_cpu_pct`): the fits are the service's work wherever they run. The workers stay
    listed with their own figures."""
    procs = measured["processes"]
    workers = [p["cpu_pct"] for n, p in procs.items() if n.split("#")[0] in SERVICE_WORKERS]
    if workers:  # the relay has none
        service = procs["service"]
        service["own_cpu_pct"] = service["cpu_pct"]
        service["cpu_pct"] += sum(workers)
    return measured


def _measure_run(
    pids: dict[str, int], t0: float, seconds: float, sample_every: float | None
) -> dict[str, Any]:
    """While the play runs (from 0.5 s in, its warm-up, to its end): each process's CPU time
    and memory at both ends and a third of the way, the machine's ticks, and every
    `sample_every` s (a soak) each process's RSS and open files.

    A process may end during the run: the service's fit worker is replaced when a busy machine
    starves it (`live.fit_worker`). The one that ended keeps the CPU time last read (a lower
    bound) and is listed in `ended`; a worker the service started meanwhile is counted from
    its start, under its kind's name with "#2" (and so on) after it."""
    warm_cpu = {n: _or(proc_cpu_s, p, 0.0) for n, p in pids.items()}
    warm_threads = thread_cpu_s(pids["service"])
    warm_machine = machine_ticks()
    time.sleep(max(0.0, seconds / 3))
    warm_mem = {n: _or(proc_mem_kb, p, {}) for n, p in pids.items()}
    mid_cpu = {n: _or(proc_cpu_s, p, warm_cpu[n]) for n, p in pids.items()}
    trace = []
    while sample_every is not None and time.time() + sample_every < t0 + seconds:
        time.sleep(sample_every)
        trace.append(
            {
                "t_s": round(time.time() - t0, 1),
                "rss_mb": {n: proc_mem_kb(p).get("VmRSS", 0) / 1024 for n, p in pids.items()},
                "open_fds": {n: open_fds(p) for n, p in pids.items()},
            }
        )
    time.sleep(max(0.0, t0 + seconds - time.time()))
    pids = {**pids, **_new_workers(pids)}
    warm_cpu = {n: warm_cpu.get(n, 0.0) for n in pids}  # a new worker: from its start
    end_cpu = {n: _or(proc_cpu_s, p, mid_cpu.get(n, 0.0)) for n, p in pids.items()}
    end_threads = thread_cpu_s(pids["service"])
    end_machine = machine_ticks()
    end_mem = {n: _or(proc_mem_kb, p, warm_mem.get(n, {})) for n, p in pids.items()}
    # gone, or a zombie its parent has not reaped yet (state Z; X: being removed)
    ended = sorted(n for n, p in pids.items() if _or(stat_fields, p, ["X"])[0] in "ZX")
    warm_mem = {n: warm_mem.get(n, end_mem[n]) for n in pids}
    run_s = seconds - 0.5
    procs_out: dict[str, dict[str, Any]] = {
        n: {
            "cpu_pct": 100.0 * (end_cpu[n] - warm_cpu[n]) / run_s,
            "peak_rss_mb": end_mem[n].get("VmHWM", 0) / 1024,
            "rss_growth_mb": (end_mem[n].get("VmRSS", 0) - warm_mem[n].get("VmRSS", 0)) / 1024,
        }
        for n in pids
    }
    procs_out["service"]["threads_cpu_pct"] = {
        kind: 100.0 * (end_threads[kind] - warm_threads[kind]) / run_s for kind in end_threads
    }
    return {
        "processes": procs_out,
        "machine": machine_share(warm_machine, end_machine),
        "trace": trace,
        "ended": ended,
    }


def _or(read: Callable[[int], Any], pid: int, last: Any) -> Any:
    """`read(pid)`, or `last` once the process has ended."""
    try:
        return read(pid)
    except (OSError, IndexError, ValueError):
        return last


def _new_workers(pids: dict[str, int]) -> dict[str, int]:
    """The service's workers started since `pids` was taken (a fit worker replaced), named
    after their kind with "#2", "#3", ... (none for the relay)."""
    known = set(pids.values())
    found: dict[str, int] = {}
    for pid in _or(children, pids["service"], []):
        if pid in known:
            continue
        line = _or(cmdline, pid, "")
        for kind, marker in SERVICE_WORKERS.items():
            if marker in line:
                n = 2
                while f"{kind}#{n}" in pids or f"{kind}#{n}" in found:
                    n += 1
                found[f"{kind}#{n}"] = pid
                break
    return found


def _results(
    items: list[tuple[float, EstimateMessage]],
    corrections: list[tuple[float, Any]],
    sent: int,
    t0: float,
    measured: dict[str, Any],
) -> dict[str, Any]:
    """What arrived against what was sent, the latencies, the processes and the machine."""
    _in_window, latencies = _latencies(items, t0)
    return {
        "tracker_samples_sent": sent,
        "estimates_received": len(items),
        "held": sum(1 for _a, m in items if m.measured is None),
        "lost": max(0, sent - len(items)),
        **latencies,
        "corrections_received": len(corrections),
        "processes": measured["processes"],
        "machine": measured["machine"],
        "trace": measured["trace"],
        "ended_during_run": measured["ended"],
    }


def _correction_results(
    items: list[tuple[float, EstimateMessage]], corrections: list[tuple[float, Any]], t0: float
) -> dict[str, Any]:
    """The correction path's latency: to the subscriber, and to the service's publish."""
    in_window, _latencies_ms = _latencies(items, t0)
    corr_lat, corr_pub = correction_latency(in_window, corrections)
    return {
        "correction_latency_ms": _percentiles(corr_lat),
        "correction_to_service_publish_ms": _percentiles(corr_pub),
    }


def _recording_files(recording: Path) -> dict[str, Any]:
    """The `--rrd` run's recording: how many files (it rolls every 10 minutes), their MB."""
    from keo_service.live.rerun_logger import rolled_path  # imports Rerun: only here

    files = list(
        itertools.takewhile(Path.exists, (rolled_path(recording, i) for i in itertools.count()))
    )
    return {"files": len(files), "mb": [round(f.stat().st_size / 2**20, 1) for f in files]}


def startup_s() -> float:
    """Seconds to give the chain's processes before the play starts: 5 on a quiet machine,
    more with the machine's load (its 1-minute average, 1.5 s per runnable process), at most
    40."""
    return min(40.0, 5.0 + 1.5 * os.getloadavg()[0])


def _latencies(
    items: list[tuple[float, EstimateMessage]], t0: float
) -> tuple[list[tuple[float, EstimateMessage]], dict[str, Any]]:
    """The estimates the latency is taken over, and its percentiles: end to end, to the
    service's publish stamp, and from there to the subscriber."""
    # latency after a warm-up of 0.5 s (connections settle, the first samples wait for encoder
    # data that predates the subscription)
    # good estimates only: the held ones at the very end (tracker samples stamped after the
    # last encoder sample, answered by the quiet-time flush) say nothing about latency
    in_window = [
        (a, m)
        for a, m in items
        if m.device_stamp is not None and m.device_stamp > t0 + 0.5 and not m.flags
    ]
    device_stamp = np.array([m.device_stamp for _a, m in in_window], dtype=float)
    lat = (np.array([a for a, _m in in_window]) - device_stamp) * 1e3
    to_publish = (np.array([m.host_ns * 1e-9 for _a, m in in_window]) - device_stamp) * 1e3
    to_subscriber = np.array([a - m.host_ns * 1e-9 for a, m in in_window]) * 1e3
    return in_window, {
        "latency_ms": _percentiles(lat),
        "latency_to_service_publish_ms": _percentiles(to_publish),
        "latency_publish_to_subscriber_ms": _percentiles(to_subscriber),
    }


def _percentiles(ms: np.ndarray) -> dict[str, float | None]:
    if not ms.size:
        return {"p50": None, "p99": None, "max": None}
    return {
        "p50": float(np.percentile(ms, 50)),
        "p99": float(np.percentile(ms, 99)),
        "max": float(ms.max()),
    }


# the end-to-end kinds a round runs, and how `end_to_end` runs each
E2E_KINDS: dict[str, dict[str, Any]] = {
    "end_to_end": {},
    "transport_floor": {"relay_only": True},
    "end_to_end_rerun": {"rrd": True},
    "end_to_end_correction": {"correction": True},
    # the relay with the naive floor's math per pose: where any estimator here starts
    "math_floor": {"relay_math": True},
}


def end_to_end_rounds(
    config: Config,
    seconds: float,
    rounds: int,
    with_rerun: bool,
    with_correction: bool = False,
    with_math: bool = False,
) -> list[dict[str, Any]]:
    """`rounds` runs of each end-to-end kind, the order rotated every round so that no kind
    always runs first (a machine's load drifts over minutes; one run's p99 moves 1-5 ms).
    `with_correction`: also the service with a correction output (its latency); `with_math`:
    also the relay with the naive floor's math (`math_floor`)."""
    skip = set()
    if not with_math:
        skip.add("math_floor")
    if not with_rerun:
        skip.add("end_to_end_rerun")
    if not with_correction:
        skip.add("end_to_end_correction")
    kinds = [k for k in E2E_KINDS if k not in skip]
    out = []
    for i in range(rounds):
        order = kinds[i % len(kinds) :] + kinds[: i % len(kinds)]
        done: dict[str, Any] = {"order": order}
        for kind in order:
            done[kind] = end_to_end(loopback_config(config), seconds, **E2E_KINDS[kind])
        out.append(done)
    return out


def spread_of(values: list[float]) -> dict[str, Any]:
    return {
        "median": float(np.median(values)),
        "min": min(values),
        "max": max(values),
        "each": values,
    }


def value_at(run: dict[str, Any], path: tuple[str, ...]) -> Any:
    for key in path:
        run = run[key]
    return run


def round_ratios(rounds: list[dict[str, Any]]) -> dict[str, Any]:
    """The service against its references, each ratio within one round (runs minutes apart,
    not a median run against another run's median)."""

    def ratio(over: str, under: str, *path: str) -> dict[str, Any] | None:
        pairs = [
            (value_at(r[over], path), value_at(r[under], path))
            for r in rounds
            if over in r and under in r
        ]
        values = [a / b for a, b in pairs if a is not None and b]
        return spread_of(values) if values else None

    cpu = ("processes", "service", "cpu_pct")
    found = {
        "service_cpu_over_relay": ratio("end_to_end", "transport_floor", *cpu),
        "p50_over_relay": ratio("end_to_end", "transport_floor", "latency_ms", "p50"),
        "p99_over_relay": ratio("end_to_end", "transport_floor", "latency_ms", "p99"),
        "rrd_p50_over_plain": ratio("end_to_end_rerun", "end_to_end", "latency_ms", "p50"),
        "rrd_p99_over_plain": ratio("end_to_end_rerun", "end_to_end", "latency_ms", "p99"),
        "correction_cpu_over_relay": ratio("end_to_end_correction", "transport_floor", *cpu),
        "correction_p99_over_relay": ratio(
            "end_to_end_correction", "transport_floor", "latency_ms", "p99"
        ),
        "math_cpu_over_relay": ratio("math_floor", "transport_floor", *cpu),
        "math_p99_over_relay": ratio("math_floor", "transport_floor", "latency_ms", "p99"),
        "service_cpu_over_math": ratio("end_to_end", "math_floor", *cpu),
        "p99_over_math": ratio("end_to_end", "math_floor", "latency_ms", "p99"),
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
