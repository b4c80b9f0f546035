"""Rerun runs in its own process: the service only buffers and writes a pipe, never blocks,
counts drops, and learns when the process dies."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from rerun.chunk import RrdReader

from keo_service.core.estimator import Estimate
from keo_service.core.kinematics import POSE_CHANNELS
from keo_service.live.rerun_logger import RerunLogger
from keo_service.live.rerun_process import RerunWorker, _frame, _Frames


def _estimate(t: float) -> Estimate:
    e = [1e-4] * 6
    return Estimate(t, e, e, (), t, POSE_CHANNELS, np.zeros(6))


def _rows(rrd, entity: str) -> int:
    chunks = [c for c in RrdReader(str(rrd)).stream().to_chunks() if not c.is_static]
    return sum(c.num_rows for c in chunks if c.entity_path == entity)


def test_a_full_buffer_drops_and_counts_without_blocking(demo_cell, tmp_path):
    rrd = tmp_path / "w.rrd"
    worker = RerunWorker(demo_cell, rrd=rrd, max_buffer=20_000)
    started = time.perf_counter()
    for i in range(1000):  # no process yet: the buffer fills
        worker.submit(_estimate(i * 0.001))
    took = time.perf_counter() - started
    kept = 1000 - worker.dropped
    assert 0 < kept < 1000  # the bound held, and what fitted was kept
    assert took < 0.5  # 1000 non-blocking submits
    worker.start()
    worker.close(timeout=30.0)  # the child imports Rerun and Pinocchio first
    assert worker.failure is None
    assert _rows(rrd, "/keo/error/px") == kept  # what was buffered reached the file, no more


def test_every_estimate_of_a_steady_stream_reaches_the_file(demo_cell, tmp_path):
    rrd = tmp_path / "s.rrd"
    worker = RerunWorker(demo_cell, rrd=rrd)
    for i in range(3000):  # more than a pipe holds, before the child can read any of it
        worker.submit(_estimate(i * 0.001))
        if i % 500 == 0:
            worker.submit({"delay_s": 0.004, "counters": {"rejected": i}})
    worker.start()
    worker.close(timeout=30.0)  # the child is still importing Rerun: close waits for it
    assert worker.failure is None
    assert worker.dropped == 0
    assert _rows(rrd, "/keo/error/rz") == 3000
    assert _rows(rrd, "/keo/status/delay/in_use") >= 1  # the status snapshots came along
    assert _rows(rrd, "/world/tool") >= 1  # the scene from the joints that came along


def test_the_rerun_process_and_its_threads_run_on_idle_time_only(demo_cell, tmp_path):
    """SCHED_IDLE on every thread of the process once it is set up: those its imports
    started (numpy's BLAS pool) and Rerun's."""
    rrd = tmp_path / "i.rrd"
    worker = RerunWorker(demo_cell, rrd=rrd)
    worker.start()
    for i in range(200):
        worker.submit(_estimate(i * 0.001))
    assert worker._proc is not None
    tasks = Path(f"/proc/{worker._proc.pid}/task")
    deadline = time.monotonic() + 30.0  # the child imports Rerun and Pinocchio first
    policies: list[int] = []
    while time.monotonic() < deadline:
        # the recording's file exists only once the child runs its sink: before that, the
        # import threads alone would be counted; the policy follows the set-up at once
        if rrd.exists():
            with contextlib.suppress(OSError):  # a thread that ended meanwhile
                policies = [os.sched_getscheduler(int(t.name)) for t in tasks.iterdir()]
            # the main thread, numpy's pool and Rerun's own
            if len(policies) >= 3 and set(policies) == {os.SCHED_IDLE}:
                break
        time.sleep(0.05)
    worker.close(timeout=30.0)
    assert worker.failure is None
    assert len(policies) >= 3
    assert set(policies) == {os.SCHED_IDLE}


def test_a_dead_process_is_reported_to_the_supervisor(demo_cell, tmp_path):
    blocked = tmp_path / "file"
    blocked.write_text("")
    worker = RerunWorker(demo_cell, rrd=blocked / "x.rrd")  # its folder cannot be made
    worker.start()
    deadline = time.monotonic() + 30.0
    while not isinstance(worker.failure, RuntimeError) and time.monotonic() < deadline:
        worker.submit(_estimate(0.0))  # never raises, even once the pipe is broken
        time.sleep(0.05)
    assert "exited with code 1" in str(worker.failure)  # also when a write saw the pipe first
    worker.close()


def test_a_long_recording_rolls_into_files_of_one_recording(demo_cell, tmp_path):
    """The SDK holds an index entry per chunk of an open file: a daemon's recording is split
    into files so that closing one frees them; each file whole, one recording id across."""
    rrd = tmp_path / "cell.rrd"
    sink = RerunLogger(demo_cell, rrd=rrd, roll_after_s=0.0)  # due at every batch
    for batch in range(3):
        for i in range(100):
            sink.add(_estimate(batch * 0.1 + i * 0.001))
        sink.flush()
    sink.close()
    files = [rrd, tmp_path / "cell-0001.rrd", tmp_path / "cell-0002.rrd"]
    assert sorted(tmp_path.iterdir()) == sorted(files)  # no empty file at the end
    ids = set()
    for path in files:
        reader = RrdReader(str(path))
        ids |= {entry.recording_id for entry in reader.recordings()}
        chunks = list(reader.stream().to_chunks())
        static = {c.entity_path for c in chunks if c.is_static}
        assert {"/world/tracker", "/keo/error/px"} <= static  # frames and series style in each
        assert _rows(path, "/keo/error/px") == 100
    assert len(ids) == 1


def test_a_backlog_is_offered_to_the_pipe_once_per_write_size_not_per_estimate(
    demo_cell, monkeypatch
):
    """A child still starting (or one that cannot keep up) leaves a backlog; the service must
    not pay a refused write per estimate meanwhile."""
    import os

    from keo_service.live import rerun_process

    read_end, write_end = os.pipe()
    os.set_blocking(write_end, False)
    with contextlib.suppress(BlockingIOError):
        while True:  # a pipe nobody reads: full
            os.write(write_end, b"x" * 65536)
    tries = []
    real_write = os.write

    def counting_write(fd: int, data: bytes) -> int:
        tries.append(len(data))
        return real_write(fd, data)

    worker = RerunWorker(demo_cell)
    worker._fd = write_end  # the pipe of a child that reads nothing yet
    monkeypatch.setattr(rerun_process.os, "write", counting_write)
    for i in range(2000):
        worker.submit(_estimate(i * 0.001))
    monkeypatch.undo()
    submitted = len(worker._buffer)
    assert submitted > 20 * rerun_process.WRITE_AT  # the backlog built up
    assert 0 < len(tries) <= submitted // rerun_process.WRITE_AT + 1
    os.close(read_end)
    os.close(write_end)


@pytest.mark.parametrize("piece", [1, 3, 7, 1000])
def test_frames_survive_any_split_of_the_stream(piece):
    payloads = [b"", b"a", b"x" * 300, bytes(range(256))]
    stream = b"".join(_frame(p) for p in payloads)
    frames = _Frames()
    got = []
    for lo in range(0, len(stream), piece):
        got.extend(frames.feed(stream[lo : lo + piece]))
    assert got == payloads


def _child(worker: RerunWorker, code: str) -> subprocess.Popen[bytes]:
    """A stand-in for the Rerun process on the worker's pipe: `code` reads stdin."""
    proc = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE)
    assert proc.stdin is not None
    worker._proc, worker._fd = proc, proc.stdin.fileno()
    os.set_blocking(worker._fd, False)
    return proc


