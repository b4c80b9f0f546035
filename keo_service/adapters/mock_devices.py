"""Device simulators: TCP servers that play a simulated scenario in real time on the real wire
formats, so an adapter cannot tell them from a MotoROS controller or a tracker.

A row stamped t (scenario seconds) is sent at wall time t0 + t; both mocks given the same t0
reproduce the scenario's delay between the streams. Without a t0 the mocks take the start of
the current period on a wall-clock grid of the scenario's period (`wall_clock_t0`), so two
mocks started by hand at any time agree. Looping plays the scenario again every `period_s`
(the same for both streams). A client that connects late gets the rows from now on, as from
a real device.
"""

from __future__ import annotations

import asyncio
import collections
import json
import logging
import math
import struct
import time
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

from keo_service.adapters import rtde
from keo_service.adapters.line_protocol import format_hello, format_pose
from keo_service.adapters.mock import MockSettings, TcpMockServer
from keo_service.adapters.simple_message import encode_joint_feedback, encode_robot_status
from keo_service.io.config import Config

log = logging.getLogger("keo.mock")
STATUS_PERIOD_S = 0.5
# the least a device's clock advances between two rows it sends (a microsecond tick)
MIN_MOCK_STEP_S = 1e-6


def wall_clock_t0(period_s: float, now: float | None = None) -> float:
    """The start of the current period on a grid of `period_s` seconds since the epoch: every
    mock playing the same scenario computes the same t0, whenever it was started."""
    now = time.time() if now is None else now
    return math.floor(now / period_s) * period_s


def _first_pass(t0: float, period_s: float, now: float) -> float:
    """The start of the pass playing at `now` (t0 when it has not begun)."""
    return t0 + max(0, math.floor((now - t0) / period_s)) * period_s


class Resampled:
    """A played track read at any instant within it: a cubic spline through its rows (joints,
    positions, quaternions' components). A device samples when its cycle runs; this process's
    timer wakes late (asyncio waits in whole milliseconds, and the host is shared), so a row
    that goes out late describes the instant it goes out: that lateness is the mock's, not
    the link's, and a real controller's cycle does not have it (stamping the planned instant
    put this process's wake-ups, moving with the host's load, into every stream's transport
    time; docs/timing-delay.md measures both)."""

    def __init__(self, t: np.ndarray, values: np.ndarray) -> None:
        from scipy.interpolate import CubicSpline  # scipy costs its import only where played

        # in time order, once per instant (a tracker's rows are in stamp order, and jittered
        # stamps need not keep the order of the instants they measured)
        order = np.argsort(np.asarray(t, dtype=float), kind="stable")
        times = np.asarray(t, dtype=float)[order]
        keep = np.concatenate([[True], np.diff(times) > 0])
        self.t = times[keep]
        self._spline = CubicSpline(self.t, np.asarray(values, dtype=float)[order][keep], axis=0)

    def at(self, t: float) -> np.ndarray:
        out: np.ndarray = self._spline(min(max(t, self.t[0]), self.t[-1]))
        return out

    def velocity(self, t: float) -> np.ndarray:
        out: np.ndarray = self._spline(min(max(t, self.t[0]), self.t[-1]), 1)
        return out


def continuous_quaternions(quat: np.ndarray) -> np.ndarray:
    """The same rotations with each quaternion on the side of its predecessor (q and -q are
    one rotation; a spline through a sign flip would pass through nonsense)."""
    out = np.array(quat, dtype=float)
    for i in range(1, out.shape[0]):
        if out[i] @ out[i - 1] < 0:
            out[i] = -out[i]
    return out


async def _sleep_until(wall: float) -> None:
    delay = wall - time.time()
    if delay > 0:
        await asyncio.sleep(delay)


class JointTrack(Protocol):
    """Joint angles to play: times (n,) [s] and angles (n, nq) [rad]."""

    t: np.ndarray
    q: np.ndarray


