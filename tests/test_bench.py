"""The benchmark's own instruments: the end-to-end chain and its transport floor (real
processes). Timing is not judged here (noisy machines); what must hold is that every tracker
sample is answered and that the stage split adds up."""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time

import numpy as np
import pytest

from keo_service.bench.benchmarks import (
    TICK,
    bench_table,
    end_to_end,
    end_to_end_rounds,
    head_files,
    hot_path,
    machine_share,
    machine_ticks,
    round_ratios,
    soak,
)
from keo_service.bench.commands import _timed_command, _watch_peak
from keo_service.bench.demo import loopback_config
from keo_service.bench.procs import free_port
from keo_service.io.cell import cell_from_config
from keo_service.io.interchange import read_encoder, read_tracker
from keo_service.sim.simulate import make_scenario, simulate, write_run


@pytest.mark.parametrize(
    "relay_only",
    # acceptance runs (13 s each; `keo bench --quick` runs the same chain in CI)
    [pytest.param(False, marks=pytest.mark.slow), pytest.param(True, marks=pytest.mark.slow)],
    ids=["service", "transport-floor"],
)
def test_end_to_end_chain_answers_every_tracker_sample(
    demo_config, relay_only, tmp_path, monkeypatch
):
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))  # where the run's folder goes
    res = end_to_end(loopback_config(demo_config), seconds=3.0, relay_only=relay_only)
    assert list(tmp_path.iterdir()) == []  # the logs' folder is gone after a clean run
    assert res["tracker_samples_sent"] == 3000
    assert res["lost"] == 0
    total = res["latency_ms"]
    to_publish = res["latency_to_service_publish_ms"]
    to_subscriber = res["latency_publish_to_subscriber_ms"]
    # the publish stamp lies between the line leaving the mock and the arrival
    assert 0.0 < to_publish["p50"] < total["p50"]
    assert 0.0 < to_subscriber["p50"] < total["p50"]
    assert total["p50"] <= total["p99"] <= total["max"]
    assert res["processes"]["service"]["cpu_pct"] > 0.0
    # its CPU by kind of thread: the loop's works, and Zenoh's runtime threads carry the data
    threads = res["processes"]["service"]["threads_cpu_pct"]
    assert threads["event_loop"] > 0.0
    assert threads["native_threads"] > 0.0
    # the whole machine works at least as hard as the service alone (a share of both cores)
    assert res["machine"]["busy_pct"] * os.cpu_count() >= res["processes"]["service"]["cpu_pct"]


def _e2e(p50: float, p99: float, cpu: float | None = None) -> dict:
    """An end-to-end run's report, as much of it as the table reads (`cpu`: the service's)."""
    lat = {"p50": p50, "p99": p99, "max": 2 * p99}
    service = {"cpu_pct": cpu, "peak_rss_mb": 100.0, "rss_growth_mb": 0.0}
    return {
        "tracker_hz": 1000.0,
        "encoder_hz": 250.0,
        "seconds": 30.0,
        "estimates_received": 30000,
        "tracker_samples_sent": 30000,
        "latency_ms": lat,
        "latency_to_service_publish_ms": lat,
        "latency_publish_to_subscriber_ms": lat,
        "processes": {} if cpu is None else {"service": service},
    }


