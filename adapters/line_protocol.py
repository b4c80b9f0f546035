"""keo's tracker line protocol (DESIGN.md section 6): newline-delimited JSON over TCP.

    {"type": "hello", "length_unit": "mm", "source": "..."}
    {"type": "pose", "seq": 17, "t": 12.345, "p": [x, y, z], "q": [w, x, y, z], "status": "ok"}

Pure codec. Poses before a hello are refused (their unit is unknown). Units are converted to
metres; non-unit quaternions, non-finite numbers, repeated or backwards seq are refused;
a device clock that steps back is counted (alignment uses the host receipt time).
"""

from __future__ import annotations

import json
import math
from collections import Counter, deque
from dataclasses import dataclass

UNITS = {"m": 1.0, "mm": 1e-3}
QUATERNION_TOLERANCE = 1e-3
MAX_LINE = 65536


@dataclass(frozen=True)
class Pose:
    seq: int
    device_t: float
    status: str
    p: tuple[float, float, float] | None  # metres
    q: tuple[float, float, float, float] | None  # scalar first; None: single reflector


def format_hello(length_unit: str = "m", source: str = "keo") -> bytes:
    return (
        json.dumps({"type": "hello", "length_unit": length_unit, "source": source}) + "\n"
    ).encode()


def format_pose(
    seq: int, t: float, p: list[float] | None, q: list[float] | None, status: str = "ok"
) -> bytes:
    doc: dict[str, object] = {"type": "pose", "seq": seq, "t": t, "status": status}
    if p is not None:
        doc["p"] = p
    if q is not None:
        doc["q"] = q
    return (json.dumps(doc) + "\n").encode()


def _finite_list(value: object, n: int) -> list[float] | None:
    if not isinstance(value, list) or len(value) != n:
        return None
    if not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value):
        return None
    out = [float(v) for v in value]
    return out if all(math.isfinite(v) for v in out) else None


class LineProtocolParser:
    def __init__(self) -> None:
        self.scale: float | None = None
        self.source = ""
        self._last_seq: int | None = None
        self._last_t = -math.inf
        self.counters: Counter[str] = Counter()
        self.messages: deque[str] = deque(maxlen=16)

    def reset(self) -> None:
        """New connection: a new hello is needed; sequence checks start over."""
        self.scale = None
        self._last_seq = None
        self._last_t = -math.inf

    def _reject(self, counter: str, message: str) -> None:
        self.counters[counter] += 1
        self.counters["rejected"] += 1
        self.messages.append(message)

    def parse(self, line: bytes) -> Pose | None:
        if len(line) > MAX_LINE:
            self._reject("too_long", f"line of {len(line)} bytes, limit {MAX_LINE}")
            return None
        try:
            doc = json.loads(line)
        except (ValueError, UnicodeDecodeError) as exc:
            self._reject("malformed", f"not JSON: {exc}")
            return None
        if not isinstance(doc, dict):
            self._reject("malformed", "a line must be a JSON object")
            return None
        kind = doc.get("type")
        if kind == "hello":
            unit = doc.get("length_unit")
            if unit not in UNITS:
                self._reject("bad_hello", f"length_unit {unit!r}, expected 'm' or 'mm'")
                return None
            self.scale = UNITS[str(unit)]
            self.source = str(doc.get("source", ""))
            self.counters["hello"] += 1
            return None
        if kind != "pose":
            self._reject("unknown_type", f"type {kind!r}, expected 'hello' or 'pose'")
            return None
        if self.scale is None:
            self._reject("no_hello", "pose before hello: its length unit is unknown")
            return None
        seq, t, status = doc.get("seq"), doc.get("t"), doc.get("status", "ok")
        if not isinstance(seq, int) or isinstance(seq, bool):
            self._reject("malformed", f"seq {seq!r}, expected an integer")
            return None
        if not isinstance(t, int | float) or isinstance(t, bool) or not math.isfinite(t):
            self._reject("non_finite", f"seq {seq}: time {t!r}, expected a finite number")
            return None
        if not isinstance(status, str):
            self._reject("malformed", f"seq {seq}: status {status!r}, expected a string")
            return None
        if self._last_seq is not None and seq <= self._last_seq:
            counter = "duplicate" if seq == self._last_seq else "out_of_order"
            self._reject(counter, f"seq {seq} after {self._last_seq}")
            return None
        if t <= self._last_t:
            # the device clock stepped (a resync, a restart): alignment uses the host's receipt
            # time, so the pose stays good; the step is counted and reported
            self.counters["device_time_step"] += 1
            self.messages.append(f"seq {seq}: device time {t} not after {self._last_t}")
        if status != "ok":
            self._last_seq, self._last_t = seq, float(t)
            self.counters["gaps"] += 1
            return Pose(seq, float(t), status, None, None)
        p = _finite_list(doc.get("p"), 3)
        if p is None:
            self._reject(
                "non_finite", f"seq {seq}: p must be 3 finite numbers, got {doc.get('p')!r}"
            )
            return None
        q = None
        if "q" in doc and doc["q"] is not None:
            q = _finite_list(doc["q"], 4)
            if q is None:
                self._reject(
                    "non_finite", f"seq {seq}: q must be 4 finite numbers, got {doc['q']!r}"
                )
                return None
            norm = math.sqrt(sum(v * v for v in q))
            if abs(norm - 1.0) > QUATERNION_TOLERANCE:
                self._reject(
                    "not_unit_quaternion", f"seq {seq}: quaternion norm {norm:.6g}, expected 1"
                )
                return None
            q = [v / norm for v in q]
        self._last_seq, self._last_t = seq, float(t)
        self.counters["poses"] += 1
        s = self.scale
        return Pose(
            seq,
            float(t),
            "ok",
            (p[0] * s, p[1] * s, p[2] * s),
            None if q is None else (q[0], q[1], q[2], q[3]),
        )
