"""Device simulators: TCP servers that play a simulated scenario in real time on the real wire
formats, so an adapter cannot tell them from a MotoROS controller or a tracker.

A row stamped t (scenario seconds) is sent at wall time t0 + t; both mocks given the same t0
reproduce the scenario's delay between the streams. A client that connects late gets the
rows from now on, as from a real device.
"""

from __future__ import annotations

import asyncio
import logging
import math
import struct
import time
from collections.abc import Callable
from typing import Protocol

import numpy as np

from adapters import rtde
from adapters.line_protocol import format_hello, format_pose
from adapters.simple_message import encode_joint_feedback, encode_robot_status

log = logging.getLogger("keo.mock")
STATUS_PERIOD_S = 0.5


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


class _MockServer:
    def __init__(self, host: str, port: int, t0: float | None, loop_play: bool) -> None:
        self.host, self.port = host, port
        self.t0 = t0
        self.loop_play = loop_play
        self.clients = 0
        self._server: asyncio.Server | None = None
        self.send_offsets: np.ndarray | None = None  # per row: when it goes out (stalls)

    async def start(self) -> None:
        self._server = await asyncio.start_server(self._on_client, self.host, self.port)
        if self.t0 is None:
            self.t0 = time.time() + 0.5
        log.info("mock listening on %s:%d, playing from t0=%.3f", self.host, self.port, self.t0)

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()

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
        self, writer: asyncio.StreamWriter, times: np.ndarray, frame: Callable[[int], bytes]
    ) -> None:
        assert self.t0 is not None
        start = self.t0
        duration = float(times[-1]) + 0.1 if times.size else 0.0
        while True:
            now = time.time()
            first = int(np.searchsorted(times, now - start))
            send = times if self.send_offsets is None else self.send_offsets
            i = first
            while i < times.size:
                await _sleep_until(start + float(send[i]))
                due = time.time() - start
                chunk = [frame(i)]
                i += 1
                while i < times.size and send[i] <= due and send[i] > times[i]:
                    chunk.append(frame(i))  # held up by a stall: out together
                    i += 1
                writer.write(b"".join(chunk))
                await writer.drain()
            if not self.loop_play:
                return
            start += duration

    async def _play(self, writer: asyncio.StreamWriter) -> None:
        raise NotImplementedError


class MockRobot(_MockServer):
    """MotoROS state server: JOINT_FEEDBACK (time left at 0) and ROBOT_STATUS every 0.5 s."""

    def __init__(
        self,
        encoder: JointTrack,
        host: str,
        port: int,
        byte_order: str = "little",
        t0: float | None = None,
        loop_play: bool = False,
    ) -> None:
        super().__init__(host, port, t0, loop_play)
        self.encoder = encoder
        self.byte_order = byte_order

    async def _play(self, writer: asyncio.StreamWriter) -> None:
        last_status = [0.0]

        def frame(i: int) -> bytes:
            data = encode_joint_feedback(self.encoder.q[i].tolist(), self.byte_order)
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
        host: str,
        port: int,
        t0: float | None = None,
        loop_play: bool = False,
        length_unit: str = "mm",
        wall_clock: bool = False,
        beam_break: tuple[float, float] | None = None,
        clock_step: tuple[float, float] | None = None,
        device_clock: tuple[float, float] | None = None,
        late_ms: float = 0.0,
        burst_every_s: float = 0.0,
        seed: int = 0,
    ) -> None:
        super().__init__(host, port, t0, loop_play)
        self.tracker = tracker
        # (offset s, drift ppm): the tracker's own free-running clock stamps each pose at the
        # instant it measured, `offset + scenario time * (1 + drift)`, whoever is connected
        # (None: the time since the connection, read when the line is sent)
        self.device_clock = device_clock
        self.send_offsets = stall_schedule(
            np.asarray(tracker.t, dtype=float),
            late_ms * 1e-3,
            burst_every_s,
            np.random.default_rng(seed),
        )
        # faults a real tracker shows: (start, duration) of a broken beam in scenario seconds,
        # and (at, step) of a jump of its own clock
        self.beam_break = beam_break
        self.clock_step = clock_step
        # device time = wall clock at sending (for latency measurements), else time since connect
        self.wall_clock = wall_clock
        self.length_unit = length_unit
        self.scale = 1e3 if length_unit == "mm" else 1.0

    async def _play(self, writer: asyncio.StreamWriter) -> None:
        writer.write(format_hello(self.length_unit, source="keo mock tracker"))
        seq = [0]
        device_t0 = time.monotonic()

        def frame(i: int) -> bytes:
            seq[0] += 1
            t = float(self.tracker.t[i])
            if self.device_clock is not None:
                offset, ppm = self.device_clock
                device_t = round(offset + t * (1.0 + ppm * 1e-6), 7)
            elif self.wall_clock:
                device_t = time.time()
            else:
                device_t = round(time.monotonic() - device_t0, 6)
            if self.clock_step is not None and t >= self.clock_step[0]:
                device_t += self.clock_step[1]
            if self.beam_break is not None and 0 <= t - self.beam_break[0] < self.beam_break[1]:
                return format_pose(seq[0], device_t, None, None, status="beam_broken")
            p = (self.tracker.p[i] * self.scale).tolist()
            q = None if self.tracker.quat is None else self.tracker.quat[i].tolist()
            return format_pose(seq[0], device_t, p, q)

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