class PoseTrack(Protocol):
    """Tracker poses to play: times (n,) [s], positions (n, 3) [m], scalar-first quaternions
    (n, 4) or None for a single reflector."""

    t: np.ndarray
    p: np.ndarray
    quat: np.ndarray | None


def stall_schedule(
    times: np.ndarray, late_s: float, burst_every_s: float, rng: np.random.Generator
) -> np.ndarray:
    """When rows stamped `times` go out if sending stalls every `burst_every_s` on average
    (0: never) for up to `late_s`: the rows held up go out together when the stall ends, as a
    congested network or a busy host delivers them."""
    send = times.astype(float).copy()
    if burst_every_s <= 0 or late_s <= 0 or times.size == 0:
        return send
    t_end = float(times[-1])
    at = float(times[0]) + float(rng.uniform(0, burst_every_s))
    while at < t_end:
        stall = float(rng.uniform(0.2, 1.0)) * late_s
        held = (times >= at) & (times < at + stall)
        send[held] = at + stall
        at += float(rng.exponential(burst_every_s)) + stall
    return send


class _MockServer(TcpMockServer):
    """A TCP server playing rows of a track to each client, from t0 on the wall clock."""

    def __init__(self, settings: MockSettings) -> None:
        self.host, self.port = settings.host, settings.port
        self.t0 = settings.t0
        self.loop_play = settings.loop
        self.period_s = settings.period_s  # None: the last row's time + 0.1 s
        # wall time after which nothing more is sent (None: no limit); with loop_play, a
        # mock on the wall-clock grid plays one whole period from wherever it starts
        self.play_until = settings.play_until
        self.clients = 0
        self._server: asyncio.Server | None = None
        self.send_offsets: np.ndarray | None = None  # per row: when it goes out (stalls)
        self.pass_offset_s = 0.0  # scenario seconds of the passes played before this one
        # a row that goes out late describes the instant it goes out (see Resampled); False:
        # every row as simulated, describing its planned instant however late it goes out
        self.resample = settings.resample

    async def _on_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.clients += 1
        try:
            await self._play(writer)
            await reader.read()  # stay connected, as a device does, until the client leaves
        except (ConnectionError, OSError):
            pass
        except asyncio.CancelledError:
            # shutting down; ending normally keeps asyncio from logging the cancelled handler
            pass
        finally:
            writer.close()

    async def _play_rows(
        self,
        writer: asyncio.StreamWriter,
        times: np.ndarray,
        frame: Callable[[int, float], bytes],
    ) -> None:
        """Play the rows at their times; `frame(i, t)` makes row i describing scenario time
        t: the row's time when it is held up by a planned stall (measured on time, delivered
        late), else the instant it goes out (see `Resampled`)."""
        assert self.t0 is not None
        duration = self.period_s or (float(times[-1]) + 0.1 if times.size else 0.0)
        start = self.t0
        if self.loop_play and duration > 0:
            start = _first_pass(self.t0, duration, time.time())
        while True:
            now = time.time()
            first = int(np.searchsorted(times, now - start))
            self.pass_offset_s = start - self.t0
            send = times if self.send_offsets is None else self.send_offsets
            i = first
            client = self.clients
            last = -math.inf  # the newest instant a row described
            try:
                while i < times.size:
                    if self.play_until is not None and start + float(times[i]) > self.play_until:
                        return
                    await _sleep_until(start + float(send[i]))
                    due = time.time() - start
                    planned = float(times[i])
                    on_time = self.resample and send[i] <= times[i]
                    at = max(planned, due) if on_time else planned
                    # a device's clock never goes back: after a row stamped late (this
                    # process woke late), a held-up row describes an instant no earlier
                    at = max(at, last + MIN_MOCK_STEP_S) if self.resample else at
                    chunk = [frame(i, at)]
                    last = at
                    i += 1
                    while i < times.size and send[i] <= due and send[i] > times[i]:
                        at = float(times[i])  # held up by a stall
                        at = max(at, last + MIN_MOCK_STEP_S) if self.resample else at
                        chunk.append(frame(i, at))
                        last = at
                        i += 1
                    writer.write(b"".join(chunk))
                    await writer.drain()
            finally:
                # what the client got of this pass: a late client misses the rows before it
                # came, a stop or a lost connection ends the pass early
                log.info(
                    "client %d: sent %d rows, from row %d of %d",
                    client,
                    i - first,
                    first,
                    len(times),
                )
            if not self.loop_play:
                return
            start += duration

    async def _play(self, writer: asyncio.StreamWriter) -> None:
        raise NotImplementedError


