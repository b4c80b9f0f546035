"""The delay fits in their worker process (issue 48): the same results as in the service's
own process, the worker left alone by stop signals, its BLAS on one thread, and its CPU counted
in the service's figure by the bench."""

from __future__ import annotations

import asyncio
import math
import os
import signal
import time
from pathlib import Path

import pytest

from keo_service.bench.demo import loopback_config


def _stretches(demo_config, demo_cell, count: int, unknown: bool = False):
    """The service's tracker fed a simulated 1 kHz / 250 Hz path as its wire fields, and the
    first `count` stretches it takes (as arrays), each with the guess it would fit from and
    its pool's arrays (`unknown`: no delay configured, so the stretches after the first carry
    a pool for the pooled fit; each stretch is then folded in, as the service does)."""
    from keo_service.fit.delay_online import OnlineDelayTracker, pool_arrays, stretch_arrays
    from keo_service.io.cell import delay_prior
    from keo_service.sim.simulate import make_scenario, simulate

    config = loopback_config(demo_config)
    prior = (0.0, None) if unknown else delay_prior(config.timing)
    tracker = OnlineDelayTracker(demo_cell, None, *prior, max_gap_s=config.timing.max_gap_s)
    fresh = OnlineDelayTracker(demo_cell, None, *prior, max_gap_s=config.timing.max_gap_s)
    sets = {"tracker_rate_hz": "1000", "encoder_rate_hz": "250", "duration_s": "12"}
    run = simulate(demo_cell, make_scenario("path", sets), seed=2)
    rows = sorted(
        [(float(t), 0, i) for i, t in enumerate(run.encoder.t)]
        + [(float(t), 1, i) for i, t in enumerate(run.tracker.t)]
    )
    out = []
    for t, kind, i in rows:
        if kind == 0:
            tracker.add_encoder(t, [float(x) for x in run.encoder.q[i]], 1, i + 1)
        else:
            p = [float(x) for x in run.tracker.p[i]]
            tracker.add_tracker(t, p, [float(x) for x in run.tracker.quat[i]], 1, i + 1)
        if tracker.due():
            current = 0.0 if unknown else config.timing.delay_s
            stretch = tracker.take()
            window, pool = stretch_arrays(stretch), pool_arrays(stretch)
            guess = tracker.guess(current)
            out.append((window, current, guess, pool))
            if unknown:
                tracker.combine(tracker.measure(window, current, guess, pool))
            if len(out) == count:
                break
    return fresh, out


@pytest.mark.parametrize("unknown", [False, True])
def test_the_worker_fits_as_the_service_would(demo_config, demo_cell, unknown):
    """Every stretch's measurement from the worker process equals, field for field, the one
    the tracker makes in this process from the same arrays (its fits' standard errors to
    1e-12 relative: BLAS on one thread may sum in another order), the pooled fit's too when
    the delay is not known; and the worker's CPU time is counted (> 0) for each fit."""
    from keo_service.live.fit_worker import FitWorker

    count = 2 if unknown else 3  # unknown: rough fits lengthen the stretches of the 12 s
    fresh, stretches = _stretches(demo_config, demo_cell, count, unknown)
    assert len(stretches) == count
    assert all(s[3] is None for s in stretches) != unknown  # a pool only while unknown
    worker = FitWorker(fresh)

    async def fit_all():
        return [await worker.measure(w, c, g, p) for w, c, g, p in stretches]

    try:
        found = asyncio.run(fit_all())
    finally:
        worker.close()
    if unknown:  # the pooled fit was made and sent back
        assert any(math.isfinite(got.pooled_s) for got, _cpu in found), found
    assert_fits_as_in_process(fresh, stretches, found)
    assert any(type(g).__name__ == "DelayMeasurement" for g, _cpu in found)


