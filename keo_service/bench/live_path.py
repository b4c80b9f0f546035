"""The service's data path in process, without Zenoh: `KeoService._handle` fed the bench's
scenario as real wire payloads, its CPU per wire sample, whole and split into stages.

The end-to-end bench measures what the service costs with Zenoh, the adapters and a shared
machine around it; here only the service's own Python runs, so a change to it shows without
the transport's noise. The streams are the bench's own: the "path" scenario at 1 kHz
(tracker) and 250 Hz (encoder), the tracker on a device clock (device stamps on a line with
its drift, as the line protocol's adapter puts them), the encoder stamped on receipt.
Wake-ups bring the samples in the sizes the service sees at 1 kHz (mostly one or two). The
delay tracker's poll runs as `_delay_loop` does it every 0.25 s of stream time, its fits in
process (their CPU is the worker's and is left out of the figures).

Two measures:

- `whole`: the thread's CPU over the whole data path (wake-ups and the delay poll's share on
  the loop), per wire sample; passes alternate, the minimum and median are reported.
- `stages`: the same run with each stage's callable wrapped in a timer (decode, estimator,
  delay intake, the delay poll's share on the loop, message build, encode, put, the fan-out
  and `_handle`'s own loop as the rest); each wrapper's own cost, measured on an empty
  callable, is taken off.

`paced` (off by default) sleeps between wake-ups as the samples' stamps say, so that each
wake-up meets the CPU as the live service does (caches cold from the sleep); its figures are
larger than a tight loop's. On a quiet machine a sleep leaves the caches warm, where the real
chain's other processes do not: `--cold MB` runs a `Cooler` (a pass over MB megabytes)
before each wake-up, its own CPU left out, which brought this path's cost near the chain's
(docs/performance.md, Round 12). Run as `python -m keo_service.bench.live_path [--seconds S]
[--passes N] [--paced] [--cold MB] [--json]`.
"""

from __future__ import annotations

import argparse
import collections
import gc
import json
import math
import statistics
import sys
import time
from collections.abc import Callable, Iterator
from typing import Any

import msgspec

from keo_service.bench.demo import loopback_config
from keo_service.io.cell import cell_from_config
from keo_service.io.config import Config, load_config
from keo_service.resources import demo_config_path

# wake-up sizes at 1 kHz, in turn (the live service's are mostly one or two samples)
WAKE_SIZES = (1, 2, 1, 1, 3, 1, 2, 1)
DELAY_POLL_S = 0.25
STATUS_PERIOD_S = 0.1


def wire_samples(
    config: Config, seconds: float, tracker_hz: float = 1000.0, encoder_hz: float = 250.0
) -> list[tuple[float, str, bytes]]:
    """The scenario as the adapters put it, in stamp order (encoder first on ties): (stamp,
    key, payload)."""
    from keo_service.live.messages import JointSample, TrackerSample, encode
    from keo_service.sim.simulate import make_scenario, simulate

    sets = {
        "tracker_rate_hz": str(tracker_hz),
        "tracker_rate_std_hz": "0",
        "encoder_rate_hz": str(encoder_hz),
        "encoder_rate_std_hz": "0",
        "drop_probability": "0",
        "duration_s": str(seconds),
    }
    run = simulate(cell_from_config(config), make_scenario("path", sets), seed=1)
    t0 = 1.7e9
    cell = config.cell
    rows: list[tuple[float, int, str, Any]] = []
    for i, t in enumerate(run.encoder.t):
        msg: Any = JointSample(
            stamp=t0 + float(t),
            host_ns=int((t0 + t) * 1e9),
            seq=i + 1,
            joints=[float(x) for x in run.encoder.q[i]],
            clock="receipt",
            clock_epoch=1,
        )
        rows.append((t0 + float(t), 0, f"keo/{cell}/encoder", msg))
    quat = run.tracker.quat
    for i, t in enumerate(run.tracker.t):
        msg = TrackerSample(
            stamp=t0 + float(t),
            host_ns=int((t0 + t) * 1e9),
            seq=i + 1,
            position=[float(x) for x in run.tracker.p[i]],
            quaternion=None if quat is None else [float(x) for x in quat[i]],
            device_stamp=1000.0 + float(t),
            clock="device",
            clock_epoch=1,
            clock_drift=2e-6,
        )
        rows.append((t0 + float(t), 1, f"keo/{cell}/tracker", msg))
    rows.sort(key=lambda r: (r[0], r[1]))
    return [(stamp, key, encode(msg)) for stamp, _k, key, msg in rows]