class MockRobot(_MockServer):
    """MotoROS state server: JOINT_FEEDBACK (time left at 0) and ROBOT_STATUS every 0.5 s."""

    def __init__(
        self, encoder: JointTrack, settings: MockSettings, byte_order: str = "little"
    ) -> None:
        super().__init__(settings)
        self.encoder = encoder
        self.byte_order = byte_order

    async def _play(self, writer: asyncio.StreamWriter) -> None:
        last_status = [0.0]
        joints = Resampled(self.encoder.t, self.encoder.q)

        def frame(i: int, at: float) -> bytes:
            q = self.encoder.q[i] if at == self.encoder.t[i] else joints.at(at)
            data = encode_joint_feedback(q.tolist(), self.byte_order)
            now = time.time()
            if now - last_status[0] > STATUS_PERIOD_S:
                last_status[0] = now
                data += encode_robot_status(byte_order=self.byte_order)
            return data

        await self._play_rows(writer, self.encoder.t, frame)


class MockTracker(_MockServer):
    """Line-protocol tracker: hello in millimetres, then one pose line per sample."""

    def __init__(
        self,
        tracker: PoseTrack,
        settings: MockSettings,
        *,
        length_unit: str = "mm",
        pose_at: Callable[[float], tuple[np.ndarray, np.ndarray] | None] | None = None,
        instants: np.ndarray | None = None,
    ) -> None:
        super().__init__(settings)
        self.tracker = tracker
        # the instant each row measured (the simulator's physical time: its stamps also carry
        # a delay, jitter and drift): a late row is read off the motion there; without them
        # the rows go out as simulated
        self.instants = None if instants is None else np.asarray(instants, dtype=float)
        self.resample = self.instants is not None and settings.resample
        # (offset s, drift ppm): the tracker's own free-running clock stamps each pose at the
        # instant it measured, `offset + scenario time * (1 + drift)`, whoever is connected
        # (None: the time since the connection, read when the line is sent)
        self.device_clock = settings.device_clock
        self.send_offsets = stall_schedule(
            np.asarray(tracker.t, dtype=float),
            settings.late_ms * 1e-3,
            settings.burst_every_s,
            np.random.default_rng(settings.seed),
        )
        # measured live instead of played: the sensor pose (m, scalar-first quaternion) for a
        # row's time, e.g. of an arm that a compensated controller moves (None: no target)
        self.pose_at = pose_at
        # faults a real tracker shows: (start, duration) of a broken beam in scenario seconds,
        # and (at, step) of a jump of its own clock
        self.beam_break = settings.beam_break
        self.clock_step = settings.clock_step
        # device time = wall clock at sending (for latency measurements), else time since connect
        self.wall_clock = settings.wall_clock
        self.length_unit = length_unit
        self.scale = 1e3 if length_unit == "mm" else 1.0

    async def _play(self, writer: asyncio.StreamWriter) -> None:
        writer.write(format_hello(self.length_unit, source="keo mock tracker"))
        seq = [0]
        device_t0 = time.monotonic()

        instants = self.tracker.t if self.instants is None else self.instants
        positions = Resampled(instants, self.tracker.p)
        quats = self.tracker.quat
        rotations = None if quats is None else Resampled(instants, continuous_quaternions(quats))

        def frame(i: int, t: float) -> bytes:
            seq[0] += 1
            if self.device_clock is not None:
                offset, ppm = self.device_clock
                device_stamp = round(offset + (t + self.pass_offset_s) * (1.0 + ppm * 1e-6), 7)
            elif self.wall_clock:
                device_stamp = time.time()
            else:
                device_stamp = round(time.monotonic() - device_t0, 6)
            if self.clock_step is not None and t >= self.clock_step[0]:
                device_stamp += self.clock_step[1]
            if self.beam_break is not None and 0 <= t - self.beam_break[0] < self.beam_break[1]:
                return format_pose(seq[0], device_stamp, None, None, status="beam_broken")
            if self.pose_at is not None:
                # measured now, as it goes out (the device time above is read now too, or is
                # the instant it goes out: see Resampled)
                assert self.t0 is not None
                measured = self.pose_at(time.time() - self.t0)
                if measured is None:
                    return format_pose(seq[0], device_stamp, None, None, status="no_target")
                return format_pose(
                    seq[0], device_stamp, (measured[0] * self.scale).tolist(), measured[1].tolist()
                )
            on_row = t == self.tracker.t[i]
            instant = float(instants[i]) + (t - float(self.tracker.t[i]))
            p = (self.tracker.p[i] if on_row else positions.at(instant)) * self.scale
            if quats is None or rotations is None:
                return format_pose(seq[0], device_stamp, p.tolist(), None)
            q = quats[i] if on_row else rotations.at(instant)
            return format_pose(seq[0], device_stamp, p.tolist(), (q / np.linalg.norm(q)).tolist())

        await self._play_rows(writer, self.tracker.t, frame)


