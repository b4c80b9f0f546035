"""The UDP real-time robot interfaces: KUKA RSI and ABB EGM. keo is the server the controller
sends to; every datagram is answered from the datagram callback itself (no queue, no task
switch in between), carrying keo's live correction when `robot.correction` names this protocol
and a zero correction otherwise.

Both publish `JointSample`s like the TCP adapters, stamped by the adapters' one rule
(`core.clock.Stamper`) from the controller's own clock (RSI's IPOC and EGM's header.tm,
milliseconds): mapped onto the host's (`robot.clock = "device"`, the default); `"receipt"`
stamps on arrival and `"shared"` takes the controller's milliseconds as they are, checked.

What the status shows: replies sent, the reply time (receipt to sendto, µs: last, max, p99 of
the last 1000), replies slower than the cycle (`late_replies`), cycles the controller's
counter skipped (`missed_cycles`; EGM also `lost` from its sequence numbers), the codec's
rejects, the clock mapping, the correction state and (RSI) the external axes.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import math
import threading
import time
from typing import Any, cast

import numpy as np
import zenoh
from scipy.spatial.transform import Rotation

from keo_service.adapters import abb_egm, kuka_rsi
from keo_service.adapters.devices import ROBOT_STATUS_PERIOD_S, EncoderAdapter
from keo_service.adapters.realtime import request_realtime
from keo_service.core.clock import Stamp
from keo_service.live.messages import (
    CorrectionMessage,
    RobotStatus,
    decode,
    encode,
    topic,
)

log = logging.getLogger("keo.adapter")

DEFAULT_CYCLE_S = 0.004
REPLY_WINDOW = 1000


class CorrectionOutput:
    """The latest `keo/<cell>/correction`, clamped by `[compensation]`, as the reply carries it.

    The magnitude is clamped to max_mm / max_mrad; the change per answer to max_rate_mm_s
    (position, mm/s) and the same number in mrad/s (rotation) times the controller's cycle,
    so that neither a new correction nor a fall to zero (invalid or stale) steps the path.
    Zenoh delivers on its own thread: the latest message is swapped in under a lock, read in
    the datagram callback."""

    def __init__(self, compensation: Any) -> None:
        limits = compensation.limits()  # [compensation] in SI units, read in one place
        self.max_m = limits.max_m
        self.max_rad = limits.max_rad
        self.rate = limits.max_rate_m_s  # m/s, and rad/s for the rotation
        # one older than this (since receipt) is not applied: ramps to zero
        self.max_age_s = limits.max_age_s
        self.counters: collections.Counter[str] = collections.Counter()
        self._lock = threading.Lock()
        self._latest: tuple[CorrectionMessage, float] | None = None
        self._sent = np.zeros(6)
        self.reason = "no correction received"

    def on_payload(self, payload: bytes) -> None:
        try:
            msg = decode(payload)
        except Exception as exc:
            self.counters["correction_undecodable"] += 1
            self.reason = f"undecodable correction: {exc}"
            return
        if not isinstance(msg, CorrectionMessage):
            self.counters["correction_wrong_type"] += 1
            return
        with self._lock:
            self._latest = (msg, time.monotonic())
        self.counters["corrections_received"] += 1

    def _target(self, now: float) -> np.ndarray:
        with self._lock:
            latest = self._latest
        if latest is None:
            return np.zeros(6)
        msg, at = latest
        if not msg.valid:
            self.reason = f"invalid: {msg.reason}"
            self.counters["correction_invalid"] += 1
            return np.zeros(6)
        if now - at > self.max_age_s:
            self.reason = f"stale: none for {now - at:.2f} s"
            self.counters["correction_stale"] += 1
            return np.zeros(6)
        values = np.array([*msg.translation, *msg.rotation], dtype=float)
        if values.shape != (6,) or not np.all(np.isfinite(values)):
            self.reason = "malformed: not 6 finite numbers"
            self.counters["correction_malformed"] += 1
            return np.zeros(6)
        self.reason = ""
        for part, limit in ((slice(0, 3), self.max_m), (slice(3, 6), self.max_rad)):
            norm = float(np.linalg.norm(values[part]))
            if norm > limit:
                values[part] *= limit / norm
                self.counters["correction_clamped"] += 1
        return values

    def next(self, now: float, cycle_s: float = DEFAULT_CYCLE_S) -> np.ndarray:
        """The correction to send now: [x y z (m), rotation vector (rad)] in the tool frame.
        It changes by at most the rate limit times the controller's cycle per answer: the
        robot applies one answer per cycle, whatever time passed on this side."""
        target = self._target(now)
        step = target - self._sent
        limit = self.rate * cycle_s
        for part in (slice(0, 3), slice(3, 6)):
            norm = float(np.linalg.norm(step[part]))
            if norm > limit:
                step[part] *= limit / norm
                self.counters["correction_rate_limited"] += 1
        self._sent = self._sent + step
        return self._sent.copy()

    def state(self) -> dict[str, Any]:
        return {
            "sent_mm": (self._sent[:3] * 1e3).tolist(),
            "sent_mrad": (self._sent[3:] * 1e3).tolist(),
            "reason": self.reason,
            "counters": dict(self.counters),
        }


class _Datagrams(asyncio.DatagramProtocol):
    def __init__(self, owner: UdpEncoderAdapter) -> None:
        self.owner = owner
        self.transport: asyncio.DatagramTransport | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = cast(asyncio.DatagramTransport, transport)

    def datagram_received(self, data: bytes, addr: tuple[str | Any, int]) -> None:
        if self.transport is None:
            return
        try:
            self.owner.on_datagram(data, addr, self.transport)
        except Exception as exc:  # a bug, not bad input (the codecs count that): stop loudly
            log.exception("encoder: internal failure on a datagram")
            self.transport.close()
            self.transport = None
            self.owner._fail(exc)

    def error_received(self, exc: Exception) -> None:
        self.owner.counters["socket_errors"] += 1
        log.warning("encoder: UDP socket error: %s", exc)


class UdpEncoderAdapter(EncoderAdapter):
    """The shared part: socket, stamps, reply timing, corrections, status. With `realtime`
    set (keo adapter encoder sets it) the event loop's thread asks for real-time scheduling."""

    protocol = ""
    realtime = False
    scheduling = "normal"

    def _declare(self, session: zenoh.Session) -> None:
        self._declare_publishers(session)
        self._peer: tuple[str | Any, int] | None = None
        self.reply_us: collections.deque[float] = collections.deque(maxlen=REPLY_WINDOW)
        # the same span in this thread's CPU time: what the answer costs keo, apart from the
        # time the scheduler or a hypervisor kept the thread waiting
        self.reply_cpu_us: collections.deque[float] = collections.deque(maxlen=REPLY_WINDOW)
        self.reply_max_us = 0.0
        self.cycle_s = DEFAULT_CYCLE_S
        self._last_device_ms: float | None = None
        self.correction: CorrectionOutput | None = None
        self._correction_sub: Any = None
        if self.config.robot.correction == self.protocol:
            self.correction = CorrectionOutput(self.config.compensation)
            self._correction_sub = session.declare_subscriber(
                topic(self.config.cell, "correction"),
                lambda sample: self.correction.on_payload(sample.payload.to_bytes()),  # type: ignore[union-attr]
            )

    async def __aexit__(self, *exc: object) -> None:
        if self._correction_sub is not None:
            self._correction_sub.undeclare()
        await super().__aexit__(*exc)

    async def _run(self) -> None:
        robot = self.config.robot
        if self.realtime:
            self.scheduling = request_realtime()
            log.info("encoder: answering thread: %s", self.scheduling)
        loop = asyncio.get_running_loop()
        transport, _ = await loop.create_datagram_endpoint(
            lambda: _Datagrams(self), local_addr=(robot.host, robot.endpoint_port)
        )
        sockname = transport.get_extra_info("sockname")
        self.bound = (sockname[0], sockname[1])
        log.info("encoder: %s server on %s:%d", self.protocol, *self.bound)
        try:
            await self._stop.wait()
        finally:
            transport.close()

    # -- per datagram ----------------------------------------------------------------------

    def on_datagram(
        self, data: bytes, addr: tuple[str | Any, int], transport: asyncio.DatagramTransport
    ) -> None:
        start = time.perf_counter_ns()
        start_cpu = time.thread_time_ns()
        host_ns = time.time_ns()
        new_peer = addr != self._peer
        if new_peer:
            self.expect_new_peer()
        frame = self.decode(data)
        if frame is None:
            return
        if new_peer:
            if self._peer is not None:
                log.info("encoder: controller now at %s:%d (was %s:%d)", *addr, *self._peer)
                self.new_session()
            self._peer = addr
        correction = None
        if self.correction is not None:
            correction = self.correction.next(time.monotonic(), self.cycle_s)
        transport.sendto(self.reply(frame, correction), addr)
        took_us = (time.perf_counter_ns() - start) * 1e-3
        self.reply_cpu_us.append((time.thread_time_ns() - start_cpu) * 1e-3)
        self.reply_us.append(took_us)
        self.reply_max_us = max(self.reply_max_us, took_us)
        self.counters["replies"] += 1
        if took_us * 1e-6 > self.cycle_s:
            self.counters["late_replies"] += 1
        self.publish(frame, host_ns)

    def expect_new_peer(self) -> None:
        """A datagram from an address not seen last: the codec judges it on its own."""

    def new_session(self) -> None:
        """The controller restarted or another one took over: a new time base."""
        self.stamper.restart(fresh=True)
        self._last_device_ms = None
        self.counters["sessions"] += 1

    def _track_cycle(self, device_ms: float) -> None:
        last = self._last_device_ms
        self._last_device_ms = device_ms
        if last is None:
            return
        step_s = (device_ms - last) * 1e-3
        if step_s <= 0:
            return
        if step_s < self.cycle_s * 0.75 or self.counters["replies"] < 3:
            self.cycle_s = max(step_s, 1e-3)  # the controller's cycle (4 or 12 ms for RSI)
        missed = round(step_s / self.cycle_s) - 1
        if missed > 0:
            self.counters["missed_cycles"] += missed

    def stamp(self, device_ms: float, host_ns: int) -> tuple[Stamp, float]:
        """(the sample's stamp under the configured clock domain, device time in s): the
        adapters' one rule (core.clock.Stamper)."""
        self._track_cycle(device_ms)
        device_stamp = device_ms * 1e-3
        return self._stamp(device_stamp, host_ns * 1e-9), device_stamp

    def put_joints(self, q: list[float], device_ms: float, host_ns: int) -> None:
        if len(q) < self.nq:
            self.rejects_short(len(q))
            return
        st, device_stamp = self.stamp(device_ms, host_ns)
        self._publish_joints(st, host_ns, q[: self.nq], None, device_stamp)

    def rejects_short(self, n: int) -> None:
        self.counters["too_few_joints"] += 1
        self.counters["rejected"] += 1
        if self.counters["too_few_joints"] == 1:  # the same every cycle: said once
            log.warning(
                "encoder: the controller sends %d joints, robot.urdf has %d: samples dropped",
                n,
                self.nq,
            )

    def status(self) -> dict[str, Any]:
        replies = np.array(self.reply_us) if self.reply_us else np.zeros(1)
        cpu = np.array(self.reply_cpu_us) if self.reply_cpu_us else np.zeros(1)
        return {
            "adapter": self.name,
            "protocol": self.protocol,
            "counters": dict(self.counters),
            "reply_us": {
                "last": float(replies[-1]),
                "p99": float(np.percentile(replies, 99)),
                "max": self.reply_max_us,
                "cpu_p50": float(np.percentile(cpu, 50)),
                "cpu_p99": float(np.percentile(cpu, 99)),
            },
            "cycle_ms": self.cycle_s * 1e3,
            "scheduling": self.scheduling,
            "clock": self.stamper.state(),
            "correction": None if self.correction is None else self.correction.state(),
            "peer": None if self._peer is None else f"{self._peer[0]}:{self._peer[1]}",
        }

    # -- per protocol ----------------------------------------------------------------------

    def decode(self, data: bytes) -> Any:
        raise NotImplementedError

    def reply(self, frame: Any, correction: np.ndarray | None) -> bytes:
        raise NotImplementedError

    def publish(self, frame: Any, host_ns: int) -> None:
        raise NotImplementedError


