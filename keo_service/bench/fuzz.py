"""Fuzzing with a fixed, counted budget: `keo selftest --fuzz N`.

Every decoder that takes bytes from outside gets N generated inputs: mutations of valid
frames (bit flips, interesting bytes and numbers, insertions, deletions, duplications,
splices, and for text formats tokens such as NaN, 1e999 or a stray quote) and plain random
bytes, from one seeded generator, so a run is reproducible from (N, seed). Each input goes
through the decoder's real entry point. An exception that escapes other than the decoder's
documented reject path is a crash, reported with the input; every rejection is counted under
the reason the decoder's own RejectLog (or documented error) gives it.

A decoder is one entry in `TARGETS`: a name, where its valid frames come from and a runner
that feeds one input. The KUKA RSI and ABB EGM codecs are listed by module name and fuzzed
whenever their modules are importable.
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib
import math
import random
import re
import struct
import tempfile
import time
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, Protocol

import msgspec

from keo_service.core.errors import ConfigError, DataFormatError
from keo_service.resources import configs_dir, demo_config_path

__all__ = ["TARGETS", "FuzzReport", "Target", "fuzz", "fuzz_table", "mutate"]


class Runner(Protocol):
    """Feeds one input; returns how many frames (samples, objects) it decoded. Rejections go
    to `counters` by reason."""

    counters: Counter[str]

    def __call__(self, data: bytes, index: int) -> int: ...


@dataclasses.dataclass(frozen=True)
class Target:
    name: str
    make: Callable[[Path], tuple[list[bytes], Runner]]  # (valid inputs, runner) in a work dir
    text: bool = False  # also apply the text mutations
    needs: str = ""  # a module that must be importable (a decoder not on every branch)


@dataclasses.dataclass
class FuzzReport:
    name: str
    inputs: int = 0
    decoded: int = 0  # inputs that gave at least one frame
    rejected: int = 0  # inputs that gave at least one counted rejection
    quiet: int = 0  # inputs that gave neither (e.g. a partial frame left buffered)
    crashes: int = 0
    seconds: float = 0.0
    reasons: dict[str, int] = dataclasses.field(default_factory=dict)
    crash_examples: list[dict[str, Any]] = dataclasses.field(default_factory=list)
    skipped: str = ""  # why the decoder was not fuzzed (its module is not here)


# ---- mutations ---------------------------------------------------------------------------

INTERESTING_BYTES = (0x00, 0x01, 0x7F, 0x80, 0xFF, 0x0A, 0x22, 0x2C, 0x3C, 0x5B, 0x7B)
INTERESTING_WORDS = [
    struct.pack(fmt, v)
    for fmt in ("<i", ">i", "<q")
    for v in (0, -1, 1, 2**31 - 1, -(2**31), 4096, 65535)
] + [
    struct.pack(fmt, v)
    for fmt in ("<d", ">d", "<f", ">f")
    for v in (math.nan, math.inf, -math.inf, 3e38, -0.0, 1e-40)
]
INTERESTING_TOKENS = [
    b"NaN",
    b"nan",
    b"Infinity",
    b"-inf",
    b"1e999",
    b"-1e999",
    b"1e-999",
    b"-0",
    b"0",
    b"-1",
    b"99999999999999999999999",
    b"null",
    b"true",
    b"[]",
    b"{}",
    b'""',
    b'"',
    b",",
    b"=",
    b"[",
    b"]",
    b"\n",
    b"\r\n",
    b"\x00",
    b"\xff\xfe",
    b"\xc3",
    b"'''",
    b"<",
    b"/>",
    b"&amp;",
    b"\t",
    b" " * 3,
    "é".encode(),
]
_TOKEN = re.compile(rb"[-+0-9.eE]+|[A-Za-z_]+|\S")


def _flip(rng: random.Random, b: bytearray, seeds: list[bytes]) -> None:
    if b:
        i = rng.randrange(len(b))
        b[i] ^= 1 << rng.randrange(8)


def _byte(rng: random.Random, b: bytearray, seeds: list[bytes]) -> None:
    if b:
        b[rng.randrange(len(b))] = rng.choice(INTERESTING_BYTES)


def _word(rng: random.Random, b: bytearray, seeds: list[bytes]) -> None:
    word = rng.choice(INTERESTING_WORDS)
    i = rng.randrange(len(b) + 1)
    b[i : i + len(word)] = word


def _insert(rng: random.Random, b: bytearray, seeds: list[bytes]) -> None:
    i = rng.randrange(len(b) + 1)
    b[i:i] = rng.randbytes(rng.randrange(1, 17))


def _delete(rng: random.Random, b: bytearray, seeds: list[bytes]) -> None:
    if b:
        i = rng.randrange(len(b))
        del b[i : i + rng.randrange(1, 17)]


def _duplicate(rng: random.Random, b: bytearray, seeds: list[bytes]) -> None:
    if b:
        i = rng.randrange(len(b))
        chunk = b[i : i + rng.randrange(1, 64)]
        j = rng.randrange(len(b) + 1)
        b[j:j] = chunk


def _truncate(rng: random.Random, b: bytearray, seeds: list[bytes]) -> None:
    if b:
        del b[rng.randrange(len(b)) :]


def _splice(rng: random.Random, b: bytearray, seeds: list[bytes]) -> None:
    other = rng.choice(seeds)
    i, j = rng.randrange(len(b) + 1), rng.randrange(len(other) + 1)
    b[i:] = other[j:]


def _token(rng: random.Random, b: bytearray, seeds: list[bytes]) -> None:
    """Replace one token (a number, a word, a punctuation mark) by an interesting one."""
    tokens = list(_TOKEN.finditer(bytes(b)))
    word = rng.choice(INTERESTING_TOKENS)
    if not tokens:
        b[:] = word
        return
    m = rng.choice(tokens)
    b[m.start() : m.end()] = word


def _insert_token(rng: random.Random, b: bytearray, seeds: list[bytes]) -> None:
    i = rng.randrange(len(b) + 1)
    b[i:i] = rng.choice(INTERESTING_TOKENS)


BYTE_MUTATIONS = (_flip, _byte, _word, _insert, _delete, _duplicate, _truncate, _splice)
TEXT_MUTATIONS = (*BYTE_MUTATIONS, _token, _token, _token, _insert_token)


def mutate(rng: random.Random, seeds: list[bytes], text: bool = False) -> bytes:
    """One input: usually 1-4 stacked mutations of a valid one, sometimes random bytes."""
    if rng.random() < 0.1:
        longest = max(len(s) for s in seeds)
        return rng.randbytes(rng.randrange(2 * longest + 1))
    b = bytearray(rng.choice(seeds))
    ops = TEXT_MUTATIONS if text else BYTE_MUTATIONS
    for _ in range(rng.choice((1, 1, 1, 2, 2, 3, 4))):
        rng.choice(ops)(rng, b, seeds)
    return bytes(b)


# ---- the decoders ------------------------------------------------------------------------


def _merge(into: Counter[str], before: dict[str, int], after: dict[str, int]) -> int:
    """Add what the decoder counted since `before`; returns how many rejections."""
    for key, value in after.items():
        delta = value - before.get(key, 0)
        if delta:
            into[key] += delta
    return after.get("rejected", 0) - before.get("rejected", 0)


class _Motoros:
    """MotoROS simple messages, either byte order, fed in random chunk sizes; the stream's
    end (`reset`) counts a frame left cut short."""

    def __init__(self) -> None:
        self.counters: Counter[str] = Counter()

    def __call__(self, data: bytes, index: int) -> int:
        from keo_service.adapters.simple_message import SimpleMessageDecoder

        dec = SimpleMessageDecoder("little" if index % 2 == 0 else "big")
        chunk = 1 + (index * 7919) % 97
        frames = 0
        for k in range(0, len(data), chunk):
            frames += len(dec.feed(data[k : k + chunk]))
        dec.reset()
        _merge(self.counters, {}, dict(dec.counters))
        return frames


def _motoros(work: Path) -> tuple[list[bytes], Runner]:
    from keo_service.adapters.simple_message import encode_joint_feedback, encode_robot_status

    seeds = []
    for order in ("little", "big"):
        seeds += [
            encode_joint_feedback([0.1, -0.2, 0.3, -0.4, 0.5, -0.6], order),
            encode_robot_status(byte_order=order),
            encode_joint_feedback([0.0] * 6, order) + encode_robot_status(byte_order=order),
        ]
    return seeds, _Motoros()


class _Line:
    """One line of the tracker line protocol after a hello (a fresh parser per input)."""

    def __init__(self) -> None:
        self.counters: Counter[str] = Counter()

    def __call__(self, data: bytes, index: int) -> int:
        from keo_service.adapters.line_protocol import LineProtocolParser, format_hello

        parser = LineProtocolParser()
        parser.parse(format_hello("mm" if index % 2 else "m"))
        pose = parser.parse(data)
        _merge(self.counters, {"hello": 1}, dict(parser.counters))
        if pose is None:
            return parser.counters["hello"] - 1  # a hello is a frame too
        values = [*(pose.position or ()), *(pose.quaternion or ()), pose.device_stamp]
        if not all(math.isfinite(v) for v in values):
            raise AssertionError(f"a decoded pose carries a non-finite value: {pose}")
        return 1


def _line(work: Path) -> tuple[list[bytes], Runner]:
    from keo_service.adapters.line_protocol import format_hello, format_pose

    seeds = [
        format_pose(17, 12.345, [1000.0, -250.5, 30.25], [1.0, 0.0, 0.0, 0.0]),
        format_pose(18, 12.355, [0.5, 0.25, 0.125], [0.5, 0.5, 0.5, 0.5]),
        format_pose(19, 12.365, [1.0, 2.0, 3.0], None),
        b'{"type": "pose", "seq": 20, "t": 12.375, "status": "beam_broken"}\n',
        format_hello("mm"),
    ]
    return seeds, _Line()


class _Rtde:
    """RTDE packages off a byte stream, each handled as the UR adapter does: data packages
    unpacked against keo's recipe, text messages, version and setup answers parsed; an
    RtdeError is the documented reject (counted by the decoder under the adapter's reason)."""

    def __init__(self) -> None:
        from keo_service.adapters import rtde

        self.counters: Counter[str] = Counter()
        self.recipe = rtde.Recipe(1, tuple(rtde.OUTPUTS), tuple(rtde.OUTPUTS.values()))

    def __call__(self, data: bytes, index: int) -> int:
        from keo_service.adapters import rtde

        dec = rtde.RtdeDecoder()
        chunk = 1 + (index * 7919) % 97
        frames = 0
        for k in range(0, len(data), chunk):
            for pkg in dec.feed(data[k : k + chunk]):
                reason = _RTDE_REASONS.get(pkg.type, "bad_answer")
                try:
                    self._handle(pkg)
                except rtde.RtdeError as exc:
                    dec.reject(reason, str(exc))
                    continue
                frames += 1
        if dec._buf:  # the stream ended inside a package
            dec.reject("truncated", f"{len(dec._buf)} bytes of an unfinished package")
        _merge(self.counters, {}, dict(dec.counters))
        return frames

    def _handle(self, pkg: Any) -> object:
        from keo_service.adapters import rtde

        if pkg.type == rtde.DATA_PACKAGE:
            return self.recipe.unpack(pkg.payload)
        if pkg.type == rtde.TEXT_MESSAGE:
            return rtde.parse_text_message(pkg)
        if pkg.type == rtde.GET_URCONTROL_VERSION:
            return rtde.parse_controller_version(pkg)
        if pkg.type == rtde.CONTROL_PACKAGE_SETUP_OUTPUTS:
            return rtde.parse_outputs_reply(pkg, list(rtde.OUTPUTS))
        return rtde.parse_accepted(pkg)


# RTDE package types (U, M, v, O) -> the reason a package of that type that fails to parse
# is counted under
_RTDE_REASONS = {85: "bad_data", 77: "bad_text", 118: "bad_version", 79: "bad_setup"}


def _rtde(work: Path) -> tuple[list[bytes], Runner]:
    from keo_service.adapters import rtde

    runner = _Rtde()
    values = {
        "timestamp": 1234.5,
        "actual_q": (0.1, -0.2, 0.3, -0.4, 0.5, -0.6),
        "actual_qd": (0.0,) * 6,
        "robot_mode": 7,
        "safety_mode": 1,
        "runtime_state": 2,
    }
    seeds = [
        rtde.data_package(runner.recipe, values),
        rtde.text_message("program started", "Controller", 2),
        rtde.controller_version(5, 11, 1, 108318),
        rtde.outputs_reply(1, list(rtde.OUTPUTS.values())),
        rtde.accepted(rtde.REQUEST_PROTOCOL_VERSION),
        rtde.data_package(runner.recipe, values) * 2,
    ]
    return seeds, runner


class _Ros2:
    """A ROS 2 sample's CDR bytes through the real adapter (`on_payload`: rosbags decodes,
    the adapter checks and publishes on an in-process Zenoh session with no peers)."""

    def __init__(self, adapter: Any, typenames: list[str]) -> None:
        self.counters: Counter[str] = Counter()
        self.adapter = adapter
        self.typenames = typenames

    def __call__(self, data: bytes, index: int) -> int:
        before_rejects = dict(self.adapter.rejects.counters)
        before = self.adapter.counters["published"]
        typename = self.typenames[index % len(self.typenames)]
        self.adapter.on_payload(data, typename, "fuzz")
        _merge(self.counters, before_rejects, dict(self.adapter.rejects.counters))
        return int(self.adapter.counters["published"] - before)


def _ros2_config() -> Any:
    from keo_service.io.config import load_config

    config = load_config(demo_config_path())
    return msgspec.structs.replace(
        config,
        robot=msgspec.structs.replace(config.robot, protocol="ros2"),
        tracker=msgspec.structs.replace(config.tracker, protocol="ros2"),
        ros2=msgspec.structs.replace(config.ros2, enabled=True),
    )


_SESSION: list[Any] = []


def _quiet_session() -> Any:
    """One Zenoh session without endpoints or scouting: publishes go nowhere."""
    if not _SESSION:
        from keo_service.live.bus import open_session

        _SESSION.append(open_session("peer"))
    return _SESSION[0]


def _ros2_joint_states(work: Path) -> tuple[list[bytes], Runner]:
    from keo_service.adapters.devices import Ros2JointStateAdapter
    from keo_service.io.cell import robot_from_config
    from keo_service.io.ros2_messages import JOINT_STATE, joint_state, typestore

    config = _ros2_config()
    names = list(robot_from_config(config).joint_names)
    adapter = Ros2JointStateAdapter(config, names, session=_quiet_session())
    adapter._declare(_quiet_session())
    store = typestore(config.ros2.distro)
    q = [0.1, -0.2, 0.3, -0.4, 0.5, -0.6][: len(names)]
    seeds = [
        store.serialize_cdr(joint_state(store.types, 12.5, names, q, q), JOINT_STATE),
        store.serialize_cdr(joint_state(store.types, 12.5, names[::-1], q, None), JOINT_STATE),
        store.serialize_cdr(
            joint_state(store.types, 1.0, [*names, "x"], [*q, 0], None), JOINT_STATE
        ),
    ]
    return [bytes(s) for s in seeds], _Ros2(adapter, [JOINT_STATE])


def _ros2_poses(work: Path) -> tuple[list[bytes], Runner]:
    from keo_service.adapters.devices import Ros2PoseAdapter
    from keo_service.io.ros2_messages import (
        POINT_STAMPED,
        POSE_STAMPED,
        point_stamped,
        pose_stamped,
        typestore,
    )

    config = _ros2_config()
    adapter = Ros2PoseAdapter(config, 6, session=_quiet_session())
    adapter._declare(_quiet_session())
    store = typestore(config.ros2.distro)
    pose = pose_stamped(store.types, 3.25, "tracker", [1.0, 2.0, 3.0], [0.5, 0.5, 0.5, 0.5])
    point = point_stamped(store.types, 3.25, "tracker", [1.0, 2.0, 3.0])
    seeds = [
        bytes(store.serialize_cdr(pose, POSE_STAMPED)),
        bytes(store.serialize_cdr(point, POINT_STAMPED)),
    ]
    # even inputs are decoded as poses, odd ones as points (a mutated pose read as a point
    # is one more kind of wrong input)
    return seeds, _Ros2(adapter, [POSE_STAMPED, POINT_STAMPED])


class _Codec:
    """A datagram codec with RejectLog counters (RSI, EGM): one long-lived codec, as the
    adapter keeps one per controller session."""

    def __init__(self, codec: Any, method: str) -> None:
        self.counters: Counter[str] = Counter()
        self.codec = codec
        self.parse = getattr(codec, method)

    def __call__(self, data: bytes, index: int) -> int:
        before = dict(self.codec.counters)
        frame = self.parse(data)
        _merge(self.counters, before, dict(self.codec.counters))
        return int(frame is not None)


def _kuka_rsi(work: Path) -> tuple[list[bytes], Runner]:
    rsi = importlib.import_module("keo_service.adapters.kuka_rsi")
    seeds = [rsi.format_rob(1000 + k, [0.0, -90.0 + k, 90.0, 0.0, 45.5, -10.25]) for k in range(3)]
    seeds.append(
        rsi.format_rob(2000, [1.0] * 6, tcp=[500.0, 0.0, 800.0, 0.0, 90.0, 0.0], external=[0.0] * 6)
    )
    return seeds, _Codec(rsi.RsiCodec(), "parse_rob")


def _abb_egm(work: Path) -> tuple[list[bytes], Runner]:
    egm = importlib.import_module("keo_service.adapters.abb_egm")
    seeds = [
        egm.format_robot(k + 1, 4 * k, [0.0, -30.0 + k, 20.0, 0.0, 45.5, -10.25]) for k in range(3)
    ]
    seeds.append(egm.format_robot(10, 40, [1.0] * 6, external=[0.5], motors_on=False))
    return seeds, _Codec(egm.EgmCodec(), "parse_robot")


_FORMAT_REASONS = (
    ("cannot open", "cannot open"),
    ("not UTF-8", "not UTF-8"),
    ("empty file", "empty file"),
    ("repeated column", "repeated columns"),
    ("first column", "bad header"),
    ("columns must", "bad header"),
    ("joint columns", "joint count"),
    ("fields, expected", "ragged row"),
    ("is not a number", "not a number"),
)


def _reason_of(exc: Exception) -> str:
    """A documented error's reason: the config key it names (or its kind), or the kind of
    format error."""
    if isinstance(exc, ConfigError):
        if exc.message in ("unknown key", "required key is missing"):
            return exc.message
        if exc.key == "(file)":
            return "not UTF-8" if "UTF-8" in exc.message else "cannot read"
        return (
            "TOML syntax" if exc.key == "(syntax)" else "key " + re.sub(r"\[\d+\]", "[]", exc.key)
        )
    text = str(exc)
    for words, reason in _FORMAT_REASONS:
        if words in text:
            return reason
    return "other: " + " ".join(text.rsplit(": ", maxsplit=1)[-1].split()[:3])


class _File:
    """A file reader fed through a real file (its documented reject: DataFormatError or
    ConfigError)."""

    def __init__(self, path: Path, read: Callable[[Path], object]) -> None:
        self.counters: Counter[str] = Counter()
        self.path = path
        self.read = read

    def __call__(self, data: bytes, index: int) -> int:
        self.path.write_bytes(data)
        try:
            self.read(self.path)
        except (DataFormatError, ConfigError) as exc:
            self.counters[_reason_of(exc)] += 1
            self.counters["rejected"] += 1
            return 0
        return 1


ENCODER_CSV = (
    b"t,q1,q2,q3,q4,q5,q6\n0.0,0.1,-0.2,0.3,-0.4,0.5,-0.6\n0.025,0.1,-0.2,0.3,-0.4,0.5,-0.6\n"
)
TRACKER_CSV = (
    b"t,x,y,z,qw,qx,qy,qz\n0.01,1.0,2.0,3.0,1.0,0.0,0.0,0.0\n0.02,1.0,2.0,3.0,0.5,0.5,0.5,0.5\n"
)


def _encoder_csv(work: Path) -> tuple[list[bytes], Runner]:
    from keo_service.io.interchange import read_encoder

    seeds = [ENCODER_CSV, b"t,q1,q2,q3,q4,q5,q6\n1e-3,-1.5E+0,2,3,4,5,6\n"]
    return seeds, _File(work / "encoder.csv", lambda p: read_encoder(p, nq=6))


def _tracker_csv(work: Path) -> tuple[list[bytes], Runner]:
    from keo_service.io.interchange import read_tracker

    position_only = b"t,x,y,z\n0.01,1.0,2.0,3.0\n0.02,1.5,2.5,3.5\n"
    return [TRACKER_CSV, position_only], _File(work / "tracker.csv", read_tracker)


def _config(work: Path) -> tuple[list[bytes], Runner]:
    from keo_service.io.config import load_config

    urdf = (configs_dir() / "robots" / "mh180.urdf").as_posix()
    demo = demo_config_path().read_text(encoding="utf-8")
    demo = demo.replace('urdf = "robots/mh180.urdf"', f'urdf = "{urdf}"')
    rich = (
        f'cell = "c1"\n[robot]\nurdf = "{urdf}"\nprotocol = "rtde"\nfrequency_hz = 500.0\n'
        'clock = "device"\n[tracker]\nprotocol = "line"\nuncertainty_um = 15.0\n'
        '[timing]\ndelay_s = 0.01\nalignment = "latest"\nmax_stamp_age_s = 0.5\n'
        "[observer]\ngain = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]\n[ros2]\nenabled = true\n"
        'domain_id = 3\n[compensation]\nmax_mm = 2.0\n[bus]\nmode = "client"\n'
        'connect = ["tcp/10.0.0.2:7447"]\n[model]\neffects = ["joint_offsets"]\n'
        "joint_offsets = [0.001, 0.0, 0.0, 0.0, 0.0, 0.0]\n"
    )
    return [demo.encode(), rich.encode()], _File(work / "keo.toml", load_config)


TARGETS: tuple[Target, ...] = (
    Target("motoros", _motoros),
    Target("tracker line protocol", _line, text=True),
    Target("rtde", _rtde),
    Target("ros2 JointState", _ros2_joint_states),
    Target("ros2 PoseStamped/PointStamped", _ros2_poses),
    Target("kuka_rsi", _kuka_rsi, text=True, needs="keo_service.adapters.kuka_rsi"),
    Target("abb_egm", _abb_egm, needs="keo_service.adapters.abb_egm"),
    Target("interchange encoder.csv", _encoder_csv, text=True),
    Target("interchange tracker.csv", _tracker_csv, text=True),
    Target("config (TOML)", _config, text=True),
)


def _available(module: str) -> bool:
    try:
        importlib.import_module(module)
    except ModuleNotFoundError:
        return False
    return True


def fuzz_one(target: Target, n: int, seed: int, work: Path, keep: int = 5) -> FuzzReport:
    report = FuzzReport(target.name)
    if target.needs and not _available(target.needs):
        report.skipped = f"{target.needs} is not in this checkout"
        return report
    seeds, runner = target.make(work)
    for s in seeds:  # the valid inputs decode: otherwise the mutations start from nothing
        if runner(s, 0) < 1 and runner(s, 1) < 1:  # (index parity: byte order, unit, type)
            raise AssertionError(f"{target.name}: a valid seed input did not decode: {s!r}")
    runner.counters.clear()
    rng = random.Random(f"{seed}:{target.name}")
    started = time.perf_counter()
    for index in range(n):
        data = mutate(rng, seeds, target.text)
        before = runner.counters["rejected"]
        try:
            frames = runner(data, index)
        except (KeyboardInterrupt, SystemExit):
            raise
        except BaseException as exc:  # anything but the documented reject path is a crash
            # (BaseException: a Rust library's panic arrives as pyo3's PanicException)
            report.crashes += 1
            if len(report.crash_examples) < keep:
                report.crash_examples.append(
                    {
                        "index": index,
                        "error": f"{type(exc).__name__}: {exc}",
                        "input_hex": data[:512].hex(),
                        "input_length": len(data),
                    }
                )
            continue
        rejected = runner.counters["rejected"] > before
        report.decoded += frames > 0
        report.rejected += rejected
        report.quiet += frames == 0 and not rejected
    report.inputs = n
    report.seconds = time.perf_counter() - started
    report.reasons = dict(runner.counters.most_common())
    return report


@contextlib.contextmanager
def _workdir() -> Iterator[Path]:
    with tempfile.TemporaryDirectory(prefix="keo-fuzz-") as tmp:
        yield Path(tmp)


def fuzz(n: int, seed: int = 1, only: list[str] | None = None) -> list[FuzzReport]:
    """N inputs for every decoder (or those whose name contains one of `only`)."""
    reports = []
    with _workdir() as work:
        for target in TARGETS:
            if only and not any(o.lower() in target.name.lower() for o in only):
                continue
            reports.append(fuzz_one(target, n, seed, work))
    return reports


def fuzz_table(reports: list[FuzzReport], n: int, seed: int) -> str:
    lines = [
        f"keo selftest --fuzz {n} --seed {seed}: {n} generated inputs per decoder",
        f"{'decoder':<31}{'inputs':>8}{'decoded':>9}{'rejected':>10}{'quiet':>7}"
        f"{'crashes':>9}{'s':>7}  rejections by reason",
    ]
    for r in reports:
        if r.skipped:
            lines.append(f"{r.name:<31}{'-':>8}  not fuzzed: {r.skipped}")
            continue
        reasons = ", ".join(f"{k} {v}" for k, v in r.reasons.items() if k != "rejected")
        lines.append(
            f"{r.name:<31}{r.inputs:>8}{r.decoded:>9}{r.rejected:>10}{r.quiet:>7}"
            f"{r.crashes:>9}{r.seconds:>7.1f}  {reasons}"
        )
        for c in r.crash_examples:
            lines.append(f"    CRASH at input {c['index']}: {c['error']}")
            lines.append(f"      input ({c['input_length']} bytes, hex): {c['input_hex']}")
    total = sum(r.crashes for r in reports)
    fuzzed = sum(1 for r in reports if not r.skipped)
    lines.append(f"{fuzzed} decoders, {fuzzed * n} inputs, {total} crashes")
    return "\n".join(lines) + "\n"
