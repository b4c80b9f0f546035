"""Controller simulators for the UDP real-time interfaces: the KUKA RSI and ABB EGM controller
side, on the real wire formats.

Each sends one datagram per cycle (4 ms by default) to keo's server, stamped with its own
millisecond clock (RSI's IPOC, EGM's header.tm: `clock_offset_s` (in ms) plus the scenario time),
the send instant jittered by up to `jitter_ms`. An answer counts as late when it arrives more
than one cycle after its datagram went out, or never; after `max_late` late answers in a row
the controller stops the robot as the real one does (RSI's late-packet limit, EGM's comm
timeout) and sends no more. Judging starts with the sensor's first answer: before it, the
controller waits for the sensor (unanswered datagrams are only counted).
`drop_probability` loses datagrams on the way (the counter goes on, as the controller's does).

Time base as the other mocks (adapters/mock_devices.py): cycle k of a pass goes out at wall
time start + k * cycle; with `loop_play` the pass playing now starts on the grid of
`period_s` from t0 (`_first_pass`), so a controller started by hand agrees with a tracker
mock of the same scenario; `play_until` ends the play. The controller's clock (IPOC, tm)
and the sequence number run on from pass to pass.

With `corrector` given, the controller applies the latest correction it received (the tool
frame transform [x y z (m), rotation vector (rad)]) as RSI's absolute TCP correction or EGM's
pose correction do: it moves the joints so that the nominal tool pose is the programmed one
times the correction (`corrector(q, c)` solves that), reports those joints and keeps the
correction applied at each instant (`correction_at`) so that a tracker can see the true pose.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from keo_service.adapters import abb_egm, kuka_rsi
from keo_service.adapters.line_protocol import format_hello, format_pose
from keo_service.adapters.mock import MockSettings, TaskMock, TcpMockServer
from keo_service.adapters.mock_devices import JointTrack, _first_pass
from keo_service.adapters.realtime import request_realtime
from keo_service.io.config import Config

log = logging.getLogger("keo.mock")

Corrector = Callable[[np.ndarray, np.ndarray], np.ndarray]


class _Replies(asyncio.DatagramProtocol):
    def __init__(self, owner: MockUdpController) -> None:
        self.owner = owner

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        self.owner.on_reply(data)

    def error_received(self, exc: Exception) -> None:
        # nobody listening yet (ICMP port unreachable): the answer simply does not come
        self.owner.counters["send_errors"] += 1


class MockUdpController(TaskMock):
    protocol = ""

    def __init__(
        self,
        track: JointTrack,
        settings: MockSettings,
        *,
        corrector: Corrector | None = None,
        drop_probability: float = 0.0,
        realtime: bool = False,
    ) -> None:
        self.realtime = realtime  # ask for real-time scheduling, as a controller has
        self.cycle_ms = settings.cycle_ms
        # looping: the track again every period_s (default: its last time + one cycle)
        self.period_s = settings.period_s or float(track.t[-1]) + self.cycle_ms * 1e-3
        self.play_until = settings.play_until  # wall time after which nothing more is sent
        self.seq = 0  # datagrams made so far (EGM's seqno), on from pass to pass
        self.track = track
        self.drop_probability = drop_probability  # datagrams lost on the way to keo
        self.host, self.port, self.t0 = settings.host, settings.port, settings.t0
        self.jitter_s = settings.jitter_ms * 1e-3
        self.max_late = settings.max_late
        # the controller's millisecond clock (RSI's IPOC, EGM's header.tm) at t0
        offset_s = 5000.0 if settings.clock_offset_s is None else settings.clock_offset_s
        self.clock_offset_ms = round(offset_s * 1e3)
        self.corrector = corrector
        self.loop_play = settings.loop
        self.rng = np.random.default_rng(settings.seed)
        self.counters: collections.Counter[str] = collections.Counter()
        self.rtt_s: collections.deque[float] = collections.deque(maxlen=200_000)
        self.correction = np.zeros(6)
        self.received: collections.deque[np.ndarray] = collections.deque(maxlen=100_000)
        self._history: collections.deque[tuple[float, np.ndarray]] = collections.deque(maxlen=4096)
        self.stopped = asyncio.Event()
        self.stop_reason = ""
        self.cycles = (-1, -1)  # the first and last cycle sent
        # ms since t0 (in the first pass: scenario ms) of the first 50 late answers
        self.late_at: list[int] = []
        self._pending: dict[int, int] = {}  # counter -> send time (perf_counter_ns)
        self._answered: set[int] = set()
        self._consecutive_late = 0
        self._transport: asyncio.DatagramTransport | None = None
        self._task: asyncio.Task[None] | None = None

    async def start(self) -> None:
        loop = asyncio.get_running_loop()
        transport, _ = await loop.create_datagram_endpoint(
            lambda: _Replies(self), remote_addr=(self.host, self.port)
        )
        self._transport = transport
        if self.t0 is None:
            self.t0 = time.time() + 0.5
        self._task = asyncio.create_task(self._run(), name=f"keo.mock.{self.protocol}")
        log.info(
            "mock %s controller -> %s:%d, %g ms cycle, from t0=%.3f",
            self.protocol,
            self.host,
            self.port,
            self.cycle_ms,
            self.t0,
        )

    async def close(self) -> None:
        await self._stop_task()
        if self._transport is not None:
            self._transport.close()

    def correction_at(self, scenario_t: float) -> np.ndarray:
        """The correction the robot had applied at `scenario_t` (zero before any)."""
        out = np.zeros(6)
        for t, c in self._history:
            if t > scenario_t:
                break
            out = c
        return out

    def joints_at(self, scenario_t: float) -> np.ndarray:
        """The programmed joints at `scenario_t` (before any correction)."""
        return np.array([np.interp(scenario_t, self.track.t, c) for c in self.track.q.T])

    def summary(self) -> dict[str, object]:
        """What the controller saw, for logs and tests: answers, late ones, round trips."""
        return {
            "protocol": self.protocol,
            "counters": dict(self.counters),
            "cycles": self.cycles[1] - self.cycles[0] + 1 if self.cycles[0] >= 0 else 0,
            "rtt_p50_ms": self.rtt_percentile(50) * 1e3,
            "rtt_p99_ms": self.rtt_percentile(99) * 1e3,
            "rtt_max_ms": max(self.rtt_s, default=math.nan) * 1e3,
            "stopped": self.stop_reason,
            "late_at_ms": self.late_at,
        }

    def rtt_percentile(self, p: float) -> float:
        return float(np.percentile(np.array(self.rtt_s), p)) if self.rtt_s else math.nan

    # -- the cycle -------------------------------------------------------------------------

    async def _run(self) -> None:
        assert self.t0 is not None
        assert self._transport is not None
        if self.realtime:
            log.info("mock %s controller: %s", self.protocol, request_realtime())
        cycle_s = self.cycle_ms * 1e-3
        t_end = min(float(self.track.t[-1]), self.period_s - 1e-9)
        start = self.t0
        if self.loop_play:
            start = _first_pass(self.t0, self.period_s, time.time())
        k = max(0, math.ceil((time.time() - start) / cycle_s))
        await self._warm_up(start + k * cycle_s)
        while True:
            t_scn = k * cycle_s
            if t_scn > t_end:
                if not self.loop_play:
                    return
                start += self.period_s
                k = 0
                continue
            if self.play_until is not None and start + t_scn > self.play_until:
                return
            jitter = float(self.rng.uniform(0.0, self.jitter_s)) if self.jitter_s else 0.0
            delay = start + t_scn + jitter - time.time()
            if delay > 0:
                await asyncio.sleep(delay)
            self._judge_previous()
            if self.stopped.is_set():
                return
            # the controller's milliseconds since t0: they run on through the passes
            self._send(t_scn, round((start - self.t0) * 1e3 + k * self.cycle_ms))
            k += 1

    async def _warm_up(self, first_send: float) -> None:
        """Wait for the first cycle awake: a process woken from a long sleep runs several
        times slower for some milliseconds (cold caches, an idle CPU), longer than a 4 ms
        cycle, and a controller's cycle never stalls so; the first answers would be judged
        before this process could read them. The last 50 ms are waited a cycle at a time,
        with the work of a cycle done (nothing sent)."""
        cycle_s = self.cycle_ms * 1e-3
        lead = first_send - time.time() - 0.05
        if lead > 0:
            await asyncio.sleep(lead)
        while (left := first_send - time.time()) > cycle_s:
            self.datagram(self.clock_offset_ms, 0, self.joints_at(0.0))
            await asyncio.sleep(min(cycle_s, left - cycle_s))

    def _send(self, t_scn: float, since_t0_ms: int) -> None:
        """One cycle: the joints at scenario time `t_scn` (corrected when a correction is
        applied), stamped `since_t0_ms` on the controller's clock; lost on the way with
        `drop_probability`."""
        assert self._transport is not None
        q = self.joints_at(t_scn)
        if self.corrector is not None and np.any(self.correction):
            q = self.corrector(q, self.correction)
        counter = self.clock_offset_ms + since_t0_ms
        self.seq += 1
        self._history.append((t_scn, self.correction.copy()))
        if self.drop_probability and self.rng.uniform() < self.drop_probability:
            self.counters["dropped"] += 1
            return
        self._pending[counter] = time.perf_counter_ns()
        self._transport.sendto(self.datagram(counter, self.seq, q))
        self.counters["sent"] += 1
        n = self.seq - 1
        self.cycles = (self.cycles[0] if self.cycles[0] >= 0 else n, n)

    def _judge_previous(self) -> None:
        """Every datagram older than one cycle without its answer is late (counted once);
        before the sensor's first answer they are only counted (the controller waits for the
        sensor to come up, as a program that starts RSI/EGM once the sensor runs)."""
        now = time.perf_counter_ns()
        limit = self.cycle_ms * 1e6
        for counter, sent in list(self._pending.items()):
            if now - sent > limit:
                del self._pending[counter]
                if not self.counters["answered"]:
                    self.counters["unanswered_before_first"] += 1
                    continue
                self.counters["late"] += 1
                self.counters["unanswered"] += 1
                self._late(counter)

    def _late(self, counter: int) -> None:
        if len(self.late_at) < 50:
            self.late_at.append(counter - self.clock_offset_ms)  # ms since t0
        self._consecutive_late += 1
        if self._consecutive_late >= self.max_late and not self.stopped.is_set():
            self.stop_reason = f"{self._consecutive_late} late answers in a row"
            log.error("mock %s controller: robot stopped, %s", self.protocol, self.stop_reason)
            self.stopped.set()

    def on_reply(self, data: bytes) -> None:
        now = time.perf_counter_ns()
        answer = self.parse(data)
        if answer is None:
            self.counters["bad_replies"] += 1
            return
        counter, correction = answer
        sent = self._pending.pop(counter, None)
        if sent is None:
            self.counters["stray_replies"] += 1  # already judged late, or never sent
            return
        rtt = (now - sent) * 1e-9
        self.rtt_s.append(rtt)
        self.counters["answered"] += 1
        if rtt > self.cycle_ms * 1e-3:
            self.counters["late"] += 1
            self._late(counter)
        else:
            self._consecutive_late = 0
        if correction is not None and self.corrector is not None:
            self.correction = correction
            self.received.append(correction)

    # -- per protocol ----------------------------------------------------------------------

    def datagram(self, counter: int, seq: int, q: np.ndarray) -> bytes:
        """One datagram: the controller's clock `counter` (ms), its sequence number."""
        raise NotImplementedError

    def parse(self, data: bytes) -> tuple[int, np.ndarray | None] | None:
        raise NotImplementedError


