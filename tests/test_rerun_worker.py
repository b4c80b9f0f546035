"""Rerun runs on its own thread: the event loop only enqueues, never blocks, counts drops."""

from __future__ import annotations

import time

import numpy as np
from rerun.chunk import RrdReader

from keo_service.core.estimator import Estimate
from keo_service.core.kinematics import POSE_CHANNELS
from keo_service.live.rerun_sink import RerunSink, RerunWorker


def _estimate(t: float) -> Estimate:
    e = np.full(6, 1e-4)
    return Estimate(t, e, e, (), t, POSE_CHANNELS, np.zeros(6))


def test_a_full_queue_drops_and_counts_without_blocking(demo_cell, tmp_path):
    rrd = tmp_path / "w.rrd"
    worker = RerunWorker(lambda: RerunSink(demo_cell, rrd=rrd), maxsize=100)
    started = time.perf_counter()
    for i in range(1000):  # the thread is not running yet: the queue fills
        worker.submit(_estimate(i * 0.001))
    took = time.perf_counter() - started
    assert worker.dropped == 900
    assert took < 0.5  # 1000 non-blocking puts, not 900 waits
    worker.start()
    started = time.perf_counter()
    worker.close()
    assert time.perf_counter() - started < 2.0
    assert worker.failure is None
    chunks = [c for c in RrdReader(str(rrd)).stream().to_chunks() if not c.is_static]
    rows = sum(c.num_rows for c in chunks if c.entity_path == "/keo/error/px")
    assert rows == 100  # what was queued reached the file, nothing more


def test_a_failure_on_the_thread_is_kept_for_the_supervisor(demo_cell):
    def broken() -> RerunSink:
        raise OSError("disk full")

    worker = RerunWorker(broken)
    worker.start()
    worker.close()
    assert isinstance(worker.failure, OSError)
