"""The device adapters: a device's TCP stream in, Zenoh samples out (MotoROS or UR RTDE
for the robot, keo's line protocol for the tracker).

Each is an async context manager that owns its session and tasks (aiomqtt style). Codec
errors are counted and visible on `keo/<cell>/adapter/<name>/status`; they never stop it.
"""

from __future__ import annotations

import asyncio
import collections
import logging
import math
import time
from collections import Counter
from pathlib import Path
from typing import Any

import msgspec
import zenoh

from keo_service.adapters import rtde
from keo_service.adapters.clock_state import SAVE_PERIOD_S, load_into, save, state_path
from keo_service.adapters.connection import DEVICE, Device, run_tcp_client
from keo_service.adapters.health import AdapterHealth, rejects_of
from keo_service.adapters.line_protocol import MAX_LINE, LineProtocolParser
from keo_service.adapters.rtde import Package, RtdeDecoder
from keo_service.adapters.simple_message import (
    JointFeedback,
    RobotStatusFrame,
    SimpleMessageDecoder,
)
from keo_service.core.clock import Stamp, Stamper
from keo_service.core.rejects import RejectLog
from keo_service.io.config import Config
from keo_service.io.ros2_messages import JOINT_STATE, POINT_STAMPED, POSE_STAMPED, seconds_of
from keo_service.live.bus import AsyncSubscription, session_for_client_async
from keo_service.live.compensation import correction_to_send
from keo_service.live.messages import (
    AdapterStatus,
    CorrectionMessage,
    JointSample,
    RobotStatus,
    TrackerSample,
    decode,
    encode,
    topic,
)
from keo_service.live.ros2 import Ros2Node
from keo_service.live.supervise import supervise

log = logging.getLogger("keo.adapter")
WATCH_PERIOD_S = 0.25


