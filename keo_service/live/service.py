"""`keo run`: the live service. It only moves data: Zenoh samples in, the Estimator (all the
math), estimates and status out. An async context manager that owns its session and tasks.

Supervision: every task is watched. A task that raises (or ends while the service runs) is
logged at error level at once with its name and traceback, the service stops its other tasks
and `run_service` raises `ServiceFailedError`, so `keo run` exits non-zero and systemd restarts it.
What one bad input can cause is counted instead (undecodable payloads, rejected samples in the
estimator, a failed publish): those never stop the service.
"""

from __future__ import annotations

import asyncio
import collections
import gc
import logging
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import msgspec
import zenoh

from keo_service.core.errors import KeoError
from keo_service.core.estimator import Estimate, Estimator
from keo_service.core.timing import DelayModel
from keo_service.core.tool_speed import ToolSpeed
from keo_service.io.cell import cell_from_config, delay_model, delay_prior, estimator_settings
from keo_service.io.config import Config
from keo_service.live.bus import AsyncSubscription, session_for_service
from keo_service.live.messages import (
    DECODER,
    AdapterStatus,
    DelayState,
    EstimateMessage,
    JointSample,
    ServiceStatus,
    TrackerSample,
    encode,
    estimate_message,
    topic,
)
from keo_service.live.sinks import EstimateBusSink, RerunSink, Sinks
from keo_service.live.status_view import DelayLog, delay_tracking_text
from keo_service.live.supervise import supervise

# keys a SIGHUP applies without a restart
HOT_KEYS = frozenset({"observer.gain", "timing.delay_s", "timing.drift_ppm", "timing.drift_ref_s"})


def _delay_state_of(tracker: OnlineDelayTracker) -> DelayState:
    """The tracker's source and last decision as the wire's `DelayState`."""
    decision, fit = tracker.decision, tracker.decision.fit_s
    return DelayState(
        source=tracker.source_kind,
        source_t=tracker.source_t if math.isfinite(tracker.source_t) else None,
        settled=tracker.settled,
        verdict=decision.verdict,
        reason=decision.reason,
        fit_s=fit if math.isfinite(fit) else None,
        fit_se_s=decision.fit_se_s if math.isfinite(fit) else None,
        decided_t=decision.t if math.isfinite(decision.t) else None,
    )


