"""Where the service's time goes: `keo run` under the standard library's deterministic
profiler (cProfile) in the bench's end-to-end chain (mock devices, adapters, subscriber as
real processes), its main thread's time split into the stages of the live path.

The profiler costs each Python call far more than a native one, so its times are larger
than the service's own and tilted toward the stages with many small Python calls; compare
stages within one profile, and runs of the same kind, not a stage with the bench's CPU
figure. Zenoh's own threads (receive, the hand-off, send) are not profiled: the relay pays
them as well. Run as `python -m keo_service.bench.stages [--config C] [--seconds S]
[--correction] [--clock cpu|wall] [--out FILE.json] [--pstats FILE]`, or
`--from-pstats FILE` for the stages of a profile kept before.
"""

from __future__ import annotations

import argparse
import importlib
import inspect
import json
import pstats
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from keo_service.bench.demo import loopback_config
from keo_service.bench.end_to_end import end_to_end
from keo_service.io.config import load_config
from keo_service.resources import demo_config_path

# the stages of the live path, each the functions (module, qualified name) whose cumulative
# time it is; a name that does not exist in the profiled code is skipped (code moves)
STAGES: dict[str, list[tuple[str, str]]] = {
    # the decoder's own method: the service calls it directly (before: through
    # `messages.decode`, whose own time this leaves out)
    "decode": [("~", "<method 'decode' of 'msgspec.msgpack.Decoder' objects>")],
    "align (interpolate the joints)": [("keo_service.core.timing", "EncoderBuffer.interpolate")],
    "estimator (all of it: checks, align, kinematics, observer)": [
        ("keo_service.core.estimator", "Estimator.on_tracker"),
        ("keo_service.core.estimator", "Estimator.on_encoder"),
    ],
    "delay tracker (per sample, on the loop)": [
        # since issue 48's ninth round a block every 0.1 s (`_feed_delay`, `add_samples`)
        ("keo_service.live.service", "KeoService._feed_delay"),
        ("keo_service.fit.delay_online", "OnlineDelayTracker.add_tracker"),
        ("keo_service.fit.delay_online", "OnlineDelayTracker.add_encoder"),
        ("keo_service.fit.delay_online", "OnlineDelayTracker.delay_now"),
        ("keo_service.live.service", "KeoService._follow_tracked_delay"),
    ],
    "delay tracker (its loop's share on the event loop)": [
        ("keo_service.fit.delay_online", "OnlineDelayTracker.due"),
        ("keo_service.fit.delay_online", "OnlineDelayTracker.take"),
        ("keo_service.fit.delay_online", "OnlineDelayTracker.combine"),
        ("keo_service.fit.delay_online", "stretch_arrays"),
    ],
    "correction (per sample and per estimate)": [
        ("keo_service.live.compensation", "CorrectionSink.on_input"),
        ("keo_service.live.compensation", "CorrectionSink.on_estimate"),
    ],
    "correction (its cycle)": [("keo_service.live.compensation", "CorrectionSink.on_tick")],
    "estimate message (build)": [("keo_service.live.service", "KeoService.to_message")],
    "encode and publish (the bus sink)": [
        ("keo_service.live.sinks", "EstimateBusSink.on_estimate"),
    ],
    "sinks (the fan-out, all sinks included)": [
        ("keo_service.live.sinks", "Sinks.on_input"),
        ("keo_service.live.sinks", "Sinks.on_estimate"),
    ],
    "status (snapshot every 0.1 s, quiet-time check)": [
        ("keo_service.live.service", "KeoService._refresh_status"),
        ("keo_service.live.service", "KeoService._resolve_if_quiet"),
    ],
    "bookkeeping (clock notes, rates)": [
        ("keo_service.live.service", "KeoService._note_sample"),
        ("keo_service.live.service", "RateMeter.tick"),
    ],
}
# the whole data path on the event loop (its cumulative time)
DATA_PATH = [("keo_service.live.service", "KeoService._consume")]
PUBLISHED = [("keo_service.live.sinks", "EstimateBusSink.on_estimate")]
# the event loop waiting for work (epoll): not work
IDLE = [("~", "<method 'poll' of 'select.epoll' objects>")]


def _functions(module: Any) -> Iterator[tuple[str, Any]]:
    for name, obj in vars(module).items():
        if inspect.isfunction(obj) and obj.__module__ == module.__name__:
            yield name, obj
        elif inspect.isclass(obj) and obj.__module__ == module.__name__:
            for attr, member in vars(obj).items():
                fn = member.fget if isinstance(member, property) else member
                if inspect.isfunction(fn):
                    yield f"{name}.{attr}", fn


def _keys(wanted: list[tuple[str, str]]) -> list[tuple[str, int, str]]:
    """cProfile's keys (file, first line, name) of the named functions."""
    out = []
    for module_name, qualname in wanted:
        if module_name == "~":
            out.append(("~", 0, qualname))
            continue
        try:
            module = importlib.import_module(module_name)
        except ImportError:
            continue
        found = dict(_functions(module))
        fn = found.get(qualname)
        if fn is None:
            continue
        code = inspect.unwrap(fn).__code__
        out.append((_package_path(code.co_filename), code.co_firstlineno, code.co_name))
    return out


def _package_path(filename: str) -> str:
    """A source file's path from the package's folder on (the same in every checkout: a
    profile taken in one may be read in another)."""
    _head, sep, tail = filename.rpartition("keo_service/")
    return sep + tail if sep else filename


