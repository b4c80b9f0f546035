"""The delay fits' worker at idle priority (issue 48, the tail): its fits' thread runs at
Linux's `SCHED_IDLE` while the service and the worker's own watch keep the normal policy; a
fit not back within the patience is made again at normal priority, with the same result, and
the later fits stay there."""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.test_fit_worker import (
    _gone,
    _stretches,
    assert_fits_as_in_process,
    inside_the_worker,
)

pytestmark = pytest.mark.skipif(
    not hasattr(os, "SCHED_IDLE"), reason="the idle scheduling policy is Linux's"
)


def _policies(pid: int) -> dict[str, list[int]]:
    """The scheduling policy of the process's main thread (which runs the fits) and of its
    other threads (the watch)."""
    out: dict[str, list[int]] = {"main": [], "others": []}
    for task in Path(f"/proc/{pid}/task").iterdir():
        out["main" if int(task.name) == pid else "others"].append(
            os.sched_getscheduler(int(task.name))
        )
    return out


def test_the_fits_thread_runs_at_idle_priority(demo_cell):
    from keo_service.fit.delay_online import OnlineDelayTracker
    from keo_service.live.fit_worker import FitWorker

    worker = FitWorker(OnlineDelayTracker(demo_cell, None, 0.01, 0.001))
    try:
        policies = _policies(worker.pid())
    finally:
        worker.close()
    assert policies["main"] == [os.SCHED_IDLE], policies
    assert policies["others"], policies  # the watch
    assert set(policies["others"]) == {os.SCHED_OTHER}, policies
    assert os.sched_getscheduler(0) == os.SCHED_OTHER  # the service's own is left alone


def test_a_starved_fit_is_made_again_at_normal_priority(
    demo_config, demo_cell, monkeypatch, caplog
):
    """With no patience at all every fit at idle priority counts as starved: the first is
    made again by a worker at normal priority, with the result the tracker makes in this
    process, and the second goes to that worker directly."""
    from keo_service.live import fit_worker
    from keo_service.live.fit_worker import FitWorker

    monkeypatch.setattr(fit_worker, "FIT_PATIENCE_S", 0.0)
    fresh, stretches = _stretches(demo_config, demo_cell, 2)
    worker = FitWorker(fresh)
    first_pid = worker.pid()

    async def fit_all():
        return [await worker.measure(w, c, g, p) for w, c, g, p in stretches]

    try:
        found = asyncio.run(fit_all())
        assert not worker.idle
        second_pid = worker.pid()
        assert _policies(second_pid)["main"] == [os.SCHED_OTHER]
    finally:
        worker.close()
    assert second_pid != first_pid
    assert sum("normal priority" in r.getMessage() for r in caplog.records) == 1
    assert_fits_as_in_process(fresh, stretches, found)


@contextlib.contextmanager
def _this_thread_at(policy: int) -> Iterator[None]:
    """The calling thread at scheduling `policy` meanwhile, its own restored after."""
    previous = os.sched_getscheduler(0), os.sched_getparam(0)
    os.sched_setscheduler(0, policy, os.sched_param(0))
    try:
        yield
    finally:
        os.sched_setscheduler(0, *previous)


def test_the_fits_keep_no_policy_of_the_service(demo_cell):
    """A process started by a service at another policy than the normal one inherits it (the
    systemd unit's commented real-time line; here SCHED_BATCH, which an unprivileged process
    may set and leave): the fits' thread of a worker at normal priority (the fallback's)
    computes at SCHED_OTHER all the same, an idle worker's at SCHED_IDLE, and the watch of
    either at SCHED_OTHER."""
    from keo_service.fit.delay_online import OnlineDelayTracker
    from keo_service.live.fit_worker import FitWorker

    tracker = OnlineDelayTracker(demo_cell, None, 0.01, 0.001)
    with _this_thread_at(os.SCHED_BATCH):
        normal, idle = FitWorker(tracker, idle=False), FitWorker(tracker)  # started here
    try:
        normal_policies, idle_policies = _policies(normal.pid()), _policies(idle.pid())
        inside = normal._pool.submit(inside_the_worker).result(30)
    finally:
        normal.close()
        idle.close()
    assert os.sched_getscheduler(0) == os.SCHED_OTHER  # the test's own, restored
    assert inside["policy"] == os.SCHED_OTHER, inside
    assert normal_policies == {"main": [os.SCHED_OTHER], "others": [os.SCHED_OTHER]}
    assert idle_policies == {"main": [os.SCHED_IDLE], "others": [os.SCHED_OTHER]}


def _stopped_idle_worker(demo_config, demo_cell, monkeypatch, grace_s: float):
    """A worker whose fits all count as starved, its process stopped (SIGSTOP: its fit never
    gets a core), and the grace after the fallback `grace_s`."""
    from keo_service.live import fit_worker
    from keo_service.live.fit_worker import FitWorker

    monkeypatch.setattr(fit_worker, "FIT_PATIENCE_S", 0.0)
    monkeypatch.setattr(fit_worker, "STARVED_GRACE_S", grace_s, raising=False)
    fresh, stretches = _stretches(demo_config, demo_cell, 1)
    worker = FitWorker(fresh)
    starved_pid = worker.pid()
    os.kill(starved_pid, signal.SIGSTOP)
    return worker, starved_pid, fresh, stretches