class _Put:
    """A publisher that takes the payload and does nothing (the transport is not measured)."""

    def put(self, payload: bytes) -> None:
        pass

    def undeclare(self) -> None:
        pass


class _Session:
    """What the bus sink asks of a Zenoh session."""

    def declare_publisher(self, key: str, **kw: Any) -> _Put:
        return _Put()

    def declare_queryable(self, key: str, handler: Any) -> _Put:
        return _Put()


def make_service(config: Config) -> Any:
    """A service with its bus sink on a publisher that does nothing; not entered (no
    session, no tasks): `_handle` and the delay poll are driven by `drive`."""
    from keo_service.live.service import KeoService
    from keo_service.live.sinks import EstimateBusSink

    service = KeoService(config)
    service.sinks.add(EstimateBusSink(_Session(), config.cell))  # type: ignore[arg-type]
    return service


def delay_poll(service: Any) -> tuple[float, float]:
    """`_delay_loop`'s one pass, synchronous: the fit in process. Returns the fit's CPU (s),
    which is the worker's, not the loop's, and its time on the performance counter (s)."""
    from keo_service.fit.delay_online import stretch_arrays

    tracker = service._delay_tracker
    feed = getattr(service, "_feed_delay", None)  # a block intake, where there is one
    if feed is not None:
        feed()
    if tracker is None or not tracker.due():
        return 0.0, 0.0
    restarts = tracker.counters["restarts"]
    window = stretch_arrays(tracker.take())
    current = service.estimator.delay.offset_s
    start, wall = time.thread_time(), time.perf_counter()
    found = tracker.measure(window, current, tracker.guess(current))
    fit_s, fit_wall = time.thread_time() - start, time.perf_counter() - wall
    if feed is not None:
        feed()
    if tracker.counters["restarts"] == restarts:
        tracker.combine(found)
        service._follow_tracked_delay(tracker, tracker.delay_now())
    return fit_s, fit_wall


class Cooler:
    """What the live service's other neighbours do to its caches between two wake-ups, done
    on purpose: a pass over a buffer larger than a core's own caches (a copy onto itself and
    a write to every cache line), so that the next wake-up finds its code's data and the
    libraries' tables evicted, as in the real chain, where other processes run on the same
    core between two samples. `drive` runs it before each wake-up and leaves its CPU out."""

    def __init__(self, megabytes: float) -> None:
        self._buffer = bytearray(int(megabytes * (1 << 20)))
        self._lines = b"\x01" * len(self._buffer[0::64])
        self.passes = 0

    def __call__(self) -> None:
        buffer = self._buffer
        buffer[:] = buffer
        buffer[0::64] = self._lines
        self.passes += 1


def drive(
    service: Any,
    wire: list[tuple[float, str, bytes]],
    paced: bool = False,
    handle: Callable[[list[tuple[str, bytes]]], None] | None = None,
    cool: Callable[[], None] | None = None,
) -> dict[str, float]:
    """The wire through `_handle` in wake-ups of `WAKE_SIZES`, the delay poll every 0.25 s of
    stream time. Returns the thread's CPU (s) without the fits, the fits' CPU, the delay
    poll's time on the loop without its fits (performance counter, s), samples. `handle`:
    another handler in the service's place (the relay's; `service` None: no delay poll).
    `cool` (a `Cooler`): run before each wake-up, each block intake and each delay poll, its
    own CPU left out of the figure (each leaves two readings of the thread's clock in it)."""
    handle = handle or service._handle
    thread_time = time.thread_time
    fits = poll_s = cooling = 0.0
    i, k, n = 0, 0, len(wire)
    next_poll = wire[0][0] + DELAY_POLL_S
    feed = getattr(service, "_feed_delay", None)  # the status loop's, every 0.1 s
    if service is None:
        next_poll = math.inf
    next_feed = wire[0][0] + STATUS_PERIOD_S
    wall0 = time.monotonic() - wire[0][0]
    start = thread_time()
    while i < n:
        size = WAKE_SIZES[k % len(WAKE_SIZES)]
        k += 1
        batch = wire[i : i + size]
        i += size
        stamp = batch[-1][0]
        if paced:
            wait = stamp + wall0 - time.monotonic()
            if wait > 0:
                time.sleep(wait)
        if cool is not None:
            t = thread_time()
            cool()
            cooling += thread_time() - t
        handle([(key, payload) for _s, key, payload in batch])
        if feed is not None and stamp >= next_feed:
            next_feed += STATUS_PERIOD_S
            if cool is not None:
                t = thread_time()
                cool()
                cooling += thread_time() - t
            feed()
        if stamp >= next_poll:
            next_poll += DELAY_POLL_S
            if cool is not None:
                t = thread_time()
                cool()
                cooling += thread_time() - t
            t = time.perf_counter()
            fit_cpu, fit_wall = delay_poll(service)
            poll_s += time.perf_counter() - t - fit_wall
            fits += fit_cpu
    cpu = thread_time() - start - fits - cooling
    return {"cpu_s": cpu, "fit_cpu_s": fits, "poll_s": poll_s, "samples": n}