class MockRtdeController:
    """A Universal Robots controller's RTDE server (protocol 2) playing a joint track.

    It samples the track at the frequency the client asks for (at most `max_hz`: 500 on
    e-Series, 125 on CB3) and stamps each package with its own clock: `clock_offset_s` plus
    the scenario time, running `clock_drift_ppm` fast. Delivery can be late in bursts: every
    `burst_every_s` on average (0: never) sending stalls for up to `late_ms` and the packages
    held up go out together, as a congested network or a busy host delivers them.
    """

    def __init__(
        self,
        track: JointTrack,
        host: str,
        port: int,
        t0: float | None = None,
        max_hz: float = 500.0,
        clock_offset_s: float = 1000.0,
        clock_drift_ppm: float = 0.0,
        late_ms: float = 0.0,
        burst_every_s: float = 0.0,
        version: tuple[int, int, int, int] = (5, 15, 0, 0),
        seed: int = 0,
    ) -> None:
        self.track = track
        self.host, self.port, self.t0 = host, port, t0
        self.max_hz = max_hz
        self.clock_offset_s, self.clock_drift = clock_offset_s, clock_drift_ppm * 1e-6
        self.late_s, self.burst_every_s = late_ms * 1e-3, burst_every_s
        self.version = version
        self.rng = np.random.default_rng(seed)
        self.clients = 0
        self.sent: list[tuple[float, float]] = []  # (scenario time, controller stamp), for tests
        self._server: asyncio.Server | None = None

    async def start(self) -> None:
        self._server = await asyncio.start_server(self._on_client, self.host, self.port)
        if self.t0 is None:
            self.t0 = time.time() + 0.5
        log.info(
            "mock RTDE controller on %s:%d, playing from t0=%.3f", self.host, self.port, self.t0
        )

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()

    def device_time(self, scenario_t: float) -> float:
        return self.clock_offset_s + scenario_t * (1.0 + self.clock_drift)

    async def _on_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.clients += 1
        decoder = rtde.RtdeDecoder()
        recipe: rtde.Recipe | None = None
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
                        writer.write(rtde.outputs_reply(1, types))
                        if "NOT_FOUND" not in types:
                            recipe = rtde.Recipe(1, tuple(names), tuple(types))
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

    def _schedule(self, frequency: float) -> tuple[np.ndarray, np.ndarray]:
        """Scenario times of the samples and the wall-clock offsets at which they go out."""
        t_end = float(self.track.t[-1])
        times = np.arange(math.ceil(float(self.track.t[0]) * frequency), t_end * frequency)
        times = times / frequency
        return times, stall_schedule(times, self.late_s, self.burst_every_s, self.rng)

    async def _stream(self, writer: asyncio.StreamWriter, recipe: rtde.Recipe, hz: float) -> None:
        assert self.t0 is not None
        times, send = self._schedule(hz)
        q = np.column_stack([np.interp(times, self.track.t, c) for c in self.track.q.T])
        qd = np.gradient(q, times, axis=0) if times.size > 1 else np.zeros_like(q)
        # a client that starts streaming late gets the samples from now on, as from a real
        # controller (not the backlog since the play began)
        i, n = int(np.searchsorted(times, time.time() - self.t0)), times.size
        while i < n:
            now = time.time() - self.t0
            if send[i] > now:
                await asyncio.sleep(send[i] - now)
                continue
            chunk = []
            while i < n and send[i] <= now:  # everything due: one write, as a burst arrives
                stamp = self.device_time(float(times[i]))
                values: dict[str, object] = {
                    name: _ZERO[kind] for name, kind in zip(recipe.names, recipe.types, strict=True)
                }
                values.update(
                    timestamp=stamp,
                    actual_q=tuple(q[i].tolist()),
                    actual_qd=tuple(qd[i].tolist()),
                    target_q=tuple(q[i].tolist()),
                    robot_mode=7,
                    safety_mode=1,
                    runtime_state=2,
                )
                chunk.append(rtde.data_package(recipe, {k: values[k] for k in recipe.names}))
                self.sent.append((float(times[i]), stamp))
                i += 1
            writer.write(b"".join(chunk))
            await writer.drain()
