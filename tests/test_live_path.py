"""The service's data path as issue 48 left it: samples taken in batches from the Zenoh
hand-off (every one, in order), and the correction cycle present only when a correction
output is configured."""

from __future__ import annotations

import asyncio

import msgspec
import numpy as np
import pytest

from keo_service.bench.demo import loopback_config
from keo_service.live.bus import AsyncSubscription, open_session


def test_batches_deliver_every_sample_in_the_publishers_order_across_keys():
    """Two keys under one prefix, 3000 samples put from another session in bursts: the
    batches, concatenated, are exactly what was put, in order; a burst comes as few
    batches (not one per sample)."""
    from keo_service.bench.procs import free_port

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    sent = [
        (("keo/t/encoder" if i % 4 == 0 else "keo/t/tracker"), f"{i}".encode()) for i in range(3000)
    ]

    async def main() -> tuple[list[tuple[str, bytes]], int]:
        listener = open_session("peer", listen=[endpoint])
        talker = open_session("peer", connect=[endpoint])
        try:
            sub = AsyncSubscription(listener, ["keo/t/encoder", "keo/t/tracker"])
            pubs = {k: talker.declare_publisher(k) for k in ("keo/t/encoder", "keo/t/tracker")}
            await asyncio.sleep(0.5)  # the sessions meet

            def put_all() -> None:
                for key, payload in sent:
                    pubs[key].put(payload)

            putter = asyncio.get_running_loop().run_in_executor(None, put_all)
            got: list[tuple[str, bytes]] = []
            batches = 0

            def handle(batch: list[tuple[str, bytes]]) -> None:
                nonlocal batches
                batches += 1
                got.extend(batch)
                if len(got) >= len(sent):
                    sub.close()

            delivering = asyncio.ensure_future(sub.deliver(handle))
            await putter
            try:
                await asyncio.wait_for(asyncio.shield(delivering), 20)
            except TimeoutError:
                sub.close()
                await delivering
            return got, batches
        finally:
            talker.close()
            listener.close()

    got, batches = asyncio.run(main())
    assert got == sent
    assert batches < len(sent)


@pytest.mark.parametrize("correction", ["none", "rtde_registers"])
def test_the_correction_cycle_runs_only_with_a_correction_output(demo_config, correction):
    from keo_service.live.service import KeoService

    config = loopback_config(demo_config)
    robot = msgspec.structs.replace(config.robot, correction=correction)
    config = msgspec.structs.replace(config, robot=robot)

    async def main() -> tuple[list[str], list[str]]:
        async with KeoService(config) as service:
            names = [s.name for s in service.sinks.sinks]
            tasks = [t.get_name() for t in service._tasks]
        return names, tasks

    names, tasks = asyncio.run(main())
    if correction == "none":
        assert names == ["bus"]
        assert "keo.service.correction" not in tasks
    else:
        assert names == ["bus", "correction"]
        assert "keo.service.correction" in tasks


class _Kept:
    """A sink that keeps each estimate's wire message (no bus)."""

    name = "kept"
    period_s = None

    def __init__(self) -> None:
        self.messages: list[bytes] = []

    def on_input(self, sample: object) -> None:
        pass

    def on_estimate(self, estimate: object, message: object) -> None:
        from keo_service.live.messages import encode

        self.messages.append(encode(message))  # type: ignore[arg-type]

    def on_tick(self) -> None:
        pass

    def counters(self) -> dict[str, int]:
        return {}

    def close(self) -> None:
        pass


def _wire(run, t0: float) -> list[tuple[str, bytes]]:
    """The simulated streams as the adapters put them, in the order `keo estimate` takes
    them (stamp order, encoder first on ties): the tracker's samples with device stamps on
    a line ("device" clock, with its drift), the encoder's without."""
    from keo_service.live.messages import JointSample, TrackerSample, encode

    enc = [
        (float(t), 0, "keo/demo/encoder", i, JointSample(
            stamp=float(t), host_ns=int((t0 + t) * 1e9), seq=i + 1,
            joints=[float(x) for x in run.encoder.q[i]], clock="receipt", clock_epoch=1,
        ))
        for i, t in enumerate(run.encoder.t)
    ]  # fmt: skip
    trk = [
        (float(t), 1, "keo/demo/tracker", i, TrackerSample(
            stamp=float(t), host_ns=int((t0 + t) * 1e9), seq=i + 1,
            position=[float(x) for x in run.tracker.p[i]],
            quaternion=[float(x) for x in run.tracker.quat[i]],
            device_stamp=t0 + float(t), clock="device", clock_epoch=1, clock_drift=2e-6,
        ))
        for i, t in enumerate(run.tracker.t)
    ]  # fmt: skip
    return [(key, encode(msg)) for _t, _k, key, _i, msg in sorted(enc + trk)]


