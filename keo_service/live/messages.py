"""Wire messages: msgspec Structs encoded as MessagePack, shared by adapters, service, clients.

The schema version is part of each message's tag ("keo.joint/2"), so a client that meets a
payload from an incompatible version gets a clear decode error instead of wrong numbers.
Units are SI. One name per thing in every message: `host_ns` is the host time (ns since the
epoch) at which the sample was received; `stamp` (seconds, same clock) is the stream time used
for alignment, kept as its own float so a replay reproduces the exact numbers; `device_stamp`
is the device's own time of the sample (s, the device's clock), where it gives one.

Schema 2 (this one) renamed schema 1's fields: `t` -> `stamp`, `device_t` and the estimate's
`tracker_device_t` -> `device_stamp`, the joint sample's `q`/`dq` -> `joints`/`velocities`,
the tracker sample's `p`/`q` -> `position`/`quaternion`. Recordings (interchange CSV, ROS 2
MCAP) never held these messages and read the same under both.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import msgspec

if TYPE_CHECKING:
    from keo_service.core.estimator import Estimate

SCHEMA_VERSION = 2


def _tag(name: str) -> str:
    return f"keo.{name}/{SCHEMA_VERSION}"


class _Message(msgspec.Struct, frozen=True, kw_only=True, tag_field="type"):
    pass


class JointSample(_Message, frozen=True, tag=_tag("joint")):
    stamp: float
    host_ns: int
    seq: int
    joints: list[float]  # rad (m for a prismatic joint), the URDF's joint order
    velocities: list[float] | None = None  # the joints' velocities, rad/s
    device_stamp: float | None = None
    # the clock domain `stamp` is on ("shared", "device", "receipt"), a counter the adapter bumps
    # whenever its time base starts anew (reconnect, device clock step) and per-sample notes
    # on the stamp (e.g. "stamp_ahead", "stamp_old", "clock_relearning")
    clock: str = ""
    clock_epoch: int = 0
    flags: list[str] = msgspec.field(default_factory=list)
    # a "device" stamp: the drift (s/s) of the clock mapping's line it was mapped with, so a
    # consumer can carry stamps onto the mapping's newer line (the delay tracker does)
    clock_drift: float | None = None


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
    """A pose (position, and quaternion scalar first for a 6-DoF probe), or a gap when
    status != "ok"."""

    stamp: float
    host_ns: int
    seq: int
    status: str = "ok"
    position: list[float] | None = None  # m, the sensor frame's origin in the tracker frame
    quaternion: list[float] | None = None  # [w, x, y, z]; None for a single reflector
    device_stamp: float | None = None
    clock: str = ""  # as in JointSample
    clock_epoch: int = 0
    flags: list[str] = msgspec.field(default_factory=list)
    clock_drift: float | None = None  # as in JointSample


class EstimateMessage(_Message, frozen=True, tag=_tag("estimate")):
    stamp: float
    host_ns: int
    channels: list[str]
    measured: list[float] | None
    estimate: list[float]
    flags: list[str]
    delay_s: float
    seq: int
    # the device stamp of the tracker sample behind this estimate, when the tracker gives one
    device_stamp: float | None = None
    # standard error of the delay in use (s), when it is known (calibrated or tracked)
    delay_se_s: float | None = None
    # tool speed at this estimate (m/s), from the joint velocities
    tool_speed_m_s: float | None = None


def estimate_message(
    estimate: Estimate,
    *,
    host_ns: int,
    seq: int,
    delay_s: float,
    delay_se_s: float | None = None,
    tool_speed_m_s: float | None = None,
) -> EstimateMessage:
    """The wire form of the estimator's record (`core.estimator.Estimate`): its fields under
    the same names, with what the publisher adds (receipt clock, sequence, the delay in use).
    The one place an `EstimateMessage` is made from an estimate."""
    return EstimateMessage(
        stamp=estimate.stamp,
        host_ns=host_ns,
        channels=list(estimate.channels),
        measured=estimate.measured_values(),
        estimate=estimate.estimate_values(),
        flags=list(estimate.flags),
        delay_s=delay_s,
        seq=seq,
        device_stamp=estimate.device_stamp,
        delay_se_s=delay_se_s,
        tool_speed_m_s=tool_speed_m_s,
    )


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
