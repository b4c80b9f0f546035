"""Real-time scheduling for the threads that must answer within a controller's cycle (RSI,
EGM: 4 ms). Best effort: SCHED_FIFO for the calling thread where the process may ask for it
(root or CAP_SYS_NICE on Linux), plain scheduling otherwise, and the outcome in words for the
adapter's status. Only the calling thread changes: threads started earlier (Zenoh's) keep
theirs. Linux keeps 5 % of each second for other work whatever real-time threads do
(sched_rt_runtime_us), and the callers only ever wait on sockets. The objects alive at the
call are frozen out of the garbage collector's passes (gc.freeze) to keep those passes short.
"""

from __future__ import annotations

import gc
import os

DEFAULT_PRIORITY = 20


def request_realtime(priority: int = DEFAULT_PRIORITY) -> str:
    # what exists now (modules, the session, the scenario) is never garbage: keep the
    # collector's full passes off it, so that one cannot hold the answering thread up
    gc.freeze()
    if not hasattr(os, "sched_setscheduler"):
        return "not available on this platform"
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except OSError as exc:
        return f"not granted ({exc.strerror or exc}): normal scheduling"
    return f"SCHED_FIFO priority {priority}"