def test_the_services_per_sample_path_gives_the_batch_estimates(demo_config, demo_cell):
    """The service's data path (decode, bookkeeping, the estimator, the delay tracker fed
    every sample, the message) over a simulated 8 s at 1 kHz / 250 Hz, in batches of
    varying size: every published estimate equals what the batch path (`keo estimate`'s
    own vectorised implementation) gives for the same streams, to 1e-12, stamp for stamp.
    The tracker holds the configured delay here (no fit runs without the event loop), so
    both use the same delay."""
    from keo_service.core.batch import estimate_batch
    from keo_service.io.cell import estimator_settings
    from keo_service.live.messages import decode
    from keo_service.live.service import KeoService
    from keo_service.sim.simulate import make_scenario, simulate

    config = loopback_config(demo_config)
    assert config.timing.track_delay  # the tracker's per-sample path is part of what runs
    sets = {"tracker_rate_hz": "1000", "encoder_rate_hz": "250", "duration_s": "8"}
    run = simulate(demo_cell, make_scenario("path", sets), seed=3)
    wire = _wire(run, 1.7e9)
    service = KeoService(config)
    kept = _Kept()
    service.sinks.add(kept)  # type: ignore[arg-type]
    i = 0
    for size in [1, 1, 2, 7, 1, 40, 3] * len(wire):  # batches as wake-ups bring them
        if i >= len(wire):
            break
        service._handle(wire[i : i + size])
        i += size
    assert service._delay_tracker is not None
    assert service._delay_tracker.counters["tracker_left_out"] == 0
    live = [decode(m) for m in kept.messages]

    want = estimate_batch(
        demo_cell, estimator_settings(config), run.encoder.t, run.encoder.q,
        run.tracker.t, run.tracker.p, run.tracker.quat,
    )  # fmt: skip
    n = len(live)  # the batch also flushes the last samples, which the live path holds
    assert n >= want.stamp.size - 10
    assert np.array_equal([m.stamp for m in live], want.stamp[:n])
    assert [("|".join(m.flags)) for m in live] == want.flags[:n]
    est = np.array([m.estimate for m in live])
    assert np.max(np.abs(est - want.estimate[:n])) <= 1e-12
    good = [m.measured is not None for m in live]
    meas = np.array([m.measured for m, g in zip(live, good, strict=True) if g])
    assert np.max(np.abs(meas - want.measured[:n][good])) <= 1e-12
    assert all(m.delay_s == config.timing.delay_s for m in live)


@pytest.mark.parametrize(
    ("position", "quaternion", "joints", "kept"),
    [
        ([0.1, 0.2, 0.3], [1.0, 0.0, 0.0, 0.0], [0.0] * 6, (1, 1)),
        ([0.1, float("nan"), 0.3], [1.0, 0.0, 0.0, 0.0], [0.0] * 6, (1, 0)),
        ([0.1, 0.2, 0.3], [1.0, float("inf"), 0.0, 0.0], [0.0] * 6, (1, 0)),
        ([0.1, 0.2, 0.3], None, [0.0, float("-inf"), 0, 0, 0, 0], (0, 1)),
    ],
)
def test_the_delay_trackers_buffers_take_finite_samples_only(
    demo_cell, position, quaternion, joints, kept
):
    """A non-finite coordinate keeps a sample out of the delay tracker's buffers (its fits
    would fail on it), whatever the check is made with; the buffered rows are float arrays."""
    from keo_service.fit.delay_online import OnlineDelayTracker

    tracker = OnlineDelayTracker(demo_cell, None, 0.0, 0.001)
    tracker.add_encoder(1.0, joints)
    tracker.add_tracker(1.0, position, quaternion)
    assert (len(tracker._enc), len(tracker._trk)) == kept
    enc = tracker._enc.between(-np.inf, np.inf)  # stamp, joints, device stamp (nan: none)
    trk = tracker._trk.between(-np.inf, np.inf)  # stamp, position, quaternion, device stamp
    assert (enc.shape[0], trk.shape[0]) == kept
    assert enc.dtype == trk.dtype == np.float64
    assert np.isfinite(enc[:, :-1]).all()
    assert np.isfinite(trk[:, :4]).all()