class _Adapter:
    name = "adapter"
    # set by each adapter when it declares its outputs (`_declare`)
    _pub: zenoh.Publisher
    _seq: int = 0

    def __init__(self, config: Config, nq: int, session: zenoh.Session | None = None) -> None:
        self.config = config
        self.nq = nq
        self._own_session = session is None
        self._session = session
        self.counters: Counter[str] = Counter()
        self._stop = asyncio.Event()
        self._task: asyncio.Task[None] | None = None
        self.failure: BaseException | None = None
        # the clock domain of this device's stamps ([robot] / [tracker] clock); the epoch
        # starts at the process's start (ms since the Unix epoch), so that a restarted
        # adapter never repeats one
        section = config.tracker if self.name == "tracker" else config.robot
        assert section.clock is not None  # the config resolves it from the protocol
        self.stamper = Stamper(
            section.clock, config.timing.max_stamp_age_s, epoch=time.time_ns() // 1_000_000
        )
        self._clock_file: Path | None = None  # where the mapping is kept (timing.clock_state_dir)
        self._clock_saved_at = 0.0
        if config.timing.clock_state_dir and section.clock == "device":
            self._clock_file, self._clock_device = self._clock_state_file(config)
            said = load_into(self.stamper, self._clock_file, self._clock_device)
            log.info("%s: device clock: %s", self.name, said)

    def _clock_state_file(self, config: Config) -> tuple[Path, str]:
        """The file that keeps this device's clock mapping, and the device's identity."""
        section = config.tracker if self.name == "tracker" else config.robot
        port = config.robot.endpoint_port if self.name != "tracker" else config.tracker.port
        device = f"{section.protocol}://{section.host}:{port}"
        return state_path(config.timing.clock_state_dir, config.cell, self.name, device), device

    async def _save_clock(self, now: float) -> None:
        """Keep the clock mapping on disk about once a second (off the loop)."""
        if self._clock_file is None or now - self._clock_saved_at < SAVE_PERIOD_S:
            return
        self._clock_saved_at = now
        state = self.stamper.export()
        if state is None:
            return
        try:
            await asyncio.to_thread(save, state, self._clock_file, self._clock_device)
        except OSError as exc:
            self.counters["clock_state_not_saved"] += 1
            if self.counters["clock_state_not_saved"] == 1:
                log.warning(
                    "%s: cannot keep the clock mapping in %s: %s", self.name, self._clock_file, exc
                )

    async def __aenter__(self) -> _Adapter:
        if self._session is None:
            self._session = await session_for_client_async(self.config)
        self._declare(self._session)
        self.health = self._make_health()
        self.device = Device(self.health.section, self.health.expected)
        DEVICE.set(self.device)  # connection messages name the keys; newest problem in status
        self._status_q = self._session.declare_queryable(
            topic(self.config.cell, f"adapter/{self.name}/status"), self._on_status_query
        )
        # the same document put on the same key at each change of state (silent, back,
        # reconnected, wrong protocol): the service subscribes, nobody polls
        self._event_pub = self._session.declare_publisher(
            topic(self.config.cell, f"adapter/{self.name}/status")
        )
        self._events = 0
        self._reported: tuple[str, int] = ("", 0)
        self._reported_error = ""  # the connection's problem as last put in an event
        task = asyncio.create_task(self._run(), name=f"keo.adapter.{self.name}")
        self._task = supervise(task, self._stop.is_set, self._fail)
        watcher = asyncio.create_task(self._watch(), name=f"keo.adapter.{self.name}.watch")
        self._watcher = supervise(watcher, self._stop.is_set, self._fail)
        return self

    def _make_health(self) -> AdapterHealth:
        section = "robot" if self.name == "encoder" else "tracker"
        device = getattr(self.config, section)
        protocol = device.protocol
        if protocol == "ros2":
            endpoint = device.joint_states_topic if section == "robot" else device.pose_topic
        else:
            port = device.endpoint_port if section == "robot" else device.port
            endpoint = f"{device.host}:{port}"
        silent = float(getattr(device, "silent_after_s", 2.0))
        return AdapterHealth(self.name, section, protocol, endpoint, silent, log)

    async def _watch(self) -> None:
        """State, rate, silence and rejects in the log and the status (adapters.health)."""
        while not self._stop.is_set():
            self.health.tick(self.status(), time.monotonic())
            if self.health.state == "receiving":
                self.device.last_error = ""  # the newest problem is over once data flows
            self._publish_change()
            self._publish_problem()
            rejects = self.health.take_reject_summary()
            if rejects:
                self._publish_event(self._status_doc(), rejects, "warning")
            await self._save_clock(time.monotonic())
            await asyncio.sleep(WATCH_PERIOD_S)

    def _status_doc(self) -> AdapterStatus:
        """What `keo status` shows of this adapter: its counters and codec's rejects, what
        adapters.health makes of them, the connection's newest problem."""
        doc = {**self.status(), **self.health.summary(time.monotonic())}
        doc["last_error"] = self.device.last_error
        return msgspec.convert(doc, AdapterStatus)

    def _publish_change(self) -> None:
        """A change of state or a new connection since the last look: the status document
        with `event` (what happened, in words, with the key to fix) put on the status key."""
        state = self.health.state
        connections = int(self.counters.get("connections", 0))
        before, seen = self._reported
        if (state, connections) == self._reported:
            return
        self._reported = (state, connections)
        if state == "disconnected":  # its event says the connection's problem
            self._reported_error = self.device.last_error
        doc = self._status_doc()
        text, level = self._event_text(before, state, connections > seen > 0, doc)
        self._publish_event(doc, text, level)

    def _publish_problem(self) -> None:
        """A device it cannot reach: the connection's problem (with the keys to fix) once per
        new problem, however often the connection is retried."""
        error = self.device.last_error
        if error == self._reported_error:
            return
        self._reported_error = error
        if error and self.health.state in ("connecting", "disconnected"):
            self._publish_event(self._status_doc(), error, "warning")

    def _publish_event(self, doc: AdapterStatus, text: str, level: str) -> None:
        """The status document with the event, its level and the next `event_seq` put on the
        status key (the service logs it; any client may listen)."""
        self._events += 1
        doc = msgspec.structs.replace(doc, event_seq=self._events, event=text, level=level)
        try:
            self._event_pub.put(doc.to_json())
        except zenoh.ZError as exc:  # counted; the state is still in the status query
            self.counters["event_publish_failed"] += 1
            log.warning("%s: publishing a state change failed: %s", self.name, exc)

    def _event_text(
        self, before: str, state: str, reconnected: bool, doc: AdapterStatus
    ) -> tuple[str, str]:
        """A change of state in words with the config keys that fix it, and its level."""
        health = self.health
        endpoint = health.endpoint
        section = health.section
        if state == "silent":
            age = doc.last_data_age_s
            if not isinstance(age, float):  # connected, and never a byte of data
                return (
                    f"connected to {endpoint} but nothing arrived within {section}.silent_after_s "
                    f"= {health.silent_after_s:g} s: is it {health.expected}? check "
                    f"{section}.port and {section}.protocol",
                    "warning",
                )
            return (
                f"the device at {endpoint} went silent: nothing for {age:.1f} s "
                f"({section}.silent_after_s = {health.silent_after_s:g})",
                "warning",
            )
        if state == "wrong_protocol":
            return health.mismatch, "error"
        if state == "disconnected":
            last = doc.last_error or ""
            why = f": {last}" if last else " (the device closed the connection)"
            return f"disconnected from {endpoint}{why}; reconnecting", "warning"
        if before == "silent":
            return f"data again from {endpoint} ({state})", "info"
        if reconnected:
            return f"reconnected to {endpoint} ({state})", "info"
        if before in ("starting", "connecting") and state in ("connected", "receiving"):
            return f"connected to {endpoint} ({state})", "info"
        text = f"{state} ({endpoint})" if not before else f"{before} -> {state} ({endpoint})"
        return text, "info"

    async def __aexit__(self, *exc: object) -> None:
        self._stop.set()
        if self._task is not None:
            await asyncio.wait({self._task}, timeout=2.0)
            self._task.cancel()
            self._watcher.cancel()
        self._status_q.undeclare()
        self._event_pub.undeclare()
        if self._own_session and self._session is not None:
            self._session.close()
        rejected, _messages = rejects_of(self.status())
        log.info(
            "%s: stopped%s: %d samples published, %d inputs rejected",
            self.name,
            "" if self.failure is None else " on an internal failure",
            self.counters.get("published", 0),
            rejected,
        )

    async def wait(self) -> None:
        await self._stop.wait()

    def stop(self) -> None:
        self._stop.set()

    def _fail(self, exc: BaseException) -> None:
        self.failure = exc
        self._stop.set()

    def status(self) -> dict[str, Any]:
        return {
            "adapter": self.name,
            "counters": dict(self.counters),
            "clock": self.stamper.state(),
        }

    def _stamp(self, device_stamp: float | None, receipt_t: float) -> Stamp:
        """The sample's stamp under this adapter's clock domain; what it flags is logged
        (the first time and then at every power of ten) besides being counted."""
        stamp = self.stamper.stamp(device_stamp, receipt_t)
        for flag in stamp.flags:
            self._log_flag(flag)
        return stamp

    def _log_flag(self, flag: str) -> None:
        n = self.stamper.counters[flag]
        if n and n == 10 ** int(math.log10(n)) and flag in self.stamper.last:
            log.warning("%s: %s (%d so far)", self.name, self.stamper.last[flag], n)

    def _clock_fields(self, stamp: Stamp) -> dict[str, Any]:
        """The clock fields every sample carries."""
        return {
            "clock": self.stamper.domain,
            "clock_epoch": self.stamper.epoch,
            "flags": list(stamp.flags),
            "clock_drift": stamp.drift,
        }

    def _publish_joints(
        self,
        stamp: Stamp,
        host_ns: int,
        joints: list[float],
        velocities: list[float] | None,
        device_stamp: float | None,
    ) -> None:
        """One joint sample out on keo/<cell>/encoder: the next `seq`, the stamp and the
        clock fields (every encoder adapter, whatever its wire format, ends here)."""
        self._seq += 1
        sample = JointSample(
            stamp=stamp.stamp,
            host_ns=host_ns,
            seq=self._seq,
            joints=joints,
            velocities=velocities,
            device_stamp=device_stamp,
            **self._clock_fields(stamp),
        )
        self._pub.put(encode(sample))
        self.counters["published"] += 1

    def _publish_pose(
        self,
        stamp: Stamp,
        host_ns: int,
        seq: int,
        position: list[float] | None,
        quaternion: list[float] | None,
        device_stamp: float | None,
        status: str = "ok",
    ) -> None:
        """One tracker sample out on keo/<cell>/tracker with the stamp and the clock fields
        (the line-protocol and ROS 2 tracker adapters both end here)."""
        sample = TrackerSample(
            stamp=stamp.stamp,
            host_ns=host_ns,
            seq=seq,
            status=status,
            position=position,
            quaternion=quaternion,
            device_stamp=device_stamp,
            **self._clock_fields(stamp),
        )
        self._pub.put(encode(sample))
        self.counters["published"] += 1

    def _on_status_query(self, query: zenoh.Query) -> None:
        key = topic(self.config.cell, f"adapter/{self.name}/status")  # not the query's wildcard
        query.reply(key, self._status_doc().to_json())

    def _declare(self, session: zenoh.Session) -> None:
        raise NotImplementedError

    async def _run(self) -> None:
        raise NotImplementedError


