"""Corrections that fail safe: the correction stream's reaction to a beam break, an encoder
stall, a step in the estimate and a NaN from a decoder. The service's own path runs here in
one process: the estimator fed sample by sample as the service feeds it, each estimate turned
into a correction by the service's CorrectionPublisher (published on a Zenoh session with no
peers). Needs the live correction (keo_service.live.compensation); skipped where it is not."""

from __future__ import annotations

import math

import numpy as np
import pytest

from keo_service.core.estimator import Estimator
from keo_service.io.cell import estimator_settings
from keo_service.live.bus import open_session
from keo_service.live.recorder import replay_plan
from keo_service.sim.simulate import make_scenario, simulate

# the live correction (issue 33's branch): these tests run where it is
compensation = pytest.importorskip("keo_service.live.compensation")
correction = pytest.importorskip("keo_service.core.correction")
CompensationLimits, CorrectionFilter = correction.CompensationLimits, correction.CorrectionFilter

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
    limits = CompensationLimits.from_config_values(5.0, 5.0, 50.0)
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
