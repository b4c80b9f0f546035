"""The delay fits' worker at idle priority (issue 48, the tail): its fits' thread runs at
Linux's `SCHED_IDLE` while the service and the worker's own watch keep the normal policy; a
fit not back within the patience is made again at normal priority, with the same result, and
the later fits stay there."""

from __future__ import annotations

import asyncio
import os
from pathlib import Path

import pytest

from tests.test_fit_worker import _stretches, assert_fits_as_in_process

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
