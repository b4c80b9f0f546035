"""The online delay tracker's fits in a process of their own.

A fit is a sizeable piece of numpy and Python every stretch (2-2.5 s of data). On a thread of
the service it held the GIL in its Python parts, and the samples that arrived meanwhile
waited for it; numpy's BLAS also ran threads of its own for the fit's linear algebra, which
on a small machine spun on the cores the data path needed (docs/performance.md has the
figures). Here the service's event loop only takes the stretch from the tracker's bounded
buffers (slices of its row arrays) and maps its stamps (between samples), hands them to one
worker process and awaits the result, which it folds in between samples as before.

Bounded: one process, one fit at a time (the delay loop awaits each before it takes the next
stretch), a stretch's arrays as its only input. The worker holds a copy of the tracker made
when the service started (its settings: `OnlineDelayTracker.measure` reads nothing else once
given the `guess` the service's tracker made). It sets for itself, in its own process, numpy's
BLAS on one thread (before numpy loads there, or through OpenBLAS's own call when the
program's main module had loaded it) and glibc's allocator keeping freed memory for the next
fit (`mallopt`; a setting the user made in the environment is kept): the service's
environment is never changed, since Zenoh's native threads may read it at any time. It
ignores SIGINT and SIGTERM (a supervisor that signals the whole group stops the service,
which then shuts the worker down); when nothing shut it down, it exits by itself within a
second of the service's death.

The worker computes at the idle scheduling priority (Linux's `SCHED_IDLE`): a fit takes a core
for 50-150 ms, and on a small machine the samples that meanwhile waited for a core behind it
made most of the service's slowest estimates (docs/performance.md, Round 12b). At idle priority
any other runnable thread of its scheduling group (the service's session or cgroup) takes the
core first. A fit that has not come back after `FIT_PATIENCE_S` (a machine kept busy by the
service's own group would starve it) is run again in a worker at normal priority, which then
takes every later fit: the result is the same, only later. That worker is spawned on a thread
of its own, not the loop's (its start holds the caller for milliseconds, on a machine that is
busy already); the starved worker is shut down, and killed if it has not exited
`STARVED_GRACE_S` later (or when the worker is closed). "Normal" is `SCHED_OTHER` whatever the
service runs at: a service at a real-time policy passes it on to the processes it starts, and a
fit there would hold a core against everything else.

A worker that dies is a failure of the service's delay task, as any task's
(`concurrent.futures.process.BrokenProcessPool`).
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import logging
import multiprocessing
import multiprocessing.connection
import os
import pickle
import signal
import sys
import threading
import time
from concurrent.futures import Future, ProcessPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from multiprocessing import Process

    import numpy as np

    from keo_service.fit.delay_online import (
        DelayMeasurement,
        DelayRefused,
        OnlineDelayTracker,
    )

    Window = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]

__all__ = ["FitWorker"]

# the thread counts numpy's BLAS builds read when they load: one, in the worker
BLAS_THREADS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
# glibc's `mallopt` parameters (its malloc.h)
M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
# glibc's allocator in the worker, set there by `mallopt` (other C libraries: nothing): a
# fit's arrays (up to a few MB each) from the heap, and up to 128 MB of freed heap kept for
# the next fit, instead of each fit mapping fresh pages from the kernel and giving them back
# (a page fault per 4 kB: docs/performance.md, Round 11). Bounded by the largest fit's peak.
# 32 MB is the highest mmap threshold glibc before 2.35 accepts (half its 64-bit heap size);
# beyond it those versions refuse the setting. Keyed by the variable (and the tunable) by
# which a user sets the same in the service's environment: a value set there is left as it is.
WORKER_MALLOC = {
    "MALLOC_MMAP_THRESHOLD_": ("glibc.malloc.mmap_threshold", M_MMAP_THRESHOLD, 32 * 2**20),
    "MALLOC_TRIM_THRESHOLD_": ("glibc.malloc.trim_threshold", M_TRIM_THRESHOLD, 128 * 2**20),
}
# the calls that set the thread count of an OpenBLAS already loaded, by build: numpy's own
# wheels (2.x, then 1.x), a system library
OPENBLAS_SET_THREADS = (
    "scipy_openblas_set_num_threads64_",
    "openblas_set_num_threads64_",
    "openblas_set_num_threads",
)

# how often the worker checks that the service is still there (s): a worker orphaned by a
# service killed outright ends within this
SERVICE_CHECK_S = 1.0
# how long a fit at idle priority may take before it runs again at normal priority (s): a fit
# takes 50-150 ms of a core, a starved one has not come back after many times that
FIT_PATIENCE_S = 2.0
# how long the worker left behind at that fallback may take to finish its fit and exit before
# it is killed (s): the fit takes 50-150 ms of a core once it gets one, and its outcome is
# read by no one; a worker that still has no core after this holds about 100 MB for nothing
STARVED_GRACE_S = 5.0

log = logging.getLogger("keo.service")

# in the worker: the service's tracker as it was at start (set once, by `_start`)
_worker: dict[str, OnlineDelayTracker] = {}


def _start(state: bytes, service_pid: int, idle: bool = False) -> None:
    """The worker's initializer: the stop signals left to the service, the normal scheduling
    policy (whatever the service's is), BLAS on one thread and the allocator's settings set
    here (never in the service: see `FitWorker`), its tracker, a watch that ends the worker
    once the service is gone, and (`idle`) the fits' thread at idle priority."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    # a service at a real-time policy (the systemd unit's commented line) would pass it on:
    # fits of 50-150 ms would then hold a core against everything else. Set before the
    # watch starts, which takes it over (Linux's policy is per thread)
    _compute_at("SCHED_OTHER")
    numpy_loaded = "numpy" in sys.modules  # by the program's main module, run again here
    os.environ.update(dict.fromkeys(BLAS_THREADS, "1"))  # read as numpy loads, with the tracker
    _keep_freed_memory()
    _worker["tracker"] = pickle.loads(state)
    if numpy_loaded:
        _one_thread_for_loaded_blas()
    watch = threading.Thread(
        target=_exit_with_service, args=(service_pid,), name="keo-service-watch", daemon=True
    )
    watch.start()  # before the idle policy: the watch keeps the normal one
    if idle:
        _compute_at("SCHED_IDLE")


