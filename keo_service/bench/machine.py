"""The machine and its processes as /proc shows them: CPU model, clock ticks, each
process's CPU time, memory, children and open files (Linux)."""

from __future__ import annotations

import os
import platform
from pathlib import Path
from typing import Any

TICK = os.sysconf("SC_CLK_TCK")


def machine() -> dict[str, Any]:
    model = ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {
        "cpu": model or platform.processor(),
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "system": platform.platform(),
        "keo_bytecode_cached": keo_bytecode_cached(),
    }


def keo_bytecode_cached() -> bool:
    """Whether keo's own modules load from compiled bytecode (`__pycache__`), as after a
    package install (pip compiles them): without it (an editable install where
    PYTHONDONTWRITEBYTECODE is set) every command compiles each keo module it imports anew,
    a cost a user's install does not pay, in every timed command."""
    import keo_service.io.config  # imported by every command

    return bytecode_cached(keo_service.io.config)


def bytecode_cached(module: Any) -> bool:
    """Whether `module`'s source has its compiled bytecode beside it, where the import system
    looks for it."""
    import importlib.util

    source = getattr(module, "__file__", None)
    if source is None:
        return False
    return Path(importlib.util.cache_from_source(source)).exists()


def stat_fields(pid: int | str) -> list[str]:
    """/proc/<pid>/stat after the command name (which may hold spaces): state, ppid, ..."""
    return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()


def machine_ticks() -> dict[str, int]:
    """The machine's CPU time so far by kind, all cores, in clock ticks (/proc/stat's first
    line: user nice system idle iowait irq softirq steal ...)."""
    with open("/proc/stat", encoding="ascii") as f:
        values = [int(v) for v in f.readline().split()[1:9]]
    return {"busy": sum(values[:3]) + sum(values[5:7]), "steal": values[7], "all": sum(values)}


def machine_share(before: dict[str, int], after: dict[str, int]) -> dict[str, float]:
    """Busy and stolen time between two `machine_ticks`, in % of all cores' time (stolen: the
    hypervisor ran something else while these cores had work)."""
    span = max(1, after["all"] - before["all"])
    return {
        "busy_pct": 100.0 * (after["busy"] - before["busy"]) / span,
        "steal_pct": 100.0 * (after["steal"] - before["steal"]) / span,
    }


def proc_cpu_s(pid: int) -> float:
    fields = stat_fields(pid)
    return (int(fields[11]) + int(fields[12])) / TICK


def thread_cpu_s(pid: int) -> dict[str, float]:
    """The process's CPU time so far (s) by kind of thread: its main thread ("event_loop": the
    asyncio loop in keo's processes), its other threads without a name of their own
    ("python_threads": zenoh-python's subscriber callback threads, executor threads) and the
    named ones ("native_threads": Zenoh's runtime, tx-0, rx-0, acc-0, ...). Split so that a
    process's CPU says where it goes: the service and the relay differ in the first only
    (docs/performance.md). A thread that ended since is not counted."""
    out = {"event_loop": 0.0, "python_threads": 0.0, "native_threads": 0.0}
    main = ""  # a thread without a name of its own has the process's (the main thread's)
    for task in sorted(Path(f"/proc/{pid}/task").iterdir(), key=lambda t: t.name != str(pid)):
        try:
            text = (task / "stat").read_text()
        except OSError:
            continue  # ended meanwhile
        name = text[text.index("(") + 1 : text.rindex(")")]
        fields = text.rsplit(")", 1)[1].split()
        cpu = (int(fields[11]) + int(fields[12])) / TICK
        if task.name == str(pid):
            main = name
            out["event_loop"] += cpu
        elif name == main:
            out["python_threads"] += cpu
        else:
            out["native_threads"] += cpu
    return out


def proc_mem_kb(pid: int) -> dict[str, int]:
    out = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(("VmRSS", "VmHWM")):
            key, value = line.split(":", 1)
            out[key] = int(value.split()[0])
    return out


def children(pid: int) -> list[int]:
    """The processes whose parent is `pid`."""
    out = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = stat_fields(entry.name)
        except OSError:
            continue  # gone meanwhile
        if int(fields[1]) == pid:
            out.append(int(entry.name))
    return out


def cmdline(pid: int) -> str:
    """The process's command line, its arguments joined by spaces ("" once it is gone)."""
    try:
        raw = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return ""
    return raw.replace(b"\0", b" ").decode(errors="replace").strip()


def open_fds(pid: int) -> int:
    return len(os.listdir(f"/proc/{pid}/fd"))
