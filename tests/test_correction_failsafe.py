"""ModelCorrections that fail safe: the correction stream's reaction to a beam break, an encoder
stall, a step in the estimate and a NaN from a decoder. The service's own path runs here in
one process: the estimator fed sample by sample as the service feeds it, each estimate turned
into a correction by the service's CorrectionPublisher (published on a Zenoh session with no
peers)."""

from __future__ import annotations

import itertools
import math

import msgspec
import numpy as np
import pytest

from keo_service.core.compensation import CompensationLimits, CorrectionFilter
from keo_service.core.estimator import Estimator
from keo_service.io.cell import estimator_settings
from keo_service.io.config import CompensationConfig
from keo_service.live import compensation
from keo_service.live.bus import open_session
from keo_service.live.recorder import replay_plan
from keo_service.sim.simulate import make_scenario, simulate

BREAK = (1.5, 2.0)  # s of stream time


@pytest.fixture(scope="module")
def run(demo_cell):
    return simulate(demo_cell, make_scenario("paper-step", {"duration_s": "3"}), seed=11)


@pytest.fixture
def publisher(demo_config):
    session = open_session("peer")
    pub = compensation.CorrectionPublisher(demo_config, session)
    yield pub
    pub.close()
    session.close()


def _stream(demo_cell, demo_config, run, publisher, tracker=None, encoder=None):
    """Feed the run as the service does; `tracker(t, p)` / `encoder(t, q)` may change a
    sample (return None to drop it, or ("gap",) for a tracker gap). Returns the corrections,
    the stream time of the input each came out at, and the estimator."""
    est = Estimator(demo_cell, estimator_settings(demo_config))
    plan = replay_plan(run.encoder.t, run.tracker.t)
    out, emitted = [], []
    for kind, i in zip(plan.kinds, plan.index, strict=True):
        if kind == 0:
            t, q = float(run.encoder.t[i]), run.encoder.q[i].tolist()
            if encoder is not None:
                q = encoder(t, q)
                if q is None:
                    continue
            estimates = est.on_encoder(t, q)
        else:
            t, p = float(run.tracker.t[i]), run.tracker.p[i].tolist()
            quat = run.tracker.quat[i].tolist()
            changed = p if tracker is None else tracker(t, p)
            if changed is None:
                continue
            if changed == ("gap",):
                estimates = est.on_tracker(t, None, None, ok=False)
            else:
                estimates = est.on_tracker(t, changed, quat)
        out += [publisher.publish(e, est) for e in estimates]
        emitted += [t] * len(estimates)
    return out, emitted, est


def _finite(c) -> bool:
    return all(math.isfinite(v) for v in (*c.translation, *c.rotation))


def test_beam_break_invalidates_the_correction_at_once_and_it_comes_back(
    demo_cell, demo_config, run, publisher
):
    def beam(t, p):
        return ("gap",) if BREAK[0] <= t < BREAK[1] else p

    out, emitted, est = _stream(demo_cell, demo_config, run, publisher, tracker=beam)
    # the first invalid correction goes out within one encoder cycle (25 ms at 40 Hz, 10 ms
    # of jitter margin) of the first gap sample
    first_invalid = next(e for e, c in zip(emitted, out, strict=True) if not c.valid)
    assert BREAK[0] <= first_invalid <= BREAK[0] + 0.035
    during = [c for c in out if BREAK[0] <= c.stamp < BREAK[1]]
    assert during, "the break must show in the stream, not as silence"
    # every correction stamped inside the break is invalid and zero, from the first one on
    assert all(not c.valid for c in during)
    assert all(c.reason == "tracker_gap" for c in during)
    assert all(c.translation == [0.0, 0.0, 0.0] and c.rotation == [0.0] * 3 for c in during)
    before = [c for c in out if c.stamp < BREAK[0]]
    after = [c for c in out if c.stamp >= BREAK[1] + 0.1]
    assert before[-1].valid
    assert after
    assert all(c.valid for c in after)
    assert publisher.counters["corrections_invalid"] == len([c for c in out if not c.valid])
    assert est.counters["tracker_gaps"] > 0


