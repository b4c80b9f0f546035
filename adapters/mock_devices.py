"""Device simulators: TCP servers that play a simulated scenario in real time on the real wire
formats, so an adapter cannot tell them from a MotoROS controller or a tracker.

A row stamped t (scenario seconds) is sent at wall time t0 + t; both mocks given the same t0
reproduce the scenario's delay between the streams. A client that connects late gets the
rows from now on, as from a real device.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from typing import Protocol

import numpy as np

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


class _MockServer:
    def __init__(self, host: str, port: int, t0: float | None, loop_play: bool) -> None:
        self.host, self.port = host, port
        self.t0 = t0
        self.loop_play = loop_play
        self.clients = 0
        self._server: asyncio.Server | None = None

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
            for i in range(first, times.size):
                await _sleep_until(start + float(times[i]))
                writer.write(frame(i))
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
    ) -> None:
        super().__init__(host, port, t0, loop_play)
        self.tracker = tracker
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
            device_t = time.time() if self.wall_clock else round(time.monotonic() - device_t0, 6)
            if self.clock_step is not None and t >= self.clock_step[0]:
                device_t += self.clock_step[1]
            if self.beam_break is not None and 0 <= t - self.beam_break[0] < self.beam_break[1]:
                return format_pose(seq[0], device_t, None, None, status="beam_broken")
            p = (self.tracker.p[i] * self.scale).tolist()
            q = None if self.tracker.quat is None else self.tracker.quat[i].tolist()
            return format_pose(seq[0], device_t, p, q)

        await self._play_rows(writer, self.tracker.t, frame)