def _compute_at(policy_name: str) -> None:
    """The calling thread (the one that runs the fits) at the scheduling policy `os.<name>`,
    where the system has it (Linux); elsewhere, or where it is refused, it stays as it is."""
    policy = getattr(os, policy_name, None)
    if policy is not None:
        with contextlib.suppress(OSError):
            os.sched_setscheduler(0, policy, os.sched_param(0))


def _keep_freed_memory() -> None:
    """In the worker: glibc's allocator as `WORKER_MALLOC` says, each setting the user has not
    made in the environment. glibc reads its variables at the process's first allocation,
    long before this, hence `mallopt`; other C libraries (musl, macOS) have other numbers or
    none: nothing is set there."""
    try:
        libc_version = os.confstr("CS_GNU_LIBC_VERSION") or ""
    except (ValueError, OSError):  # not a name this system knows
        return
    if not libc_version.startswith("glibc"):
        return
    mallopt = getattr(ctypes.CDLL(None), "mallopt", None)  # glibc's symbols are the program's
    if mallopt is None:
        return
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    tunables = os.environ.get("GLIBC_TUNABLES", "")
    for variable, (tunable, parameter, value) in WORKER_MALLOC.items():
        if variable not in os.environ and f"{tunable}=" not in tunables:
            mallopt(parameter, value)  # 0 where refused: the allocator as it was


def _one_thread_for_loaded_blas() -> None:
    """In the worker, when numpy loaded before `_start` (a program whose main module imports
    it: the spawn runs that module again here) and so read its thread count before
    `BLAS_THREADS` were set: its OpenBLAS told through its own call, found among the
    process's mapped libraries (Linux; elsewhere, or for another BLAS, it stays as it is)."""
    try:
        maps = Path("/proc/self/maps").read_text()
    except OSError:
        return
    fields = (line.split(maxsplit=5) for line in maps.splitlines())
    libraries = {f[5] for f in fields if len(f) == 6 and "openblas" in f[5].lower()}
    for library in sorted(libraries):
        with contextlib.suppress(OSError):
            loaded = ctypes.CDLL(library)
            for name in OPENBLAS_SET_THREADS:
                set_threads = getattr(loaded, name, None)
                if set_threads is not None:
                    set_threads.argtypes = (ctypes.c_int,)
                    set_threads(1)
                    break


def _exit_with_service(service_pid: int) -> None:
    """In the worker: exit once the service that started it is no longer its parent. A
    service killed outright (SIGKILL, the OOM killer, a supervisor that signals only its main
    process) cannot shut the worker down, and the worker would never notice: it holds both
    ends of its pool's call queue, so no end-of-file comes, and it ignores SIGINT and
    SIGTERM. Without this it would wait for work for good, one more per restart."""
    while os.getppid() == service_pid:
        time.sleep(SERVICE_CHECK_S)
    os._exit(0)  # nothing to hand back: the fit it may be running has no one to read it


def _ready() -> int:
    """Answered once the worker has started (its pid)."""
    return os.getpid()


def _measure(
    window: Window, current: float, guess: float, pool: Window | None = None
) -> tuple[DelayMeasurement | DelayRefused, float]:
    """In the worker: one stretch's fit (and the pooled fit, given the pool), and the
    worker's CPU time for it (s), all of its threads, counted in the service's status
    (`delay_fit_cpu_ms`)."""
    start = time.process_time()
    found = _worker["tracker"].measure(window, current, guess, pool)
    return found, time.process_time() - start


def _spawn(state: bytes, idle: bool) -> tuple[ProcessPoolExecutor, Future[int]]:
    """A pool of one worker for the fits, its process started (spawn, not fork: Zenoh runs
    threads in the service), and the future of its pid, answered once it runs."""
    pool = ProcessPoolExecutor(
        1,
        mp_context=multiprocessing.get_context("spawn"),
        initializer=_start,
        initargs=(state, os.getpid(), idle),
    )
    return pool, pool.submit(_ready)  # the process starts here


