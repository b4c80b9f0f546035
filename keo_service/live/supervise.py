"""Supervision of a process's tasks: a task that fails is never silent.

`supervise(task, stopping, on_failure)` watches one task. When it raises, or returns while
the process is not stopping, its name, the exception and the traceback are logged at error
level at once and `on_failure` is called; the owner then stops its other tasks and the process
exits non-zero so that its supervisor (systemd: Restart=on-failure) restarts it.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable

from keo_service.core.errors import KeoError

__all__ = ["TaskFailedError", "supervise"]

log = logging.getLogger("keo.supervise")


class TaskFailedError(KeoError, RuntimeError):
    """A supervised task ended while its process was running."""


def supervise(
    task: asyncio.Task[None],
    stopping: Callable[[], bool],
    on_failure: Callable[[BaseException], None],
) -> asyncio.Task[None]:
    def done(t: asyncio.Task[None]) -> None:
        if t.cancelled():
            return
        exc = t.exception()
        if exc is None:
            if stopping():
                return  # a loop that ends because its process stops
            exc = TaskFailedError(f"task {t.get_name()} ended while the process was running")
        log.error(
            "task %s failed: %s: %s; stopping",
            t.get_name(),
            type(exc).__name__,
            exc,
            exc_info=exc,
        )
        on_failure(exc)

    task.add_done_callback(done)
    return task