# ---- stages ------------------------------------------------------------------------------


def _best_us(run: Callable[[], int], passes: int) -> float:
    """The least thread CPU of `passes` calls of `run` (which returns how many wire samples it
    stands for), us per wire sample."""
    best = math.inf
    for _ in range(passes):
        t = time.thread_time()
        n = run()
        best = min(best, (time.thread_time() - t) / n * 1e6)
    return best


# complexity (C901): one closure per stage, each timed alone
def stages(  # noqa: C901
    config: Config, wire: list[tuple[float, str, bytes]], passes: int = 5
) -> dict[str, Any]:
    """Each stage of the data path alone, over the inputs one whole run gave it (recorded),
    in a loop of its own: the least thread CPU of `passes` passes, us per wire sample. The
    stages: decode; the estimator (`on_tracker`, `on_encoder`); the delay tracker's intake
    (what the service hands it per sample, or per block where it takes blocks); the message
    build (`to_message`); encode; the fan-out with the bus sink (a put that does nothing);
    the whole path; `_handle`'s own loop and the rest is the whole less the stages."""
    from keo_service.core.estimator import Estimator
    from keo_service.io.cell import estimator_settings
    from keo_service.live.messages import DECODER, ENCODER, TrackerSample

    cell = cell_from_config(config)
    payloads = [payload for _s, _k, payload in wire]
    # tracker and joint samples only (the wire a run gave); the loops below dispatch on type
    msgs: list[Any] = [DECODER.decode(p) for p in payloads]
    n = len(wire)
    out: dict[str, float] = {}

    def decode() -> int:
        dec = DECODER.decode
        for p in payloads:
            dec(p)
        return n

    def estimator() -> int:
        est = Estimator(cell, estimator_settings(config))
        on_tracker, on_encoder = est.on_tracker, est.on_encoder
        for m in msgs:
            if type(m) is TrackerSample:
                on_tracker(
                    m.stamp, m.position, m.quaternion, ok=m.status == "ok",
                    device_stamp=m.device_stamp,
                )  # fmt: skip
            else:
                on_encoder(m.stamp, m.joints)
        return n

    out["decode"] = _best_us(decode, passes)
    out["estimator"] = _best_us(estimator, passes)
    out["delay intake (per sample and block, and delay_now)"] = _best_us(
        lambda: _intake(config, msgs), passes
    )
    # the estimates and their messages as one whole run made them
    service = make_service(config)
    drive(service, wire)
    from keo_service.live.sinks import Sinks

    kept: list[Any] = []
    bus = service.sinks.sinks[-1]
    service2 = make_service(config)
    service2.sinks = Sinks([_Keep(kept)])
    drive(service2, wire)
    estimates = [e for e, _m in kept]
    messages = [m for _e, m in kept]

    def build() -> int:
        to_message = service2.to_message
        for e in estimates:
            to_message(e)
        return n

    def encode() -> int:
        enc = ENCODER.encode
        for m in messages:
            enc(m)
        return n

    def fanout() -> int:
        on_estimate = bus.on_estimate
        for e, m in kept:
            on_estimate(e, m)
        return n

    out["message build"] = _best_us(build, passes)
    out["encode"] = _best_us(encode, passes)
    out["fan-out and bus sink, encode in it (no transport)"] = _best_us(fanout, passes)
    whole_us = min(drive(make_service(config), wire)["cpu_s"] / n * 1e6 for _ in range(passes))
    counted = sum(v for k, v in out.items() if k != "encode")
    out["_handle's own loop and the rest"] = whole_us - counted
    return {
        "us_per_sample": {k: round(v, 2) for k, v in out.items()},
        "whole_us_per_sample": round(whole_us, 2),
        "estimates": len(kept),
        "samples": n,
        "delay_source": getattr(service2._delay_tracker, "source_kind", None),
    }


