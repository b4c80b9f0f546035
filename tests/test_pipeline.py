"""The estimator without plumbing: holds, flags, counters, delivery-order independence."""

from __future__ import annotations

import math

import numpy as np
import pytest

from keo_service.core.estimator import Estimate, Estimator, run_offline
from keo_service.core.kinematics import POSE_CHANNELS
from keo_service.core.observer import KinematicErrorObserver
from keo_service.core.settings import EstimatorSettings
from keo_service.core.timing import Coverage, DelayModel, EncoderBuffer
from keo_service.sim.simulate import make_scenario, simulate


@pytest.fixture(scope="module")
def run(demo_cell):
    return simulate(demo_cell, make_scenario("paper-vertical", {"duration_s": "8"}), seed=9)


def settings(**kw):
    base = {"gains": (2.0,) * 6, "delay": DelayModel(0.028)}
    base.update(kw)
    return EstimatorSettings(**base)


def test_delivery_order_does_not_change_estimates(demo_cell, run):
    """Time-ordered feeding and 'encoder arrives in bursts 0.2 s late' give identical output."""
    ordered = run_offline(
        Estimator(demo_cell, settings()),
        run.encoder.t,
        run.encoder.q,
        run.tracker.t,
        run.tracker.p,
        run.tracker.quat,
    )
    est = Estimator(demo_cell, settings())
    bursty = []
    i = 0
    for j in range(run.tracker.t.size):
        while i < run.encoder.t.size and run.encoder.t[i] <= run.tracker.t[j] - 0.2:
            bursty += est.on_encoder(run.encoder.t[i], run.encoder.q[i])
            i += 1
        bursty += est.on_tracker(run.tracker.t[j], run.tracker.p[j], run.tracker.quat[j])
    for k in range(i, run.encoder.t.size):
        bursty += est.on_encoder(run.encoder.t[k], run.encoder.q[k])
    bursty += est.flush()
    assert len(bursty) == len(ordered)
    for a, b in zip(ordered, bursty, strict=True):
        assert a.stamp == b.stamp
        assert a.flags == b.flags
        assert np.array_equal(a.estimate, b.estimate)


def test_missing_encoder_holds_and_flags(demo_cell, run):
    est = Estimator(demo_cell, settings())
    out = run_offline(
        est,
        run.encoder.t[run.encoder.t < 3.0],
        run.encoder.q[run.encoder.t < 3.0],
        run.tracker.t,
        run.tracker.p,
        run.tracker.quat,
    )
    good = [e for e in out if not e.held]
    held = [
        e for e in out if e.held and e.stamp > good[0].stamp
    ]  # before any encoder data: too_old
    assert good
    assert held
    assert all(e.flags == ("encoder_stale",) for e in held)
    assert all(e.measured is None for e in held)
    # the observer holds: every held estimate equals the last good one
    assert all(np.array_equal(e.estimate, good[-1].estimate) for e in held)
    assert est.counters["held_encoder_stale"] == len(held)


def test_encoder_gap_is_not_interpolated_across(demo_cell, run):
    keep = (run.encoder.t < 3.0) | (run.encoder.t > 3.5)
    est = Estimator(demo_cell, settings())
    out = run_offline(
        est,
        run.encoder.t[keep],
        run.encoder.q[keep],
        run.tracker.t,
        run.tracker.p,
        run.tracker.quat,
    )
    gap = [e for e in out if "encoder_gap" in e.flags]
    assert gap
    assert all(3.0 - 0.05 < e.stamp - 0.028 < 3.5 + 0.05 for e in gap)
    assert not any(e.held for e in out if e.stamp > 3.7)  # back to normal after the gap


def test_tracker_gap_and_bad_samples(demo_cell):
    est = Estimator(demo_cell, settings(delay=DelayModel(0.0)))
    q = np.zeros(6)
    for k in range(20):
        est.on_encoder(k * 0.025, q)
    p = np.array([1.0, 0.0, 1.0])
    quat = np.array([1.0, 0.0, 0.0, 0.0])
    assert est.on_tracker(0.1, p, quat)[0].measured is not None
    (gap,) = est.on_tracker(0.11, None, None, ok=False)
    assert gap.flags == ("tracker_gap",)
    assert est.on_tracker(0.11, p, quat) == []  # duplicate stamp
    assert est.on_tracker(0.105, p, quat) == []  # backwards
    assert est.on_tracker(0.12, [np.nan, 0, 0], quat) == []
    assert est.on_tracker(0.13, p, [0.5, 0, 0, 0]) == []  # not a unit quaternion
    assert est.on_tracker(0.14, p, None) == []  # 3 channels on a 6-channel stream
    assert est.on_encoder(est.encoder.newest_t, q) == []  # the newest stamp again
    assert est.on_encoder(0.1, q) == []
    assert est.on_encoder(1.0, [0.0] * 5) == []
    assert est.on_encoder(1.0, np.zeros((6, 1))) == []  # six values, not six joints
    est.on_encoder(0.5, (0.0,) * 6)  # a tuple is joints too
    assert est.encoder.newest_t == 0.5
    c = est.counters
    assert (c["tracker_duplicate"], c["tracker_out_of_order"], c["tracker_non_finite"]) == (1, 1, 1)
    assert (c["tracker_not_unit_quaternion"], c["tracker_channel_mismatch"]) == (1, 1)
    assert (c["encoder_out_of_order"], c["encoder_duplicate"], c["encoder_wrong_length"]) == (
        1,
        1,
        2,
    )
    assert len(est.messages) > 0
    assert "t=0.11" in " ".join(est.messages)