def _table_report() -> dict:
    hot = {"samples_per_s": 20000.0, "us_per_sample": 50.0, "core_share_at_1kHz_pct": 5.0}
    return {
        "machine": {"cpu": "test", "cores": 2, "python": "3.11"},
        "quick": False,
        "hot_path": hot,
        "hot_path_rerun": {**hot, "samples_per_s": 10000.0, "rerun": "process"},
        "recording": {
            "seconds": 600.0,
            "tracker_samples": 600000,
            "encoder_samples": 150000,
            "floor_s": 3.0,
            "over_floor": 0.45,
            "over_floor_best": 0.41,
            "over_floor_worst": 0.52,
            "batch": {
                "wall_s": 1.5,
                "cpu_s": 2.1,
                "peak_rss_mb": 450.0,
                "runs_wall_s": [1.5, 1.4, 1.6],
                "warmup_wall_s": 1.9,
            },
            "calibrate_delay": {"wall_s": 6.5, "cpu_s": 7.9, "peak_rss_mb": 820.0},
            "analyze": {
                "wall_s": 41.7,
                "cpu_s": 70.2,
                "peak_rss_mb": 310.0,
                "seconds": 10.0,
                "poses": 9986,
            },
            "analyze_long": {
                "wall_s": 58.2,
                "cpu_s": 75.0,
                "peak_rss_mb": 790.0,
                "over_floor": 29.1,
                "samples": {"recorded": 599_000, "used": 20_000, "how": "h"},
                "held_out_pos_rms_mm": 1.17,
            },
        },
        "capacity": {"highest_rate_without_drops_hz": 4000.0, "steps": []},
        "accuracy": {
            "scenario": "s",
            "configured_gain": 2.0,
            "best_gain": 2.0,
            "interpolate_pos_mm": 0.04,
            "latest_pos_mm": 0.7,
            "best_gain_interpolate_pos_mm": 0.04,
            "reference_over_keo": 17.5,
        },
    }


def test_bench_table_states_the_ratio_over_the_floor():
    # a report from before rounds: one pair, its ratio
    report = {**_table_report(), "end_to_end": _e2e(1.0, 3.0), "transport_floor": _e2e(0.5, 2.0)}
    table = bench_table(report)
    assert "p50 x2.00, p99 x1.50" in table
    # the recording's ratio is the pairs' median, not the median run over the median floor
    assert "command / floor = 0.45 (median of 3 pairs" in table
    assert "0.41 to 0.52" in table
    assert "Rerun worker" in table
    assert "x2.00 the cost" in table
    assert "transport floor" in table
    assert "keo calibrate-delay, same files" in table
    assert "6.50 s wall, 7.90 s CPU, peak RSS 820 MB" in table
    assert "keo analyze, the first 10 s of the same files (9,986 poses" in table
    assert "41.7 s wall, 70.2 s CPU, peak RSS 310 MB" in table
    assert "20,000 informative ones used; held out 1.170 mm" in table
    assert "58.2 s wall, 75.0 s CPU, peak RSS 790 MB; command / floor = 29 (wall)" in table


def test_a_commands_peak_memory_is_its_own_not_the_benchs(tmp_path):
    """rusage of a child counts the parent's size at the fork; the bench reads the command's
    own high-water mark instead."""
    ballast = np.ones(50_000_000)  # 400 MB in the bench's process
    got = _timed_command(["--help"], tmp_path / "help.log")
    assert ballast[-1] == 1.0
    assert 5.0 < got["peak_rss_mb"] < 150.0  # `keo --help` itself: tens of MB


def test_the_peak_watcher_sees_what_a_process_allocates():
    code = "import numpy, time; a = numpy.ones(25_000_000); time.sleep(0.3)"  # 200 MB
    argv = [sys.executable, "-c", code]
    proc = subprocess.Popen(argv)
    peak_kb = [0]
    _watch_peak(proc.pid, argv, peak_kb)
    proc.wait()
    assert 195.0 < peak_kb[0] / 1024.0 < 400.0


def test_the_rerun_pass_runs_the_services_worker_and_its_process_logs_everything(demo_config):
    """The pass raises when the Rerun process fails or an estimate is dropped."""
    res = hot_path(loopback_config(demo_config), 2.0, with_rerun=True, repeats=1)
    assert res["samples"] > 1900
    assert res["rerun"] == "process"