def assert_fits_as_in_process(fresh, stretches, found) -> None:
    """Each fit sent back by a worker equals the same fit made here by `fresh` (floats to
    1e-12 relative: BLAS on one thread may sum in another order), and its CPU was counted."""
    for (window, current, guess, pool), (got, cpu_s) in zip(stretches, found, strict=True):
        want = fresh.measure(window, current, guess, pool)
        assert type(got) is type(want)
        assert cpu_s > 0
        for name, value in vars(want).items():
            other = vars(got)[name]
            if isinstance(value, float):
                assert other == pytest.approx(value, rel=1e-12, abs=1e-15, nan_ok=True), name
            else:
                assert other == value, name


OPENBLAS_GET_THREADS = (
    "scipy_openblas_get_num_threads64_",
    "openblas_get_num_threads64_",
    "openblas_get_num_threads",
)


def blas_threads_here() -> int | None:
    """The thread count numpy's OpenBLAS would compute with in this process (asked through
    its own call in the library mapped here), None where there is no such library (another
    BLAS, not Linux)."""
    import ctypes

    import numpy  # noqa: F401  (loads the library)

    for line in Path("/proc/self/maps").read_text().splitlines():
        fields = line.split(maxsplit=5)
        if len(fields) == 6 and "openblas" in fields[5].lower():
            library = ctypes.CDLL(fields[5])
            for name in OPENBLAS_GET_THREADS:
                if hasattr(library, name):
                    return int(getattr(library, name)())
    return None


def inside_the_worker() -> dict[str, object]:
    """Run in the worker: its own environment's BLAS thread counts, its OpenBLAS's thread
    count and its fits' thread's scheduling policy."""
    from keo_service.live.fit_worker import BLAS_THREADS

    return {
        "environ": {name: os.environ.get(name) for name in BLAS_THREADS},
        "blas_threads": blas_threads_here(),
        "policy": os.sched_getscheduler(0) if hasattr(os, "sched_getscheduler") else None,
    }


def test_the_worker_ignores_stop_signals_and_runs_blas_on_one_thread(demo_cell):
    """A SIGTERM or SIGINT to the worker (a supervisor signalling the whole group) leaves it
    running: the service stops it. Inside the worker its environment asks BLAS for one
    thread and its OpenBLAS computes on one; the service's own environment is left as it
    was."""
    from keo_service.fit.delay_online import OnlineDelayTracker
    from keo_service.live.fit_worker import BLAS_THREADS, FitWorker

    before = {name: os.environ.get(name) for name in BLAS_THREADS}
    worker = FitWorker(OnlineDelayTracker(demo_cell, None, 0.01, 0.001))
    try:
        pid = worker.pid()
        assert {name: os.environ.get(name) for name in BLAS_THREADS} == before
        inside = worker._pool.submit(inside_the_worker).result(30)
        assert inside["environ"] == dict.fromkeys(BLAS_THREADS, "1"), inside
        assert inside["blas_threads"] in (1, None), inside
        os.kill(pid, signal.SIGTERM)
        os.kill(pid, signal.SIGINT)
        time.sleep(0.5)
        assert Path(f"/proc/{pid}").exists()
        assert worker.pid() == pid
    finally:
        worker.close()
    deadline = time.monotonic() + 10
    while Path(f"/proc/{pid}").exists() and time.monotonic() < deadline:
        time.sleep(0.05)
        try:  # reaped by the pool's manager thread; a zombie still has a /proc entry
            if Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z":
                break
        except OSError:
            break
    state = Path(f"/proc/{pid}/stat")
    assert not state.exists() or state.read_text().rsplit(")", 1)[1].split()[0] == "Z"


def _c_environ() -> tuple[int, list[bytes]]:
    """The C library's `environ`: the address of its array (a new one whenever a variable is
    added) and its entries."""
    import ctypes

    environ = ctypes.POINTER(ctypes.c_char_p).in_dll(ctypes.CDLL(None), "environ")
    entries = []
    while (entry := environ[len(entries)]) is not None:
        entries.append(entry)
    return ctypes.cast(environ, ctypes.c_void_p).value or 0, entries


