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

import logging
from typing import TYPE_CHECKING, Any

import msgspec
from msgspec import UNSET, UnsetType

if TYPE_CHECKING:
    from keo_service.core.estimator import Estimate

SCHEMA_VERSION = 2


def _tag(name: str) -> str:
    return f"keo.{name}/{SCHEMA_VERSION}"


class _Message(msgspec.Struct, frozen=True, kw_only=True, tag_field="type"):
    pass


class JointSample(_Message, frozen=True, tag=_tag("joint")):
    """keo/<cell>/encoder: one joint sample of the robot, as an encoder adapter read it.

    Attributes:
        stamp: the stream time used for alignment, s (the host's clock, in `clock`'s domain).
        host_ns: when the adapter received it, ns since the epoch.
        seq: the adapter's counter, one per sample (a gap is a sample lost on the bus).
        joints: positions, rad (m for a prismatic joint), in the URDF's joint order.
        velocities: the joints' velocities, rad/s, where the controller gives them.
        device_stamp: the controller's own time of the sample, s, where it gives one.
    """

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
    """keo/<cell>/robot_status: the controller's state as ROS-Industrial's ROBOT_STATUS has it
    (MotoROS sends it; the RTDE adapter maps UR's robot and safety modes onto it), each field
    1 (true), 0 (false) or -1 (unknown); `error_code` and `mode` as the controller gives them;
    `host_ns` when it was received, ns since the epoch."""

    host_ns: int
    drives_powered: int
    e_stopped: int
    error_code: int
    in_error: int
    in_motion: int
    mode: int
    motion_possible: int


class TrackerSample(_Message, frozen=True, tag=_tag("tracker")):
    """keo/<cell>/tracker: a pose (position, and quaternion scalar first for a 6-DoF probe),
    or a gap when status != "ok" (`stamp`, `host_ns`, `device_stamp`, the clock fields as in
    `JointSample`; `seq` the tracker's own sequence number)."""

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
    """keo/<cell>/status (a queryable): what the service is doing, for `keo status` and
    `Client.status()`.

    Attributes:
        health: "ok", "waiting" (no estimate yet) or "stale" (none fresh for a second, or
            the newest one held).
        uptime_s: seconds since the service started; `host_ns` when this was made, ns.
        rates_hz: samples per second of each stream and of the estimates.
        delay_s: the delay in use (s): the tracker stream lags the encoder stream by it.
        drift: the delay model's drift, s per s of stream time.
        gains: the observer's gains, 1/s (px py pz rx ry rz).
        counters: rejects, held steps and the rest, by name.
        last_estimate: the newest estimate, if any; `messages`: the newest findings.
    """

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
    adapters: dict[str, AdapterStatus] = msgspec.field(default_factory=dict)


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


# An adapter's states that are trouble: logged as warnings by the service and the Rerun log,
# shown as such by `keo status` (the others are logged at info)
ADAPTER_TROUBLE = frozenset({"silent", "wrong_protocol", "disconnected"})


class AdapterStatus(msgspec.Struct, frozen=True, kw_only=True):
    """An adapter's own status on keo/<cell>/adapter/<name>/status, as JSON: what it answers to
    a query and puts on the key at each change of state (then with `event` and `event_seq`).

    JSON rather than MessagePack so that `keo echo` and any tool read it as it is; every field
    but `adapter` is absent (UNSET) where that kind of adapter has nothing to say, so the
    document on the wire is what each adapter wrote before it was typed. Units: `rate_hz` Hz,
    `last_data_age_s` and `cycle_ms` as named, `reply_us` microseconds.
    """

    adapter: str  # "encoder" or "tracker"
    # what adapters.health makes of it: "starting", "connecting", "connected", "receiving",
    # "silent", "wrong_protocol", "disconnected"
    state: str | UnsetType = UNSET
    endpoint: str | UnsetType = UNSET  # host:port, or the ROS 2 topic
    protocol: str | UnsetType = UNSET  # the configured protocol (io.protocols)
    rate_hz: float | UnsetType = UNSET  # published samples per second, over the last 5 s
    last_data_age_s: float | UnsetType | None = UNSET  # None: nothing yet on this connection
    silent_events: int | UnsetType = UNSET
    problem: str | UnsetType = UNSET  # a device that does not speak the protocol, in words
    last_error: str | UnsetType = UNSET  # the connection's newest problem, with the key to fix
    counters: dict[str, int] = msgspec.field(default_factory=dict)
    clock: dict[str, Any] | UnsetType = UNSET  # core.clock.Stamper.state()
    # the codec's reject counters ("decoder"; the line protocol's "parser") and newest messages
    decoder: dict[str, int] | UnsetType = UNSET
    parser: dict[str, int] | UnsetType = UNSET
    messages: list[str] | UnsetType = UNSET
    stamps_held_back: int | UnsetType = UNSET  # MotoROS: receipt stamps held back
    controller: str | UnsetType = UNSET  # RTDE: the controller's version
    topics: list[str] | UnsetType = UNSET  # ROS 2: the topics subscribed
    # the UDP servers (RSI, EGM): answer times, cycle, scheduling, the peer, corrections
    reply_us: dict[str, float] | UnsetType = UNSET
    cycle_ms: float | UnsetType = UNSET
    scheduling: str | UnsetType = UNSET
    correction: dict[str, Any] | UnsetType | None = UNSET
    peer: str | UnsetType | None = UNSET
    external_axes: list[float] | UnsetType | None = UNSET
    controller_late_count: int | UnsetType | None = UNSET
    robot_state: dict[str, bool | None] | UnsetType = UNSET
    event_seq: int | UnsetType = UNSET  # counts the changes put on the key
    event: str | UnsetType = UNSET  # what changed, in words, with the key to fix
    # how much the event matters, as the adapter judges it: "info", "warning" or "error" (the
    # service logs it at this level; absent: `trouble` decides)
    level: str | UnsetType = UNSET

    @property
    def trouble(self) -> bool:
        """Whether a user must act: a state in `ADAPTER_TROUBLE`, or a device it cannot reach
        (still connecting, with the connection's error)."""
        return self.state in ADAPTER_TROUBLE or (
            self.state == "connecting" and bool(self.last_error)
        )

    @property
    def log_level(self) -> int:
        """The `logging` level of its event: its own `level`, else warning for trouble."""
        levels = {"info": logging.INFO, "warning": logging.WARNING, "error": logging.ERROR}
        if isinstance(self.level, str) and self.level in levels:
            return levels[self.level]
        return logging.WARNING if self.trouble else logging.INFO

    def to_json(self) -> bytes:
        return msgspec.json.encode(self)

    @classmethod
    def from_json(cls, payload: bytes) -> AdapterStatus:
        """Raises msgspec.DecodeError (with where and what) for anything else."""
        return msgspec.json.decode(payload, type=cls)


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