def _flatten(doc: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in doc.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out.update(_flatten(value, name + "."))
        else:
            out[name] = value
    return out


if TYPE_CHECKING:
    from keo_service.fit.delay_online import OnlineDelayTracker
    from keo_service.live.fit_worker import FitWorker
    from keo_service.live.sinks import Sink

log = logging.getLogger("keo.service")
VIZ_PERIOD_S = 0.1  # Rerun gets batches at display rate, never one call per sample
STATUS_PERIOD_S = 0.1
# how often the delay tracker is asked whether a stretch is ready (a cheap check): a fit then
# waits at most this long (its stretches are 2-2.5 s)
DELAY_POLL_S = 0.25
# the samples kept for the delay tracker between two blocks (`_feed_delay`, every 0.1 s from
# the status loop: about 125 at 1 kHz and 250 Hz); a fuller list is handed over at once
DELAY_INBOX = 2048
STALE_AFTER_S = 1.0  # wall time without a fresh estimate before health says "stale"
UNSETTLED = ("delay_unsettled",)  # the flag of an estimate made with a delay not settled yet


MAX_ADAPTERS = 16  # adapters whose newest state change the service keeps (bounded)
MAX_MESSAGES = 16  # the service's own newest messages kept for its status (bounded)


class RateMeter:
    """Samples per second over the last `window` arrivals (bounded)."""

    def __init__(self, window: int = 200) -> None:
        self._times: collections.deque[float] = collections.deque(maxlen=window)
        # one arrival at monotonic time `now`: the deque's own append (no Python call per
        # sample on the data path)
        self.tick: Callable[[float], None] = self._times.append

    def rate(self, now: float) -> float:
        if len(self._times) < 2 or now - self._times[-1] > 2.0:
            return 0.0
        span = self._times[-1] - self._times[0]
        if span <= 0.0:  # a burst handled at one instant (e.g. the first encoder sample
            return 0.0  # releasing the tracker samples that waited for it): no rate yet
        return (len(self._times) - 1) / span


class ServiceFailedError(KeoError):
    """A task of the service failed; the cause is chained and was logged when it happened."""


class KeoService:
    def __init__(
        self,
        config: Config,
        session: zenoh.Session | None = None,
        rrd: Path | None = None,
        viewer: str | None = None,
        viewer_window_s: float | None = None,
    ) -> None:
        self.config = config
        self.cell = config.cell
        cell = cell_from_config(config)
        self.estimator = Estimator(cell, estimator_settings(config))
        self._tool_speed = ToolSpeed(cell)  # sampled in the status cycle, not per estimate
        self._delay_tracker: OnlineDelayTracker | None = None
        self._delay_followed: float | None = None  # the delay last set from the tracker
        self._delay_log = DelayLog(None)  # what of the tracker's decisions the log says
        self._delay_state: DelayState | None = None  # the tracker's, as last made
        self._delay_state_for: object = None  # the tracker's decision it was made from
        self._fit_cpu_s = 0.0  # the delay fits' CPU time in the worker, all of them (s)
        self._fits: FitWorker | None = None  # the fits' worker process, while running
        # the samples not yet handed to the delay tracker, in arrival order (`_feed_delay`)
        self._delay_inbox: list[JointSample | TrackerSample] = []
        if config.timing.track_delay:
            from keo_service.fit.delay_online import OnlineDelayTracker

            self._delay_tracker = OnlineDelayTracker(
                cell, None, *delay_prior(config.timing), max_gap_s=config.timing.max_gap_s
            )
            self._delay_log = DelayLog(self._delay_tracker.delay_now())
        # the outputs, in order: bus, corrections, ROS 2, Rerun (`keo_service.live.sinks`)
        self.sinks = Sinks()
        self._viz: RerunSink | None = None
        if rrd is not None or viewer is not None:
            from keo_service.live.rerun_process import RerunWorker

            worker = RerunWorker(
                cell, rrd=rrd, viewer=viewer, urdf=config.robot.urdf, window_s=viewer_window_s
            )
            self._viz = RerunSink(worker, VIZ_PERIOD_S, self.status)
        self._own_session = session is None
        self._session = session
        self._stop = asyncio.Event()
        self._tasks: list[asyncio.Task[None]] = []
        self.failure: BaseException | None = None
        self._progress_at = time.monotonic()
        self._started = time.monotonic()
        self._rates = {"encoder": RateMeter(), "tracker": RateMeter(), "estimate": RateMeter()}
        self._tick_estimate = self._rates["estimate"].tick
        # the configured delay's standard error, what estimates carry with tracking off (made
        # once, and again at a reload, instead of per estimate)
        self._configured_se = delay_prior(config.timing)[1]
        self._status_bytes = b""
        self._last_estimate_wall = 0.0
        self._seq = 0
        self.received = 0
        self._last_arrival = time.monotonic()
        self.decode_errors = 0
        self._clock_domains: dict[str, str] = {}
        self._clock_flags: collections.Counter[str] = collections.Counter()
        # each adapter's newest state change (keo/<cell>/adapter/<name>/status, put on change)
        self._adapters: dict[str, AdapterStatus] = {}
        # the service's own findings (bad payloads, clock domains); the estimator keeps its own
        self._messages: collections.deque[str] = collections.deque(maxlen=MAX_MESSAGES)
        self.adapters_dropped = 0

    async def __aenter__(self) -> KeoService:
        if self._session is None:
            self._session = session_for_service(self.config)
        s = self._session
        self._status_q = s.declare_queryable(topic(self.cell, "status"), self._on_status_query)
        self._token = s.liveliness().declare_token(topic(self.cell, "alive/service"))
        self._add_sinks(s)
        self._sub = AsyncSubscription(s, [topic(self.cell, "encoder"), topic(self.cell, "tracker")])
        self._adapter_sub = AsyncSubscription(s, [topic(self.cell, "adapter/*/status")], maxlen=64)
        self._refresh_status()
        self._start(self._consume(), "keo.service.consume")
        self._start(self._status_loop(), "keo.service.status")
        self._start(self._adapter_events(), "keo.service.adapters")
        for sink in self.sinks.sinks:  # a sink with a cycle of its own: its own task
            if sink.period_s is not None:
                self._start(self._sink_loop(sink), f"keo.service.{sink.name}")
        if self._delay_tracker is not None:
            from keo_service.live.fit_worker import FitWorker

            self._fits = FitWorker(self._delay_tracker)
            self._start(self._delay_loop(), "keo.service.delay")
        log.info("keo service for cell %s up; listening on %s", self.cell, self.config.bus.listen)
        return self

    async def __aexit__(self, *exc: object) -> None:
        self._stop.set()
        self._sub.close()
        self._adapter_sub.close()
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        if self._fits is not None:
            self._fits.close()
        self._token.undeclare()
        self._status_q.undeclare()
        self.sinks.close()
        if self._own_session and self._session is not None:
            self._session.close()
        self._log_stopped()

    def stop(self, why: str = "") -> None:
        """Stop the service; `why` (a signal's name) is logged once."""
        if why and not self._stop.is_set():
            log.info("keo service for cell %s: %s received, stopping", self.cell, why)
        self._stop.set()

    def _log_stopped(self) -> None:
        """The last line of the service's log: how long it ran and what it did."""
        counters = self.estimator.counters
        log.info(
            "keo service for cell %s stopped%s after %.1f s: %d samples received, %d estimates, "
            "%d inputs rejected by the service",
            self.cell,
            "" if self.failure is None else " on an internal failure",
            time.monotonic() - self._started,
            self.received,
            counters.get("estimates", 0),
            counters.get("rejected", 0) + self.decode_errors,
        )

    def _add_sinks(self, session: zenoh.Session) -> None:
        """The configured outputs: the bus (with the latest estimate for a client that joins
        late), the corrections when `robot.correction` names an output (also on ROS 2 when
        enabled), ROS 2's estimate, Rerun when asked. The ROS 2 node closes after the
        corrections that use it (sinks close in reverse). Without a correction output the
        correction's filter, its messages and its cycle are not run at all: they were half
        of the service's work per estimate (docs/performance.md)."""
        # a session of its own has no subscriber of the estimates in this process
        self.sinks.add(EstimateBusSink(session, self.cell, local_subscribers=not self._own_session))
        ros2 = None
        if self.config.ros2.enabled:
            from keo_service.live.ros2_bridge import EstimateBridge
            from keo_service.live.sinks import Ros2EstimateSink

            bridge = EstimateBridge(session, self.config)
            ros2 = Ros2EstimateSink(bridge, self.config, lambda: self.config.observer.gain)
        if self.config.robot.correction != "none":
            from keo_service.live.compensation import CorrectionPublisher, CorrectionSink

            node = None if ros2 is None else ros2.bridge.node
            local = not self._own_session
            publisher = CorrectionPublisher(self.config, session, node, local_subscribers=local)
            self.sinks.add(CorrectionSink(publisher, self.estimator))
        if ros2 is not None:
            self.sinks.add(ros2)
        if self._viz is not None:
            self._viz.start()
            self.sinks.add(self._viz)

    # ---- supervision ----------------------------------------------------------------------

    def _start(self, coro: Any, name: str) -> None:
        task = asyncio.create_task(coro, name=name)
        self._tasks.append(supervise(task, self._stop.is_set, self._fail))

    def _fail(self, exc: BaseException) -> None:
        if self.failure is None:
            self.failure = exc
        self._stop.set()

    def data_path_healthy(self, now: float, within_s: float) -> bool:
        """For the watchdog: the consume task runs and has either nothing to do (no input) or
        has made progress within `within_s` seconds."""
        if self.failure is not None or not self._tasks or self._tasks[0].done():
            return False
        return self._sub.pending == 0 or now - self._progress_at < within_s

    async def wait(self) -> None:
        await self._stop.wait()

    # ---- data path ------------------------------------------------------------------------

    async def _consume(self) -> None:
        """The data path: every sample that waited since the last wake-up, in arrival order,
        each through the estimator and its estimates out before the next sample; `_handle`
        runs in the wake-up's own callback on the loop (`AsyncSubscription.deliver`), and a
        failure there fails this task."""
        await self._sub.deliver(self._handle)

    # complexity (C901, PLR0912): the per-sample path keeps its checks inline (a stream's clock
    # notes only when a sample has flags or a new domain): a Python call per sample is a real
    # share of its cost (docs/performance.md)
    def _handle(self, batch: list[tuple[str, bytes]]) -> None:  # noqa: C901, PLR0912
        """One wake-up's samples (key, payload), in arrival order, each through the
        estimator and its estimates out before the next sample (synchronous: no await). The
        delay tracker gets the samples a block at a time (`_feed_delay`): here each is only
        put on its bounded list."""
        sinks = self.sinks
        inputs = sinks.takes_input
        estimator = self.estimator
        domains = self._clock_domains
        tick_tracker, tick_encoder = self._rates["tracker"].tick, self._rates["encoder"].tick
        # bound once per wake-up, not looked up per sample: the decoder's own method (raises
        # what `messages.decode` raises), the clock, the publish step
        decode_payload, monotonic, publish = DECODER.decode, time.monotonic, self._publish
        on_tracker, on_encoder = estimator.on_tracker, estimator.on_encoder
        keep = None if self._delay_tracker is None else self._delay_inbox.append
        received, now = 0, 0.0
        for key, payload in batch:
            now = monotonic()
            try:
                msg = decode_payload(payload)
            except msgspec.DecodeError as exc:
                self.decode_errors += 1
                self._messages.append(f"undecodable payload on {key}: {exc}")
                continue
            received += 1
            if type(msg) is TrackerSample:
                if msg.flags or (msg.clock and domains.get("tracker") != msg.clock):
                    self._note_sample("tracker", msg)
                tick_tracker(now)
                if inputs:
                    sinks.on_input(msg)  # before the estimates it may cause
                out = on_tracker(
                    msg.stamp,
                    msg.position,
                    msg.quaternion,
                    ok=msg.status == "ok",
                    device_stamp=msg.device_stamp,
                )
            elif type(msg) is JointSample:
                if msg.flags or (msg.clock and domains.get("encoder") != msg.clock):
                    self._note_sample("encoder", msg)
                tick_encoder(now)
                out = on_encoder(msg.stamp, msg.joints)
                if inputs:
                    sinks.on_input(msg)
            else:
                estimator.counters["unexpected_message"] += 1
                continue
            if keep is not None:
                keep(msg)
            for estimate in out:
                publish(estimate, now)
        # the wake-up's count and newest arrival, once (nothing reads them mid-batch)
        if received:
            self.received += received
            self._last_arrival = self._progress_at = now
            if keep is not None and len(self._delay_inbox) >= DELAY_INBOX:
                self._feed_delay()  # bounded: a fit that takes long does not let it grow

    def _feed_delay(self) -> None:
        """The samples since the last block into the delay tracker, in arrival order, in one
        call (`OnlineDelayTracker.add_samples`: the same checks, restarts and clock lines as
        sample by sample), then the estimator set to the tracked delay if it moved (a
        stream's clock line moved, or a restart). Called by the delay loop before it asks
        for a stretch and after each fit, by the status loop (every 0.1 s), and when the
        list reaches `DELAY_INBOX`; on the loop, between samples."""
        tracker, inbox = self._delay_tracker, self._delay_inbox
        if tracker is None or not inbox:
            return
        tracker.add_samples(inbox, TrackerSample)
        inbox.clear()
        target = tracker.delay_now()
        if target is not None and target != self._delay_followed:
            self._follow_tracked_delay(tracker, target)

    async def _adapter_events(self) -> None:
        """The adapters' state changes (silent, back, reconnected, wrong protocol): into the
        log, the status (`adapters`) and so Rerun's text log. Published by the adapters when
        their state changes; nothing is polled."""
        async for key, payload in self._adapter_sub:
            try:
                doc = AdapterStatus.from_json(payload)
            except msgspec.DecodeError as exc:
                self.decode_errors += 1
                self._messages.append(f"undecodable adapter status on {key}: {exc}")
                continue
            name = doc.adapter
            if name not in self._adapters and len(self._adapters) >= MAX_ADAPTERS:
                self.adapters_dropped += 1  # bounded: a 17th name is counted, not kept
                continue
            self._adapters[name] = doc
            if doc.event:
                log.log(doc.log_level, "adapter %s: %s", name, doc.event)

    def _note_sample(self, stream: str, msg: JointSample | TrackerSample) -> None:
        """Record the clock domain a stream's samples declare and count their stamp flags;
        warn once per change when the domain is not the configured one (a delay calibrated
        under the config's domains need not hold for these stamps). The data path calls it
        only for a sample with flags or a domain other than the one noted."""
        for flag in msg.flags:
            self._clock_flags[f"{stream}_{flag}"] += 1
        if not msg.clock or self._clock_domains.get(stream) == msg.clock:
            return
        self._clock_domains[stream] = msg.clock
        section = self.config.robot if stream == "encoder" else self.config.tracker
        configured = section.clock
        if msg.clock != configured:
            text = (
                f"the {stream} samples declare clock domain {msg.clock!r}, the config's "
                f"{'robot' if stream == 'encoder' else 'tracker'}.clock is {configured!r}: "
                "timing.delay_s was calibrated under the config's domains and may not hold"
            )
            log.warning(text)
            self._messages.append(text)

    def _publish(self, estimate: Estimate, now: float) -> None:
        """One estimate out to every configured sink (`keo_service.live.sinks`). With one sink
        (the bus alone, the default) it is called directly, one frame fewer per estimate;
        a failure there takes the fan-out's careful path (counted, logged, raised)."""
        self._seq += 1
        self._tick_estimate(now)
        if not estimate.held:
            self._last_estimate_wall = now
        message = self.to_message(estimate)
        only = self.sinks.only_estimate
        if only is None:
            self.sinks.on_estimate(estimate, message)
            return
        try:
            only(estimate, message)
        except Exception as exc:
            self.sinks.estimate_failed(0, exc, estimate, message)

    def to_message(self, estimate: Estimate) -> EstimateMessage:
        """The estimate's wire form, with the delay's state as now (`delay_state` and
        `delay_se` written out: this runs per estimate)."""
        tracker = self._delay_tracker
        stamp, delay = estimate.stamp, self.estimator.delay
        flags: tuple[str, ...] = ()
        if tracker is None:
            se, state = self._configured_se, None
        else:
            se = tracker.applied_se
            if tracker.decision is not self._delay_state_for:
                self._delay_state_for = tracker.decision
                self._delay_state = _delay_state_of(tracker)
            state = self._delay_state
            # the delay in use is not known yet (found from the motion): every estimate says so
            if not tracker.settled:
                flags = UNSETTLED
        return estimate_message(
            estimate,
            host_ns=time.time_ns(),
            seq=self._seq,
            delay_s=delay.offset_s + delay.drift * (stamp - delay.t_ref),  # `delay.at(stamp)`
            delay_se_s=se,
            tool_speed_m_s=self._tool_speed.at(stamp),
            delay_state=state,
            more_flags=flags,
        )

    def delay_state(self) -> DelayState | None:
        """The delay's source and the tracker's last decision (None: tracking off), made anew
        only when the tracker decided something (one identity test per estimate)."""
        tracker = self._delay_tracker
        if tracker is None:
            return None
        if tracker.decision is not self._delay_state_for:
            self._delay_state_for = tracker.decision
            self._delay_state = _delay_state_of(tracker)
        return self._delay_state

    def delay_se(self) -> float | None:
        """The standard error of the delay in use: the tracker's (the configured prior's, or
        that of the fits it came from); without tracking, the configured one, if any."""
        if self._delay_tracker is None:
            return self._configured_se
        return self._delay_tracker.applied_se

    # ---- status -----------------------------------------------------------------------------

    def health(self, now: float) -> str:
        last = self.estimator.last
        if last is None:
            return "waiting"
        if now - self._last_estimate_wall > STALE_AFTER_S or last.held:
            return "stale"
        return "ok"

    def status(self) -> ServiceStatus:
        now = time.monotonic()
        counters = dict(self.estimator.counters)
        counters["received"] = self.received
        counters["decode_errors"] = self.decode_errors
        counters["queue_dropped"] = self._sub.dropped
        if self.adapters_dropped:
            counters["adapter_status_dropped"] = self.adapters_dropped
        counters.update(self._clock_flags)
        counters.update(self.sinks.counters())
        if self._delay_tracker is not None:
            for name, value in self._delay_tracker.counters.items():
                counters[f"delay_{name}"] = value
            counters["delay_fit_cpu_ms"] = round(1e3 * self._fit_cpu_s)
        last = self.estimator.last
        delay = self.estimator.delay
        delay_state = self.delay_state()
        return ServiceStatus(
            cell=self.cell,
            health=self.health(now),
            host_ns=time.time_ns(),
            uptime_s=now - self._started,
            rates_hz={k: round(v.rate(now), 3) for k, v in self._rates.items()},
            delay_s=delay.offset_s,
            drift=delay.drift,
            gains=list(self.estimator.settings.gains),
            alignment=self.estimator.settings.alignment,
            clock_domains=dict(self._clock_domains),
            counters=counters,
            last_estimate=None if last is None else self.to_message(last),
            # the estimator's rejects, then the service's own findings: the newest ten
            messages=[*self.estimator.messages, *self._messages][-10:],
            delay_tracking=None if delay_state is None else delay_tracking_text(delay_state),
            delay_se_s=self.delay_se(),
            delay_state=delay_state,
            adapters=dict(self._adapters),
        )

    def _resolve_if_quiet(self) -> None:
        """Both streams quiet for stale_after_s: what still waits for encoder data will not
        get it; publish those steps as held (flagged) instead of leaving them unanswered."""
        now = time.monotonic()
        quiet = now - self._last_arrival > self.config.timing.stale_after_s
        if quiet and self.estimator.has_pending:
            for estimate in self.estimator.flush():
                self._publish(estimate, now)

    def _refresh_status(self) -> None:
        self._status_bytes = encode(self.status())

    async def _status_loop(self) -> None:
        """Every `STATUS_PERIOD_S`: the delay tracker's block, the quiet-time check, the tool
        speed's point, the status snapshot. In three steps with the loop free between them:
        a sample that arrives meanwhile waits for one step, not for all of them (each takes
        0.07-0.24 ms on the cold cache the service meets: docs/performance.md, Round 11)."""
        while not self._stop.is_set():
            self._feed_delay()
            self._resolve_if_quiet()
            await asyncio.sleep(0)
            self._tool_speed.sample(self.estimator.last)
            await asyncio.sleep(0)
            self._refresh_status()
            await asyncio.sleep(STATUS_PERIOD_S)

    def _follow_tracked_delay(self, tracker: OnlineDelayTracker, target: float | None) -> None:
        """The estimator slews to the tracked delay (`target`: the tracker's `delay_now()`)
        when it changed (a fit applied, a line moved); nothing before one was applied."""
        if target is not None and target != self._delay_followed:
            self._delay_followed = target
            if tracker.step:  # a confirmed change, or the delay found while unknown: at once
                delay = self.estimator.delay
                self.estimator.set_delay(DelayModel(target, delay.drift, delay.t_ref))
                tracker.step = False
            else:  # a refinement too small to matter at speed: no step in the estimates
                self.estimator.set_delay_target(target)

    async def _delay_loop(self) -> None:
        """Online delay tracking: take each stretch from the tracker's bounded buffers (slices
        of its row arrays) and map its stamps on the loop (`stretch_arrays`); fit it in the
        worker process (one fit at a time, `live/fit_worker.py`), fold the result in on the
        loop, between samples, and set the estimator's delay (a step for a confirmed change, a
        slew for a refinement). A fit of data from before a time base started anew is
        dropped."""
        from keo_service.fit.delay_online import pool_arrays, stretch_arrays

        tracker, fits = self._delay_tracker, self._fits
        assert tracker is not None
        assert fits is not None
        while not self._stop.is_set():
            self._feed_delay()
            if not tracker.due():  # else a stretch is waiting already (a slow fit, a replay)
                await asyncio.sleep(DELAY_POLL_S)
                continue
            restarts = tracker.counters["restarts"]  # before the samples the fit lets in
            stretch = tracker.take()
            window, pool = stretch_arrays(stretch), pool_arrays(stretch)
            current = self.estimator.delay.offset_s
            found, cpu_s = await fits.measure(window, current, tracker.guess(current), pool)
            self._fit_cpu_s += cpu_s
            self._feed_delay()  # what came during the fit (a restart in it drops the fit)
            if tracker.counters["restarts"] == restarts:
                tracker.combine(found)
                self._follow_tracked_delay(tracker, tracker.delay_now())
            # said when the kind of decision changes (a refusal's advice once, not at every
            # stretch) or the delay in use moved beyond its se; a confirmation and the
            # refinements (bounded) on their own lines; every decision at debug level
            for level, text in self._delay_log.lines(
                tracker.state,
                tracker.last_result,
                tracker.delay_now(),
                tracker.applied_se,
                self.delay_state(),
                tracker.counters["refinements"],
            ):
                log.log(level, "%s", text)

    async def _sink_loop(self, sink: Sink) -> None:
        """A sink's own cycle (the corrections' validity, Rerun's status snapshots), its
        period read at every cycle; a failure there stops the service like any task's, after
        it was counted and logged (`Sinks`)."""
        while not self._stop.is_set():
            await asyncio.sleep(sink.period_s or VIZ_PERIOD_S)
            self.sinks.on_tick(sink)

    # ---- reload (SIGHUP) ------------------------------------------------------------------

    def reload(self, new: Config) -> tuple[list[str], list[str]]:
        """Apply what can change live (gains, delay); list what needs a restart."""
        old_flat = _flatten(msgspec.to_builtins(self.config))
        new_flat = _flatten(msgspec.to_builtins(new))
        changed = sorted(
            k
            for k in old_flat.keys() | new_flat.keys()
            if old_flat.get(k) != new_flat.get(k) and k != "source"
        )
        applied = [k for k in changed if k in HOT_KEYS]
        restart = [k for k in changed if k not in HOT_KEYS]
        if "observer.gain" in applied:
            self.estimator.set_gains(new.observer.gain)
        if {"timing.delay_s", "timing.drift_ppm", "timing.drift_ref_s"} & set(applied):
            timing = new.timing
            # the samples before the reload into the tracker first, as they came (so that
            # nothing it followed from them lands after the delay set by hand)
            self._feed_delay()
            self.estimator.set_delay(delay_model(timing))
            if self._delay_tracker is not None:
                # tracking goes on from the delay set by hand, a prior as at start
                self._delay_tracker.forget(*delay_prior(timing))
                self._delay_log.forget(self._delay_tracker.delay_now())
        hot = {k: v for k, v in msgspec.structs.asdict(new).items() if k in ("observer", "timing")}
        self.config = msgspec.structs.replace(self.config, **hot) if applied else self.config
        self._configured_se = delay_prior(self.config.timing)[1]
        self._refresh_status()
        return applied, restart

    def _on_status_query(self, query: zenoh.Query) -> None:  # zenoh thread: reply with a snapshot
        # none before the first snapshot: an empty payload is no status, and a querier that
        # decodes it fails (a test's own query in the service's first instant did, in CI)
        if self._status_bytes:
            query.reply(topic(self.cell, "status"), self._status_bytes)


# complexity (C901): start-up in order, each optional part (ROS 2, Rerun, systemd) a branch
async def run_service(  # noqa: C901
    config: Config,
    rrd: Path | None = None,
    viewer: str | None = None,
    ready: Any = None,
    viewer_window_s: float | None = None,
) -> None:
    """Run until SIGINT/SIGTERM; SIGHUP reloads the config file. Talks to systemd when
    NOTIFY_SOCKET is set: READY, WATCHDOG pings while the loop runs, RELOADING, STOPPING."""
    import signal

    from keo_service.core.errors import ConfigError
    from keo_service.io.config import load_config
    from keo_service.live import systemd

    loop = asyncio.get_running_loop()
    async with KeoService(
        config, rrd=rrd, viewer=viewer, viewer_window_s=viewer_window_s
    ) as service:

        def reload() -> None:
            systemd.notify("RELOADING=1")
            try:
                new = load_config(config.source)
            except ConfigError as exc:
                log.error("reload refused, keeping the running config: %s", exc)
            else:
                applied, restart = service.reload(new)
                log.info("reloaded %s: applied %s", config.source, applied or "nothing")
                if restart:
                    log.warning("changed but NOT applied (needs a restart): %s", ", ".join(restart))
            systemd.notify("READY=1")

        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, service.stop, sig.name)
        loop.add_signal_handler(signal.SIGHUP, reload)
        period = systemd.watchdog_period()
        watchdog = None
        if period is not None:

            async def ping() -> None:
                # an honest watchdog: no ping while the data path is stuck with input waiting
                # (or failed); a blocked event loop sends none either
                while True:
                    if service.data_path_healthy(time.monotonic(), period):
                        systemd.notify("WATCHDOG=1")
                    else:
                        log.error("data path stalled: watchdog pings withheld")
                    await asyncio.sleep(period / 2)

            watchdog = asyncio.create_task(ping(), name="keo.service.watchdog")
        # what start-up made (modules, the cell, the sessions) lives as long as the process:
        # out of the cyclic collector's way, so that no collection on the data path walks it
        # (the first ones after start-up were long pauses: docs/performance.md)
        gc.collect()
        gc.freeze()
        systemd.notify(f"READY=1\nSTATUS=cell {config.cell} on {', '.join(config.bus.listen)}")
        if ready is not None:
            ready()
        await service.wait()
        systemd.notify("STOPPING=1")
        if watchdog is not None:
            watchdog.cancel()
        if service.failure is not None:
            raise ServiceFailedError(
                f"stopped after an internal failure: {type(service.failure).__name__}: "
                f"{service.failure}"
            ) from service.failure