@pytest.mark.slow  # an acceptance run (> 9 s): .ci/run runs the slow tests after the default run
def test_the_rrd_run_reports_the_rerun_process_apart(demo_config, tmp_path, monkeypatch):
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    res = end_to_end(loopback_config(demo_config), seconds=3.0, rrd=True)
    assert res["lost"] == 0
    rerun = res["processes"]["rerun-process"]  # the service's child, not counted in its CPU
    assert rerun["cpu_pct"] > 0.0
    assert rerun["peak_rss_mb"] > 20.0  # Python with Rerun and Pinocchio loaded
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow  # an acceptance run (> 9 s): .ci/run runs the slow tests after the default run
def test_a_soak_with_rrd_traces_the_rerun_process_and_its_recording(
    demo_config, tmp_path, monkeypatch
):
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    res = soak(demo_config, 4.0, rrd=True, sample_every=0.5)
    assert res["rrd"]
    # what this run is about is the trace; whether every sample is answered is judged by the
    # end-to-end tests above. Beside the Rerun child on a loaded CI machine (load 8 on 2
    # cores) 93 of 4000 estimates did not reach the collector within the run.
    assert res["estimates_received"] > 0.95 * res["tracker_samples_sent"], res["lost"]
    assert len(res["trace"]) >= 3
    rerun = res["summary"]["rerun-process"]  # traced beside the service, not inside it
    assert rerun["rss_first_mb"] > 20.0
    assert rerun["rss_max_mb"] >= rerun["rss_last_mb"]
    assert "service" in res["summary"]
    assert res["recording"]["files"] == 1  # shorter than a roll
    assert res["recording"]["mb"][0] > 0.0
    assert list(tmp_path.iterdir()) == []


def test_bench_refuses_rrd_without_a_soak():
    from keo_service.cli import main

    assert main(["bench", "--quick", "--rrd"]) == 2  # (were it run: a minute, exit 0)


@pytest.mark.parametrize(
    "argv",
    [["--rounds", "0"], ["--soak", "5", "--rounds", "2"]],
    ids=["no-rounds", "rounds-with-soak"],
)
def test_bench_refuses_rounds_it_cannot_run(argv, capsys):
    from keo_service.cli import main

    assert main(["bench", "--quick", *argv]) == 2
    assert "--rounds" in capsys.readouterr().err


def test_round_ratios_pair_runs_within_their_round():
    rounds = [
        {
            "end_to_end": _e2e(1.0, 2.0, 30.0),
            "transport_floor": _e2e(0.5, 1.0, 20.0),
            "end_to_end_rerun": _e2e(1.0, 3.0, 31.0),
        },
        {
            "end_to_end": _e2e(1.0, 4.0, 30.0),
            "transport_floor": _e2e(0.5, 4.0, 25.0),
            "end_to_end_rerun": _e2e(1.0, 4.0, 31.0),
        },
        {
            "end_to_end": _e2e(1.0, 1.5, 27.0),
            "transport_floor": _e2e(0.5, 1.0, 30.0),
            "end_to_end_rerun": _e2e(1.0, 1.5, 31.0),
        },
    ]
    r = round_ratios(rounds)
    # by hand: p99 2/1, 4/4, 1.5/1 -> median 1.5 (the ratio of the medians would be 2/1)
    assert r["p99_over_relay"]["each"] == [2.0, 1.0, 1.5]
    assert r["p99_over_relay"]["median"] == 1.5
    assert r["service_cpu_over_relay"]["each"] == [1.5, 1.2, 0.9]
    assert r["service_cpu_over_relay"]["median"] == pytest.approx(1.2)
    assert r["rrd_p99_over_plain"]["each"] == [1.5, 1.0, 1.0]
    assert (r["rrd_p99_over_plain"]["min"], r["rrd_p99_over_plain"]["max"]) == (1.0, 1.5)
    # a bench without the --rrd run has no such ratio, rather than a made-up one
    plain = [{k: v for k, v in x.items() if k != "end_to_end_rerun"} for x in rounds]
    assert "rrd_p99_over_plain" not in round_ratios(plain)