# outputs the mock controller knows (name -> RTDE type); anything else is NOT_FOUND
MOCK_RTDE_OUTPUTS = {
    **rtde.OUTPUTS,
    "target_q": "VECTOR6D",
    "target_qd": "VECTOR6D",
    "actual_TCP_pose": "VECTOR6D",
    "actual_current": "VECTOR6D",
    "speed_scaling": "DOUBLE",
    "robot_status_bits": "UINT32",
    "safety_status_bits": "UINT32",
}
_ZERO = {"DOUBLE": 0.0, "INT32": 0, "UINT32": 0, "VECTOR6D": (0.0,) * 6}
# inputs the mock controller accepts (UR's RTDE guide); registers by pattern, see _input_type
MOCK_RTDE_INPUTS = {
    "speed_slider_mask": "UINT32",
    "speed_slider_fraction": "DOUBLE",
    "standard_digital_output_mask": "UINT8",
    "standard_digital_output": "UINT8",
    "configurable_digital_output_mask": "UINT8",
    "configurable_digital_output": "UINT8",
    "tool_digital_output_mask": "UINT8",
    "tool_digital_output": "UINT8",
    "standard_analog_output_mask": "UINT8",
    "standard_analog_output_type": "UINT8",
    "standard_analog_output_0": "DOUBLE",
    "standard_analog_output_1": "DOUBLE",
    "input_bit_registers0_to_31": "UINT32",
    "input_bit_registers32_to_63": "UINT32",
    "external_force_torque": "VECTOR6D",
}
INPUT_LOG = 20000  # register writes the mock keeps (wall time, values), for tests


def _input_type(name: str) -> str:
    for prefix, kind, top in (
        ("input_double_register_", "DOUBLE", 47),
        ("input_int_register_", "INT32", 47),
        ("input_bit_register_", "BOOL", 127),
    ):
        if name.startswith(prefix):
            index = name[len(prefix) :]
            ok = index.isdigit() and int(index) <= top
            if prefix == "input_bit_register_":
                ok = ok and int(index) >= 64
            return kind if ok else "NOT_FOUND"
    return MOCK_RTDE_INPUTS.get(name, "NOT_FOUND")


