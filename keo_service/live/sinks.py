"""The service's outputs behind one protocol (python-can's Listener is the model): `KeoService`
calls each configured `Sink` with every input sample, every estimate and, for a sink that asks
for it, a status snapshot at its own period; `Sinks` does the fan-out.

A sink counts and logs what one sample can cause on its own (the bus refusing one put): that
is not a failure. Anything else a sink raises is an internal failure: `Sinks` counts it
(`sink_failed_<name>`), logs it with its cause, still serves the other sinks with the same
item, and then raises `SinkFailedError` from it, so that the service task that called fails
under supervision (logged with its name and traceback) and `keo run` exits non-zero (the
project's rule: an internal failure is logged with its cause and the process exits non-zero;
systemd restarts it). No output is ever dropped silently.
"""

from __future__ import annotations

import collections
import logging
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, Any, Protocol

import msgspec
import zenoh

from keo_service.core.errors import KeoError
from keo_service.core.estimator import Estimate
from keo_service.core.observer import NoiseMeter, covariance_noise, tracker_noise_floor
from keo_service.io.config import Config
from keo_service.live.bus import output_publisher
from keo_service.live.messages import (
    ENCODER,
    EstimateMessage,
    JointSample,
    ServiceStatus,
    TrackerSample,
    topic,
)

# the bus sink's encoder call, bound once (the same encoder as `encode`, one call less per
# estimate)
_encode = ENCODER.encode

if TYPE_CHECKING:
    from keo_service.live.rerun_process import RerunWorker
    from keo_service.live.ros2_bridge import EstimateBridge

__all__ = [
    "EstimateBusSink",
    "RerunSink",
    "Ros2EstimateSink",
    "Sink",
    "SinkFailedError",
    "Sinks",
]

log = logging.getLogger("keo.service")
Sample = JointSample | TrackerSample


class SinkFailedError(KeoError):
    """An output of the service failed inside (not a refused put); the cause is chained."""


class Sink(Protocol):
    """One output of the service. `period_s`: how often it wants `on_tick` (None: never); the
    service runs that in a task of its own, named `keo.service.<name>`."""

    name: str

    @property
    def period_s(self) -> float | None:
        """The sink's cycle (s), None without one."""

    def on_input(self, sample: Sample) -> None:
        """An encoder or tracker sample as it arrived (before the estimator)."""

    def on_estimate(self, estimate: Estimate, message: EstimateMessage) -> None:
        """An estimate and its wire message."""

    def on_tick(self) -> None:
        """Every `period_s` (only for a sink that has one)."""

    def counters(self) -> dict[str, int]:
        """What the sink counted, merged into the service's status counters."""

    def close(self) -> None:
        """Undeclare, flush, stop; called once at shutdown."""