def test_each_round_starts_with_another_kind(monkeypatch, demo_config):
    from keo_service.bench import end_to_end as e2e_module

    calls = []

    def fake(config, seconds, relay_only=False, rrd=False):
        calls.append("relay" if relay_only else "rrd" if rrd else "service")
        return _e2e(1.0, 2.0, 30.0)

    monkeypatch.setattr(e2e_module, "end_to_end", fake)
    done = end_to_end_rounds(demo_config, 1.0, rounds=3, with_rerun=True)
    assert calls == [
        *("service", "relay", "rrd"),
        *("relay", "rrd", "service"),
        *("rrd", "service", "relay"),
    ]
    assert [set(r) for r in done] == [
        {"order", "end_to_end", "transport_floor", "end_to_end_rerun"}
    ] * 3


def test_bench_table_prints_each_rounds_ratio_and_their_median():
    rounds = [
        {"end_to_end": _e2e(1.0, 2.0, 30.0), "transport_floor": _e2e(0.5, 1.0, 30.0)},
        {"end_to_end": _e2e(1.0, 4.0, 30.0), "transport_floor": _e2e(0.5, 4.0, 30.0)},
    ]
    for i, r in enumerate(rounds):
        for e in r.values():
            e["machine"] = {"busy_pct": 60.0, "steal_pct": 0.5 + i}
    rounds[1]["end_to_end"]["machine"]["steal_pct"] = 0.0  # none stolen is a number too
    report = {
        **_table_report(),
        **rounds[0],
        "end_to_end_rounds": rounds,
        "round_ratios": round_ratios(rounds),
    }
    table = bench_table(report)
    assert "p99 x1.50 (median; each round: 2.00, 1.00)" in table
    assert "CPU x1.00 (median; each round: 1.00, 1.00)" in table
    assert "end to end (round 1 of 2)" in table
    assert "| p99 in each round (ms) | service 2.00, 4.00; relay 1.00, 4.00 |" in table
    assert "--rrd over the plain run" not in table  # no --rrd run in these rounds
    assert "(% of all cores) | service 0.5, 0.0; relay 0.5, 1.5 |" in table
    assert "the machine 60 % busy, 0.5 % stolen" in table


def test_machine_share_by_hand():
    before = {"busy": 100, "steal": 10, "all": 1000}
    after = {"busy": 400, "steal": 30, "all": 2000}
    assert machine_share(before, after) == {"busy_pct": 30.0, "steal_pct": 2.0}


def test_a_processs_cpu_is_split_by_its_kind_of_thread():
    """A Python thread (no name of its own) that spends 0.3 s of CPU shows under
    "python_threads", the main thread's own 0.3 s under "event_loop"; a thread named by the
    kernel interface (as Zenoh's are) under "native_threads"."""
    import threading

    from keo_service.bench.machine import thread_cpu_s

    def spin(seconds: float) -> None:
        end = time.thread_time() + seconds
        while time.thread_time() < end:
            pass

    spent, release = threading.Event(), threading.Event()

    def worker(name: str | None) -> None:
        if name is not None:  # the kernel's name of this thread, as a native thread sets it
            with open(f"/proc/self/task/{threading.get_native_id()}/comm", "w") as comm:
                comm.write(name)
        spin(0.3)
        spent.set()
        release.wait(30)  # alive while read: an ended thread leaves /proc

    for name, kind in ((None, "python_threads"), ("rx-test", "native_threads")):
        spent.clear()
        release.clear()
        before = thread_cpu_s(os.getpid())
        thread = threading.Thread(target=worker, args=(name,))
        thread.start()
        assert spent.wait(60)
        after = thread_cpu_s(os.getpid())
        release.set()
        thread.join()
        assert after[kind] - before[kind] >= 0.28  # (whole ticks of 10 ms)
    before = thread_cpu_s(os.getpid())
    spin(0.3)
    assert thread_cpu_s(os.getpid())["event_loop"] - before["event_loop"] >= 0.28


def test_the_machines_busy_time_holds_this_process_own():
    before, own_before = machine_ticks(), os.times()
    end = time.process_time() + 0.3
    while time.process_time() < end:
        pass
    after, own_after = machine_ticks(), os.times()
    # whole ticks: os.times() is in seconds, and 0.3 * 100 is 30.000000000000206 in floats
    own = round((own_after.user + own_after.system - own_before.user - own_before.system) * TICK)
    assert after["busy"] - before["busy"] >= own - 2  # (ticks are counted per core)
    assert after["all"] - before["all"] >= after["busy"] - before["busy"]


