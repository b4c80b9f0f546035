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
        clock: the clock domain `stamp` is on: "shared", "device" or "receipt"
            (`core.clock.Stamper`); "" from a writer that did not say.
        clock_epoch: a counter the adapter bumps whenever its time base starts anew
            (reconnect, device clock step): stamps of two epochs are not comparable.
        flags: notes on this sample's stamp (e.g. "stamp_ahead", "stamp_old",
            "clock_relearning").
        clock_drift: for a "device" stamp, the drift (s/s) of the clock mapping's line it was
            mapped with, so that a consumer can carry stamps onto the mapping's newer line
            (the delay tracker does); None otherwise.
    """

    stamp: float
    host_ns: int
    seq: int
    joints: list[float]
    velocities: list[float] | None = None
    device_stamp: float | None = None
    clock: str = ""
    clock_epoch: int = 0
    flags: list[str] = msgspec.field(default_factory=list)
    clock_drift: float | None = None


class RobotStatus(_Message, frozen=True, tag=_tag("robot_status")):
    """keo/<cell>/robot_status: the controller's state as ROS-Industrial's ROBOT_STATUS has it.

    MotoROS sends it; the RTDE adapter maps UR's robot and safety modes onto it and the EGM
    adapter its motor and EGM states. One message type for every controller, so that a
    client asks one question ("may the robot move?") whatever the protocol. The flags are
    integers, not booleans, because the controller may not know: 1 (true), 0 (false) or -1
    (unknown).

    Attributes:
        host_ns: when the adapter received it, ns since the epoch.
        drives_powered: the servo drives have power (1, 0, -1).
        e_stopped: an emergency stop is engaged (1, 0, -1).
        error_code: the controller's own error code as it gives it (RTDE: the safety mode
            of a fault); 0: none.
        in_error: the controller reports an error (1, 0, -1).
        in_motion: the robot is moving (1, 0, -1).
        mode: the controller's mode as it numbers it (MotoROS: ROS-Industrial's 1 manual,
            2 auto, -1 unknown; RTDE: UR's robot mode); 0 where the protocol does not tell.
        motion_possible: the robot would move if commanded (1, 0, -1).
    """

    host_ns: int
    drives_powered: int
    e_stopped: int
    error_code: int
    in_error: int
    in_motion: int
    mode: int
    motion_possible: int


class TrackerSample(_Message, frozen=True, tag=_tag("tracker")):
    """keo/<cell>/tracker: one measurement of the tracker, a pose or a gap.

    A gap is a sample too (status other than "ok", no pose): the estimator must know that
    the tracker lost the target, not only that nothing arrived.

    Attributes:
        stamp: the stream time used for alignment, s (the host's clock, in `clock`'s domain).
        host_ns: when the adapter received it, ns since the epoch.
        seq: the tracker's own sequence number.
        status: "ok", or why there is no pose, in the tracker's word for it.
        position: the sensor frame's origin in the tracker frame, m; None in a gap.
        quaternion: the sensor frame's orientation in the tracker frame, [w, x, y, z]
            (scalar first); None for a single reflector or in a gap.
        device_stamp: the tracker's own time of the sample, s, where it gives one.
        clock: the clock domain `stamp` is on, as in `JointSample`.
        clock_epoch: the time base's counter, as in `JointSample`.
        flags: notes on this sample's stamp, as in `JointSample`.
        clock_drift: the drift (s/s) of a device stamp's mapping line, as in `JointSample`.
    """

    stamp: float
    host_ns: int
    seq: int
    status: str = "ok"
    position: list[float] | None = None
    quaternion: list[float] | None = None
    device_stamp: float | None = None
    clock: str = ""
    clock_epoch: int = 0
    flags: list[str] = msgspec.field(default_factory=list)
    clock_drift: float | None = None


class DelayState(msgspec.Struct, frozen=True, kw_only=True):
    """Where the delay in use comes from and what the online delay tracker last decided, as
    data. Every `EstimateMessage` and `ServiceStatus` carries one in `delay_state` (None when
    `timing.track_delay` is off); the delay itself and its standard error are the message's
    `delay_s` and `delay_se_s`, so there is one delay, never a second. The status line's
    words (`delay_tracking`) are rendered from it in one place
    (`keo_service.live.status_view.delay_tracking_text`).

        msg = sync_client.latest()                  # the newest EstimateMessage, or None
        if msg is not None and (state := msg.delay_state) is not None and not state.settled:
            ...                                     # "delay_unsettled" is in msg.flags too

    Attributes:
        source: where the delay in use comes from: "configured" (`timing.delay_s`),
            "confirmed" (configured, and a precise fit agreed with it), "fit" (found or
            refined by the fits) or "unknown" (nothing configured, nothing found yet).
        source_t: the stream time of the fit behind the delay in use, s on the service's
            time base (seconds since the epoch for host-clock stamps); None: configured or
            unknown.
        settled: whether the delay in use is known to 20 um at the tool's speed; while
            False every estimate carries the flag "delay_unsettled".
        verdict: the tracker's last decision, one word: "waiting", "kept", "unsettled",
            "settled", "changed", "refined" or "restarted".
        reason: why, in words (no delay values in it: the one delay is `delay_s`).
        fit_s: the newest fit that decision was about, s; None: no fit.
        fit_se_s: its standard error, s, the fits' scatter beyond their own included; None:
            no fit.
        decided_t: the stream time of the end of the stretch that decision was about, s;
            None: no stretch yet.
    """

    source: str
    source_t: float | None = None
    settled: bool = True
    verdict: str = ""
    reason: str = ""
    fit_s: float | None = None
    fit_se_s: float | None = None
    decided_t: float | None = None


class EstimateMessage(_Message, frozen=True, tag=_tag("estimate")):
    """keo/<cell>/estimate: the observer's output for one tracker sample, as published.

    Made from the estimator's record (`core.estimator.Estimate`) by `estimate_message`, its
    fields under the same names, plus what only the publisher knows (when it was sent, the
    delay in use): a client can judge the estimate without asking the service anything.

    Attributes:
        stamp: the tracker sample's stream time, s (the tick's for "latest" alignment).
        host_ns: when the service published it, ns since the epoch.
        channels: the channel names: ["px", "py", "pz"] or with "rx", "ry", "rz".
        measured: the measured error of this sample per channel (m for px, py, pz; rad for
            rx, ry, rz, a rotation vector); None when the step was held (see `flags`).
        estimate: the observer's estimate of the error per channel, m and rad.
        flags: why the step was held, or what to know about it (e.g. "delay_unsettled").
        delay_s: the delay in use at `stamp`, s: the tracker stream lags the encoder's by it.
        seq: the service's counter, one per estimate (a gap is an estimate lost on the bus).
        device_stamp: the tracker's own time of the sample behind it, s, where it gives one.
        delay_se_s: the standard error of the delay in use, s, when it is known (calibrated
            or tracked); None when nobody measured it.
        tool_speed_m_s: the nominal tool point's speed at this estimate, m/s, from the
            joints of the estimates of the last 0.6 s (`core.tool_speed`); None before four
            were sampled, or after a pause.
        delay_state: the delay in use's source and the online tracker's last decision
            (`DelayState`); None when tracking is off.
    """

    stamp: float
    host_ns: int
    channels: list[str]
    measured: list[float] | None
    estimate: list[float]
    flags: list[str]
    delay_s: float
    seq: int
    device_stamp: float | None = None
    delay_se_s: float | None = None
    tool_speed_m_s: float | None = None
    delay_state: DelayState | None = None


def estimate_message(
    estimate: Estimate,
    *,
    host_ns: int,
    seq: int,
    delay_s: float,
    delay_se_s: float | None = None,
    tool_speed_m_s: float | None = None,
    delay_state: DelayState | None = None,
    more_flags: tuple[str, ...] = (),
) -> EstimateMessage:
    """The wire form of the estimator's record (`core.estimator.Estimate`): its fields under
    the same names, with what the publisher adds (receipt clock, sequence, the delay in use,
    `more_flags` after the estimate's own). The one place an `EstimateMessage` is made from
    an estimate."""
    # the record's values as it keeps them: plain lists on the live path, where this runs per
    # estimate (`measured_values` / `estimate_values` without their two calls)
    measured, values = estimate._measured, estimate._estimate
    return EstimateMessage(
        stamp=estimate.stamp,
        host_ns=host_ns,
        channels=list(estimate.channels),
        measured=measured if measured is None or isinstance(measured, list) else measured.tolist(),
        estimate=values if isinstance(values, list) else values.tolist(),
        flags=[*estimate.flags, *more_flags],
        delay_s=delay_s,
        seq=seq,
        device_stamp=estimate.device_stamp,
        delay_se_s=delay_se_s,
        tool_speed_m_s=tool_speed_m_s,
        delay_state=delay_state,
    )


class ServiceStatus(_Message, frozen=True, tag=_tag("status")):
    """keo/<cell>/status (a queryable): what the service is doing, for `keo status` and
    `Client.status()`.

    Attributes:
        cell: the config's `cell`.
        health: "ok", "waiting" (no estimate yet) or "stale" (none fresh for a second, or
            the newest one held).
        host_ns: when this status was made, ns since the epoch.
        uptime_s: seconds since the service started.
        rates_hz: samples per second of each stream and of the estimates.
        delay_s: the delay in use (s): the tracker stream lags the encoder stream by it.
        drift: the delay model's drift, s per s of stream time.
        gains: the observer's gains, 1/s (px py pz rx ry rz).
        alignment: how a tracker sample finds its joints: "interpolate" or "latest"
            (`[timing] alignment`).
        counters: rejects, held steps and the rest, by name.
        last_estimate: the newest estimate, if any.
        messages: the newest findings in words (at most 10), newest last.
        delay_tracking: the delay's source and what online delay tracking last did, in words
            (rendered from `delay_state`); None when it is off.
        delay_se_s: the standard error of the delay in use, s, when known.
        delay_state: the same as data (`DelayState`); None when tracking is off.
        clock_domains: each stream's clock domain as its samples declare it
            ({"encoder": "device", ...}).
        adapters: each adapter's own status (`AdapterStatus`), by adapter name, as the
            service last gathered them.
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
    delay_tracking: str | None = None
    delay_se_s: float | None = None
    clock_domains: dict[str, str] = msgspec.field(default_factory=dict)
    adapters: dict[str, AdapterStatus] = msgspec.field(default_factory=dict)
    delay_state: DelayState | None = None


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
    document on the wire is what each adapter wrote before it was typed.

    Attributes:
        adapter: which adapter: "encoder" or "tracker".
        state: what `adapters.health` makes of the connection: "starting", "connecting",
            "connected", "receiving", "silent", "wrong_protocol" or "disconnected".
        endpoint: where the device is: host:port, or the ROS 2 topic.
        protocol: the configured protocol (a row of `io.protocols`).
        rate_hz: samples published per second, Hz, over the last 5 s.
        last_data_age_s: seconds since the device last sent data; None: nothing yet on this
            connection.
        silent_events: how often a connected device went silent (nothing for its
            `silent_after_s`).
        problem: a device that does not speak the protocol, in words.
        last_error: the connection's newest problem in words, with the key to fix.
        counters: samples published, rejects and the rest, by name.
        clock: the stamping rule's state (`core.clock.Stamper.state()`: the domain, the
            epoch and, for a device clock, the mapping: offset s, drift ppm, residual s).
        decoder: the codec's reject counters, by reason.
        parser: the line protocol's reject counters, by reason (its codec's name for them).
        messages: the codec's newest reject messages, each saying where in the input it was.
        stamps_held_back: MotoROS: receipt stamps moved to just after the previous one, so
            that none goes back in time.
        controller: RTDE: the controller's version.
        topics: ROS 2: the topics subscribed.
        reply_us: the UDP servers (RSI, EGM): the time from a datagram's receipt to the
            answer's send, microseconds: "last", "p99", "max", and the answering thread's CPU
            time "cpu_p50", "cpu_p99".
        cycle_ms: the UDP servers: the controller's cycle, ms.
        scheduling: the UDP servers: what real-time scheduling the answering thread got.
        correction: the UDP servers: the corrections sent ("sent_mm", "sent_mrad": the
            newest, mm and mrad; "reason" it is zero, if so; its counters); None:
            corrections are off.
        peer: the UDP servers: the controller's host:port, None before it spoke.
        external_axes: RSI, EGM: the external axes' values as the controller sends them
            (None when it sends none).
        controller_late_count: RSI: the controller's own count of late answers (its `Delay`
            element), None when it sends none.
        robot_state: EGM: the motors, EGM and RAPID states (True, False, None: not told).
        event_seq: counts the changes put on the key.
        event: what changed, in words, with the key to fix.
        level: how much the event matters, as the adapter judges it: "info", "warning" or
            "error" (the service logs it at this level; absent: `trouble` decides).
    """

    adapter: str
    state: str | UnsetType = UNSET
    endpoint: str | UnsetType = UNSET
    protocol: str | UnsetType = UNSET
    rate_hz: float | UnsetType = UNSET
    last_data_age_s: float | UnsetType | None = UNSET
    silent_events: int | UnsetType = UNSET
    problem: str | UnsetType = UNSET
    last_error: str | UnsetType = UNSET
    counters: dict[str, int] = msgspec.field(default_factory=dict)
    clock: dict[str, Any] | UnsetType = UNSET
    decoder: dict[str, int] | UnsetType = UNSET
    parser: dict[str, int] | UnsetType = UNSET
    messages: list[str] | UnsetType = UNSET
    stamps_held_back: int | UnsetType = UNSET
    controller: str | UnsetType = UNSET
    topics: list[str] | UnsetType = UNSET
    reply_us: dict[str, float] | UnsetType = UNSET
    cycle_ms: float | UnsetType = UNSET
    scheduling: str | UnsetType = UNSET
    correction: dict[str, Any] | UnsetType | None = UNSET
    peer: str | UnsetType | None = UNSET
    external_axes: list[float] | UnsetType | None = UNSET
    controller_late_count: int | UnsetType | None = UNSET
    robot_state: dict[str, bool | None] | UnsetType = UNSET
    event_seq: int | UnsetType = UNSET
    event: str | UnsetType = UNSET
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
        """The JSON document put on the status key (absent fields left out), UTF-8."""
        return msgspec.json.encode(self)

    @classmethod
    def from_json(cls, payload: bytes) -> AdapterStatus:
        """An adapter's status as read from its key.

        Args:
            payload: the JSON document, UTF-8 bytes.

        Returns:
            The status; fields the document lacks are UNSET.

        Raises:
            msgspec.DecodeError: the payload is not an adapter's status (the message says
                where and what).
        """
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