def test_encoder_stall_invalidates_the_correction_once_stale(
    demo_cell, demo_config, run, publisher
):
    def stall(t, q):
        return None if BREAK[0] <= t < BREAK[1] else q

    out, emitted, _ = _stream(demo_cell, demo_config, run, publisher, encoder=stall)
    stale = estimator_settings(demo_config).stale_after_s
    # nothing valid comes out while the encoder is silent; the first invalid correction once
    # the tracker is `stale` ahead of the last joints (the controller interfaces zero a
    # correction older than 0.1 s in between)
    valid_during = [
        c for e, c in zip(emitted, out, strict=True) if BREAK[0] < e < BREAK[1] and c.valid
    ]
    assert valid_during == []
    first_invalid = next(e for e, c in zip(emitted, out, strict=True) if not c.valid)
    assert first_invalid <= BREAK[0] + stale + 0.035
    invalid = [c for c in out if not c.valid]
    assert invalid
    assert {c.reason for c in invalid} <= {"encoder_gap", "encoder_stale", "encoder_too_old"}
    assert all(c.translation == [0.0] * 3 for c in invalid)
    # no correction is valid for an instant later than the last encoder sample + the stale
    # limit; one tracker period (10 ms) of margin for the instant the limit is checked
    late = [c for c in out if BREAK[0] + stale + 0.01 < c.stamp < BREAK[1] and c.valid]
    assert late == []
    assert any(c.valid for c in out if c.stamp > BREAK[1] + 0.1)


def test_a_step_in_the_estimate_is_clamped_in_size_and_rate_and_counted():
    limits = CompensationConfig(max_mm=5.0, max_mrad=5.0, max_rate_mm_s=50.0).limits()
    f = CorrectionFilter(limits)
    rate = 100.0  # Hz
    sent = []
    for k in range(100):
        t = k / rate
        step = 0.008 if t >= 0.2 else 0.0  # an 8 mm step in the estimated error
        c = f.step(t, [step, 0.0, 0.0, 0.0, 0.0, 0.0], None)
        sent.append((t, c))
    p = np.array([c.translation[0] for _, c in sent])
    # the correction undoes the error (minus sign), never more than 5 mm, at most 50 mm/s
    assert p.min() >= -0.005 - 1e-12
    assert np.all(np.abs(np.diff(p)) <= 0.05 / rate + 1e-12)
    assert p[-1] == pytest.approx(-0.005)
    # 5 mm at 50 mm/s: 0.1 s of rate-limited steps after the step, the size clamp from then on
    first_full = next(t for t, c in sent if c.translation[0] <= -0.005 + 1e-12)
    assert first_full == pytest.approx(0.2 + 0.1, abs=1.5 / rate)
    assert f.counters["corrections_clamped_rate"] >= 9
    assert f.counters["corrections_clamped_size"] >= 60
    assert all(c.clamped for t, c in sent if t >= 0.2)