class MockRtdeController(TcpMockServer):
    """A Universal Robots controller's RTDE server (protocol 2) playing a joint track.

    It samples the track at the frequency the client asks for (at most `max_hz`: 500 on
    e-Series, 125 on CB3) and stamps each package with its own clock: `clock_offset_s` plus
    the scenario time, running `clock_drift_ppm` fast. Delivery can be late in bursts: every
    `burst_every_s` on average (0: never) sending stalls for up to `late_ms` and the packages
    held up go out together, as a congested network or a busy host delivers them.

    Inputs: clients set up input recipes (registers, outputs' masks) and write them with
    data packages; the latest values are kept in `inputs`, each change of the correction
    registers logged in `input_log`. With `follow` (scenario time, the six input double
    registers from `correction_register` on, None before any were written -> joints) the
    joints are not played from the track but made live, sample by sample: a controller
    running a program that adds the registers to its commanded tool pose.
    """

    kind = "mock RTDE controller"

    def __init__(
        self,
        track: JointTrack,
        settings: MockSettings,
        *,
        version: tuple[int, int, int, int] = (5, 15, 0, 0),
        follow: Callable[[float, tuple[float, ...] | None], np.ndarray] | None = None,
        correction_register: int = 24,
    ) -> None:
        self.track = track
        self.follow = follow
        self.correction_names = rtde.input_double_registers(correction_register)
        self.inputs: dict[str, object] = {}
        self.input_log: collections.deque[tuple[float, tuple[float, ...]]] = collections.deque(
            maxlen=INPUT_LOG
        )
        # looping: the track again every period_s (default: its last time + 0.1 s), the
        # controller's clock running on
        self.loop_play = settings.loop
        self.period_s = settings.period_s or float(track.t[-1]) + 0.1
        self.play_until = settings.play_until  # as _MockServer.play_until
        self.host, self.port, self.t0 = settings.host, settings.port, settings.t0
        self.max_hz = settings.max_hz
        offset = settings.clock_offset_s
        self.clock_offset_s = 1000.0 if offset is None else offset
        self.clock_drift = settings.clock_drift_ppm * 1e-6
        self.late_s, self.burst_every_s = settings.late_ms * 1e-3, settings.burst_every_s
        self.version = version
        self.rng = np.random.default_rng(settings.seed)
        self.resample = settings.resample  # as _MockServer.resample
        self.clients = 0
        # (scenario time, controller stamp) of the newest packages, for tests
        self.sent: collections.deque[tuple[float, float]] = collections.deque(maxlen=100_000)
        self._server: asyncio.Server | None = None

    def device_time(self, scenario_t: float) -> float:
        return self.clock_offset_s + scenario_t * (1.0 + self.clock_drift)

    # the controller's session: one branch per message it answers, in the protocol's order
    async def _on_client(  # noqa: C901, PLR0912, PLR0915
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ) -> None:
        self.clients += 1
        decoder = rtde.RtdeDecoder()
        recipe: rtde.Recipe | None = None
        input_recipes: dict[int, rtde.Recipe] = {}
        setups = 0
        frequency = self.max_hz
        streaming: asyncio.Task[None] | None = None
        try:
            while data := await reader.read(4096):
                for pkg in decoder.feed(data):
                    kind = pkg.type
                    if kind == rtde.REQUEST_PROTOCOL_VERSION:
                        (version,) = struct.unpack(">H", pkg.payload[:2])
                        writer.write(rtde.accepted(kind, version == rtde.PROTOCOL_VERSION))
                    elif kind == rtde.GET_URCONTROL_VERSION:
                        writer.write(rtde.controller_version(*self.version))
                    elif kind == rtde.CONTROL_PACKAGE_SETUP_OUTPUTS:
                        asked, names = rtde.parse_setup_request(pkg)
                        if asked > 0:
                            frequency = min(asked, self.max_hz)
                        types = [MOCK_RTDE_OUTPUTS.get(n, "NOT_FOUND") for n in names]
                        setups += 1  # recipe ids count every setup of the connection, from 1
                        writer.write(rtde.outputs_reply(setups, types))
                        if "NOT_FOUND" not in types:
                            recipe = rtde.Recipe(setups, tuple(names), tuple(types))
                    elif kind == rtde.CONTROL_PACKAGE_SETUP_INPUTS:
                        names = rtde.parse_setup_inputs_request(pkg)
                        types = [_input_type(n) for n in names]
                        setups += 1
                        recipe_id = setups
                        log.debug("input recipe %d: %s -> %s", recipe_id, names, types)
                        writer.write(rtde.inputs_reply(recipe_id, types))
                        if names and "NOT_FOUND" not in types and recipe_id < 256:
                            input_recipes[recipe_id] = rtde.Recipe(
                                recipe_id, tuple(names), tuple(types)
                            )
                    elif kind == rtde.DATA_PACKAGE:
                        self._on_inputs(decoder, input_recipes, pkg)
                    elif kind == rtde.CONTROL_PACKAGE_START:
                        writer.write(rtde.accepted(kind, recipe is not None))
                        if recipe is not None and streaming is None:
                            writer.write(rtde.text_message(f"streaming at {frequency:g} Hz"))
                            streaming = asyncio.create_task(self._stream(writer, recipe, frequency))
                    elif kind == rtde.CONTROL_PACKAGE_PAUSE:
                        if streaming is not None:
                            streaming.cancel()
                            streaming = None
                        writer.write(rtde.accepted(kind))
                    await writer.drain()
        except (ConnectionError, OSError, asyncio.CancelledError):
            pass
        finally:
            if streaming is not None:
                streaming.cancel()
            writer.close()

    def _on_inputs(
        self, decoder: rtde.RtdeDecoder, recipes: dict[int, rtde.Recipe], pkg: rtde.Package
    ) -> None:
        recipe = recipes.get(pkg.payload[0]) if pkg.payload else None
        if recipe is None:
            decoder.reject("unknown_input_recipe", "data package for no input recipe set up")
            return
        try:
            values = recipe.unpack(pkg.payload)
        except rtde.RtdeError as exc:
            decoder.reject("bad_input", str(exc))
            return
        before = self.correction()
        changed = {k: v for k, v in values.items() if self.inputs.get(k) != v}
        if changed:
            log.debug("inputs written: %s", json.dumps(changed, sort_keys=True))
        self.inputs.update(values)
        after = self.correction()
        if after is not None and after != before:
            self.input_log.append((time.time(), after))

    def correction(self) -> tuple[float, ...] | None:
        """The six correction registers as last written, None before any were."""
        if not all(n in self.inputs for n in self.correction_names):
            return None
        return tuple(float(self.inputs[n]) for n in self.correction_names)  # type: ignore[arg-type]

    def _schedule(self, frequency: float) -> tuple[np.ndarray, np.ndarray]:
        """Scenario times of the samples and the wall-clock offsets at which they go out."""
        t_end = float(self.track.t[-1])
        times = np.arange(math.ceil(float(self.track.t[0]) * frequency), t_end * frequency)
        times = times / frequency
        send = times.copy()
        if self.burst_every_s > 0 and self.late_s > 0:
            at = float(self.rng.uniform(0, self.burst_every_s))
            while at < t_end:
                stall = float(self.rng.uniform(0.2, 1.0)) * self.late_s
                held = (times >= at) & (times < at + stall)
                send[held] = at + stall  # held up, then out together
                at += float(self.rng.exponential(self.burst_every_s)) + stall
        return times, send

    async def _stream(self, writer: asyncio.StreamWriter, recipe: rtde.Recipe, hz: float) -> None:
        assert self.t0 is not None
        start = self.t0
        if self.loop_play:
            start = _first_pass(self.t0, self.period_s, time.time())
        while True:
            # the pass number keeps the controller's clock running on from pass to pass
            passes = round((start - self.t0) / self.period_s) if self.loop_play else 0
            await self._stream_pass(writer, recipe, hz, start, passes * self.period_s)
            if not self.loop_play or (self.play_until is not None and start > self.play_until):
                return
            start += self.period_s

    # one pass of the track: each row's time, its stall, looping and the stop, in order
    async def _stream_pass(  # noqa: C901
        self,
        writer: asyncio.StreamWriter,
        recipe: rtde.Recipe,
        hz: float,
        start: float,
        offset_s: float,
    ) -> None:
        """One pass of the track from wall time `start`; the scenario time of each package
        on the controller's clock is its time in the track + `offset_s`."""
        times, send = self._schedule(hz)
        resample = self.follow is None and self.resample
        track = Resampled(self.track.t, self.track.q) if resample else None
        if self.follow is None and track is None:  # as simulated
            q = np.column_stack([np.interp(times, self.track.t, c) for c in self.track.q.T])
            qd = np.gradient(q, times, axis=0) if times.size > 1 else np.zeros_like(q)
        else:  # made live, sample by sample (follow), or read off the track when it goes out
            q = np.zeros((times.size, len(self.track.q[0])))
            qd = np.zeros_like(q)
        n = times.size
        if self.play_until is not None:
            n = int(np.searchsorted(send, self.play_until - start, side="right"))
        i = int(np.searchsorted(send, time.time() - start))  # a late client: from now on
        first, last = i, -math.inf  # last: the newest instant a package described
        made = i - 1  # follow: samples made so far, each ahead of its planned time

        def make(k: int) -> None:
            assert self.follow is not None
            q[k] = self.follow(float(times[k]), self.correction())
            if k > first:
                qd[k] = (q[k] - q[k - 1]) / (times[k] - times[k - 1])

        while i < n:
            if self.follow is not None and made < i:
                make(i)
                made = i
            now = time.time() - start
            if send[i] > now:
                await asyncio.sleep(send[i] - now)
                continue
            chunk = []
            while i < n and send[i] <= now:  # everything due: one write, as a burst arrives
                at, joints, speed = float(times[i]), q[i], qd[i]
                if track is not None:
                    # on time: the instant it goes out (Resampled); the controller's clock
                    # never goes back: after a package stamped late (this process woke late),
                    # a held-up one describes an instant no earlier
                    on_time = time.time() - start if send[i] <= times[i] else at
                    at = last = max(at, on_time, last + MIN_MOCK_STEP_S)
                    joints, speed = track.at(at), track.velocity(at)
                elif self.follow is not None:
                    if made < i:
                        make(i)
                        made = i
                    # stamped when it goes out (an asyncio wake-up comes up to a millisecond
                    # late; a controller's cycle does not): the joints carried there along the
                    # last step's velocity
                    at = time.time() - start
                    joints = q[i] + qd[i] * (at - times[i])
                stamp = self.device_time(at + offset_s)
                values: dict[str, object] = {
                    name: _ZERO[kind] for name, kind in zip(recipe.names, recipe.types, strict=True)
                }
                values.update(
                    timestamp=stamp,
                    actual_q=tuple(joints.tolist()),
                    actual_qd=tuple(speed.tolist()),
                    target_q=tuple(joints.tolist()),
                    robot_mode=7,
                    safety_mode=1,
                    runtime_state=2,
                )
                chunk.append(rtde.data_package(recipe, {k: values[k] for k in recipe.names}))
                self.sent.append((at, stamp))
                i += 1
            writer.write(b"".join(chunk))
            await writer.drain()


# ---- the protocol table's builders (io.protocols: MockSettings -> the mock) ----


def motoros_mock(s: MockSettings, config: Config, run: Any) -> MockRobot:
    """A MotoROS controller playing the run's joints in the config's byte order."""
    return MockRobot(run.encoder, s, config.robot.byte_order)


def rtde_mock(s: MockSettings, config: Config, run: Any) -> MockRtdeController:
    """A UR controller's RTDE server playing the run's joints on its own clock."""
    return MockRtdeController(run.encoder, s, correction_register=config.robot.correction_register)


def line_mock(s: MockSettings, config: Config, run: Any) -> MockTracker:
    """A line-protocol tracker playing the run's poses, with the faults asked for."""
    return MockTracker(run.tracker, s, instants=run.physical_t)