def test_the_analyze_benchs_files_are_the_recordings_first_seconds(demo_config, tmp_path):
    scenario = make_scenario("path", {"duration_s": "3.0", "tracker_rate_hz": "200"})
    run = simulate(cell_from_config(demo_config), scenario, seed=4)
    write_run(run, tmp_path)
    head, poses = head_files(run, tmp_path, 1.25)
    tracker, encoder = read_tracker(head / "tracker.csv"), read_encoder(head / "encoder.csv")
    kept = run.tracker.t < 1.25
    assert poses == kept.sum() == tracker.t.size
    assert 200 < poses < 300  # about a quarter of 3 s at 200 Hz: the cut is in time
    np.testing.assert_array_equal(tracker.t, run.tracker.t[kept])
    np.testing.assert_array_equal(tracker.p, run.tracker.p[kept])
    np.testing.assert_array_equal(encoder.t, run.encoder.t[run.encoder.t < 1.25])
    np.testing.assert_array_equal(encoder.q, run.encoder.q[run.encoder.t < 1.25])


def test_correction_latency_takes_each_estimates_first_valid_correction():
    """Joined by stream time: the renewal (a later seq of the same stamp), an invalid one and
    one of no estimate are not counted; the latency is from the tracker's device stamp."""
    from keo_service.bench.end_to_end import correction_latency
    from keo_service.live.messages import CorrectionMessage, EstimateMessage

    def est(stamp: float, device: float) -> EstimateMessage:
        return EstimateMessage(
            stamp=stamp, host_ns=0, channels=[], measured=[], estimate=[], flags=[],
            delay_s=0.0, seq=0, device_stamp=device,
        )  # fmt: skip

    def corr(stamp: float, seq: int, host_s: float, valid: bool = True) -> CorrectionMessage:
        zero = [0.0] * 3
        return CorrectionMessage(
            stamp=stamp, host_ns=round(host_s * 1e9), seq=seq, translation=zero, rotation=zero,
            feedback_translation=zero, feedback_rotation=zero, feedforward_translation=zero,
            feedforward_rotation=zero, valid=valid,
        )  # fmt: skip

    estimates = [(0.0, est(10.0, 100.0)), (0.0, est(10.001, 100.001))]
    corrections = [
        (100.0030, corr(10.0, 7, 100.0020)),  # the first: 3 ms to arrive, 2 ms to publish
        (100.0100, corr(10.0, 8, 100.0090)),  # its renewal: not counted
        (100.0015, corr(10.001, 9, 100.0012, valid=False)),  # invalid: not counted
        (100.0200, corr(55.0, 10, 100.0190)),  # no estimate of that stamp
    ]
    arrived, published = correction_latency(estimates, corrections)
    assert arrived.tolist() == pytest.approx([3.0], abs=1e-6)
    assert published.tolist() == pytest.approx([2.0], abs=1e-3)


def test_bench_table_compares_the_correction_path_with_the_protocol_cycles():
    rounds = []
    for p99 in (1.5, 3.0):
        corr = _e2e(1.0, p99, 40.0)
        corr["correction_latency_ms"] = {"p50": 1.0, "p99": p99, "max": 2 * p99}
        rounds.append(
            {
                "end_to_end": _e2e(1.0, 2.0, 30.0),
                "transport_floor": _e2e(1.0, 2.0, 20.0),
                "end_to_end_correction": corr,
            }
        )
    report = {**_table_report(), "end_to_end_rounds": rounds, "round_ratios": round_ratios(rounds)}
    text = bench_table(report)
    row = next(line for line in text.splitlines() if line.startswith("| correction path"))
    assert "p99 1.50, 3.00 ms" in row
    assert "RSI/EGM 4 ms: within at p99" in row
    assert "RTDE 2 ms: NOT within at p99" in row
    assert "CPU x2.00" in text  # 40 % over the relay's 20 %


