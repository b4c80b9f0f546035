"""Universal Robots RTDE, protocol version 2 (TCP port 30004), as a pure codec: bytes in,
typed packages out, no I/O.

Framing (UR's public RTDE description): every package is a big-endian header `uint16 size`
(the whole package, header included) and `uint8 type`, then the payload:

    V  86  request protocol version   client: uint16 version     controller: uint8 accepted
    v 118  get controller version     client: (empty)            controller: uint32 x4
    O  79  setup outputs              client: double frequency + names "a,b,c"
                                      controller: uint8 recipe id + types "DOUBLE,VECTOR6D"
    I  73  setup inputs               client: names "input_double_register_24,..."
                                      controller: uint8 recipe id + types ("IN_USE" when
                                      another client writes that variable)
    S  83  start                      client: (empty)            controller: uint8 accepted
    P  80  pause                      client: (empty)            controller: uint8 accepted
    U  85  data package               controller: uint8 recipe id + the fields, packed;
                                      client: the same for an input recipe (its id first)
    M  77  text message (v2)          uint8 length + message, uint8 length + source, uint8 level

A variable the controller does not know comes back as type `NOT_FOUND`. Clients may end the
name list with a comma (ur_rtde does): the empty name is ignored.

`RtdeDecoder.feed` splits a byte stream into packages. A header with an unknown type or an
impossible size is counted and skipped byte by byte until a plausible header follows, so one
corrupt package never ends the stream.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass, field

from keo_service.core.errors import KeoError
from keo_service.core.rejects import RejectLog

HEADER = struct.Struct(">HB")
PROTOCOL_VERSION = 2
DEFAULT_PORT = 30004

REQUEST_PROTOCOL_VERSION = 86  # V
GET_URCONTROL_VERSION = 118  # v
TEXT_MESSAGE = 77  # M
DATA_PACKAGE = 85  # U
CONTROL_PACKAGE_SETUP_OUTPUTS = 79  # O
CONTROL_PACKAGE_SETUP_INPUTS = 73  # I
CONTROL_PACKAGE_START = 83  # S
CONTROL_PACKAGE_PAUSE = 80  # P
KNOWN_TYPES = frozenset(
    {
        REQUEST_PROTOCOL_VERSION,
        GET_URCONTROL_VERSION,
        TEXT_MESSAGE,
        DATA_PACKAGE,
        CONTROL_PACKAGE_SETUP_OUTPUTS,
        CONTROL_PACKAGE_SETUP_INPUTS,
        CONTROL_PACKAGE_START,
        CONTROL_PACKAGE_PAUSE,
    }
)
MAX_PACKAGE = 4096  # a data package of every output variable stays well below this

# RTDE type name -> struct format (big endian), for the variables keo asks for and their kin
TYPE_FORMATS = {
    "BOOL": "?",
    "UINT8": "B",
    "UINT32": "I",
    "UINT64": "Q",
    "INT32": "i",
    "DOUBLE": "d",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}

# the outputs keo sets up, with their types on every controller since CB3 3.4 / e-Series
OUTPUTS = {
    "timestamp": "DOUBLE",
    "actual_q": "VECTOR6D",
    "actual_qd": "VECTOR6D",
    "robot_mode": "INT32",
    "safety_mode": "INT32",
    "runtime_state": "UINT32",
}


class RtdeError(KeoError, ValueError):
    """A package that is not what the protocol says at this point."""


@dataclass(frozen=True)
class Package:
    type: int
    payload: bytes


@dataclass(frozen=True)
class TextMessage:
    message: str
    source: str
    level: int


@dataclass(frozen=True)
class Recipe:
    """The output recipe the controller accepted: its id, names and types."""

    recipe_id: int
    names: tuple[str, ...]
    types: tuple[str, ...]
    layout: struct.Struct = field(init=False, repr=False, compare=False)
    widths: tuple[int, ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        missing = [n for n, t in zip(self.names, self.types, strict=True) if t == "NOT_FOUND"]
        if missing:
            raise RtdeError(f"the controller does not know the variable(s) {', '.join(missing)}")
        taken = [n for n, t in zip(self.names, self.types, strict=True) if t == "IN_USE"]
        if taken:
            raise RtdeError(f"another RTDE client already writes {', '.join(taken)}")
        unknown = [t for t in self.types if t not in TYPE_FORMATS]
        if unknown:
            raise RtdeError(f"output type(s) {', '.join(unknown)} are not supported")
        formats = [TYPE_FORMATS[t] for t in self.types]
        object.__setattr__(self, "layout", struct.Struct(">B" + "".join(formats)))
        object.__setattr__(self, "widths", tuple(int(f[:-1]) if len(f) > 1 else 1 for f in formats))

    def unpack(self, payload: bytes) -> dict[str, float | int | tuple[float, ...]]:
        """A data package's payload (recipe id first) as {name: value}."""
        if len(payload) != self.layout.size:
            raise RtdeError(
                f"data package of {len(payload)} bytes, recipe needs {self.layout.size}"
            )
        flat = self.layout.unpack(payload)
        if flat[0] != self.recipe_id:
            raise RtdeError(f"data package for recipe {flat[0]}, expected {self.recipe_id}")
        out: dict[str, float | int | tuple[float, ...]] = {}
        i = 1
        for name, width in zip(self.names, self.widths, strict=True):
            out[name] = flat[i] if width == 1 else tuple(flat[i : i + width])
            i += width
        return out

    def pack(self, values: dict[str, object]) -> bytes:
        """The payload of a data package with these values (the mock controller's side)."""
        flat: list[object] = [self.recipe_id]
        for name in self.names:
            value = values[name]
            flat.extend(value if isinstance(value, tuple | list) else [value])
        return self.layout.pack(*flat)


