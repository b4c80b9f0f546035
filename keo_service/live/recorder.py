"""`keo record` and `keo replay`: raw streams to the interchange files and back onto the bus.

The recorder writes rows as samples arrive (bounded memory) and flushes at least once a
second, so a killed recorder loses at most a second. Numbers are written with repr(), so a
replay publishes exactly the floats that were recorded. Tracker gaps are counted, not written:
the interchange format has no row for "no pose".
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import msgspec
import numpy as np
import zenoh

from keo_service.core.errors import KeoError
from keo_service.io.interchange import (
    TRACKER_POSE_COLUMNS,
    TRACKER_POSITION_COLUMNS,
    read_encoder,
    read_tracker,
)
from keo_service.io.mcap_files import McapWriter, is_mcap, read_mcap
from keo_service.live.bus import AsyncSubscription
from keo_service.live.messages import (
    EstimateMessage,
    JointSample,
    ServiceStatus,
    TrackerSample,
    decode,
    encode,
    topic,
)
from keo_service.live.supervise import supervise

log = logging.getLogger("keo.record")
FLUSH_PERIOD_S = 1.0
# a stream with nothing for this long while the other still sends has stopped: warned, counted
STREAM_STOPPED_S = 2.0


@dataclass
class RecordStats:
    encoder_rows: int = 0
    tracker_rows: int = 0
    tracker_gaps: int = 0
    rejected: int = 0
    messages: list[str] = field(default_factory=list)
    stream_stops: int = 0  # one stream stopped while the other went on (see messages)
    # why recording stopped before it was asked to (the disk is full, the file went away);
    # empty when it did not, and the samples that arrived after it
    stopped: str = ""
    not_recorded: int = 0


class _StreamRecorder:
    """Decodes and checks what arrives; the subclasses write it."""

    def __init__(self, nq: int) -> None:
        self.nq = nq
        self.stats = RecordStats()
        self.last_seen: dict[str, float] = {}  # stream -> monotonic time of its newest sample
        self._stopped: set[str] = set()
        self.where = "the output"  # for messages: where the recording goes

    def check_streams(self, now: float) -> None:
        """Warn (once per stop) when one stream has stopped while the other goes on: the rows
        recorded from then on have no partner to be aligned with."""
        if len(self.last_seen) < 2:
            return
        for name, other in (("encoder", "tracker"), ("tracker", "encoder")):
            quiet = now - self.last_seen[name]
            if quiet >= STREAM_STOPPED_S and now - self.last_seen[other] < STREAM_STOPPED_S / 2:
                if name not in self._stopped:
                    self._stopped.add(name)
                    self.stats.stream_stops += 1
                    text = (
                        f"the {name} stream stopped {quiet:.1f} s ago while the {other} stream "
                        f"goes on: {other} rows from then on have no {name} data to align with"
                    )
                    log.warning("%s", text)
                    if len(self.stats.messages) < 20:
                        self.stats.messages.append(text)
            elif quiet < STREAM_STOPPED_S and name in self._stopped:
                self._stopped.discard(name)
                log.info("the %s stream is back", name)

    def _note(self, text: str) -> None:
        self.stats.rejected += 1
        if len(self.stats.messages) < 20:
            self.stats.messages.append(text)

    def on_payload(self, payload: bytes) -> None:
        """One sample; a write that fails (ENOSPC, EIO...) stops the recording for good: it
        is said once in the log and in `stats.stopped`, later samples are only counted."""
        if self.stats.stopped:
            self.stats.not_recorded += 1
            return
        try:
            self._on_payload(payload)
        except OSError as exc:
            self._give_up(exc)

    def flush(self) -> None:
        if self.stats.stopped:
            return
        try:
            self.maybe_flush()
        except OSError as exc:
            self._give_up(exc)

    def _give_up(self, exc: OSError) -> None:
        where = getattr(exc, "filename", None) or self.where
        self.stats.stopped = f"cannot write the recording in {where}: {exc.strerror or exc}"
        log.error(
            "%s; recording stopped, the service and the bus are not affected", self.stats.stopped
        )
        with contextlib.suppress(OSError):
            self.abandon()

    def abandon(self) -> None:
        """Close what is open without writing more (after a failed write)."""

    def _on_payload(self, payload: bytes) -> None:
        try:
            msg = decode(payload)
        except msgspec.DecodeError as exc:
            self._note(f"undecodable payload: {exc}")
            return
        if isinstance(msg, JointSample | TrackerSample):
            self.last_seen["encoder" if isinstance(msg, JointSample) else "tracker"] = (
                time.monotonic()
            )
        if isinstance(msg, JointSample):
            if len(msg.joints) != self.nq:
                self._note(
                    f"joint sample seq {msg.seq} with {len(msg.joints)} joints, expected {self.nq}"
                )
                return
            self._joints(msg)
            self.stats.encoder_rows += 1
        elif isinstance(msg, TrackerSample):
            if msg.status != "ok" or msg.position is None:
                self.stats.tracker_gaps += 1
                return
            if self._pose(msg):
                self.stats.tracker_rows += 1
        elif isinstance(msg, EstimateMessage) and msg.measured is not None:
            self._estimate(msg)
        self.maybe_flush()

    def _joints(self, msg: JointSample) -> None:
        raise NotImplementedError

    def _pose(self, msg: TrackerSample) -> bool:
        raise NotImplementedError

    def _estimate(self, msg: EstimateMessage) -> None:
        pass

    def maybe_flush(self, force: bool = False) -> None:
        pass

    def close(self) -> None:
        pass


class Recorder(_StreamRecorder):
    """Writes encoder.csv and tracker.csv in `out_dir` from samples as they arrive."""

    def __init__(self, out_dir: Path, nq: int) -> None:
        super().__init__(nq)
        out_dir.mkdir(parents=True, exist_ok=True)
        self.out_dir = out_dir
        self.where = str(out_dir)
        self._enc: TextIO = (out_dir / "encoder.csv").open("w", encoding="utf-8")
        self._enc.write(",".join(["t", *(f"q{i + 1}" for i in range(nq))]) + "\n")
        self._trk: TextIO | None = None
        self._trk_has_q: bool | None = None
        self._last_flush = time.monotonic()

    def _joints(self, msg: JointSample) -> None:
        self._enc.write(",".join(repr(float(v)) for v in (msg.stamp, *msg.joints)) + "\n")

    def _pose(self, msg: TrackerSample) -> bool:
        assert msg.position is not None
        has_q = msg.quaternion is not None
        if self._trk is None:
            self._trk = (self.out_dir / "tracker.csv").open("w", encoding="utf-8")
            cols = TRACKER_POSE_COLUMNS if has_q else TRACKER_POSITION_COLUMNS
            self._trk.write(",".join(cols) + "\n")
            self._trk_has_q = has_q
        if has_q != self._trk_has_q:
            self._note(f"tracker sample seq {msg.seq}: orientation presence changed mid-stream")
            return False
        values = (msg.stamp, *msg.position, *(msg.quaternion or ()))
        self._trk.write(",".join(repr(float(v)) for v in values) + "\n")
        return True

    def maybe_flush(self, force: bool = False) -> None:
        now = time.monotonic()
        if force or now - self._last_flush >= FLUSH_PERIOD_S:
            self._enc.flush()
            if self._trk is not None:
                self._trk.flush()
            self._last_flush = now

    def close(self) -> None:
        if self.stats.stopped:
            return
        try:
            self.maybe_flush(force=True)
        except OSError as exc:
            self._give_up(exc)
            return
        self._enc.close()
        if self._trk is not None:
            self._trk.close()

    def abandon(self) -> None:
        for f in (self._enc, self._trk):
            if f is not None:
                with contextlib.suppress(OSError):
                    f.close()  # buffered rows that cannot be written are lost with it


class McapRecorder(_StreamRecorder):
    """The same streams, and the service's estimates, as a ROS 2 MCAP recording (rosbags
    writes its chunks as they fill)."""

    def __init__(self, writer: McapWriter, nq: int) -> None:
        super().__init__(nq)
        self.writer = writer

    def _joints(self, msg: JointSample) -> None:
        self.writer.joints(msg.stamp, msg.joints, msg.velocities)

    def _pose(self, msg: TrackerSample) -> bool:
        assert msg.position is not None
        self.writer.pose(msg.stamp, msg.position, msg.quaternion)
        return True

    def _estimate(self, msg: EstimateMessage) -> None:
        self.writer.estimate(msg.stamp, msg.estimate)

    def close(self) -> None:
        if self.stats.stopped:
            return
        try:
            self.writer.close()
        except OSError as exc:
            self._give_up(exc)

    def abandon(self) -> None:
        self.writer.close()


# complexity (C901): its tasks (subscriber, flusher, stream watch, duration) set up in order
async def record(  # noqa: C901
    session: zenoh.Session,
    cell: str,
    out_dir: Path,
    nq: int,
    stop: asyncio.Event,
    duration: float | None = None,
    mcap: McapWriter | None = None,
) -> RecordStats:
    """Record until `stop` (or `duration`): interchange CSV files, or with `mcap` a ROS 2
    MCAP recording that also holds the estimates."""
    recorder = Recorder(out_dir, nq) if mcap is None else McapRecorder(mcap, nq)
    keys = [topic(cell, "encoder"), topic(cell, "tracker")]
    if mcap is not None:
        keys.append(topic(cell, "estimate"))
    sub = AsyncSubscription(session, keys)

    async def consume() -> None:
        async for _key, payload in sub:
            recorder.on_payload(payload)
            if recorder.stats.stopped:
                stop.set()

    async def flusher() -> None:
        while True:
            await asyncio.sleep(FLUSH_PERIOD_S / 2)
            recorder.flush()
            recorder.check_streams(time.monotonic())
            if recorder.stats.stopped:
                stop.set()

    failures: list[BaseException] = []

    def fail(exc: BaseException) -> None:
        failures.append(exc)
        stop.set()

    tasks = [
        supervise(asyncio.create_task(consume(), name="keo.record.consume"), stop.is_set, fail),
        supervise(asyncio.create_task(flusher(), name="keo.record.flush"), stop.is_set, fail),
    ]
    try:
        if duration is None:
            await stop.wait()
        else:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), duration)
    finally:
        sub.close()
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        recorder.close()
    if failures:  # logged with its traceback when it happened
        raise KeoError(f"recording stopped after an internal failure: {failures[0]}") from failures[
            0
        ]
    recorder.stats.rejected += sub.dropped
    return recorder.stats


@dataclass
class ReplayPlan:
    """Both streams merged in stamp order (encoder first on ties), as `keo estimate` feeds them."""

    kinds: np.ndarray  # 0 encoder, 1 tracker
    index: np.ndarray
    t: np.ndarray


def replay_plan(enc_t: np.ndarray, trk_t: np.ndarray) -> ReplayPlan:
    t = np.concatenate([enc_t, trk_t])
    kinds = np.concatenate([np.zeros(enc_t.size, int), np.ones(trk_t.size, int)])
    index = np.concatenate([np.arange(enc_t.size), np.arange(trk_t.size)])
    order = np.lexsort((kinds, t))
    return ReplayPlan(kinds[order], index[order], t[order])


def _status_received(session: zenoh.Session, cell: str) -> int | None:
    for reply in session.get(topic(cell, "status"), timeout=1.0):
        if reply.ok:
            msg = decode(reply.ok.payload.to_bytes())
            if isinstance(msg, ServiceStatus):
                return int(msg.counters.get("received", 0))
    return None


async def replay(
    session: zenoh.Session,
    cell: str,
    directory: Path,
    nq: int,
    as_fast_as_possible: bool,
    stop: asyncio.Event,
    joint_names: Sequence[str] = (),
) -> dict[str, Any]:
    """Publish recorded files (interchange CSV, or a ROS 2 MCAP recording) back onto the bus,
    at the recorded pace or as fast as the service takes them (it waits on the service's
    `received` counter between chunks)."""
    if is_mcap(directory):
        enc, trk = read_mcap(directory, joint_names)
    else:
        enc = read_encoder(directory / "encoder.csv", nq=nq)
        trk = read_tracker(directory / "tracker.csv")
    plan = replay_plan(enc.t, trk.t)
    block = zenoh.CongestionControl.BLOCK
    enc_pub = session.declare_publisher(topic(cell, "encoder"), congestion_control=block)
    trk_pub = session.declare_publisher(topic(cell, "tracker"), congestion_control=block)
    chunk = 250
    baseline = (
        await asyncio.to_thread(_status_received, session, cell) if as_fast_as_possible else None
    )
    start_wall = time.time()
    sent = 0
    for k in range(plan.t.size):
        if stop.is_set():
            break
        if not as_fast_as_possible:
            delay = start_wall + (plan.t[k] - plan.t[0]) - time.time()
            if delay > 0:
                await asyncio.sleep(delay)
        i = int(plan.index[k])
        now_ns = time.time_ns()
        if plan.kinds[k] == 0:
            enc_pub.put(
                encode(
                    JointSample(
                        stamp=float(enc.t[i]), host_ns=now_ns, seq=i + 1, joints=enc.q[i].tolist()
                    )
                )
            )
        else:
            quat = None if trk.quat is None else trk.quat[i].tolist()
            trk_pub.put(
                encode(
                    TrackerSample(
                        stamp=float(trk.t[i]),
                        host_ns=now_ns,
                        seq=i + 1,
                        position=trk.p[i].tolist(),
                        quaternion=quat,
                    )
                )
            )
        sent += 1
        if as_fast_as_possible and baseline is not None and sent % chunk == 0:
            await _wait_for_service(session, cell, baseline + sent, stop)
    if as_fast_as_possible and baseline is not None:
        await _wait_for_service(session, cell, baseline + sent, stop)
    enc_pub.undeclare()
    trk_pub.undeclare()
    return {
        "published": sent,
        "encoder_rows": int(enc.t.size),
        "tracker_rows": int(trk.t.size),
        "seconds": time.time() - start_wall,
    }


async def _wait_for_service(
    session: zenoh.Session, cell: str, target: int, stop: asyncio.Event, timeout: float = 30.0
) -> None:
    deadline = time.monotonic() + timeout
    while not stop.is_set() and time.monotonic() < deadline:
        received = await asyncio.to_thread(_status_received, session, cell)
        if received is not None and received >= target:
            return
        await asyncio.sleep(0.05)