def test_bench_table_shows_the_services_cpu_without_its_delay_fits():
    """The fits' worker CPU (the service's `delay_fit_cpu_ms`) is taken off the service's
    CPU within each round: 60 % of a core with 3 s of fits over 30 s is 50 % without them,
    against a relay at 25 %: x2.00."""
    from keo_service.bench.table import _round_rows

    def run(cpu: float, fits_ms: int | None) -> dict:
        counters = {} if fits_ms is None else {"delay_fit_cpu_ms": fits_ms}
        return {
            "seconds": 30.0,
            "processes": {"service": {"cpu_pct": cpu}},
            "latency_ms": {"p50": 1.0, "p99": 2.0},
            "service_counters": counters,
        }

    rounds = [{"end_to_end": run(60.0, 3000), "transport_floor": run(25.0, None)}]
    rows = _round_rows({"end_to_end_rounds": rounds, "round_ratios": round_ratios(rounds)})
    line = next(r for r in rows if "without its delay fits" in r)
    assert "x2.00" in line
    rounds[0]["end_to_end"]["service_counters"] = {}  # runs from before the counter
    rows = _round_rows({"end_to_end_rounds": rounds, "round_ratios": round_ratios(rounds)})
    assert not any("without its delay fits" in r for r in rows)


def test_keo_estimate_is_judged_by_the_wait_against_the_floors_wait():
    """On a busy machine the command and the floor pass both wait for a core: the ratio is
    wall over wall, pair by pair (the command's wall over the floor's CPU charged the wait to
    one side only); CPU over CPU beside it, and the old measure kept for comparison."""
    from keo_service.bench.commands import _pair_ratios

    runs = [
        {"wall_s": 2.0, "cpu_s": 1.0},
        {"wall_s": 3.0, "cpu_s": 1.5},
        {"wall_s": 1.0, "cpu_s": 1.0},
    ]
    got = _pair_ratios(runs, floor_cpu=[2.0, 3.0, 2.0], floor_wall=[4.0, 5.0, 2.0])
    assert got["over_floor_runs"] == [0.5, 0.6, 0.5]
    assert got["over_floor"] == 0.5
    assert got["over_floor_cpu"] == 0.5
    assert got["over_floor_wall_over_cpu"] == 1.0
    assert got["floor_wall_s"] == 4.0
    rec = {**_table_report()["recording"], **got}
    table = bench_table({**_table_report(), "recording": rec})
    assert "command / floor = 0.50 (median of 3 pairs" in table
    assert "(wall over wall)" in table
    assert "4.00 s wall (command wall / floor CPU 1.00)" in table


def test_free_ports_are_not_handed_out_twice():
    """Ports from the kernel's bind(0) repeat within a few hundred draws (about 1 in 15 of
    2000 here): two endpoints of one test then collide. free_port hands out none of the last
    256 it gave."""
    ports = [free_port() for _ in range(300)]
    assert len(set(ports[-256:])) == 256


def test_math_floor_ratios_and_rows_pair_runs_within_their_round():
    from keo_service.bench.table import _round_rows

    rounds = [
        {
            "end_to_end": _e2e(1.0, 3.0, 30.0),
            "transport_floor": _e2e(0.5, 1.0, 20.0),
            "math_floor": _e2e(0.8, 2.0, 25.0),
        },
        {
            "end_to_end": _e2e(1.0, 2.0, 36.0),
            "transport_floor": _e2e(0.5, 2.0, 24.0),
            "math_floor": _e2e(0.8, 2.0, 30.0),
        },
    ]
    r = round_ratios(rounds)
    # by hand: CPU 25/20, 30/24; 30/25, 36/30; p99 2/1, 2/2; 3/2, 2/2
    assert r["math_cpu_over_relay"]["each"] == [1.25, 1.25]
    assert r["service_cpu_over_math"]["each"] == [1.2, 1.2]
    assert r["math_p99_over_relay"]["each"] == [2.0, 1.0]
    assert r["p99_over_math"]["each"] == [1.5, 1.0]
    rows = "\n".join(_round_rows({"end_to_end_rounds": rounds, "round_ratios": r}))
    assert "over the transport floor | CPU x1.25 (median; each round: 1.25, 1.25)" in rows
    assert "keo over that naive math floor | CPU x1.20" in rows
    assert "naive math 2.00, 2.00" in rows  # its p99 in each round
    # a bench without the math floor has no such ratio or row
    plain = [{k: v for k, v in x.items() if k != "math_floor"} for x in rounds]
    assert "math_cpu_over_relay" not in round_ratios(plain)
    assert "naive math" not in "\n".join(
        _round_rows({"end_to_end_rounds": plain, "round_ratios": round_ratios(plain)})
    )