def test_a_starved_worker_is_killed_after_the_grace(demo_config, demo_cell, monkeypatch):
    """The worker left behind at the fallback, its fit never run, is gone once the grace has
    passed, and so is its pool's thread; no task is left on the loop for it. The fit itself
    came back from the new worker as the tracker makes it in this process."""
    worker, starved_pid, fresh, stretches = _stopped_idle_worker(
        demo_config, demo_cell, monkeypatch, grace_s=0.5
    )
    manager = worker._pool._executor_manager_thread
    assert manager is not None

    async def fit_then_wait():
        found = await worker.measure(*stretches[0])
        deadline = time.monotonic() + 20
        while (not _gone(starved_pid) or manager.is_alive()) and time.monotonic() < deadline:
            await asyncio.sleep(0.05)
        return found, asyncio.all_tasks() - {asyncio.current_task()}

    try:
        found, tasks = asyncio.run(fit_then_wait())
        gone = _gone(starved_pid)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.kill(starved_pid, signal.SIGKILL)  # on the code before: never ends by itself
        worker.close()
    assert gone, f"the starved worker {starved_pid} is still there"
    assert not manager.is_alive()
    assert tasks == set()
    assert_fits_as_in_process(fresh, stretches, [found])


def test_closing_kills_a_starved_worker_at_once(demo_config, demo_cell, monkeypatch):
    """Closed within the grace (the service stopping), the worker left behind at the
    fallback is killed then, not left to the timer of a loop that may be gone."""
    worker, starved_pid, _fresh, stretches = _stopped_idle_worker(
        demo_config, demo_cell, monkeypatch, grace_s=600.0
    )

    async def fit():
        await worker.measure(*stretches[0])

    try:
        asyncio.run(fit())
        assert not _gone(starved_pid)  # within the grace
        worker.close()
        deadline = time.monotonic() + 20
        while not _gone(starved_pid) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert _gone(starved_pid), f"the starved worker {starved_pid} is still there"
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.kill(starved_pid, signal.SIGKILL)
        worker.close()


def _spawns_recorded(monkeypatch, delay_s: float = 0.0) -> list[dict[str, object]]:
    """Each worker spawned from now on: the thread that spawned it (is it the main one, which
    runs the loop?), its priority and its processes; `delay_s`: the spawn starts that late."""
    from keo_service.live import fit_worker

    real = fit_worker._spawn
    spawns: list[dict[str, object]] = []

    def spawn(state: bytes, idle: bool):
        time.sleep(delay_s)
        pool, started = real(state, idle)
        spawns.append(
            {
                "on_main_thread": threading.current_thread() is threading.main_thread(),
                "idle": idle,
                "pids": [p.pid for p in (pool._processes or {}).values()],
                "pool": pool,  # held here: its worker must end on a shutdown, not on its GC
            }
        )
        return pool, started

    monkeypatch.setattr(fit_worker, "_spawn", spawn)
    return spawns


def test_the_fallbacks_worker_is_spawned_off_the_loop(demo_config, demo_cell, monkeypatch):
    """The worker at normal priority that the fallback starts is spawned on another thread
    than the loop's, and the fit comes back from it as the tracker makes it here."""
    worker, _starved_pid, fresh, stretches = _stopped_idle_worker(
        demo_config, demo_cell, monkeypatch, grace_s=600.0
    )
    spawns = _spawns_recorded(monkeypatch)

    async def fit():
        return await worker.measure(*stretches[0])

    try:
        found = asyncio.run(fit())
    finally:
        worker.close()
    assert [(s["on_main_thread"], s["idle"]) for s in spawns] == [(False, False)], spawns
    assert worker.pid() in spawns[0]["pids"]  # type: ignore[operator]
    assert_fits_as_in_process(fresh, stretches, [found])


def test_a_service_stopping_during_the_fallbacks_spawn_leaves_no_worker(
    demo_config, demo_cell, monkeypatch
):
    """The service stops (its delay task cancelled, the worker closed) while the fallback's
    new worker is still being spawned: both that worker and the starved one end, and the
    loop is not held by the spawn meanwhile."""
    worker, starved_pid, _fresh, stretches = _stopped_idle_worker(
        demo_config, demo_cell, monkeypatch, grace_s=600.0
    )
    spawns = _spawns_recorded(monkeypatch, delay_s=1.5)

    async def stop_during_the_spawn() -> float:
        fit = asyncio.create_task(worker.measure(*stretches[0]))
        ticks = time.monotonic()
        for _ in range(10):  # the loop turns while the spawn waits on its thread
            await asyncio.sleep(0.03)
        loop_free_s = time.monotonic() - ticks
        fit.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await fit
        worker.close()
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and not (
            spawns and all(_gone(pid) for pid in [starved_pid, *spawns[0]["pids"]])  # type: ignore[misc]
        ):
            await asyncio.sleep(0.05)
        return loop_free_s

    try:
        loop_free_s = asyncio.run(stop_during_the_spawn())
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.kill(starved_pid, signal.SIGKILL)
        worker.close()
    assert loop_free_s < 1.2  # 0.3 s of sleeps: the 1.5 s spawn did not hold the loop
    assert len(spawns) == 1, spawns
    assert spawns[0]["pids"], spawns
    assert _gone(starved_pid), f"the starved worker {starved_pid} is still there"
    left = [pid for pid in spawns[0]["pids"] if not _gone(pid)]  # type: ignore[attr-defined]
    assert left == [], f"the fallback's worker {left} is still there"