class MockRsiController(MockUdpController):
    """A KUKA controller's RSI ETHERNET object: `<Rob>` with AIPos, RIst, IPOC (and EIPos
    when `external` is given); reads RKorr as an absolute correction in the TCP frame."""

    protocol = "kuka_rsi"

    def __init__(
        self,
        track: JointTrack,
        settings: MockSettings,
        *,
        external: list[float] | None = None,
        **hooks: Any,
    ) -> None:
        super().__init__(track, settings, **hooks)
        self.external = external
        self.codec = kuka_rsi.RsiCodec()

    def datagram(self, counter: int, seq: int, q: np.ndarray) -> bytes:
        return kuka_rsi.format_rob(
            counter,
            np.degrees(q).tolist(),
            external=self.external,
            delay=self.counters["late"],
        )

    def parse(self, data: bytes) -> tuple[int, np.ndarray | None] | None:
        sen = self.codec.parse_sen(data)
        if sen is None:
            return None
        if sen.rkorr is None:
            return sen.ipoc, None
        x, y, z, a, b, c = sen.rkorr
        rotvec = Rotation.from_euler("ZYX", [a, b, c], degrees=True).as_rotvec()
        return sen.ipoc, np.array([x * 1e-3, y * 1e-3, z * 1e-3, *rotvec])