# ---- encoding -------------------------------------------------------------------------------


def package(kind: int, payload: bytes = b"") -> bytes:
    return HEADER.pack(HEADER.size + len(payload), kind) + payload


def request_protocol_version(version: int = PROTOCOL_VERSION) -> bytes:
    return package(REQUEST_PROTOCOL_VERSION, struct.pack(">H", version))


def get_controller_version() -> bytes:
    return package(GET_URCONTROL_VERSION)


def setup_outputs(frequency_hz: float, names: Sequence[str]) -> bytes:
    return package(
        CONTROL_PACKAGE_SETUP_OUTPUTS,
        struct.pack(">d", frequency_hz) + ",".join(names).encode("ascii"),
    )


def setup_inputs(names: Sequence[str]) -> bytes:
    return package(CONTROL_PACKAGE_SETUP_INPUTS, ",".join(names).encode("ascii"))


def input_double_registers(first: int, count: int = 6) -> list[str]:
    """The names of `count` input double registers from `first` on."""
    return [f"input_double_register_{first + k}" for k in range(count)]


def start() -> bytes:
    return package(CONTROL_PACKAGE_START)


def pause() -> bytes:
    return package(CONTROL_PACKAGE_PAUSE)


def accepted(kind: int, ok: bool = True) -> bytes:
    """The controller's answer to V, S or P."""
    return package(kind, struct.pack(">B", 1 if ok else 0))


def controller_version(major: int, minor: int, bugfix: int, build: int) -> bytes:
    return package(GET_URCONTROL_VERSION, struct.pack(">IIII", major, minor, bugfix, build))


def outputs_reply(recipe_id: int, types: Sequence[str]) -> bytes:
    return package(
        CONTROL_PACKAGE_SETUP_OUTPUTS, struct.pack(">B", recipe_id) + ",".join(types).encode()
    )


def inputs_reply(recipe_id: int, types: Sequence[str]) -> bytes:
    return package(
        CONTROL_PACKAGE_SETUP_INPUTS, struct.pack(">B", recipe_id) + ",".join(types).encode()
    )


def data_package(recipe: Recipe, values: dict[str, object]) -> bytes:
    return package(DATA_PACKAGE, recipe.pack(values))


def text_message(message: str, source: str = "keo", level: int = 1) -> bytes:
    m, s = message.encode()[:255], source.encode()[:255]
    return package(TEXT_MESSAGE, bytes([len(m)]) + m + bytes([len(s)]) + s + bytes([level]))


# ---- decoding -------------------------------------------------------------------------------


