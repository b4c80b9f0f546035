"""keo's tracker line protocol (docs/design.md §6): newline-delimited JSON over TCP.

    {"type": "hello", "length_unit": "mm", "source": "..."}
    {"type": "pose", "seq": 17, "t": 12.345, "p": [x, y, z], "q": [w, x, y, z], "status": "ok"}

Pure codec. Poses before a hello are refused (their unit is unknown). Units are converted to
metres; non-unit quaternions, non-finite numbers, repeated or backwards seq are refused;
a device clock that steps back is counted (alignment uses the host receipt time).

The lines' shapes are msgspec Structs; Python's json reads the text first because devices
write NaN and Infinity, which strict JSON lacks and which must count as non-finite numbers,
not as malformed lines.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Literal

import msgspec

from keo_service.core.rejects import RejectLog

UNITS = {"m": 1.0, "mm": 1e-3}
QUATERNION_TOLERANCE = 1e-3
MAX_LINE = 65536


@dataclass(frozen=True)
class Pose:
    """One parsed pose line: the line's `t` is `device_stamp`, `p` and `q` are `position`
    and `quaternion` (the wire messages' names)."""

    seq: int
    device_stamp: float
    status: str
    position: tuple[float, float, float] | None  # metres
    quaternion: tuple[float, float, float, float] | None  # scalar first; None: one reflector


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


class _Line(msgspec.Struct, tag_field="type", forbid_unknown_fields=False):
    pass


class HelloLine(_Line, tag="hello"):
    length_unit: Literal["m", "mm"]
    source: str = ""


class PoseLine(_Line, tag="pose"):
    seq: int
    t: float
    status: str = "ok"
    p: tuple[float, float, float] | None = None
    q: tuple[float, float, float, float] | None = None


# what a shape error at each field means, as counted in status
_FIELD_REASON = {
    "type": "unknown_type",
    "length_unit": "bad_hello",
    "t": "non_finite",
    "p": "non_finite",
    "q": "non_finite",
}
_AT = " - at `$."


def _reason(error: str) -> str:
    if _AT in error:
        field = error.split(_AT, 1)[1].split("`", maxsplit=1)[0].split("[", maxsplit=1)[0]
        return _FIELD_REASON.get(field, "malformed")
    if "field `type`" in error:
        return "unknown_type"
    return "malformed"


def _finite(values: tuple[float, ...]) -> bool:
    return all(math.isfinite(v) for v in values)


class LineProtocolParser:
    def __init__(self) -> None:
        self.scale: float | None = None
        self.source = ""
        self._last_seq: int | None = None
        self._last_t = -math.inf
        self._rejects = RejectLog(keep=16)
        self.counters = self._rejects.counters
        self.messages = self._rejects.messages
        self.lines = 0  # lines of this connection so far
        self.offset = 0  # bytes of this connection before the current line

    def reset(self) -> None:
        """New connection: a new hello is needed; sequence checks and positions start over."""
        self.scale = None
        self._last_seq = None
        self._last_t = -math.inf
        self.lines = self.offset = 0

    def _reject(self, counter: str, message: str) -> None:
        self._rejects.reject(counter, message)

    # one early reject per malformed field, in wire order
    def parse(self, line: bytes) -> Pose | None:  # noqa: C901, PLR0912
        """One line (with its newline) of the connection: a pose, or None for a hello or a
        reject (counted; its message says which line of the connection and at which byte)."""
        self.lines += 1
        self._rejects.at = f"line {self.lines} at byte {self.offset} of the connection"
        self.offset += len(line)
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
        try:
            msg = msgspec.convert(doc, HelloLine | PoseLine)
        except msgspec.ValidationError as exc:
            self._reject(_reason(str(exc)), f"seq {doc.get('seq')!r}: {exc}")
            return None
        if isinstance(msg, HelloLine):
            self.scale = UNITS[msg.length_unit]
            self.source = msg.source
            self.counters["hello"] += 1
            return None
        if self.scale is None:
            self._reject("no_hello", "pose before hello: its length unit is unknown")
            return None
        seq, t, status = msg.seq, msg.t, msg.status
        if not math.isfinite(t):
            self._reject("non_finite", f"seq {seq}: time {t!r}, expected a finite number")
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
        p = msg.p
        if p is None or not _finite(p):
            self._reject("non_finite", f"seq {seq}: p must be 3 finite numbers, got {p!r}")
            return None
        q = msg.q
        if q is not None:
            if not _finite(q):
                self._reject("non_finite", f"seq {seq}: q must be 4 finite numbers, got {q!r}")
                return None
            norm = math.sqrt(sum(v * v for v in q))
            if abs(norm - 1.0) > QUATERNION_TOLERANCE:
                self._reject(
                    "not_unit_quaternion", f"seq {seq}: quaternion norm {norm:.6g}, expected 1"
                )
                return None
            q = (q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm)
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