class MockEgmController(MockUdpController):
    """An ABB controller's EGM channel: `EgmRobot` (feedBack joints in degrees, header seqno and
    tm); reads `EgmSensor.planned.cartesian` as the pose correction in the tool frame."""

    protocol = "abb_egm"

    def __init__(
        self,
        track: JointTrack,
        settings: MockSettings,
        *,
        external: list[float] | None = None,
        **hooks: Any,
    ) -> None:
        super().__init__(track, settings, **hooks)
        self.external = external
        self.codec = abb_egm.EgmCodec()
        self._tm_of_seq: dict[int, int] = {}

    def datagram(self, counter: int, seq: int, q: np.ndarray) -> bytes:
        return abb_egm.format_robot(seq, counter, np.degrees(q).tolist(), self.external)

    def parse(self, data: bytes) -> tuple[int, np.ndarray | None] | None:
        sensor = self.codec.parse_sensor(data)
        if sensor is None:
            return None
        if sensor.position_mm is None or sensor.quaternion is None:
            return sensor.tm_ms, None
        w, x, y, z = sensor.quaternion
        rotvec = Rotation.from_quat([x, y, z, w]).as_rotvec()
        p = np.array(sensor.position_mm) * 1e-3
        return sensor.tm_ms, np.array([*p, *rotvec])