def rkorr_of(correction: np.ndarray) -> tuple[float, ...]:
    """[x y z (m), rotation vector (rad)] -> RSI X Y Z (mm), A B C (degrees; R = Rz(A) Ry(B)
    Rx(C), KUKA's convention)."""
    a, b, c = Rotation.from_rotvec(correction[3:]).as_euler("ZYX", degrees=True)
    x, y, z = (correction[:3] * 1e3).tolist()
    return (x, y, z, float(a), float(b), float(c))


class KukaRsiAdapter(UdpEncoderAdapter):
    """KUKA RSI: `<Rob>` in, `<Sen>` with the echoed IPOC and RKorr out, within the cycle."""

    protocol = "kuka_rsi"

    def _declare(self, session: zenoh.Session) -> None:
        if self.nq != 6:
            raise ValueError(
                f"robot.urdf has {self.nq} joints; RSI's AIPos reports A1..A6 (external axes "
                "E1..E6 go to the status)"
            )
        super()._declare(session)
        self.codec = kuka_rsi.RsiCodec()
        self.external_axes: list[float] | None = None
        self.controller_delay: int | None = None
        self.sen_type = kuka_rsi.DEFAULT_SEN_TYPE

    def decode(self, data: bytes) -> kuka_rsi.RobFrame | None:
        return self.codec.parse_rob(data)

    def reply(self, frame: kuka_rsi.RobFrame, correction: np.ndarray | None) -> bytes:
        rkorr = (0.0,) * 6 if correction is None else rkorr_of(correction)
        return kuka_rsi.format_sen(frame.ipoc, rkorr, self.sen_type)

    def publish(self, frame: kuka_rsi.RobFrame, host_ns: int) -> None:
        if frame.external is not None:
            self.external_axes = list(frame.external)
        if frame.delay is not None:
            self.controller_delay = frame.delay
        q = [math.radians(v) for v in frame.axes_deg]
        self.put_joints(q, float(frame.ipoc), host_ns)

    def status(self) -> dict[str, Any]:
        return {
            **super().status(),
            "decoder": dict(self.codec.counters),
            "messages": list(self.codec.messages),
            "external_axes": self.external_axes,
            "controller_late_count": self.controller_delay,
        }