def stage_times(stats: pstats.Stats) -> dict[str, Any]:
    """Each stage's cumulative time (s) and call count in a profile of the service, and the
    data path's and the idle wait's, for shares."""
    table: dict[Any, Any] = {
        (_package_path(f), line, name): v
        for (f, line, name), v in stats.stats.items()  # type: ignore[attr-defined]
    }

    def cumulative(wanted: list[tuple[str, str]]) -> dict[str, float]:
        keys = [k for k in _keys(wanted) if k in table]
        return {
            "s": sum(table[k][3] for k in keys),
            "calls": sum(table[k][1] for k in keys),
            "found": len(keys),
        }

    stages = {name: cumulative(funcs) for name, funcs in STAGES.items()}
    total = stats.total_tt  # type: ignore[attr-defined]
    idle = cumulative(IDLE)["s"]
    found = {k: v for k, v in stages.items() if v["found"]}
    # per estimate the service published (the bus sink's calls), not per estimate that
    # reached the subscriber: a profiled service falls behind, and its backlog at the end
    # is not delivered
    published = int(cumulative(PUBLISHED)["calls"])
    return {
        "profiled_s": total,
        "idle_s": idle,
        "data_path": cumulative(DATA_PATH),
        "stages": found,
        "published": published,
        "per_estimate_us": {k: 1e6 * v["s"] / max(1, published) for k, v in found.items()},
        "data_path_per_estimate_us": 1e6 * cumulative(DATA_PATH)["s"] / max(1, published),
    }


# `keo run` under a profiler whose clock is the main thread's CPU time (`cpu`) or the wall
# clock (`wall`: what the loop waits for inside a call, e.g. the GIL after a native call that
# released it, counts too); the profile is written when the service exits
_PROFILED_RUN = """
import cProfile, runpy, sys, time
# imported before the profiler starts: a profiled import takes many times as long
import keo_service.cli.live, keo_service.live.service, keo_service.live.compensation
import keo_service.fit.delay, keo_service.fit.delay_online, keo_service.io.cell
timer = time.thread_time if sys.argv[1] == "cpu" else time.perf_counter
out = sys.argv[2]
sys.argv = ["keo", *sys.argv[3:]]
profile = cProfile.Profile(timer)
profile.enable()
try:
    runpy.run_module("keo_service.cli", run_name="__main__")
except SystemExit:
    pass
finally:
    profile.disable()
    profile.dump_stats(out)
"""


def profile_service(
    seconds: float,
    correction: bool,
    pstats_out: Path | None = None,
    config: str | None = None,
    clock: str = "cpu",
) -> dict[str, Any]:
    """One end-to-end run at 1 kHz with `keo run` under cProfile (`clock`: "cpu", the main
    thread's CPU time, or "wall"); the run's figures and the profile's stages."""
    base = load_config(config or demo_config_path())
    with tempfile.TemporaryDirectory(prefix="keo-stages-") as tmp:
        prof = Path(tmp) / "service.pstats"
        res = end_to_end(
            loopback_config(base),
            seconds,
            correction=correction,
            service_python=["-c", _PROFILED_RUN, clock, str(prof)],
        )
        for _ in range(50):  # written when the service exits, after the run
            if prof.exists():
                break
            import time

            time.sleep(0.1)
        stats = pstats.Stats(str(prof))
        if pstats_out is not None:
            stats.dump_stats(str(pstats_out))
    found = stage_times(stats)
    found["estimates"] = res["estimates_received"]
    keep = ("latency_ms", "processes", "machine", "correction_latency_ms", "service_counters")
    found["run"] = {k: res[k] for k in keep if k in res}
    found["clock"] = clock
    # the delay fits run in the service's worker process, which the profiler does not see:
    # their CPU as the service counted it, per estimate published
    fits_ms = res.get("service_counters", {}).get("delay_fit_cpu_ms")
    if fits_ms is not None:
        found["delay_fits_per_estimate_us"] = 1e3 * fits_ms / max(1, found["published"])
        found["delay_fits_core_pct"] = 100.0 * fits_ms * 1e-3 / seconds
    return found


def stages_table(found: dict[str, Any]) -> str:
    lines = [
        "| stage | us per estimate (under the profiler) | share of the data path |",
        "|---|---|---|",
    ]
    path = found["data_path_per_estimate_us"]
    for name, us in found["per_estimate_us"].items():
        lines.append(f"| {name} | {us:.1f} | {100.0 * us / path:.0f} % |" if path else "")
    lines.append(f"| the data path (`_consume`, all of it) | {path:.1f} | 100 % |")
    if "delay_fits_per_estimate_us" in found:
        lines.append(
            f"| delay fits (the service's worker process, not profiled: its CPU time) | "
            f"{found['delay_fits_per_estimate_us']:.1f} | "
            f"{found['delay_fits_core_pct']:.1f} % of a core |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config")
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--correction", action="store_true")
    parser.add_argument("--out")
    parser.add_argument("--pstats")
    parser.add_argument("--clock", choices=("cpu", "wall"), default="cpu")
    parser.add_argument("--from-pstats", help="the stages of a profile written before")
    args = parser.parse_args()
    if args.from_pstats:
        sys.stdout.write(stages_table(stage_times(pstats.Stats(args.from_pstats))))
        return
    found = profile_service(
        args.seconds,
        args.correction,
        Path(args.pstats) if args.pstats else None,
        args.config,
        args.clock,
    )
    if args.out:
        Path(args.out).write_text(json.dumps(found, indent=1))
    sys.stdout.write(stages_table(found))
    run = found["run"]
    sys.stdout.write(
        f"latency {run['latency_ms']}; service CPU {run['processes']['service']['cpu_pct']:.1f} %"
        f"; correction latency {run.get('correction_latency_ms')}\n"
    )


if __name__ == "__main__":
    main()