def _shut_down(spawn: asyncio.Future[tuple[ProcessPoolExecutor, Future[int]]]) -> None:
    """A pool spawned for a fallback that no one will use (the service stopped meanwhile):
    its worker exits now."""
    if not spawn.cancelled() and spawn.exception() is None:
        spawn.result()[0].shutdown(wait=False, cancel_futures=True)


def _forget(fit: asyncio.Future[Any]) -> None:
    """Reads a superseded fit's outcome, so that nothing reports it as never retrieved."""
    if not fit.cancelled():
        fit.exception()


class FitWorker:
    """One worker process for the delay fits (see the module). `tracker`: the service's
    tracker, copied as it is now (at start: its settings, empty buffers). `idle`: the fits at
    idle priority, until one of them is starved (`FIT_PATIENCE_S`).

    The service's environment is never changed, at start or at the fallback: Zenoh's native
    threads may read it meanwhile, and a concurrent change can free what they read. What the
    worker needs it sets in its own process (`_start`)."""

    def __init__(self, tracker: OnlineDelayTracker, idle: bool = True) -> None:
        self._state = pickle.dumps(tracker)
        # the worker left behind at the fallback, until it has exited or is killed
        self._starved: list[Process] = []
        self._starved_timer: asyncio.TimerHandle | None = None
        self.idle = idle
        self._pool, self._started = _spawn(self._state, idle)

    async def measure(
        self, window: Window, current: float, guess: float, pool: Window | None = None
    ) -> tuple[DelayMeasurement | DelayRefused, float]:
        """One stretch's fit in the worker (`OnlineDelayTracker.measure`; with `pool`, the
        arrays of the stretch's pool while the delay is not settled, the pooled fit too),
        and its CPU (s). A fit at idle priority not back within `FIT_PATIENCE_S` is made again
        by a new worker at normal priority, which makes every later one too (the starved
        worker is shut down: it exits once its fit ends, or is killed `STARVED_GRACE_S`
        after)."""
        loop = asyncio.get_running_loop()
        fit = loop.run_in_executor(self._pool, _measure, window, current, guess, pool)
        if not self.idle:
            return await fit
        try:
            return await asyncio.wait_for(asyncio.shield(fit), FIT_PATIENCE_S)
        except TimeoutError:
            pass
        fit.add_done_callback(_forget)  # the starved fit's outcome, whatever it is, unread
        log.warning(
            "delay fit not back after %.1f s at idle priority (the machine is busy): the "
            "delay fits run at normal priority from now on",
            FIT_PATIENCE_S,
        )
        starved = self._pool
        # the new worker spawned off the loop: its start (fork, exec, its state sent) holds
        # the calling thread 3-12 ms, more on the busy machine that caused the fallback
        spawn = loop.run_in_executor(None, _spawn, self._state, False)
        try:
            self._pool, self._started = await asyncio.shield(spawn)
            self.idle = False
        except asyncio.CancelledError:  # the service stops: the new worker is shut down too
            spawn.add_done_callback(_shut_down)
            raise
        finally:
            self._leave(starved, loop)
        return await loop.run_in_executor(self._pool, _measure, window, current, guess, pool)

    def _leave(self, starved: ProcessPoolExecutor, loop: asyncio.AbstractEventLoop) -> None:
        """Shut the starved pool down, and kill its worker if it has not exited within
        `STARVED_GRACE_S`: a timer on the loop, no thread or task, and at most one worker
        waiting (an earlier one is ended at once)."""
        # the pool's processes are in CPython's `_processes` (no public accessor), which its
        # shutdown drops
        processes = list((starved._processes or {}).values())
        starved.shutdown(wait=False, cancel_futures=True)
        self._end_starved()
        self._starved = processes
        self._starved_timer = loop.call_later(STARVED_GRACE_S, self._end_starved)

    def _end_starved(self) -> None:
        """Kill the worker left behind at the fallback, unless it has exited (its fit has no
        reader). SIGKILL: the worker ignores SIGTERM."""
        if self._starved_timer is not None:
            self._starved_timer.cancel()
            self._starved_timer = None
        for process in self._starved:
            # its end of file says it exited, without reaping it from under the pool's thread
            if not multiprocessing.connection.wait([process.sentinel], 0):
                log.warning(
                    "the delay fits' starved worker (pid %s) had not exited: killed", process.pid
                )
                process.kill()
        self._starved = []

    def pid(self, timeout: float = 30.0) -> int:
        """The worker's process id, once it runs (blocking: for tests and tools)."""
        return int(self._started.result(timeout))

    def close(self) -> None:
        """Stop the worker without waiting for a fit it may be running (it exits after); a
        worker left behind at the fallback is killed now."""
        self._pool.shutdown(wait=False, cancel_futures=True)
        self._end_starved()