PoseAt = Callable[[float], tuple[list[float], list[float] | None]]


class LiveTracker(TcpMockServer):
    """A line-protocol tracker that measures a pose computed at each sample instant
    (`pose_at(scenario_t)` -> position m and scalar-first quaternion, in the tracker frame),
    so that it sees the true tool of a controller that applies corrections."""

    kind = "mock live tracker"

    def __init__(
        self, pose_at: PoseAt, host: str, port: int, t0: float, rate_hz: float = 100.0
    ) -> None:
        self.pose_at = pose_at
        self.host, self.port, self.t0 = host, port, t0
        self.period = 1.0 / rate_hz

    async def _on_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        assert self.t0 is not None  # given to the constructor
        t0 = self.t0
        writer.write(format_hello("mm", source="keo live mock tracker"))
        seq = 0
        try:
            k = max(0, math.ceil((time.time() - t0) / self.period))
            while True:
                t = k * self.period
                delay = t0 + t - time.time()
                if delay > 0:
                    await asyncio.sleep(delay)
                p, q = self.pose_at(t)
                seq += 1
                writer.write(format_pose(seq, t, [v * 1e3 for v in p], q))
                await writer.drain()
                k += 1
        except (ConnectionError, OSError, asyncio.CancelledError):
            pass
        finally:
            writer.close()


# ---- the protocol table's builders (io.protocols: MockSettings -> the mock) ----


def _controller(
    cls: type[MockUdpController], s: MockSettings, config: Config, run: Any
) -> MockUdpController:
    """The RSI or EGM controller side, sending to keo's server (the config's robot host and
    port); with `robot.correction` naming its protocol it applies the corrections it gets."""
    from keo_service.io.cell import cell_from_config
    from keo_service.sim.controller import tool_corrector

    corrector = None
    if config.robot.correction == cls.protocol:
        corrector = tool_corrector(cell_from_config(config))
    return cls(run.encoder, s, corrector=corrector, realtime=True)


def rsi_mock(s: MockSettings, config: Config, run: Any) -> MockUdpController:
    """A KUKA controller's RSI object sending `<Rob>` to keo every cycle."""
    return _controller(MockRsiController, s, config, run)


def egm_mock(s: MockSettings, config: Config, run: Any) -> MockUdpController:
    """An ABB controller's EGM channel sending `EgmRobot` to keo every cycle."""
    return _controller(MockEgmController, s, config, run)