def test_the_services_environment_is_never_changed(demo_config, demo_cell, monkeypatch):
    """Zenoh's native threads may read the service's environment at any time: starting the
    worker and starting another at the fallback (no patience at all: the first fit falls
    back) change none of it, not even for a moment. Every change of `os.environ` goes
    through `os.putenv`/`os.unsetenv`, recorded here; the C library's own array is compared
    before and after (adding a variable moves it)."""
    from keo_service.live import fit_worker
    from keo_service.live.fit_worker import FitWorker

    monkeypatch.setattr(fit_worker, "FIT_PATIENCE_S", 0.0)
    fresh, stretches = _stretches(demo_config, demo_cell, 1)
    changes: list[tuple[str, tuple[object, ...]]] = []
    real_putenv, real_unsetenv = os.putenv, os.unsetenv

    def putenv(*args: object) -> None:
        changes.append(("putenv", args))
        real_putenv(*args)  # type: ignore[arg-type]

    def unsetenv(*args: object) -> None:
        changes.append(("unsetenv", args))
        real_unsetenv(*args)  # type: ignore[arg-type]

    python_before, c_before = dict(os.environ), _c_environ()
    monkeypatch.setattr(os, "putenv", putenv)
    monkeypatch.setattr(os, "unsetenv", unsetenv)
    worker = FitWorker(fresh)

    async def fit():
        return await worker.measure(*stretches[0])

    try:
        worker.pid()
        found = asyncio.run(fit())
        assert not worker.idle  # the fallback happened
        worker.pid()
    finally:
        worker.close()
    monkeypatch.undo()
    assert changes == []
    assert dict(os.environ) == python_before
    assert _c_environ() == c_before
    assert_fits_as_in_process(fresh, stretches, [found])


def test_numpy_loaded_by_the_main_module_still_computes_on_one_thread(demo_cell, tmp_path):
    """The spawn runs the program's main module again in the worker before the worker's
    initializer (keo's own entry points load no numpy there: `keo` imports only the command
    line, `python -m` is not run again): a main module that imports numpy at its top has
    loaded OpenBLAS with its own thread count before the worker sets its environment. The
    worker's OpenBLAS computes on one thread all the same. Can fail only on a machine with
    more than one core (OpenBLAS's own count is the cores')."""
    from tests.conftest import DEMO, run_script

    if blas_threads_here() is None:
        pytest.skip("no OpenBLAS found in this process's libraries")
    script = tmp_path / "embedding.py"
    script.write_text(
        "import numpy  # at the top: run again in the worker before its initializer\n"
        "from keo_service.fit.delay_online import OnlineDelayTracker\n"
        "from keo_service.io.cell import cell_from_config\n"
        "from keo_service.io.config import load_config\n"
        "from keo_service.live.fit_worker import FitWorker\n"
        "from tests.test_fit_worker import inside_the_worker\n"
        "if __name__ == '__main__':\n"
        f"    cell = cell_from_config(load_config({str(DEMO)!r}))\n"
        "    worker = FitWorker(OnlineDelayTracker(cell, None, 0.01, 0.001))\n"
        "    print(worker._pool.submit(inside_the_worker).result(60)['blas_threads'])\n"
        "    worker.close()\n"
    )
    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}
    done = run_script(script, env)
    assert done.stdout.split() == ["1"], done.stdout + done.stderr


def test_the_bench_counts_the_services_workers_in_its_cpu():
    """The end-to-end run's service CPU is its own process's plus its fit worker's (and the
    worker's helper's); the Rerun process stays apart."""
    from keo_service.bench.end_to_end import _fold_service_workers

    def proc(cpu: float) -> dict[str, float]:
        return {"cpu_pct": cpu, "peak_rss_mb": 1.0, "rss_growth_mb": 0.0}

    measured = {
        "processes": {
            "service": proc(30.0),
            "service-fit-worker": proc(4.0),
            "service-mp-helper": proc(0.5),
            "rerun-process": proc(7.0),
            "relay": proc(99.0),
        }
    }
    out = _fold_service_workers(measured)["processes"]["service"]
    assert out["cpu_pct"] == pytest.approx(34.5)
    assert out["own_cpu_pct"] == pytest.approx(30.0)
    relay = {"processes": {"service": proc(25.0), "mock-robot": proc(8.0)}}
    assert _fold_service_workers(relay)["processes"]["service"] == proc(25.0)


