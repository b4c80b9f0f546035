"""`keo bench`: hot path, end to end over real processes, capacity, accuracy, Rerun's cost.

Prints numbers, judges nothing: timing on shared machines is noisy, so ratios measured in one
run are what to compare. `--quick` (CI's smoke test) shortens every part.
"""

from __future__ import annotations

from typing import Any

from keo_service.bench.accuracy import accuracy
from keo_service.bench.commands import head_files, recording
from keo_service.bench.demo import loopback_config
from keo_service.bench.end_to_end import (
    E2E_KINDS,
    capacity,
    end_to_end,
    end_to_end_rounds,
    round_ratios,
)
from keo_service.bench.hot_path import hot_path, hot_path_and_floor
from keo_service.bench.machine import TICK, machine, machine_share, machine_ticks
from keo_service.bench.table import bench_table, dumps
from keo_service.io.config import Config

__all__ = [
    "TICK",
    "accuracy",
    "bench_table",
    "capacity",
    "dumps",
    "end_to_end",
    "end_to_end_rounds",
    "head_files",
    "hot_path",
    "machine_share",
    "machine_ticks",
    "recording",
    "round_ratios",
    "run_bench",
    "soak",
]


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
        analyze_whole=not quick,
    )
    done = end_to_end_rounds(
        config,
        e2e_seconds,
        rounds,
        with_rerun=not quick,
        with_correction=not quick,
        with_math=not quick,
    )
    for kind in E2E_KINDS:  # the first round's runs in full, as before rounds
        if kind in done[0]:
            out[kind] = done[0][kind]
    out["end_to_end_rounds"] = done
    out["round_ratios"] = round_ratios(done)
    rates = [1000.0, 2000.0] if quick else [1000.0, 2000.0, 4000.0, 8000.0]
    out["capacity"] = capacity(loopback_config(config), rates, 3.0 if quick else 8.0)
    out["accuracy"] = accuracy(config)
    return out
