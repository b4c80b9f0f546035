"""The delay fits' worker process reuses the memory a fit freed for the next one (issue 48):
without it, each fit mapped its arrays' pages fresh from the kernel and gave them back, a
page fault per 4 kB touched, counted in the service's CPU (docs/performance.md, Round 11)."""

from __future__ import annotations

import asyncio
import os
from pathlib import Path

from tests.test_fit_worker import _stretches


def _minor_faults(pid: int) -> int:
    """The process's minor page faults so far (/proc/<pid>/stat, field 10)."""
    return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[7])


def test_the_worker_keeps_freed_memory_for_the_next_fit(demo_config, demo_cell):
    """The same stretch fitted three times in the worker: the first fit grows its heap, the
    next two find it there (before this change the next two faulted 6 468 pages in, the
    same count every run: each fit's arrays mapped anew; with the heap kept, 0-1). The
    worker's environment names the allocator's settings; the service's own is left as it
    was."""
    from keo_service.live.fit_worker import WORKER_MALLOC, FitWorker

    before = {name: os.environ.get(name) for name in WORKER_MALLOC}
    fresh, stretches = _stretches(demo_config, demo_cell, 1)
    window, current, guess, pool = stretches[0]
    worker = FitWorker(fresh)
    try:
        pid = worker.pid()
        assert {name: os.environ.get(name) for name in WORKER_MALLOC} == before
        environ = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
        for name, value in WORKER_MALLOC.items():
            assert f"{name}={value}".encode() in environ

        async def fit() -> None:
            await worker.measure(window, current, guess, pool)

        asyncio.run(fit())
        first = _minor_faults(pid)
        asyncio.run(fit())
        asyncio.run(fit())
        again = _minor_faults(pid) - first
    finally:
        worker.close()
    assert again < 1000, f"{again} page faults in two fits of a stretch already fitted once"