def parse_accepted(p: Package) -> bool:
    if len(p.payload) != 1:
        raise RtdeError(f"answer of {len(p.payload)} bytes to package {chr(p.type)}, expected 1")
    return p.payload[0] == 1


def parse_controller_version(p: Package) -> tuple[int, int, int, int]:
    if len(p.payload) != 16:
        raise RtdeError(f"controller version of {len(p.payload)} bytes, expected 16")
    major, minor, bugfix, build = struct.unpack(">IIII", p.payload)
    return major, minor, bugfix, build


def parse_outputs_reply(p: Package, names: Sequence[str]) -> Recipe:
    if not p.payload:
        raise RtdeError("empty answer to a recipe setup")
    types = tuple(t for t in p.payload[1:].decode("ascii", "replace").split(",") if t)
    if len(types) != len(names):
        raise RtdeError(f"{len(types)} types for {len(names)} names")
    return Recipe(p.payload[0], tuple(names), types)


def parse_inputs_reply(p: Package, names: Sequence[str]) -> Recipe:
    """The controller's answer to an input setup (raises for NOT_FOUND and IN_USE)."""
    return parse_outputs_reply(p, names)


def parse_setup_inputs_request(p: Package) -> list[str]:
    """The client's input setup: the names (an empty name from a trailing comma dropped)."""
    names = [n.strip() for n in p.payload.decode("ascii", "replace").split(",")]
    return [n for n in names if n]


def parse_setup_request(p: Package) -> tuple[float, list[str]]:
    """The client's output setup: frequency and names (an empty name from a trailing comma
    is dropped)."""
    if len(p.payload) < 8:
        raise RtdeError("output setup without its frequency")
    (frequency,) = struct.unpack(">d", p.payload[:8])
    names = [n.strip() for n in p.payload[8:].decode("ascii", "replace").split(",")]
    return frequency, [n for n in names if n]


def parse_text_message(p: Package) -> TextMessage:
    b = p.payload
    try:
        n = b[0]
        message = b[1 : 1 + n].decode("utf-8", "replace")
        k = b[1 + n]
        source = b[2 + n : 2 + n + k].decode("utf-8", "replace")
        level = b[2 + n + k]
    except IndexError:
        raise RtdeError(f"text message of {len(b)} bytes is cut short") from None
    return TextMessage(message, source, level)


class RtdeDecoder:
    """A byte stream to packages. Bounded: at most one package is ever buffered."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self._rejects = RejectLog(keep=16)
        self.counters = self._rejects.counters
        self.messages = self._rejects.messages
        self._skipped = 0
        self._offset = 0  # bytes of the connection before the buffer's first

    def feed(self, data: bytes) -> list[Package]:
        self._buf += data
        out: list[Package] = []
        while len(self._buf) >= HEADER.size:
            size, kind = HEADER.unpack_from(self._buf)
            self._rejects.at = f"byte {self._offset} of the connection"
            if kind not in KNOWN_TYPES or size < HEADER.size or size > MAX_PACKAGE:
                if self._skipped == 0:
                    self._rejects.reject(
                        "bad_header",
                        f"header type {kind} size {size}: not an RTDE package, resynchronising",
                    )
                self._skipped += 1
                del self._buf[0]
                self._offset += 1
                continue
            if len(self._buf) < size:
                break
            if self._skipped:
                self._rejects.note("resync", f"resynchronised after skipping {self._skipped} bytes")
                self._skipped = 0
            out.append(Package(kind, bytes(self._buf[HEADER.size : size])))
            del self._buf[:size]
            self._offset += size
            self.counters["packages"] += 1
        if len(self._buf) > MAX_PACKAGE:  # cannot happen with a valid size; keep memory bounded
            self._offset += len(self._buf) - MAX_PACKAGE
            del self._buf[: len(self._buf) - MAX_PACKAGE]
        return out

    def reject(self, reason: str, message: str) -> None:
        """A package that framed well but says something wrong (counted, never fatal; its
        place is given as the end of the bytes decoded so far, the package came before)."""
        self._rejects.at = f"before byte {self._offset} of the connection"
        self._rejects.reject(reason, message)