class _Keep:
    """A sink that keeps (estimate, message)."""

    name = "keep"
    period_s = None

    def __init__(self, kept: list[Any]) -> None:
        self.kept = kept

    def on_estimate(self, estimate: Any, message: Any) -> None:
        self.kept.append((estimate, message))

    def on_input(self, sample: Any) -> None:
        pass

    def on_tick(self) -> None:
        pass

    def counters(self) -> dict[str, int]:
        return {}

    def close(self) -> None:
        pass


def _intake(config: Config, msgs: list[Any]) -> int:
    """The delay tracker's intake as the service drives it: per sample `add_tracker` /
    `add_encoder` and `delay_now`, or the service's own block intake where it has one."""
    from keo_service.live.messages import TrackerSample

    service = make_service(config)
    tracker = service._delay_tracker
    if hasattr(service, "_feed_delay"):  # the block intake: per sample onto the service's
        keep, feed = service._delay_inbox.append, service._feed_delay  # list, every 0.1 s
        for k, m in enumerate(msgs):  # of samples (125 at 1 kHz / 250 Hz) one block
            keep(m)
            if k % 125 == 124:
                feed()
        feed()
        return len(msgs)
    add_tracker, add_encoder = tracker.add_tracker, tracker.add_encoder
    delay_now = tracker.delay_now
    for m in msgs:
        if type(m) is TrackerSample:
            add_tracker(
                m.stamp, m.position, m.quaternion, m.clock_epoch, m.seq, bool(m.flags),
                m.device_stamp, m.clock_drift,
            )  # fmt: skip
        else:
            add_encoder(
                m.stamp, m.joints, m.clock_epoch, m.seq, bool(m.flags), m.device_stamp,
                m.clock_drift,
            )  # fmt: skip
        delay_now()
    return len(msgs)


def _wake_ups(
    wire: list[tuple[float, str, bytes]],
) -> Iterator[tuple[list[tuple[str, bytes]], bool]]:
    """The wire in wake-ups of `WAKE_SIZES`: each wake-up's (key, payload) pairs, and whether
    the status loop's delay block is due after it (every `STATUS_PERIOD_S` of stream time)."""
    k = i = 0
    next_feed = wire[0][0] + STATUS_PERIOD_S
    while i < len(wire):
        size = WAKE_SIZES[k % len(WAKE_SIZES)]
        k += 1
        batch = [(key, payload) for _s, key, payload in wire[i : i + size]]
        stamp = wire[min(i + size, len(wire)) - 1][0]
        i += size
        due = stamp >= next_feed
        if due:
            next_feed += STATUS_PERIOD_S
        yield batch, due


def calls(config: Config, wire: list[tuple[float, str, bytes]]) -> dict[str, float]:
    """Calls per wire sample inside `_handle` (`sys.setprofile`: Python functions entered and
    C functions called), deterministic; the delay poll and the block intake outside it run
    unprofiled (their calls are once per block: given apart, per wire sample)."""
    service = make_service(config)
    handle = service._handle
    counts = {"call": 0, "c_call": 0}

    def count(frame: Any, event: str, arg: Any) -> None:
        if event in counts:
            counts[event] += 1

    block = {"call": 0, "c_call": 0}

    def count_block(frame: Any, event: str, arg: Any) -> None:
        if event in block:
            block[event] += 1

    feed = getattr(service, "_feed_delay", None)
    for batch, feed_due in _wake_ups(wire):
        sys.setprofile(count)
        handle(batch)
        sys.setprofile(None)
        if feed is not None and feed_due:
            sys.setprofile(count_block)
            feed()
            sys.setprofile(None)
    n = len(wire)
    return {
        "python_calls": round(counts["call"] / n, 2),
        "c_calls": round(counts["c_call"] / n, 2),
        "block_intake_python_calls": round(block["call"] / n, 3),
        "block_intake_c_calls": round(block["c_call"] / n, 2),
    }