def test_a_slow_but_reading_child_gets_its_whole_backlog_at_shutdown(demo_cell, tmp_path):
    """A niced child on a loaded machine reads slowly: the shutdown waits while it makes
    progress (a fixed 0.75 s for the buffer lost the end of the recording under load)."""
    counted = tmp_path / "read"
    worker = RerunWorker(demo_cell)
    for i in range(3000):  # about 0.6 MB: two seconds for the child below
        worker.submit(_estimate(i * 0.001))
    backlog = len(worker._buffer)
    assert worker.dropped == 0
    assert backlog > 500_000
    _child(
        worker,
        "import sys, time\n"
        "n = 0\n"
        "while chunk := sys.stdin.buffer.read1(16384):\n"
        "    n += len(chunk)\n"
        "    time.sleep(0.05)\n"
        f"open({str(counted)!r}, 'w').write(str(n))\n",
    )
    worker.close(timeout=1.5)
    assert not worker._buffer
    assert int(counted.read_text()) == backlog  # every byte reached the child


def test_a_child_that_reads_nothing_is_stopped_within_the_bound(demo_cell):
    worker = RerunWorker(demo_cell)
    for i in range(500):
        worker.submit(_estimate(i * 0.001))
    proc = _child(worker, "import time\ntime.sleep(60)\n")
    started = time.monotonic()
    worker.close(timeout=1.0, most=2.0)
    assert time.monotonic() - started < 2.0 + 1.0  # the bound, plus the kill's reaping
    assert proc.returncode is not None  # killed, not left behind


def test_the_rerun_process_sets_up_on_a_share_of_the_cpu_not_idle_time():
    """Under SCHED_IDLE on a loaded machine the set-up (Rerun's import, the recording opened)
    could outlast a short run, and the stop found a process that had read nothing: until set
    up it runs niced, not idle. Here it waits for its first frame (none is sent)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "keo_service.live.rerun_process"], stdin=subprocess.PIPE
    )
    try:
        deadline = time.monotonic() + 30.0  # its module's imports first
        niced = False
        while time.monotonic() < deadline and not niced:
            niced = os.getpriority(os.PRIO_PROCESS, proc.pid) >= min(19, os.nice(0) + 10)
            time.sleep(0.05)
        assert niced
        assert os.sched_getscheduler(proc.pid) == os.SCHED_OTHER
    finally:
        assert proc.stdin is not None
        proc.stdin.close()  # end of file before it began: it exits 0
        assert proc.wait(timeout=30) == 0