def test_estimates_carry_the_configured_delays_se_with_tracking_off_also_after_a_reload(
    demo_config, monkeypatch
):
    """With tracking off an estimate carries the configured `timing.delay_se_s` (none for
    `delay_s = 0`); a reload that changes the delay brings the new section's value. The
    service reads it once per config, not per estimate, so a stale copy would show here."""
    from keo_service.core.estimator import Estimate
    from keo_service.live.service import KeoService

    base = loopback_config(demo_config)

    def with_timing(**kw: object):
        return msgspec.structs.replace(
            base, timing=msgspec.structs.replace(base.timing, track_delay=False, **kw)
        )

    service = KeoService(with_timing(delay_s=0.012, delay_se_s=0.0007))
    monkeypatch.setattr(service, "_refresh_status", lambda: None)  # no session here
    estimate = Estimate(1.0, [0.0] * 6, [0.0] * 6, (), 0.99, ("px", "py", "pz", "rx", "ry", "rz"))
    message = service.to_message(estimate)
    assert (message.delay_se_s, message.delay_state, message.flags) == (0.0007, None, [])
    applied, _ = service.reload(with_timing(delay_s=0.015, delay_se_s=0.0003))
    assert "timing.delay_s" in applied
    assert service.to_message(estimate).delay_se_s == 0.0003
    service.reload(with_timing(delay_s=0.0, delay_se_s=0.0003))
    assert service.to_message(estimate).delay_se_s is None
    assert service.delay_se() is None


def test_the_only_sink_called_directly_still_fails_loudly(demo_config, demo_cell):
    """With one sink the service calls it without the fan-out's loop; a sink that raises is
    still counted (`sink_failed_<name>`) and the data path fails with `SinkFailedError`,
    the cause chained, as through the fan-out."""
    from keo_service.live.service import KeoService
    from keo_service.live.sinks import SinkFailedError
    from keo_service.sim.simulate import make_scenario, simulate

    class Broken(_Kept):
        name = "broken"

        def on_estimate(self, estimate: object, message: object) -> None:
            raise ValueError("inside the sink")

    config = loopback_config(demo_config)
    sets = {"tracker_rate_hz": "1000", "encoder_rate_hz": "250", "duration_s": "1"}
    wire = _wire(simulate(demo_cell, make_scenario("path", sets), seed=3), 1.7e9)
    service = KeoService(config)
    service.sinks.add(Broken())  # type: ignore[arg-type]
    assert service.sinks.only_estimate is not None
    with pytest.raises(SinkFailedError) as failed:
        service._handle(wire)
    assert isinstance(failed.value.__cause__, ValueError)
    assert service.sinks.counters()["sink_failed_broken"] == 1


def test_the_delay_trackers_block_reaches_it_before_a_reload_sets_the_delay(
    demo_config, demo_cell, monkeypatch
):
    """Tracking on: the samples not yet handed to the delay tracker (its list, a block every
    0.1 s) reach it at a reload that sets the delay by hand, before that delay is set, and
    the estimator uses the delay the reload gave, the tracker starting from it as a prior.
    The list is bounded: a wake-up that leaves `DELAY_INBOX` samples on it hands them over."""
    from keo_service.live.service import DELAY_INBOX, KeoService
    from keo_service.sim.simulate import make_scenario, simulate

    config = loopback_config(demo_config)
    sets = {"tracker_rate_hz": "1000", "encoder_rate_hz": "250", "duration_s": "1"}
    wire = _wire(simulate(demo_cell, make_scenario("path", sets), seed=3), 1.7e9)
    service = KeoService(config)
    service.sinks.add(_Kept())  # type: ignore[arg-type]
    monkeypatch.setattr(service, "_refresh_status", lambda: None)  # no session here
    tracker = service._delay_tracker
    assert tracker is not None
    service._handle(wire[:300])
    assert len(service._delay_inbox) == 300
    assert len(tracker._trk) == 0
    timing = msgspec.structs.replace(config.timing, delay_s=0.031, delay_se_s=0.0004)
    applied, _ = service.reload(msgspec.structs.replace(config, timing=timing))
    assert "timing.delay_s" in applied
    assert service._delay_inbox == []
    assert len(tracker._trk) > 200  # the tracker samples among the 300 (poses, not gaps)
    assert service.estimator.delay.offset_s == 0.031
    assert (tracker.delay_now(), tracker.applied_se) == (0.031, 0.0004)
    many = (wire * (DELAY_INBOX // len(wire) + 2))[:DELAY_INBOX]
    service._handle(many)  # the stamps repeat: the estimator refuses them, the list fills
    assert service._delay_inbox == []