def call_names(config: Config, wire: list[tuple[float, str, bytes]]) -> dict[str, Any]:
    """What `calls` counts, by name: each Python function entered and each C function called
    inside `_handle`, per estimate, most first (deterministic). A call into Pinocchio
    (Boost.Python) or a type's constructor (a msgspec Struct) is no C-function event and is
    not listed: the kinematics' calls are read from the code."""
    service = make_service(config)
    handle = service._handle
    counts: collections.Counter[str] = collections.Counter()

    def count(frame: Any, event: str, arg: Any) -> None:
        if event == "call":
            code = frame.f_code
            counts[f"{code.co_filename.rsplit('/', 1)[-1]}:{code.co_name}"] += 1
        elif event == "c_call":
            owner = getattr(arg, "__self__", None)
            where = getattr(arg, "__module__", None) or type(owner).__name__
            counts[f"{where}.{arg.__name__} (C)"] += 1

    feed = getattr(service, "_feed_delay", None)
    for batch, feed_due in _wake_ups(wire):
        sys.setprofile(count)
        handle(batch)
        sys.setprofile(None)
        if feed is not None and feed_due:
            feed()
    counts.pop("sys.setprofile (C)", None)  # the counting's own
    estimates = max(1, service.estimator.counters["estimates"])
    return {
        "estimates": estimates,
        "per_estimate": {name: round(n / estimates, 3) for name, n in counts.most_common()},
    }


def whole(
    config: Config,
    wire: list[tuple[float, str, bytes]],
    passes: int,
    paced: bool = False,
    cold_mb: float = 0.0,
) -> dict[str, Any]:
    """`passes` runs of a fresh service each, alternating with the bench's relay handler
    (`bench.relay.relay_handler`, the transport floor's own work) and the relay with the
    naive floor's math (`bench.relay.naive_math_handler`, what any estimator in this stack
    does per sample): the thread's CPU per wire sample (us), and the ratios pair by pair.
    `cold_mb`: a `Cooler` of that size before each wake-up (0: none)."""
    from keo_service.bench.relay import naive_math_handler, relay_handler

    cool = Cooler(cold_mb) if cold_mb > 0 else None
    cell = cell_from_config(config)
    each, floor, math_floor = [], [], []
    for _ in range(passes):
        # each pass from a collected heap (the passes before left services behind), as the
        # service runs after its start-up's collection (`run_service`)
        service = make_service(config)
        gc.collect()
        ran = drive(service, wire, paced, cool=cool)
        each.append(ran["cpu_s"] / ran["samples"] * 1e6)
        del service, ran
        gc.collect()
        ran = drive(None, wire, paced, relay_handler(_Put()), cool=cool)
        floor.append(ran["cpu_s"] / ran["samples"] * 1e6)
        ran = drive(None, wire, paced, naive_math_handler(_Put(), cell), cool=cool)
        math_floor.append(ran["cpu_s"] / ran["samples"] * 1e6)

    def pairs(a: list[float], b: list[float]) -> float:
        return round(statistics.median(x / y for x, y in zip(a, b, strict=True)), 3)

    return {
        "us_per_sample_min": round(min(each), 2),
        "us_per_sample_median": round(statistics.median(each), 2),
        "each": [round(v, 2) for v in each],
        "relay_us_per_sample_median": round(statistics.median(floor), 2),
        "relay_each": [round(v, 2) for v in floor],
        "math_us_per_sample_median": round(statistics.median(math_floor), 2),
        "math_each": [round(v, 2) for v in math_floor],
        "over_relay_median": pairs(each, floor),
        "math_over_relay_median": pairs(math_floor, floor),
        "over_math_median": pairs(each, math_floor),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m keo_service.bench.live_path")
    parser.add_argument("--config", default=str(demo_config_path()))
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--passes", type=int, default=5)
    parser.add_argument("--paced", action="store_true")
    parser.add_argument(
        "--cold",
        type=float,
        default=0.0,
        metavar="MB",
        help="a pass over MB megabytes before each wake-up, its CPU left out (the chain's "
        "cold caches; Round 12 used 4, twice the measuring machine's L2 per core)",
    )
    parser.add_argument("--whole-only", action="store_true", help="no stage table")
    parser.add_argument(
        "--list-calls", action="store_true", help="the calls inside `_handle` by name, only"
    )
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    config = loopback_config(load_config(args.config))
    wire = wire_samples(config, args.seconds)
    if args.list_calls:
        print(msgspec.json.format(msgspec.json.encode(call_names(config, wire))).decode())
        return 0
    out = {
        "seconds": args.seconds,
        "paced": args.paced,
        "cold_mb": args.cold,
        "wire_samples": len(wire),
        "whole": whole(config, wire, args.passes, args.paced, args.cold),
    }
    if not args.whole_only:
        out["calls_per_sample"] = calls(config, wire)
        out["stages"] = stages(config, wire, args.passes)
    if args.json:
        print(json.dumps(out))
    else:
        print(msgspec.json.format(msgspec.json.encode(out)).decode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