class EncoderAdapter(_Adapter):
    """MotoROS state port -> keo/<cell>/encoder (JointSample) and keo/<cell>/robot_status."""

    name = "encoder"

    def _declare(self, session: zenoh.Session) -> None:
        self.decoder = SimpleMessageDecoder(self.config.robot.byte_order)
        self._declare_publishers(session)

    def _declare_publishers(self, session: zenoh.Session) -> None:
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
            "stamps_held_back": self.stamper.receipt.held_back,
        }

    async def _run(self) -> None:
        robot = self.config.robot
        await run_tcp_client(
            "encoder", robot.host, robot.endpoint_port, self._read, self._stop, self.counters
        )

    async def _read(self, reader: asyncio.StreamReader, _writer: asyncio.StreamWriter) -> None:
        self.stamper.restart()  # a new connection: a new time base
        try:
            while True:
                data = await reader.read(4096)
                if not data:
                    return
                host_ns = time.time_ns()
                frames = self.decoder.feed(data)
                joints = [isinstance(f, JointFeedback) and f.group == 0 for f in frames]
                if sum(joints) > 1:
                    self.counters["coalesced_frames"] += sum(joints) - 1
                if self.stamper.domain == "receipt":  # MotoROS: no device time
                    stamps = iter(self.stamper.stamp_received_together(sum(joints), host_ns * 1e-9))
                    for frame, is_joint in zip(frames, joints, strict=True):
                        self.publish_frame(frame, host_ns, next(stamps) if is_joint else None)
                else:
                    for frame in frames:
                        self.publish_frame(frame, host_ns)
        finally:
            self.decoder.reset()

    def publish_frame(
        self, frame: JointFeedback | RobotStatusFrame, host_ns: int, stamp: Stamp | None = None
    ) -> None:
        """One decoded frame out; `stamp` is the joint sample's stamp (None: the clock
        domain's rule on the frame's time and its receipt)."""
        if isinstance(frame, RobotStatusFrame):
            self._status_pub.put(encode(RobotStatus(host_ns=host_ns, **frame.__dict__)))
            return
        if frame.group != 0:
            self.counters["other_group"] += 1
            return
        q = list(frame.positions[: self.nq])
        dq = list(frame.velocities[: self.nq]) if frame.velocities is not None else None
        device_stamp = frame.time if frame.valid_fields & 1 else None
        if stamp is None:
            stamp = self._stamp(device_stamp, host_ns * 1e-9)
        self._publish_joints(stamp, host_ns, q, dq, device_stamp)


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

    async def _read(self, reader: asyncio.StreamReader, _writer: asyncio.StreamWriter) -> None:
        self.parser.reset()
        self.stamper.restart()  # a new connection may bring a new device clock
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
            # the tracker's own stamps ("device": mapped onto the host clock, which carries
            # less jitter than the receipt time; "shared": used as they are)
            stamp = self._stamp(pose.device_stamp, host_ns * 1e-9)
            self._publish_pose(
                stamp,
                host_ns,
                pose.seq,
                list(pose.position) if pose.position is not None else None,
                list(pose.quaternion) if pose.quaternion is not None else None,
                pose.device_stamp,
                pose.status,
            )


