"""The two device adapters: a device's TCP stream in, Zenoh samples out.

Each is an async context manager that owns its session and tasks (aiomqtt style). Codec
errors are counted and visible on `keo/<cell>/adapter/<name>/status`; they never stop it.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from collections import Counter
from typing import Any

import zenoh

from adapters.connection import run_tcp_client
from adapters.line_protocol import MAX_LINE, LineProtocolParser
from adapters.simple_message import JointFeedback, RobotStatusFrame, SimpleMessageDecoder
from keo_service.live.bus import session_for_client_async
from keo_service.live.messages import JointSample, RobotStatus, TrackerSample, encode, topic
from keo_service.live.supervise import supervise

log = logging.getLogger("keo.adapter")


class _Adapter:
    name = "adapter"

    def __init__(self, config: Any, nq: int, session: zenoh.Session | None = None) -> None:
        self.config = config
        self.nq = nq
        self._own_session = session is None
        self._session = session
        self.counters: Counter[str] = Counter()
        self._stop = asyncio.Event()
        self._task: asyncio.Task[None] | None = None
        self.failure: BaseException | None = None

    async def __aenter__(self) -> _Adapter:
        if self._session is None:
            self._session = await session_for_client_async(self.config)
        self._declare(self._session)
        self._status_q = self._session.declare_queryable(
            topic(self.config.cell, f"adapter/{self.name}/status"), self._on_status_query
        )
        task = asyncio.create_task(self._run(), name=f"keo.adapter.{self.name}")
        self._task = supervise(task, self._stop.is_set, self._fail)
        return self

    async def __aexit__(self, *exc: object) -> None:
        self._stop.set()
        if self._task is not None:
            await asyncio.wait({self._task}, timeout=2.0)
            self._task.cancel()
        self._status_q.undeclare()
        if self._own_session and self._session is not None:
            self._session.close()

    async def wait(self) -> None:
        await self._stop.wait()

    def stop(self) -> None:
        self._stop.set()

    def _fail(self, exc: BaseException) -> None:
        self.failure = exc
        self._stop.set()

    def status(self) -> dict[str, Any]:
        return {"adapter": self.name, "counters": dict(self.counters)}

    def _on_status_query(self, query: zenoh.Query) -> None:
        query.reply(query.key_expr, json.dumps(self.status()).encode())

    def _declare(self, session: zenoh.Session) -> None:
        raise NotImplementedError

    async def _run(self) -> None:
        raise NotImplementedError


class EncoderAdapter(_Adapter):
    """MotoROS state port -> keo/<cell>/encoder (JointSample) and keo/<cell>/robot_status."""

    name = "encoder"

    def _declare(self, session: zenoh.Session) -> None:
        self.decoder = SimpleMessageDecoder(self.config.robot.byte_order)
        self._pub = session.declare_publisher(
            topic(self.config.cell, "encoder"),
            congestion_control=zenoh.CongestionControl.BLOCK,
            express=True,
        )
        self._status_pub = session.declare_publisher(topic(self.config.cell, "robot_status"))
        self._seq = 0

    def status(self) -> dict[str, Any]:
        return {
            **super().status(),
            "decoder": dict(self.decoder.counters),
            "messages": list(self.decoder.messages),
        }

    async def _run(self) -> None:
        robot = self.config.robot
        await run_tcp_client(
            "encoder", robot.host, robot.port, self._read, self._stop, self.counters
        )

    async def _read(self, reader: asyncio.StreamReader) -> None:
        try:
            while True:
                data = await reader.read(4096)
                if not data:
                    return
                host_ns = time.time_ns()
                for frame in self.decoder.feed(data):
                    self.publish_frame(frame, host_ns)
        finally:
            self.decoder.reset()

    def publish_frame(self, frame: JointFeedback | RobotStatusFrame, host_ns: int) -> None:
        if isinstance(frame, RobotStatusFrame):
            self._status_pub.put(encode(RobotStatus(host_ns=host_ns, **frame.__dict__)))
            return
        if frame.group != 0:
            self.counters["other_group"] += 1
            return
        self._seq += 1
        q = list(frame.positions[: self.nq])
        dq = list(frame.velocities[: self.nq]) if frame.velocities is not None else None
        device_t = frame.time if frame.valid_fields & 1 else None
        self._pub.put(
            encode(
                JointSample(
                    t=host_ns * 1e-9, host_ns=host_ns, seq=self._seq, q=q, dq=dq, device_t=device_t
                )
            )
        )
        self.counters["published"] += 1


class TrackerAdapter(_Adapter):
    """Line-protocol tracker -> keo/<cell>/tracker (TrackerSample; gaps with status != ok)."""

    name = "tracker"

    def _declare(self, session: zenoh.Session) -> None:
        self.parser = LineProtocolParser()
        self._pub = session.declare_publisher(
            topic(self.config.cell, "tracker"),
            congestion_control=zenoh.CongestionControl.BLOCK,
            express=True,
        )

    def status(self) -> dict[str, Any]:
        return {
            **super().status(),
            "parser": dict(self.parser.counters),
            "messages": list(self.parser.messages),
        }

    async def _run(self) -> None:
        tracker = self.config.tracker
        await run_tcp_client(
            "tracker", tracker.host, tracker.port, self._read, self._stop, self.counters
        )

    async def _read(self, reader: asyncio.StreamReader) -> None:
        self.parser.reset()
        while True:
            try:
                line = await reader.readuntil(b"\n")
            except asyncio.IncompleteReadError as exc:
                if exc.partial:
                    self.parser.counters["truncated"] += 1
                return
            except asyncio.LimitOverrunError:
                # an overlong line: drop what is buffered up to the next newline
                self.parser.counters["too_long"] += 1
                self.parser.counters["rejected"] += 1
                await reader.read(MAX_LINE)
                continue
            host_ns = time.time_ns()
            pose = self.parser.parse(line)
            if pose is None:
                continue
            sample = TrackerSample(
                t=host_ns * 1e-9,
                host_ns=host_ns,
                seq=pose.seq,
                status=pose.status,
                p=list(pose.p) if pose.p is not None else None,
                q=list(pose.q) if pose.q is not None else None,
                device_t=pose.device_t,
            )
            self._pub.put(encode(sample))
            self.counters["published"] += 1