@pytest.mark.parametrize("quats", [True, False])
def test_a_stretchs_arrays_map_its_stamps_row_by_row(quats):
    """`stretch_arrays` (on the loop: a stretch's rows as arrays, its mapped stamps under
    their lines) gives what mapping each row on its own gives: a device stamp carried by the
    stream's line, its own stamp without one; joints, positions, quaternions or None for a
    single reflector; and no encoder rows at all as an empty (0, 0) joints array."""
    import math

    import numpy as np

    from keo_service.fit.delay_online import Stretch, stretch_arrays
    from keo_service.fit.stamp_lines import Anchor

    rng = np.random.default_rng(5)
    nan = math.nan
    enc = [
        (0.004 * i, *rng.normal(size=6), nan if i % 7 == 0 else 100.0 + 0.004 * i)
        for i in range(300)
    ]
    trk = [
        (
            0.001 * i,
            *rng.normal(size=3),
            *(rng.normal(size=4) if quats else (nan,) * 4),
            nan if i % 11 == 0 else 50.0 + 0.001 * i,
        )
        for i in range(1100)
    ]
    enc_line, trk_line = Anchor(0.5, 100.5, 3e-6), Anchor(0.2, 50.2, -2e-6)

    def row_stamp(line, row):
        device = row[-1]
        if math.isnan(device):
            return row[0]
        return line.stamp + (device - line.device) * (1.0 + line.drift)

    stretch = Stretch(np.array(enc), np.array(trk), enc_line, trk_line)
    got = stretch_arrays(stretch)
    assert np.array_equal(got[0], [row_stamp(enc_line, r) for r in enc])
    assert np.array_equal(got[1], [r[1:7] for r in enc])
    assert np.array_equal(got[2], [row_stamp(trk_line, r) for r in trk])
    assert np.array_equal(got[3], [r[1:4] for r in trk])
    if quats:
        assert got[4] is not None
        assert np.array_equal(got[4], [r[4:8] for r in trk])
    else:
        assert got[4] is None
    # no encoder rows at all: an empty joints array, as the fit expects
    bare = Stretch(np.empty((0, 8)), np.array(trk), None, None)
    got = stretch_arrays(bare)
    assert got[1].shape == (0, 0)
    assert np.array_equal(got[2], [r[0] for r in trk])


def _gone(pid: int) -> bool:
    """No process `pid`, or only its zombie (exited, not yet reaped)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except OSError:
        return True


def test_the_worker_ends_when_the_service_is_killed_outright(demo_cell, tmp_path):
    """A service killed with SIGKILL (or by the OOM killer) cannot shut its worker down; the
    worker, which ignores SIGINT and SIGTERM and holds both ends of its pool's pipes, must
    notice and exit by itself instead of waiting for work for good."""
    import subprocess
    import sys

    from tests.conftest import DEMO

    script = tmp_path / "service.py"
    script.write_text(
        "import sys, time\n"
        "from keo_service.fit.delay_online import OnlineDelayTracker\n"
        "from keo_service.live.fit_worker import FitWorker\n"
        "from keo_service.io.cell import cell_from_config\n"
        "from keo_service.io.config import load_config\n"
        f"cell = cell_from_config(load_config({str(DEMO)!r}))\n"
        "if __name__ == '__main__':\n"
        "    worker = FitWorker(OnlineDelayTracker(cell, None, 0.01, 0.001))\n"
        "    print(worker.pid(), flush=True)\n"
        "    time.sleep(60)\n"
    )
    repo = Path(__file__).resolve().parent.parent
    service = subprocess.Popen(
        [sys.executable, str(script)], stdout=subprocess.PIPE, text=True, cwd=repo
    )
    try:
        assert service.stdout is not None
        pid = int(service.stdout.readline())
        assert not _gone(pid)
        service.kill()  # SIGKILL: no shutdown of the pool
        service.wait(timeout=10)
        deadline = time.monotonic() + 10
        while not _gone(pid) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert _gone(pid), f"the worker {pid} outlived its service"
    finally:
        service.kill()