def test_a_nan_from_a_decoder_never_reaches_the_correction(demo_cell, demo_config, run, publisher):
    def nan_tracker(t, p):
        return [math.nan, p[1], p[2]] if 1.0 <= t < 1.1 else p

    def nan_encoder(t, q):
        return [math.nan, *q[1:]] if 2.0 <= t < 2.1 else q

    out, _, est = _stream(
        demo_cell, demo_config, run, publisher, tracker=nan_tracker, encoder=nan_encoder
    )
    assert all(_finite(c) for c in out)
    assert est.counters["rejected"] > 0  # the estimator refused them, counted
    assert all(c.valid for c in out[len(out) // 4 :] if c.stamp > 2.3)
    # and a correction that carries a NaN (from anywhere) is sent as zero to the controller
    bad = out[-1].__class__(**{**{f: getattr(out[-1], f) for f in out[-1].__struct_fields__},
                               "translation": [math.nan, 0.0, 0.0]})  # fmt: skip
    p, r = compensation.correction_to_send(bad, demo_config.compensation, now_ns=bad.host_ns)
    assert p == [0.0, 0.0, 0.0]
    assert r == [0.0, 0.0, 0.0]
    # a non-finite estimate (should one pass a decoder and the estimator) is invalid, zero
    f = CorrectionFilter(CompensationLimits())
    c = f.step(0.0, [math.nan, 0, 0, 0, 0, 0], None)
    assert not c.valid
    assert c.reason == "non_finite_estimate"


# ---- timer-driven validity: the service's correction cycle in real time --------------------

STALL = (1.2, 2.2)  # s of scenario time: the encoder sends nothing


async def _stall_run(demo_cell, config) -> dict:
    """The service in this process, fed over a real Zenoh session in real time (encoder at
    40 Hz, tracker at 100 Hz, as simulated), the encoder stalled during STALL; every
    correction gathered with its arrival (monotonic)."""
    import asyncio
    import time

    from keo_service.live.bus import session_for_client
    from keo_service.live.messages import JointSample, TrackerSample, decode, encode, topic
    from keo_service.live.service import KeoService

    run = simulate(demo_cell, make_scenario("paper-step", {"duration_s": "3"}), seed=11)
    plan = replay_plan(run.encoder.t, run.tracker.t)
    got: list[tuple[float, object]] = []
    async with KeoService(config) as service:
        client = session_for_client(config)
        sub = client.declare_subscriber(
            topic(config.cell, "correction"),
            lambda s: got.append((time.monotonic(), decode(s.payload.to_bytes()))),
        )
        enc_key, trk_key = topic(config.cell, "encoder"), topic(config.cell, "tracker")
        try:
            await asyncio.sleep(0.5)
            wall0, mono0 = time.time() + 0.2, time.monotonic() + 0.2
            last_encoder = 0.0
            for n, (kind, i) in enumerate(zip(plan.kinds, plan.index, strict=True)):
                t_run = float((run.encoder.t if kind == 0 else run.tracker.t)[i])
                if kind == 0 and STALL[0] <= t_run < STALL[1]:
                    continue
                delay = mono0 + t_run - time.monotonic()
                if delay > 0:
                    await asyncio.sleep(delay)
                t, host_ns = wall0 + t_run, time.time_ns()
                if kind == 0:
                    q = run.encoder.q[i].tolist()
                    client.put(
                        enc_key, encode(JointSample(stamp=t, host_ns=host_ns, seq=n, joints=q))
                    )
                    if t_run < STALL[0]:
                        last_encoder = time.monotonic()
                else:
                    p, quat = run.tracker.p[i].tolist(), run.tracker.quat[i].tolist()
                    sample = TrackerSample(
                        stamp=t, host_ns=host_ns, seq=n, position=p, quaternion=quat
                    )
                    client.put(trk_key, encode(sample))
            last_input = time.monotonic()
            await asyncio.sleep(0.3)
            status = service.status()
        finally:
            sub.undeclare()
            client.close()
    return {
        "got": got,
        "last_encoder": last_encoder,
        "stall_end": mono0 + STALL[1],
        "last_input": last_input,
        "status": status,
    }


@pytest.mark.e2e
async def test_an_encoder_stall_invalidates_the_correction_within_one_cycle(demo_cell, demo_config):
    """Timer-driven validity: the correction's own cycle (the observer's period, 10 ms here)
    renews the newest correction while the inputs are fresh and publishes a zero, invalid one
    at the first cycle after the newest encoder sample is `compensation.stale_after_s` old;
    the stream is never silent in between. The controller interfaces (RTDE registers through
    `correction_to_send`, RSI/EGM through `CorrectionOutput`) send zero from that message on."""
    from keo_service.adapters.udp_devices import CorrectionOutput
    from keo_service.bench.demo import loopback_config
    from keo_service.live.messages import encode

    config = loopback_config(demo_config)  # with a correction output: the service runs it
    config = msgspec.structs.replace(
        config, robot=msgspec.structs.replace(config.robot, correction="rtde_registers")
    )
    limit = config.compensation.stale_after_s
    cycle = 0.01  # the tracker's period: the observer's
    out = await _stall_run(demo_cell, config)
    got, stalled = out["got"], out["last_encoder"]
    assert [m for w, m in got if w < stalled and m.valid], "valid corrections before the stall"
    first = next((w, m) for w, m in got if w > stalled and not m.valid)
    gap = first[0] - stalled
    around = [w for w, _ in got if stalled <= w <= first[0]]
    silence = max(b - a for a, b in itertools.pairwise(around))
    during = [(w, m) for w, m in got if first[0] <= w < out["stall_end"] - 0.05]
    print(
        f"encoder stall -> first invalid correction {1e3 * gap:.1f} ms (stale limit "
        f"{1e3 * limit:.0f} ms, cycle {1e3 * cycle:.0f} ms); longest silence before it "
        f"{1e3 * silence:.1f} ms; {len(during)} corrections during the rest of the stall"
    )
    assert first[1].reason == "encoder_stale"
    assert limit <= gap <= limit + cycle + 0.08  # one cycle, and a loaded machine's margin
    assert silence < 0.1  # renewed every cycle, never the estimator's 0.5 s of silence
    assert len(during) > 0.5 * (out["stall_end"] - first[0]) / cycle  # the cycle goes on
    assert all(not m.valid and m.translation == [0.0] * 3 for _, m in during)
    assert any(m.valid for w, m in got if w > out["stall_end"] + 0.3)  # and it comes back
    assert out["status"].counters["corrections_stale"] >= 1
    # once every input is quiet the stream rests (an idle cell's bus is quiet): at most the
    # invalid correction that says so, within the limit and a cycle
    late = [m for w, m in got if w > out["last_input"] + limit + cycle + 0.08]
    assert late == []
    # the controller interfaces follow the same validity: zero from the first invalid one
    last_valid = next(m for w, m in reversed(got) if w < stalled and m.valid)
    p, _ = compensation.correction_to_send(last_valid, config.compensation, last_valid.host_ns)
    assert any(p)
    p, r = compensation.correction_to_send(first[1], config.compensation, first[1].host_ns)
    assert p == [0.0] * 3
    assert r == [0.0] * 3
    rsi = CorrectionOutput(config.compensation)
    rsi.on_payload(encode(last_valid))
    rsi.next(0.0)
    assert rsi.reason == ""
    rsi.on_payload(encode(first[1]))
    rsi.next(0.0)
    assert rsi.reason == "invalid: encoder_stale"


def test_the_correction_cycle_step_by_step(demo_config):
    """`CorrectionPublisher.tick` with the clock given: renewals while fresh, the first cycle
    past the limit invalid with the reason, renewals of it while the tracker still sends, and
    rest once nothing arrives."""
    import time

    from keo_service.core.estimator import Estimate
    from keo_service.live.messages import JointSample, TrackerSample

    session = open_session("peer")
    pub = compensation.CorrectionPublisher(demo_config, session)
    limit = demo_config.compensation.stale_after_s
    channels = ("px", "py", "pz", "rx", "ry", "rz")
    enc = JointSample(stamp=0.0, host_ns=0, seq=1, joints=[0.0] * 6)
    trk = TrackerSample(
        stamp=0.0, host_ns=0, seq=1, position=[1.0, 0.0, 0.0], quaternion=[1.0, 0, 0, 0]
    )
    try:
        assert pub.tick(time.monotonic()) is None  # nothing before the first estimate
        enc_at = time.monotonic()  # the encoder's last sample
        pub.note_input(enc, enc_at)
        pub.note_input(trk, enc_at)
        first = pub.publish(Estimate(1.0, [0.0] * 6, [1e-4] * 6, (), None, channels))
        assert first.valid
        now = time.monotonic()  # from here on the test's clock
        cycle = pub.cycle_s
        assert cycle == pytest.approx(0.01)  # the default before the observer's period is known
        assert pub.tick(now + 0.5 * cycle) is None  # a put half a cycle ago: nothing to renew
        renewed = pub.tick(now + 1.6 * cycle)
        assert renewed is not None
        assert renewed.valid
        assert renewed.seq == first.seq + 1
        assert renewed.translation == first.translation
        # the encoder stops; the tracker goes on (and the estimate is renewed by arrivals)
        t = now
        out = []
        while t < now + limit + 3 * cycle:
            t += cycle / 2
            pub.note_input(trk, t)
            out.append((t, pub.tick(t)))
        invalid = [(at, m) for at, m in out if m is not None and not m.valid]
        assert invalid
        at, msg = invalid[0]
        assert msg.reason == "encoder_stale"
        assert msg.translation == [0.0] * 3
        assert enc_at + limit < at <= enc_at + limit + cycle  # the first cycle past the limit
        assert pub.counters["corrections_stale"] == 1
        assert all(m.valid for a, m in out if m is not None and a < at)
        # still invalid and renewed while the tracker sends; once nothing arrives, rest
        later = [pub.tick(t + k * cycle) for k in range(1, 4)]
        assert any(m is not None and not m.valid for m in later)
        quiet = [pub.tick(t + limit + k * cycle) for k in range(2, 10)]
        assert quiet == [None] * 8
        assert pub.counters["corrections_stale"] == 1  # one stale stretch, counted once
    finally:
        pub.close()
        session.close()


def test_a_correction_from_an_unsettled_delay_is_held_and_counted(demo_cell, demo_config, run):
    """Issue 45: while the delay in use is not settled (found from the motion, possibly
    milliseconds off) the estimate message says `delay_unsettled`; a correction computed from
    it is held (invalid, zero, reason "delay_unsettled") and counted. Once the flag goes, the
    corrections are valid again."""
    from keo_service.core.estimator import Estimator
    from keo_service.io.cell import estimator_settings

    session = open_session("peer")
    pub = compensation.CorrectionPublisher(demo_config, session)
    sink = compensation.CorrectionSink(pub, None)
    try:
        est = Estimator(demo_cell, estimator_settings(demo_config))
        plan = replay_plan(run.encoder.t, run.tracker.t)
        estimates = []
        for kind, i in zip(plan.kinds, plan.index, strict=True):
            if kind == 0:
                estimates += est.on_encoder(float(run.encoder.t[i]), run.encoder.q[i].tolist())
            else:
                estimates += est.on_tracker(
                    float(run.tracker.t[i]), run.tracker.p[i].tolist(), run.tracker.quat[i].tolist()
                )
        fresh = [e for e in estimates if not e.held]
        assert len(fresh) > 20
        half = len(fresh) // 2
        for e in fresh[:half]:
            sink.on_estimate(e, msgspec.structs.replace(_message(e), flags=["delay_unsettled"]))
        held = pub.latest
        for e in fresh[half:]:
            sink.on_estimate(e, _message(e))
        assert pub.counters["corrections_delay_unsettled"] == half
        assert held is not None
        assert not held.valid
        assert held.reason == "delay_unsettled"
        assert held.translation == [0.0, 0.0, 0.0]
        assert held.rotation == [0.0] * 3
        assert pub.latest is not None
        assert pub.latest.valid
    finally:
        pub.close()
        session.close()


def _message(estimate):
    from keo_service.live.messages import estimate_message

    return estimate_message(estimate, host_ns=0, seq=0, delay_s=0.0)


@pytest.mark.parametrize(("step_s", "cycle_s"), [(0.001, 0.002), (0.004, 0.004), (0.5, 0.1)])
def test_the_correction_cycle_follows_the_observer_within_its_bounds(demo_config, step_s, cycle_s):
    """Without `[compensation] rate_hz` the cycle is the observer's period (the estimates'
    mean step in stream time), no faster than RTDE's 2 ms and no slower than 0.1 s: at 1 kHz
    estimates the cycle is 2 ms, not a second timer at the estimate rate."""
    from keo_service.core.estimator import Estimate

    session = open_session("peer")
    pub = compensation.CorrectionPublisher(demo_config, session)
    channels = ("px", "py", "pz", "rx", "ry", "rz")
    try:
        assert demo_config.compensation.rate_hz == 0.0
        for i in range(20):
            pub.publish(Estimate(1.0 + i * step_s, [0.0] * 6, [1e-5] * 6, (), None, channels))
        assert pub.cycle_s == pytest.approx(cycle_s)
    finally:
        pub.close()
        session.close()
