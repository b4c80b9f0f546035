"""The delay fits' worker process reuses the memory a fit freed for the next one (issue 48):
without it, each fit mapped its arrays' pages fresh from the kernel and gave them back, a
page fault per 4 kB touched, counted in the service's CPU (docs/performance.md, Round 11)."""

from __future__ import annotations

import asyncio
import os
from pathlib import Path

import pytest

from tests.test_fit_worker import _stretches


def _minor_faults(pid: int) -> int:
    """The process's minor page faults so far (/proc/<pid>/stat, field 10)."""
    return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[7])


def test_the_worker_keeps_freed_memory_for_the_next_fit(demo_config, demo_cell):
    """The same stretch fitted three times in the worker: the first fit grows its heap, the
    next two find it there (before this change the next two faulted 6 468 pages in, the
    same count every run: each fit's arrays mapped anew; with the heap kept, 0-1). The
    worker sets its allocator itself; the service's environment is left as it was."""
    from keo_service.live.fit_worker import WORKER_MALLOC, FitWorker

    before = {name: os.environ.get(name) for name in WORKER_MALLOC}
    fresh, stretches = _stretches(demo_config, demo_cell, 1)
    window, current, guess, pool = stretches[0]
    worker = FitWorker(fresh)
    try:
        pid = worker.pid()
        assert {name: os.environ.get(name) for name in WORKER_MALLOC} == before

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


@pytest.mark.parametrize(
    "chosen",
    [
        {"MALLOC_MMAP_THRESHOLD_": "131072", "MALLOC_TRIM_THRESHOLD_": "131072"},
        {"GLIBC_TUNABLES": "glibc.malloc.mmap_threshold=131072:glibc.malloc.trim_threshold=131072"},
    ],
)
def test_the_users_allocator_settings_are_left_as_they_are(tmp_path, chosen):
    """A service started with the allocator's settings chosen by the user, by variable or by
    tunable (here glibc's own 128 kB thresholds, fixed): the worker keeps them, so a fit's
    larger arrays are mapped fresh each time and the two fits after the first fault
    thousands of pages in (40 000 when this was written), where the worker's own settings
    make it fewer than a thousand (the test above)."""
    from tests.conftest import DEMO, run_script

    script = tmp_path / "service.py"
    script.write_text(
        "import asyncio\n"
        "from keo_service.io.cell import cell_from_config\n"
        "from keo_service.io.config import load_config\n"
        "from keo_service.live.fit_worker import FitWorker\n"
        "from tests.test_fit_worker import _stretches\n"
        "from tests.test_live_fit_worker_memory import _minor_faults\n"
        "if __name__ == '__main__':\n"
        f"    config = load_config({str(DEMO)!r})\n"
        "    fresh, stretches = _stretches(config, cell_from_config(config), 1)\n"
        "    worker = FitWorker(fresh)\n"
        "    async def fit():\n"
        "        await worker.measure(*stretches[0])\n"
        "    asyncio.run(fit())\n"
        "    first = _minor_faults(worker.pid())\n"
        "    asyncio.run(fit())\n"
        "    asyncio.run(fit())\n"
        "    print(_minor_faults(worker.pid()) - first)\n"
        "    worker.close()\n"
    )
    done = run_script(script, {**os.environ, **chosen})
    assert int(done.stdout.split()[-1]) > 1000, done.stdout + done.stderr