# UR robot_mode values that mean the arm's drives have power, and safety modes that are stops
_UR_POWERED = frozenset({4, 5, 6, 7})  # POWER_ON, IDLE, BACKDRIVE, RUNNING
_UR_RUNNING = 7
_UR_ESTOP = frozenset({6, 7})  # SYSTEM / ROBOT EMERGENCY STOP
_UR_FAULT = frozenset({8, 9})  # VIOLATION, FAULT
_UR_MOTION_OK = frozenset({1, 2})  # NORMAL, REDUCED
HANDSHAKE_TIMEOUT_S = 5.0
ROBOT_STATUS_PERIOD_S = 0.5


class RtdeEncoderAdapter(EncoderAdapter):
    """Universal Robots RTDE (protocol 2) -> keo/<cell>/encoder and keo/<cell>/robot_status.

    Each joint sample keeps the controller's `timestamp` as `device_stamp` and gets `stamp` on the
    host clock from the clock mapping (not the receipt time, which carries TCP and
    scheduling jitter)."""

    def _declare(self, session: zenoh.Session) -> None:
        self._declare_publishers(session)
        if self.nq != 6:
            raise ValueError(
                f"robot.urdf has {self.nq} joints; a UR controller reports 6 (base, shoulder, "
                "elbow, wrist 1-3) in the URDF's joint order"
            )
        self.rtde_decoder = RtdeDecoder()
        self.controller = ""
        self._pending: collections.deque[Package] = collections.deque(maxlen=64)
        self._last_status: tuple[int, int] | None = None
        self._last_status_at = 0.0
        self._declare_corrections(session)

    # ---- corrections to the controller: six input double registers (robot.correction) ----

    def _declare_corrections(self, session: zenoh.Session) -> None:
        """With robot.correction = "rtde_registers": keo/<cell>/correction in, written to the
        controller as input double registers correction_register .. +5 (x, y, z m, then the
        rotation vector rad, tool frame: a URScript program applies pose_trans(target, p)),
        zero when none is fresh or valid (live.compensation.correction_to_send)."""
        self._latest_correction: CorrectionMessage | None = None
        self._correction_sub: zenoh.Subscriber[None] | None = None
        if self.config.robot.correction != "rtde_registers":
            return
        self._correction_sub = session.declare_subscriber(
            topic(self.config.cell, "correction"), self._on_correction
        )

    def _on_correction(self, sample: zenoh.Sample) -> None:  # zenoh thread
        try:
            msg = decode(sample.payload.to_bytes())
        except msgspec.DecodeError:
            self.counters["correction_undecodable"] += 1
            return
        if isinstance(msg, CorrectionMessage):
            self._latest_correction = msg  # one reference, swapped whole
            self.counters["corrections_received"] += 1

    def _correction_package(self, recipe: rtde.Recipe) -> bytes:
        p, r = correction_to_send(self._latest_correction, self.config.compensation)
        values = [*p, *r]
        self.counters["corrections_written"] += 1
        if any(values):
            self.counters["corrections_written_nonzero"] += 1
        return rtde.data_package(recipe, dict(zip(recipe.names, values, strict=True)))

    async def __aexit__(self, *exc: object) -> None:
        if getattr(self, "_correction_sub", None) is not None:
            assert self._correction_sub is not None
            self._correction_sub.undeclare()
        await super().__aexit__(*exc)

    def status(self) -> dict[str, Any]:
        return {
            "adapter": self.name,
            "counters": dict(self.counters),
            "decoder": dict(self.rtde_decoder.counters),
            "messages": list(self.rtde_decoder.messages),
            "controller": self.controller,
            "clock": self.stamper.state(),
        }

    async def _run(self) -> None:
        robot = self.config.robot
        await run_tcp_client(
            "encoder", robot.host, robot.endpoint_port, self._rtde, self._stop, self.counters
        )

    async def _rtde(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.rtde_decoder = RtdeDecoder()
        self._pending.clear()
        self.stamper.restart()  # a new connection: the controller may have restarted
        writer.write(rtde.request_protocol_version())
        try:
            answer = await self._expect(reader, rtde.REQUEST_PROTOCOL_VERSION)
        except (TimeoutError, rtde.RtdeError) as exc:  # the first answer: is this RTDE at all?
            why = str(exc) or f"no answer within {HANDSHAKE_TIMEOUT_S:g} s"
            raise rtde.RtdeError(
                f"RTDE's protocol version request: {why}; the device does not speak RTDE"
            ) from None
        if not rtde.parse_accepted(answer):
            raise rtde.RtdeError("the controller refused RTDE protocol version 2")
        writer.write(rtde.get_controller_version())
        version = rtde.parse_controller_version(
            await self._expect(reader, rtde.GET_URCONTROL_VERSION)
        )
        self.controller = ".".join(map(str, version))
        names = list(rtde.OUTPUTS)
        writer.write(rtde.setup_outputs(self.config.robot.frequency_hz, names))
        recipe = rtde.parse_outputs_reply(
            await self._expect(reader, rtde.CONTROL_PACKAGE_SETUP_OUTPUTS), names
        )
        inputs = None
        if self._correction_sub is not None:
            registers = rtde.input_double_registers(self.config.robot.correction_register)
            writer.write(rtde.setup_inputs(registers))
            inputs = rtde.parse_inputs_reply(
                await self._expect(reader, rtde.CONTROL_PACKAGE_SETUP_INPUTS), registers
            )
        writer.write(rtde.start())
        if not rtde.parse_accepted(await self._expect(reader, rtde.CONTROL_PACKAGE_START)):
            raise rtde.RtdeError("the controller refused to start streaming")
        log.info(
            "encoder: RTDE controller %s streaming %s at %g Hz",
            self.controller,
            ", ".join(names),
            self.config.robot.frequency_hz,
        )
        while self._pending:
            self._on_package(self._pending.popleft(), recipe, time.time_ns())
        while True:
            data = await reader.read(65536)
            if not data:
                return
            host_ns = time.time_ns()
            for pkg in self._feed(data):
                self._on_package(pkg, recipe, host_ns)
            if inputs is not None:  # with every controller cycle seen: the correction now
                writer.write(self._correction_package(inputs))

    def _feed(self, data: bytes) -> list[Package]:
        return self.rtde_decoder.feed(data)

    async def _expect(self, reader: asyncio.StreamReader, kind: int) -> Package:
        """The controller's answer of type `kind`; text messages on the way are logged."""
        async with asyncio.timeout(HANDSHAKE_TIMEOUT_S):
            while True:
                while self._pending:
                    pkg = self._pending.popleft()
                    if pkg.type == kind:
                        return pkg
                    self._on_side_package(pkg)
                data = await reader.read(65536)
                if not data:
                    raise rtde.RtdeError(
                        f"the controller closed during the handshake ({chr(kind)})"
                    )
                self._pending.extend(self._feed(data))

    def _on_side_package(self, pkg: Package) -> None:
        if pkg.type == rtde.TEXT_MESSAGE:
            try:
                text = rtde.parse_text_message(pkg)
            except rtde.RtdeError as exc:
                self.rtde_decoder.reject("bad_text", str(exc))
                return
            log.log(
                logging.WARNING if text.level >= 2 else logging.INFO,
                "controller (%s): %s",
                text.source,
                text.message,
            )
            self.counters["text_messages"] += 1
        else:
            self.rtde_decoder.reject("unexpected", f"package {pkg.type} at this point, skipped")

    def _on_package(self, pkg: Package, recipe: rtde.Recipe, host_ns: int) -> None:
        if pkg.type != rtde.DATA_PACKAGE:
            self._on_side_package(pkg)
            return
        try:
            values = recipe.unpack(pkg.payload)
        except rtde.RtdeError as exc:
            self.rtde_decoder.reject("bad_data", str(exc))
            return
        stamp = values["timestamp"]
        q, qd = values["actual_q"], values["actual_qd"]
        assert isinstance(stamp, float)
        assert isinstance(q, tuple)
        assert isinstance(qd, tuple)
        if not all(math.isfinite(v) for v in (stamp, *q, *qd)):
            self.rtde_decoder.reject("non_finite", f"data package at controller time {stamp!r}")
            return
        self._publish_joints(self._stamp(stamp, host_ns * 1e-9), host_ns, list(q), list(qd), stamp)
        self._maybe_publish_status(values, host_ns)

    def _maybe_publish_status(self, values: dict[str, Any], host_ns: int) -> None:
        robot_mode, safety_mode = int(values["robot_mode"]), int(values["safety_mode"])
        now = host_ns * 1e-9
        changed = (robot_mode, safety_mode) != self._last_status
        if not changed and now - self._last_status_at < ROBOT_STATUS_PERIOD_S:
            return
        self._last_status, self._last_status_at = (robot_mode, safety_mode), now
        moving = any(abs(v) > 1e-3 for v in values["actual_qd"])
        status = RobotStatus(
            host_ns=host_ns,
            drives_powered=int(robot_mode in _UR_POWERED),
            e_stopped=int(safety_mode in _UR_ESTOP),
            error_code=safety_mode if safety_mode in _UR_FAULT else 0,
            in_error=int(safety_mode in _UR_FAULT),
            in_motion=int(moving),
            mode=robot_mode,
            motion_possible=int(robot_mode == _UR_RUNNING and safety_mode in _UR_MOTION_OK),
        )
        self._status_pub.put(encode(status))


class _Ros2Adapter(_Adapter):
    """A ROS 2 topic over rmw_zenoh in, keo's samples out; the ROS messages arrive on the same
    Zenoh session (a client of the service or router), through the bounded hand-off."""

    topics: tuple[tuple[str, str], ...] = ()  # (topic, ROS type) pairs, set per instance

    def _declare(self, session: zenoh.Session) -> None:
        ros = self.config.ros2
        self.node = Ros2Node(
            session, f"keo_{self.config.cell}_{self.name}", ros.domain_id, ros.distro
        )
        self.rejects = RejectLog(keep=16)
        self._received = 0
        self._seq = 0
        self._declare_output(session)

    def _declare_output(self, session: zenoh.Session) -> None:
        raise NotImplementedError

    def status(self) -> dict[str, Any]:
        return {
            **super().status(),
            "decoder": dict(self.rejects.counters),
            "messages": list(self.rejects.messages),
            "topics": [ros_topic for ros_topic, _type in self.topics],
        }

    async def _run(self) -> None:
        keys = {}
        for ros_topic, typename in self.topics:
            self.node.declare_subscription(ros_topic, typename)
            keys[self.node.subscription_key(ros_topic, typename)] = typename
        sub = AsyncSubscription(self.node.session, list(keys))
        stopping = asyncio.ensure_future(self._stop.wait())
        try:
            async for key, payload in _until(sub, stopping):
                self.on_payload(payload, _type_of(key, keys), key)
        finally:
            stopping.cancel()
            sub.close()
            self.node.close()

    def on_payload(self, payload: bytes, typename: str, key: str = "") -> None:
        """One sample's CDR bytes: decoded by rosbags and published; whatever rosbags cannot
        decode is counted as `bad_cdr` (its errors are not one documented type). A reject
        names the message's number among those received."""
        self._received += 1
        self.rejects.at = f"message {self._received} received"
        try:
            message = self.node.deserialize(payload, typename)
        except Exception as exc:
            self.rejects.reject("bad_cdr", f"{typename} on {key}: {exc}")
            return
        self._on_message(message, typename, time.time_ns())

    def _on_message(self, message: Any, typename: str, host_ns: int) -> None:
        raise NotImplementedError


def _type_of(key: str, keys: dict[str, str]) -> str:
    for pattern, typename in keys.items():
        if key.rsplit("/", 1)[0] == pattern.rsplit("/", 1)[0]:
            return typename
    return next(iter(keys.values()))


async def _until(sub: AsyncSubscription, stopping: asyncio.Future[Any]) -> Any:
    iterator = sub.__aiter__()
    while True:
        nxt = asyncio.ensure_future(anext(iterator))
        done, _ = await asyncio.wait({nxt, stopping}, return_when=asyncio.FIRST_COMPLETED)
        if nxt not in done:
            nxt.cancel()
            return
        try:
            yield nxt.result()
        except StopAsyncIteration:
            return


class Ros2JointStateAdapter(_Ros2Adapter):
    """sensor_msgs/msg/JointState on `robot.joint_states_topic` -> keo/<cell>/encoder, joints
    picked by name into the URDF's order (other names ignored), header.stamp as device time."""

    name = "encoder"

    def __init__(self, config: Config, joint_names: list[str], session: Any = None) -> None:
        super().__init__(config, len(joint_names), session)
        self.joint_names = list(joint_names)
        self.topics = ((config.robot.joint_states_topic, JOINT_STATE),)

    def _declare_output(self, session: zenoh.Session) -> None:
        self._pub = session.declare_publisher(
            topic(self.config.cell, "encoder"),
            congestion_control=zenoh.CongestionControl.BLOCK,
            express=True,
        )

    def _on_message(self, message: Any, typename: str, host_ns: int) -> None:
        if len(message.position) != len(message.name):  # found fuzzing: an IndexError
            self.rejects.reject(
                "bad_lengths",
                f"JointState with {len(message.name)} names and {len(message.position)} "
                "positions (a position per name)",
            )
            return
        index = {name: i for i, name in enumerate(message.name)}
        missing = [n for n in self.joint_names if n not in index]
        if missing:
            self.rejects.reject(
                "missing_joint",
                f"JointState without {', '.join(missing)} (has {', '.join(message.name)}); "
                "the URDF's joints are " + ", ".join(self.joint_names),
            )
            return
        q = [float(message.position[index[n]]) for n in self.joint_names]
        dq = None
        if len(message.velocity) == len(message.name):
            dq = [float(message.velocity[index[n]]) for n in self.joint_names]
        stamp = seconds_of(message.header)
        if not all(math.isfinite(v) for v in (*q, stamp)):
            self.rejects.reject("non_finite", f"JointState at stamp {stamp!r}")
            return
        self._publish_joints(self._stamp(stamp, host_ns * 1e-9), host_ns, q, dq, stamp)


class Ros2PoseAdapter(_Ros2Adapter):
    """geometry_msgs/msg/PoseStamped (a 6-DoF probe) or PointStamped (a single reflector) on
    `tracker.pose_topic`, in metres -> keo/<cell>/tracker; header.stamp as device time."""

    name = "tracker"

    def __init__(self, config: Config, nq: int, session: Any = None) -> None:
        super().__init__(config, nq, session)
        topic_ = config.tracker.pose_topic
        self.topics = ((topic_, POSE_STAMPED), (topic_, POINT_STAMPED))

    def _declare_output(self, session: zenoh.Session) -> None:
        self._pub = session.declare_publisher(
            topic(self.config.cell, "tracker"),
            congestion_control=zenoh.CongestionControl.BLOCK,
            express=True,
        )

    def _on_message(self, message: Any, typename: str, host_ns: int) -> None:
        stamp = seconds_of(message.header)
        if typename == POSE_STAMPED:
            pos, o = message.pose.position, message.pose.orientation
            p = [pos.x, pos.y, pos.z]
            q: list[float] | None = [o.w, o.x, o.y, o.z]
        else:
            p, q = [message.point.x, message.point.y, message.point.z], None
        values = [*p, *(q or []), stamp]
        if not all(math.isfinite(v) for v in values):
            self.rejects.reject("non_finite", f"{typename} at stamp {stamp!r}")
            return
        if q is not None:
            norm = math.sqrt(sum(v * v for v in q))
            if abs(norm - 1.0) > 1e-3:
                self.rejects.reject("not_unit_quaternion", f"quaternion norm {norm:.6g}")
                return
            q = [v / norm for v in q]
        self._seq += 1
        self._publish_pose(self._stamp(stamp, host_ns * 1e-9), host_ns, self._seq, p, q, stamp)