def test_malformed_tracker_values_are_refused_by_name(demo_cell):
    """Wrong counts, non-numbers and infinities in any position, as lists (the service's
    decoded messages) and as arrays: each is counted under its name, none reaches the
    observer, and a good sample after them is estimated."""
    est = Estimator(demo_cell, settings(delay=DelayModel(0.0)))
    for k in range(20):
        est.on_encoder(k * 0.025, [0.0] * 6)
    p, quat = [1.0, 0.0, 1.0], [1.0, 0.0, 0.0, 0.0]
    wrong_length = [([1.0, 0.0], quat), (p, []), (p, [1.0, 0.0, 0.0]), (p, [1, 0, 0, 0, 0])]
    wrong_length += [(np.zeros((1, 3)), quat), (5.0, quat)]
    non_finite = [([1.0, "x", 0.0], quat), (p, [1.0, 0.0, math.inf, 0.0]), ([None, 0, 0], quat)]
    non_finite += [(np.array([0.0, -math.inf, 0.0]), np.array(quat))]
    t = 0.1
    for bad_p, bad_q in wrong_length + non_finite:
        t += 0.001
        assert est.on_tracker(t, bad_p, bad_q) == [], (bad_p, bad_q)
    c = est.counters
    assert c["tracker_wrong_length"] == len(wrong_length)
    assert c["tracker_non_finite"] == len(non_finite)
    assert c["estimates"] == 0
    (good,) = est.on_tracker(t + 0.001, ["1.0", 0, 1], quat)  # numbers as text pass as numbers
    assert good.measured is not None
    assert np.all(np.isfinite(good.measured))


def test_encoder_buffer_is_bounded_and_interpolates_linearly():
    buf = EncoderBuffer(2, capacity=8)
    for k in range(20):
        buf.push(float(k), np.array([k, -2.0 * k]))
    assert len(buf) == 8
    assert buf.oldest_t == 12.0
    assert buf.newest_t == 19.0
    q = buf.interpolate(15.25, max_gap=2.0)
    assert isinstance(q, np.ndarray)
    assert np.allclose(q, [15.25, -30.5])
    assert buf.interpolate(11.0, 2.0) is Coverage.TOO_OLD
    assert buf.interpolate(19.5, 2.0) is Coverage.NOT_YET
    assert buf.interpolate(15.5, 0.5) is Coverage.GAP
    assert EncoderBuffer(2, capacity=8).interpolate(1.0, 2.0) is Coverage.EMPTY


def test_latest_alignment_runs_at_the_fixed_rate(demo_cell, run):
    out = run_offline(
        Estimator(demo_cell, settings(alignment="latest", sample_rate_hz=40.0)),
        run.encoder.t,
        run.encoder.q,
        run.tracker.t,
        run.tracker.p,
        run.tracker.quat,
    )
    t = np.array([e.stamp for e in out])
    assert np.allclose(np.diff(t), 0.025)


def test_persisted_directions_equal_a_row_by_row_forward_fill():
    from keo_service.core.model_corrections import persist_directions

    rng = np.random.default_rng(1)
    for _ in range(50):
        d = rng.choice([-1.0, 0.0, 0.0, 1.0], size=(int(rng.integers(1, 40)), 6))
        expected = d.copy()
        for i in range(1, expected.shape[0]):  # a joint that stands keeps its last direction
            still = expected[i] == 0
            expected[i, still] = expected[i - 1, still]
        assert np.array_equal(persist_directions(d), expected)


def test_an_estimate_reads_the_same_as_floats_and_as_arrays(demo_cell):
    """The hot path keeps plain floats; readers get arrays of the same numbers, the service
    gets the floats, and the joints are the ones the measured error used."""
    est = Estimator(demo_cell, settings(delay=DelayModel(0.0)))
    for k in range(20):
        est.on_encoder(k * 0.025, [0.1 * k, 0.2, -0.3, 0.0, 0.5, 0.0])
    (e,) = est.on_tracker(0.1, [1.0, 0.0, 1.0], [1.0, 0.0, 0.0, 0.0])
    floats, state = e.measured_values(), e.estimate_values()
    assert isinstance(floats, list)
    assert isinstance(state, list)
    assert isinstance(e.measured, np.ndarray)
    assert e.measured.tolist() == floats
    assert e.estimate.tolist() == state
    assert e.measured is e.measured  # made once
    assert np.allclose(e.joints, [0.4, 0.2, -0.3, 0.0, 0.5, 0.0], atol=1e-15)
    held = Estimate(1.0, None, np.zeros(3), ("tracker_gap",), None, ("px", "py", "pz"))
    assert held.held
    assert held.measured is None
    assert held.measured_values() is None
    assert held.estimate_values() == [0.0, 0.0, 0.0]
    assert "tracker_gap" in repr(held)


def test_channels_equal_to_the_streams_pass_whatever_tuple_holds_them(demo_cell):
    """The channel check compares values: a stream whose channels were set from an equal
    tuple (e.g. restored state) is not a mismatch."""
    est = Estimator(demo_cell, settings(delay=DelayModel(0.0)))
    equal = (*POSE_CHANNELS[:3], *POSE_CHANNELS[3:])
    assert equal == POSE_CHANNELS
    assert equal is not POSE_CHANNELS
    est.channels = equal
    for k in range(20):
        est.on_encoder(k * 0.025, [0.0] * 6)
    est.observer = KinematicErrorObserver([2.0] * 6)
    (e,) = est.on_tracker(0.1, [1.0, 0.0, 1.0], [1.0, 0.0, 0.0, 0.0])
    assert e.measured is not None
    assert est.counters["tracker_channel_mismatch"] == 0