def test_rounds_run_the_math_floor_only_when_asked(monkeypatch, demo_config):
    from keo_service.bench import end_to_end as e2e_module

    calls = []

    def fake(config, seconds, relay_only=False, rrd=False, relay_math=False):
        calls.append("math" if relay_math else "relay" if relay_only else "service")
        return _e2e(1.0, 2.0, 30.0)

    monkeypatch.setattr(e2e_module, "end_to_end", fake)
    end_to_end_rounds(demo_config, 1.0, rounds=1, with_rerun=False)
    assert calls == ["service", "relay"]
    calls.clear()
    done = end_to_end_rounds(demo_config, 1.0, rounds=2, with_rerun=False, with_math=True)
    assert calls == ["service", "relay", "math", "relay", "math", "service"]
    assert set(done[0]) == {"order", "end_to_end", "transport_floor", "math_floor"}


def test_bytecode_cached_tells_a_compiled_module_from_one_compiled_at_each_import(tmp_path):
    import importlib.util
    import py_compile
    import types

    from keo_service.bench.machine import bytecode_cached

    source = tmp_path / "some_module.py"
    source.write_text("x = 1\n")
    module = types.ModuleType("some_module")
    module.__file__ = str(source)
    assert not bytecode_cached(module)
    py_compile.compile(str(source), cfile=importlib.util.cache_from_source(str(source)))
    assert bytecode_cached(module)
    assert not bytecode_cached(types.ModuleType("built_in_like"))  # no file at all


def test_a_worker_that_ends_or_is_replaced_during_a_run_is_measured_not_fatal():
    """The fit worker is replaced when a busy machine starves it, and the one left behind is
    killed: the run's measure keeps the ended one's CPU as last read, lists it, and counts
    the new one (found among the service's children by its command line)."""
    import subprocess
    import sys

    from keo_service.bench.end_to_end import _fold_service_workers, _measure_run

    # the "service": after 0.5 s it starts a second "worker" (the marker in its arguments)
    service = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import subprocess, sys, time\n"
            "time.sleep(0.5)\n"
            "w = subprocess.Popen([sys.executable, '-c', 'import time\\n"
            "t = time.process_time()\\nwhile time.process_time() - t < 0.3: pass\\n"
            "time.sleep(5)', 'multiprocessing.spawn'])\n"
            "time.sleep(5)\n"
            "w.kill()\n",
        ]
    )
    first = subprocess.Popen(
        [sys.executable, "-c", "import time; time.sleep(0.3)", "multiprocessing.spawn"]
    )
    try:
        t0 = time.time() - 0.5
        measured = _measure_run(
            {"service": service.pid, "service-fit-worker": first.pid}, t0, 2.0, None
        )
    finally:
        service.kill()
        first.kill()
        service.wait()
        first.wait()
    procs = measured["processes"]
    assert measured["ended"] == ["service-fit-worker"]
    assert "service-fit-worker#2" in procs
    assert procs["service-fit-worker#2"]["cpu_pct"] > 10.0  # 0.3 s of CPU over 1.5 s
    folded = _fold_service_workers(measured)["processes"]["service"]
    assert folded["cpu_pct"] >= folded["own_cpu_pct"] + procs["service-fit-worker#2"]["cpu_pct"]
