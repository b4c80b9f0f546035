"""The batch path's kinematics chunks between its worker and the calling thread: each chunk
computed once, taken in row order, an error raised where its chunk is taken."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from keo_service.core.batch import _SharedChunks


class _Recorder:
    """Kinematics that return their chunk's start and note which thread ran it; the worker
    waits at its first chunk until `release` is set."""

    def __init__(self) -> None:
        self.release = threading.Event()
        self.worker_waits = threading.Event()
        self.threads: dict[int, str] = {}
        self.lock = threading.Lock()

    def __call__(self, start: int) -> np.ndarray:
        name = threading.current_thread().name
        if name == "keo-batch":
            self.worker_waits.set()
            self.release.wait(timeout=10.0)
        with self.lock:
            assert start not in self.threads  # computed once
            self.threads[start] = name
        return np.array([start])


def test_the_calling_thread_computes_what_the_worker_has_not_taken():
    kinematics = _Recorder()
    starts = range(0, 50, 10)
    chunks = _SharedChunks(kinematics, starts, caller_helps=True)
    try:
        # the worker holds chunk 0; the caller takes the others while it waits for chunk 0
        assert kinematics.worker_waits.wait(timeout=10.0)
        caller = threading.Thread(target=lambda: chunks.result(0))
        caller.start()
        for _ in range(1000):
            if len(kinematics.threads) == len(starts) - 1:
                break
            threading.Event().wait(0.005)
        kinematics.release.set()
        caller.join(timeout=10.0)
        assert [int(chunks.result(i)[0]) for i in range(len(starts))] == list(starts)
    finally:
        chunks.stop()
    assert kinematics.threads[0] == "keo-batch"
    assert all(kinematics.threads[s] != "keo-batch" for s in starts[1:])


def test_without_help_the_worker_computes_every_chunk():
    kinematics = _Recorder()
    kinematics.release.set()
    starts = range(0, 40, 8)
    chunks = _SharedChunks(kinematics, starts, caller_helps=False)
    try:
        got = [int(chunks.result(i)[0]) for i in range(len(starts))]
    finally:
        chunks.stop()
    assert got == list(starts)
    assert set(kinematics.threads.values()) == {"keo-batch"}


def test_an_error_comes_where_its_chunk_is_taken():
    def kinematics(start: int) -> np.ndarray:
        if start == 20:
            raise ValueError("chunk 20")
        return np.array([start])

    chunks = _SharedChunks(kinematics, range(0, 40, 10), caller_helps=True)
    try:
        assert int(chunks.result(0)[0]) == 0
        assert int(chunks.result(1)[0]) == 10
        with pytest.raises(ValueError, match="chunk 20"):
            chunks.result(2)
    finally:
        chunks.stop()


def test_an_exit_in_the_worker_reaches_the_calling_thread_instead_of_hanging_it():
    # not an Exception (KeyboardInterrupt, SystemExit): the chunk's future must still end,
    # or a caller that does not help (compliance) waits for it forever
    def kinematics(start: int) -> np.ndarray:
        raise KeyboardInterrupt(f"chunk {start}")

    chunks = _SharedChunks(kinematics, range(0, 20, 10), caller_helps=False)
    raised: list[BaseException] = []

    def take() -> None:
        try:
            chunks.result(0)
        except BaseException as exc:  # what the calling thread would see
            raised.append(exc)

    caller = threading.Thread(target=take, daemon=True)  # on a thread: a hang fails, not blocks
    caller.start()
    caller.join(timeout=10.0)
    assert not caller.is_alive(), "the calling thread still waits for the chunk"
    chunks.stop()
    assert len(raised) == 1
    assert isinstance(raised[0], KeyboardInterrupt)
    assert str(raised[0]) == "chunk 0"


def test_no_worker_thread_outlives_a_batch_whose_own_work_failed(
    demo_cell, demo_config, monkeypatch
):
    from keo_service.core import batch
    from keo_service.io.cell import estimator_settings
    from keo_service.sim.simulate import make_scenario, simulate

    def failing(*args: object) -> None:
        raise RuntimeError("the verdicts failed")

    monkeypatch.setattr(batch, "_verdicts", failing)
    run = simulate(demo_cell, make_scenario("path", {"duration_s": "3"}), seed=3)
    settings = estimator_settings(demo_config)
    with pytest.raises(RuntimeError, match="the verdicts failed"):
        batch.estimate_batch(
            demo_cell,
            settings,
            run.encoder.t,
            run.encoder.q,
            run.tracker.t,
            run.tracker.p,
            run.tracker.quat,
        )
    assert not [t for t in threading.enumerate() if t.name == "keo-batch" and t.is_alive()]