class AbbEgmAdapter(UdpEncoderAdapter):
    """ABB EGM: `EgmRobot` in, `EgmSensor` with the correction pose out, within the cycle."""

    protocol = "abb_egm"

    def _declare(self, session: zenoh.Session) -> None:
        super()._declare(session)
        self.codec = abb_egm.EgmCodec()
        self._sent_seq = 0
        self._tm_wraps = 0
        self._last_tm: int | None = None
        self.external_axes: list[float] | None = None
        self.robot_state: dict[str, bool | None] = {}
        self._status_at = -math.inf

    def expect_new_peer(self) -> None:
        self.codec.reset()  # another socket: its sequence numbers are its own

    def new_session(self) -> None:
        super().new_session()
        self._tm_wraps = 0
        self._last_tm = None

    def decode(self, data: bytes) -> abb_egm.EgmRobotFrame | None:
        restarts = self.codec.counters["restarts"]
        frame = self.codec.parse_robot(data)
        if self.codec.counters["restarts"] != restarts:
            log.info("encoder: the EGM controller counts anew: a new time base")
            self.new_session()
        return frame

    def reply(self, frame: abb_egm.EgmRobotFrame, correction: np.ndarray | None) -> bytes:
        self._sent_seq += 1
        if correction is None:
            return abb_egm.format_sensor(self._sent_seq, frame.tm_ms)
        x, y, z, w = Rotation.from_rotvec(correction[3:]).as_quat()  # scalar last
        position = (correction[:3] * 1e3).tolist()
        return abb_egm.format_sensor(
            self._sent_seq, frame.tm_ms, position, (float(w), float(x), float(y), float(z))
        )

    def publish(self, frame: abb_egm.EgmRobotFrame, host_ns: int) -> None:
        if self._last_tm is not None and frame.tm_ms < self._last_tm - 2**31:
            self._tm_wraps += 1  # the uint32 ms counter wrapped (every 49.7 days)
        self._last_tm = frame.tm_ms
        if frame.external is not None:
            self.external_axes = list(frame.external)
        state = {
            "motors_on": frame.motors_on,
            "egm_running": frame.egm_running,
            "rapid_running": frame.rapid_running,
        }
        device_ms = float(frame.tm_ms + self._tm_wraps * 2**32)
        self.put_joints(list(frame.joints_rad), device_ms, host_ns)
        now = host_ns * 1e-9
        if state != self.robot_state or now - self._status_at >= ROBOT_STATUS_PERIOD_S:
            self.robot_state, self._status_at = state, now
            self._status_pub.put(
                encode(
                    RobotStatus(
                        host_ns=host_ns,
                        drives_powered=int(bool(frame.motors_on)),
                        e_stopped=0,  # EGM does not tell
                        error_code=0,
                        in_error=0,
                        in_motion=0,
                        mode=0,
                        motion_possible=int(bool(frame.motors_on and frame.egm_running)),
                    )
                )
            )

    def status(self) -> dict[str, Any]:
        return {
            **super().status(),
            "decoder": dict(self.codec.counters),
            "messages": list(self.codec.messages),
            "external_axes": self.external_axes,
            "robot_state": self.robot_state,
        }


UDP_ADAPTERS: dict[str, type[UdpEncoderAdapter]] = {
    "kuka_rsi": KukaRsiAdapter,
    "abb_egm": AbbEgmAdapter,
}