class Sinks:
    """The fan-out over the configured sinks, in order (see the module). Per sample and per
    estimate the sinks are called in a plain loop (no closure, one `try` around it); only
    when one raises does the careful path take over, which still serves the sinks after it.
    A sample goes only to the sinks that take samples (a sink built on `_Base` that keeps
    its no-op `on_input` gets none)."""

    def __init__(self, sinks: Iterable[Sink] = ()) -> None:
        self.sinks: list[Sink] = []
        self._inputs: list[Sink] = []  # the sinks with an `on_input` of their own
        self.failures: collections.Counter[str] = collections.Counter()
        self.only_estimate: Callable[[Estimate, EstimateMessage], None] | None = None
        # whether any sink takes the input samples (else `on_input` need not be called): an
        # attribute, read at every wake-up
        self.takes_input = False
        for sink in sinks:
            self.add(sink)

    def add(self, sink: Sink) -> None:
        self.sinks.append(sink)
        if getattr(type(sink), "on_input", None) is not _Base.on_input:
            self._inputs.append(sink)
        # with one sink, the service calls its `on_estimate` itself (one frame fewer per
        # estimate) and `estimate_failed` when it raises
        self.only_estimate = self.sinks[0].on_estimate if len(self.sinks) == 1 else None
        self.takes_input = bool(self._inputs)

    def _failed(self, what: str, sink: Sink, exc: Exception) -> None:
        self.failures[sink.name] += 1
        log.error(
            "the %s output failed on %s (%d so far): %s: %s",
            sink.name,
            what,
            self.failures[sink.name],
            type(exc).__name__,
            exc,
            exc_info=exc,
        )

    def _call(
        self,
        what: str,
        sinks: Iterable[Sink],
        call: Callable[[Sink], None],
        first: tuple[Sink, Exception] | None = None,
    ) -> None:
        """Each of `sinks` called; a failure counted and logged, the others served, then the
        first (`first`: one that happened before these) raised."""
        for sink in sinks:
            try:
                call(sink)
            except Exception as exc:  # counted, logged, the others served, then raised
                self._failed(what, sink, exc)
                first = first or (sink, exc)
        if first is not None:
            failed, cause = first
            raise SinkFailedError(f"the {failed.name} output failed on {what}: {cause}") from cause

    def _rest(
        self, what: str, sinks: list[Sink], i: int, exc: Exception, call: Callable[[Sink], None]
    ) -> None:
        """sinks[i] raised `exc` on the fast path: count and log it, serve the ones after it,
        raise."""
        self._failed(what, sinks[i], exc)
        self._call(what, sinks[i + 1 :], call, (sinks[i], exc))

    def on_input(self, sample: Sample) -> None:
        sinks = self._inputs
        i = 0
        try:
            for sink in sinks:
                sink.on_input(sample)
                i += 1
        except Exception as exc:
            self._rest("a sample", sinks, i, exc, lambda s: s.on_input(sample))

    def on_estimate(self, estimate: Estimate, message: EstimateMessage) -> None:
        sinks = self.sinks
        i = 0
        try:
            for sink in sinks:
                sink.on_estimate(estimate, message)
                i += 1
        except Exception as exc:
            self._rest("an estimate", sinks, i, exc, lambda s: s.on_estimate(estimate, message))

    def estimate_failed(
        self, i: int, exc: Exception, estimate: Estimate, message: EstimateMessage
    ) -> None:
        """sinks[i] raised `exc` on an estimate the caller gave it directly
        (`only_estimate`): as `on_estimate` does, count and log it, serve the ones after
        it, raise `SinkFailedError`."""
        self._rest("an estimate", self.sinks, i, exc, lambda s: s.on_estimate(estimate, message))

    def on_tick(self, sink: Sink) -> None:
        self._call("its cycle", [sink], lambda s: s.on_tick())

    def counters(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for sink in self.sinks:
            out.update(sink.counters())
        for name, n in self.failures.items():
            out[f"sink_failed_{name}"] = n
        return out

    def close(self) -> None:
        """Close every sink, in reverse order; one that fails to close is logged, the others
        still close."""
        for sink in reversed(self.sinks):
            try:
                sink.close()
            except Exception as exc:  # shutting down: logged with its cause
                log.error(
                    "closing the %s output failed: %s: %s", sink.name, type(exc).__name__, exc
                )


class _Base:
    """No-op defaults for the hooks a sink does not need."""

    name = "sink"
    period_s: float | None = None

    def on_input(self, sample: Sample) -> None:
        pass

    def on_estimate(self, estimate: Estimate, message: EstimateMessage) -> None:
        pass

    def on_tick(self) -> None:
        pass

    def counters(self) -> dict[str, int]:
        return {}

    def close(self) -> None:
        pass


def estimate_publisher(
    session: zenoh.Session, cell: str, local_subscribers: bool = True
) -> zenoh.Publisher:
    """The publisher of keo/<cell>/estimate (`bus.output_publisher`: without
    `local_subscribers`, to other sessions only)."""
    return output_publisher(session, topic(cell, "estimate"), local_subscribers)


class EstimateBusSink(_Base):
    """keo/<cell>/estimate: each estimate put on the bus, and the newest kept for a client
    that joins late and asks (the queryable on the same key). `local_subscribers`: see
    `estimate_publisher`."""

    name = "bus"

    def __init__(self, session: zenoh.Session, cell: str, local_subscribers: bool = True) -> None:
        self.cell = cell
        self._pub = estimate_publisher(session, cell, local_subscribers)
        self._latest = b""
        self._latest_q = session.declare_queryable(topic(cell, "estimate"), self._on_latest_query)
        self.published = 0
        self.failures = 0

    def on_estimate(self, estimate: Estimate, message: EstimateMessage) -> None:
        payload = _encode(message)
        try:
            self._pub.put(payload)
        except zenoh.ZError as exc:  # the bus refused one sample: counted, the next may pass
            self.failures += 1
            if self.failures == 1 or self.failures % 1000 == 0:
                log.warning("publishing an estimate failed (%d so far): %s", self.failures, exc)
        self._latest = payload
        self.published += 1

    def _on_latest_query(self, query: zenoh.Query) -> None:  # zenoh thread
        latest = self._latest
        if latest:  # answer with our own key, so a wildcard query tells the cells apart
            query.reply(topic(self.cell, "estimate"), latest)

    def counters(self) -> dict[str, int]:
        return {"published": self.published, "publish_failed": self.failures}

    def close(self) -> None:
        self._latest_q.undeclare()
        self._pub.undeclare()


class Ros2EstimateSink(_Base):
    """/keo/<cell>/kinematic_error (and /tf) through the ROS 2 bridge, with the covariance's
    bookkeeping: the measured noise, the tracker's newest position (the noise floor depends on
    its distance) and the observer's period over its last updates. `gains`: the gains in use
    now (they change on reload)."""

    name = "ros2"

    def __init__(self, bridge: EstimateBridge, config: Config, gains: Callable[[], Any]) -> None:
        self.bridge = bridge
        self._tracker = config.tracker
        self._gains = gains
        self._noise = NoiseMeter()
        self._last_tracker_p: list[float] | None = None
        self._update_stamps: collections.deque[float] = collections.deque(maxlen=50)

    def on_input(self, sample: Sample) -> None:
        if isinstance(sample, TrackerSample) and sample.position is not None:
            self._last_tracker_p = sample.position

    def on_estimate(self, estimate: Estimate, message: EstimateMessage) -> None:
        if estimate.measured is None:
            return
        self._noise.add(estimate.measured)
        tracker = self._tracker
        floor = tracker_noise_floor(
            tracker.uncertainty_um,
            tracker.uncertainty_um_per_m,
            self._last_tracker_p,
            estimate.measured.size,
        )
        noise = covariance_noise(self._noise.std(), floor)
        self._update_stamps.append(estimate.stamp)
        self.bridge.publish(message, noise, self._gains(), self.period())

    def period(self) -> float:
        """The observer's mean step [s] over its last updates, in stream time (its nominal
        10 ms before two). Not the arrival rate: arrivals bunch when samples wait for encoder
        data, and a step that looks short would shrink the covariance."""
        stamps = self._update_stamps
        if len(stamps) < 2 or stamps[-1] <= stamps[0]:
            return 0.01
        return (stamps[-1] - stamps[0]) / (len(stamps) - 1)

    def close(self) -> None:
        self.bridge.close()


class RerunSink(_Base):
    """Rerun, through the worker process: every estimate, and a status snapshot (`status()`)
    every `period_s` (its rates, counters and events for the text log). A Rerun process that
    died is an internal failure (raised at the next tick)."""

    name = "viz"

    def __init__(
        self, worker: RerunWorker, period_s: float, status: Callable[[], ServiceStatus]
    ) -> None:
        self.worker = worker
        self.period_s = period_s
        self._status = status

    def start(self) -> None:
        self.worker.start()

    def on_estimate(self, estimate: Estimate, message: EstimateMessage) -> None:
        self.worker.submit(estimate)

    def on_tick(self) -> None:
        if self.worker.failure is not None:  # the Rerun process died: fail like any task
            raise RuntimeError("Rerun logging failed") from self.worker.failure
        self.worker.submit(msgspec.to_builtins(self._status()))

    def counters(self) -> dict[str, int]:
        return {"rerun_dropped": self.worker.dropped}

    def close(self) -> None:
        self.worker.close()
