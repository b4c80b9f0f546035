"""Wire messages: msgspec Structs encoded as MessagePack, shared by adapters, service, clients.

The schema version is part of each message's tag ("keo.joint/1"), so a client that meets a
payload from an incompatible version gets a clear decode error instead of wrong numbers.
Units are SI. `host_ns` is the host time (ns since the epoch) at which the sample was received;
`t` (seconds, same clock) is the stream time used for alignment, kept as its own float so a
replay reproduces the exact numbers.
"""

from __future__ import annotations

from typing import Any

import msgspec

SCHEMA_VERSION = 1


def _tag(name: str) -> str:
    return f"keo.{name}/{SCHEMA_VERSION}"


class _Message(msgspec.Struct, frozen=True, kw_only=True, tag_field="type"):
    pass


class JointSample(_Message, frozen=True, tag=_tag("joint")):
    t: float
    host_ns: int
    seq: int
    q: list[float]
    dq: list[float] | None = None
    device_t: float | None = None
    # the clock domain `t` is on ("shared", "device", "receipt"), a counter the adapter bumps
    # whenever its time base starts anew (reconnect, device clock step) and per-sample notes
    # on the stamp (e.g. "stamp_ahead", "stamp_old", "clock_relearning")
    clock: str = ""
    clock_epoch: int = 0
    flags: list[str] = msgspec.field(default_factory=list)


class RobotStatus(_Message, frozen=True, tag=_tag("robot_status")):
    host_ns: int
    drives_powered: int
    e_stopped: int
    error_code: int
    in_error: int
    in_motion: int
    mode: int
    motion_possible: int


class TrackerSample(_Message, frozen=True, tag=_tag("tracker")):
    """A pose (p, and q scalar first for a 6-DoF probe), or a gap when status != "ok"."""

    t: float
    host_ns: int
    seq: int
    status: str = "ok"
    p: list[float] | None = None
    q: list[float] | None = None
    device_t: float | None = None
    clock: str = ""  # as in JointSample
    clock_epoch: int = 0
    flags: list[str] = msgspec.field(default_factory=list)


class EstimateMessage(_Message, frozen=True, tag=_tag("estimate")):
    stamp: float
    host_ns: int
    channels: list[str]
    measured: list[float] | None
    estimate: list[float]
    flags: list[str]
    delay_s: float
    seq: int
    # device time of the tracker sample behind this estimate, when the tracker gives one
    tracker_device_t: float | None = None
    # standard error of the delay in use (s), when it is known (calibrated or tracked)
    delay_se_s: float | None = None
    # tool speed at this estimate (m/s), from the joint velocities
    tool_speed_m_s: float | None = None


class ServiceStatus(_Message, frozen=True, tag=_tag("status")):
    cell: str
    health: str
    host_ns: int
    uptime_s: float
    rates_hz: dict[str, float]
    delay_s: float
    drift: float
    gains: list[float]
    alignment: str
    counters: dict[str, int]
    last_estimate: EstimateMessage | None
    messages: list[str]
    delay_tracking: str | None = None  # what online delay tracking last did (when enabled)
    delay_se_s: float | None = None  # standard error of the delay in use (s), when known
    # each stream's clock domain as the samples declare it ("encoder": "device", ...)
    clock_domains: dict[str, str] = msgspec.field(default_factory=dict)
    # each adapter's own status (state, rates, counters, newest rejects), as gathered
    adapters: dict[str, dict[str, Any]] = msgspec.field(default_factory=dict)


class CorrectionMessage(_Message, frozen=True, tag=_tag("correction")):
    """keo/<cell>/correction: the transform to apply to the commanded tool pose now so that
    the tool lands where commanded (translation m, rotation vector rad, in the tool frame),
    the sum of a feedback part (the live estimate) and a feedforward part (the identified
    model at the current joints). Zero and `valid = False` with the reason when it must not
    be applied (held step, stale input, outside the calibrated range)."""

    stamp: float
    host_ns: int
    seq: int
    translation: list[float]
    rotation: list[float]
    feedback_translation: list[float]
    feedback_rotation: list[float]
    feedforward_translation: list[float]
    feedforward_rotation: list[float]
    valid: bool
    reason: str = ""
    clamped: bool = False


Message = (
    JointSample | RobotStatus | TrackerSample | EstimateMessage | ServiceStatus | CorrectionMessage
)

ENCODER = msgspec.msgpack.Encoder()
DECODER = msgspec.msgpack.Decoder(Message)


def encode(message: Message) -> bytes:
    return ENCODER.encode(message)


def decode(payload: bytes) -> Message:
    """Raises msgspec.DecodeError (with where and what) for malformed or foreign payloads."""
    message: Message = DECODER.decode(payload)
    return message


def topic(cell: str, name: str) -> str:
    return f"keo/{cell}/{name}"
