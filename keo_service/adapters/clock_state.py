"""An adapter's device-clock mapping kept on disk (`timing.clock_state_dir`), so that a
restarted adapter goes on on the line it had (docs/timing.md): one small JSON file per device,
named after the cell, the adapter and the device's address, written atomically (a temporary
file, then a rename) about once a second. Reading is forgiving: a missing, unreadable or
malformed file only means that the mapping is learned anew (the reason is logged).
"""

from __future__ import annotations

import json
import logging
import os
import re
import time
from pathlib import Path

from keo_service.core.clock import Stamper

log = logging.getLogger("keo.adapter")
SAVE_PERIOD_S = 1.0
_UNSAFE = re.compile(r"[^A-Za-z0-9_.-]+")


def state_path(state_dir: str, cell: str, adapter: str, device: str) -> Path:
    """The file of one device's mapping: <dir>/<cell>-<adapter>-<device address>.json."""
    name = _UNSAFE.sub("_", f"{cell}-{adapter}-{device}")
    return Path(state_dir) / f"{name}.json"


def load_into(stamper: Stamper, path: Path, device: str, now: float | None = None) -> str:
    """Hand the mapping saved at `path` to `stamper` (it decides by the file's age whether
    the line goes on, only its drift helps, or nothing); what was done, in words."""
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return "no saved mapping"
    except (OSError, ValueError) as exc:
        return f"saved mapping {path} unreadable ({exc}): learning anew"
    if not isinstance(doc, dict) or doc.get("device") != device:
        return f"saved mapping {path} is not this device's: learning anew"
    saved_at = doc.get("saved_at")
    if not isinstance(saved_at, (int, float)):
        return f"saved mapping {path} has no time: learning anew"
    age = (time.time() if now is None else now) - float(saved_at)
    return stamper.resume(doc.get("state"), age)


def save(stamper_state: dict[str, object], path: Path, device: str) -> None:
    """Write one mapping (a worker thread: file I/O stays off the event loop)."""
    doc = {"device": device, "saved_at": time.time(), "state": stamper_state}
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(f".{os.getpid()}.tmp")
    tmp.write_text(json.dumps(doc), encoding="utf-8")
    os.replace(tmp, path)
