"""The batch path (`core.batch.estimate_batch`) against the streaming estimator fed sample by
sample (`run_offline`): the same rows, values to 1e-12, flags, counters and messages, on every
simulator scenario and on hand-made faults in both streams."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from keo_service.core.batch import (
    BatchResult,
    BatchUnsupportedError,
    _counts_up_to,
    estimate_batch,
    first_order_recursion,
    measured_errors,
)
from keo_service.core.chain import Chain
from keo_service.core.estimator import Estimator, run_offline
from keo_service.core.kinematics import Cell, measured_error
from keo_service.core.model_corrections import ModelCorrections
from keo_service.core.rules import first_beyond
from keo_service.core.timing import DelayModel
from keo_service.io.cell import estimator_settings
from keo_service.io.interchange import (
    EncoderData,
    TrackerData,
    read_estimates,
    write_encoder,
    write_tracker,
)
from keo_service.sim.simulate import SCENARIOS, make_scenario, simulate
from tests.conftest import DEMO, keo

TOL = 1e-12


def compare(cell, settings, enc_t, enc_q, trk_t, trk_p, trk_quat):
    streaming = Estimator(cell, settings)
    reference = run_offline(streaming, enc_t, enc_q, trk_t, trk_p, trk_quat)
    batch = estimate_batch(cell, settings, enc_t, enc_q, trk_t, trk_p, trk_quat)
    got = batch.to_estimates()
    assert len(got) == len(reference)
    for g, r in zip(got, reference, strict=True):
        assert g.stamp == r.stamp
        assert g.flags == r.flags, (g.stamp, g.flags, r.flags)
        assert (g.measured is None) == (r.measured is None), g.stamp
        if r.measured is not None:
            assert np.max(np.abs(g.measured - r.measured)) < TOL
            assert np.max(np.abs(g.joints - r.joints)) < TOL
        assert np.max(np.abs(g.estimate - r.estimate), initial=0.0) < TOL
        assert g.encoder_stamp == pytest.approx(r.encoder_stamp, abs=0.0)
    assert batch.counters == dict(streaming.counters)
    assert batch.messages == list(streaming.messages)
    # and back: the streaming rows as arrays (what `keo estimate --streaming` writes)
    back = BatchResult.from_estimates(
        reference, batch.channels, cell.robot.nq, batch.counters, batch.messages
    )
    assert back.flags == batch.flags
    for name in ("stamp", "measured", "estimate", "encoder_stamp", "joints"):
        np.testing.assert_allclose(getattr(back, name), getattr(batch, name), rtol=0, atol=TOL)
    return batch, reference


def streams(run):
    return (run.encoder.t, run.encoder.q, run.tracker.t, run.tracker.p, run.tracker.quat)


@pytest.mark.parametrize("scenario", SCENARIOS)
@pytest.mark.parametrize("start", ["zero", "first"])
def test_every_scenario_equals_the_streaming_estimator(demo_cell, demo_config, scenario, start):
    run = simulate(demo_cell, make_scenario(scenario), seed=11)
    settings = dataclasses.replace(estimator_settings(demo_config), start=start)
    batch, reference = compare(demo_cell, settings, *streams(run))
    assert len(reference) > 100
    if scenario != "static-poses":  # poses far apart in time: every step is an encoder gap
        assert batch.counters["estimates"] > 0


def test_position_only_equals_the_streaming_estimator(demo_cell, demo_config):
    run = simulate(demo_cell, make_scenario("path", {"duration_s": "6"}), seed=2)
    enc_t, enc_q, trk_t, trk_p, _quat = streams(run)
    batch, _ = compare(demo_cell, estimator_settings(demo_config), enc_t, enc_q, trk_t, trk_p, None)
    assert batch.channels == ("px", "py", "pz")


def _faulty(run):
    """Bad rows of every kind in both streams, and dropouts long enough to hold steps."""
    enc_t, enc_q = run.encoder.t.copy(), run.encoder.q.copy()
    trk_t, trk_p = run.tracker.t.copy(), run.tracker.p.copy()
    quat = run.tracker.quat.copy()
    enc_q[10, 2] = np.nan  # non-finite joint
    enc_t[20] = enc_t[19]  # duplicate stamp
    enc_t[30] = enc_t[25]  # older than the newest
    enc_t[40] = np.inf
    keep = (run.encoder.t < 3.0) | (run.encoder.t > 3.6)  # a 0.6 s hole: encoder gap
    enc_t, enc_q = enc_t[keep], enc_q[keep]
    trk_p[5, 1] = np.nan
    quat[7] = [0.9, 0.1, 0.0, 0.0]  # not a unit quaternion
    quat[8, 0] = np.inf
    trk_t[50] = trk_t[49]  # duplicate
    trk_t[60] = trk_t[55]  # out of order
    trk_t[70] = np.nan
    tkeep = (run.tracker.t < 5.0) | (run.tracker.t > 5.4)  # a tracker dropout
    return enc_t, enc_q, trk_t[tkeep], trk_p[tkeep], quat[tkeep]


def test_faults_in_both_streams_equal_the_streaming_estimator(demo_cell, demo_config):
    run = simulate(demo_cell, make_scenario("path", {"duration_s": "10"}), seed=5)
    batch, _ = compare(demo_cell, estimator_settings(demo_config), *_faulty(run))
    c = batch.counters
    for name in (
        "encoder_non_finite",
        "encoder_duplicate",
        "encoder_out_of_order",
        "tracker_non_finite",
        "tracker_duplicate",
        "tracker_out_of_order",
        "tracker_not_unit_quaternion",
        "held_encoder_gap",
    ):
        assert c.get(name, 0) > 0, name


def test_encoder_ending_early_and_too_old_and_stale(demo_cell, demo_config):
    """The encoder stops before the tracker (stale, resolved at flush) and a delay longer than
    the buffer (too old)."""
    run = simulate(demo_cell, make_scenario("path", {"duration_s": "8"}), seed=6)
    enc_t, enc_q, trk_t, trk_p, quat = streams(run)
    keep = enc_t < 6.0
    settings = estimator_settings(demo_config)
    batch, _ = compare(demo_cell, settings, enc_t[keep], enc_q[keep], trk_t, trk_p, quat)
    assert batch.counters["held_encoder_stale"] > 0
    late = dataclasses.replace(settings, delay=DelayModel(offset_s=-2.5), buffer_s=1.0)
    batch, _ = compare(demo_cell, late, enc_t, enc_q, trk_t, trk_p, quat)
    assert (
        batch.counters.get("held_encoder_too_old", 0) + batch.counters.get("held_encoder_stale", 0)
        > 0
    )
    drift = dataclasses.replace(settings, delay=DelayModel(0.004, 2e-4, 1.0))
    compare(demo_cell, drift, enc_t, enc_q, trk_t, trk_p, quat)


def test_a_corrected_model_with_backlash_compliance_and_maps(demo_cell, demo_config):
    """Every joint correction the live estimator applies, including the direction of motion
    for backlash and the flag outside a map's calibrated range."""
    nq = demo_cell.robot.nq
    rng = np.random.default_rng(3)
    run = simulate(demo_cell, make_scenario("path", {"duration_s": "6"}), seed=9)
    lo, hi = np.percentile(run.encoder.q[:, 0], [25, 75])
    knots = np.linspace(lo, hi, 11)  # joint 1 leaves this range: flagged there
    corr = ModelCorrections(
        nq,
        joint_offsets=rng.normal(0, 1e-4, nq),
        compliance=np.full(nq, 1e-7),
        backlash=np.full(nq, 5e-5),
        cyclic=rng.normal(0, 1e-5, (nq, 2, 2)),
        maps=((knots, rng.normal(0, 2e-4, knots.size)),) + ((np.empty(0), np.empty(0)),) * (nq - 1),
    )
    nominal = demo_cell.robot.model
    cell = Cell(
        demo_cell.robot,
        demo_cell.T_nt,
        demo_cell.T_bk,
        corrections=corr,
        nominal_model=nominal,
        gravity_data=nominal.createData(),
    )
    batch, _ = compare(cell, estimator_settings(demo_config), *streams(run))
    assert batch.counters.get("outside_calibrated_range", 0) > 0


@pytest.mark.parametrize(("chunk", "observer_rows"), [(50, 120), (64, 64), (7, 1000)])
def test_chunk_boundaries_change_nothing(demo_cell, demo_config, monkeypatch, chunk, observer_rows):
    """Recordings here fit one chunk of the real sizes: small chunks put faults, held rows
    and observer steps across chunk boundaries (the state and the held rows' carry)."""
    from keo_service.core import batch as batch_module

    monkeypatch.setattr(batch_module, "CHUNK", chunk)
    monkeypatch.setattr(batch_module, "OBSERVER_ROWS", observer_rows)
    run = simulate(demo_cell, make_scenario("path", {"duration_s": "10"}), seed=5)
    settings = estimator_settings(demo_config)
    batch, _ = compare(demo_cell, settings, *_faulty(run))
    assert batch.counters["held_encoder_gap"] > 0
    enc_t, enc_q, trk_t, trk_p, quat = streams(run)
    keep = enc_t < 6.0  # the encoder ends early: stale rows after the last update
    batch, _ = compare(demo_cell, settings, enc_t[keep], enc_q[keep], trk_t, trk_p, quat)
    assert batch.counters["held_encoder_stale"] > 0


def test_a_sample_on_the_first_encoder_stamp_after_a_gap(demo_cell, demo_config):
    """A tracker time that falls exactly on an encoder stamp takes that sample's joints, even
    just after a hole in the encoder stream; one between the two samples around the hole is
    held as a gap."""
    run = simulate(demo_cell, make_scenario("path", {"duration_s": "6"}), seed=3)
    enc_t, enc_q, trk_t, trk_p, quat = streams(run)
    keep = (enc_t < 2.0) | (enc_t > 2.5)
    enc_t, enc_q = enc_t[keep], enc_q[keep]
    after = enc_t[np.argmax(enc_t > 2.5)]
    inside = 0.5 * (2.0 + after)
    # two tracker samples moved onto those times (their neighbours keep their order)
    k_after = int(np.argmin(np.abs(trk_t - after)))
    k_inside = int(np.argmin(np.abs(trk_t - inside)))
    trk_t = trk_t.copy()
    trk_t[k_after], trk_t[k_inside] = after, inside
    settings = dataclasses.replace(estimator_settings(demo_config), delay=DelayModel(0.0))
    _batch, reference = compare(demo_cell, settings, enc_t, enc_q, trk_t, trk_p, quat)
    by_t = {e.stamp: e for e in reference}
    assert by_t[after].flags == ()  # on the sample: joints, no gap
    assert by_t[inside].flags == ("encoder_gap",)


def test_no_encoder_data_holds_every_row(demo_cell, demo_config):
    run = simulate(demo_cell, make_scenario("path", {"duration_s": "2"}), seed=1)
    _enc_t, _enc_q, trk_t, trk_p, quat = streams(run)
    settings = estimator_settings(demo_config)
    batch, _ = compare(demo_cell, settings, np.empty(0), np.empty((0, 6)), trk_t, trk_p, quat)
    assert np.isnan(batch.measured).all()
    assert batch.counters["held_encoder_stale"] == trk_t.size


def test_vectorised_measured_error_equals_the_per_sample_one(demo_cell):
    rng = np.random.default_rng(1)
    n = 300
    robot = demo_cell.robot
    q = rng.uniform(np.maximum(robot.lower, -3), np.minimum(robot.upper, 3), (n, robot.nq))
    p = rng.normal(0, 1.0, (n, 3))
    quat = rng.normal(size=(n, 4))
    quat /= np.linalg.norm(quat, axis=1)[:, None]
    got = measured_errors(demo_cell, Chain(robot), q, p, quat)
    data = robot.create_data()
    want = np.array([measured_error(demo_cell, data, q[k], p[k], quat[k]) for k in range(n)])
    assert np.max(np.abs(got - want)) < TOL


def test_recursion_equals_the_sequential_loop():
    rng = np.random.default_rng(0)
    n = 5000
    b = np.exp(-rng.uniform(0, 3, (n, 2)))  # including steps that forget almost everything
    c = rng.normal(size=(n, 2))
    x0 = np.array([1.0, -2.0])
    want = np.empty((n, 2))
    x = x0
    for k in range(n):
        x = b[k] * x + c[k]
        want[k] = x
    assert np.max(np.abs(first_order_recursion(x0, b, c) - want)) < 1e-12


@pytest.mark.parametrize("limit", [0.003, 0.0025, 0.01])
def test_stale_boundary_uses_the_estimators_subtraction(limit):
    # stamps on a millisecond grid far from zero: t_a + limit and t_b - t_a round apart at
    # many boundaries, and the estimator decides by the subtraction
    t = 1000.0 + 0.001 * np.arange(3000) + np.where(np.arange(3000) % 7 == 0, 1e-13, 0.0)
    want = []
    for a in range(t.size):
        b = a + 1
        while b < t.size and not t[b] - t[a] > limit:
            b += 1
        want.append(b)
    got = first_beyond(t, limit)
    assert got.tolist() == want


def test_counting_positions_answers_as_a_binary_search():
    # positions in the merged order, repeated (resolution times) or distinct (arrivals), with
    # "never" (int64 max) and beyond-the-end values; queried at every x in [-1, events)
    rng = np.random.default_rng(3)
    events = 500
    never = np.iinfo(np.int64).max
    repeated = np.sort(rng.integers(0, events + 40, 400))
    repeated[-25:] = never
    distinct = np.sort(rng.choice(events, 180, replace=False))
    x = np.arange(-1, events)
    for positions in (repeated, distinct, np.empty(0, dtype=np.int64)):
        want = np.searchsorted(positions, x, side="right")
        assert _counts_up_to(positions, events)[x + 1].tolist() == want.tolist()


def test_the_batch_path_refuses_exactly_when_the_pending_queue_would_overflow(
    demo_cell, demo_config, monkeypatch
):
    """A 2 s encoder hole at 1 kHz leaves ~2000 tracker samples waiting. Around the queue size
    at which the streaming estimator first drops one, the batch path must hand over (raise)
    exactly when it drops and equal it otherwise."""
    from keo_service.core import batch as batch_module
    from keo_service.core import estimator as estimator_module

    scenario = {"duration_s": "5", "tracker_rate_hz": "1000", "encoder_rate_hz": "250"}
    run = simulate(demo_cell, make_scenario("path", scenario), seed=5)
    keep = (run.encoder.t < 1.0) | (run.encoder.t > 3.0)
    args = (run.encoder.t[keep], run.encoder.q[keep], *streams(run)[2:])
    settings = dataclasses.replace(
        estimator_settings(demo_config), stale_after_s=10.0, max_gap_s=10.0, buffer_s=10.0
    )

    def drops(limit: int) -> bool:
        monkeypatch.setattr(estimator_module, "MAX_PENDING", limit)
        streaming = Estimator(demo_cell, settings)
        run_offline(streaming, *args)
        return streaming.counters.get("pending_overflow", 0) > 0

    low, high = 1000, 4000  # drops at low, not at high: the smallest size that does not drop
    assert drops(low)
    assert not drops(high)
    while high - low > 1:
        middle = (low + high) // 2
        low, high = (middle, high) if drops(middle) else (low, middle)
    for limit in (high - 1, high, high + 1):
        monkeypatch.setattr(batch_module, "MAX_PENDING", limit)
        if drops(limit):
            with pytest.raises(BatchUnsupportedError, match="wait at once"):
                estimate_batch(demo_cell, settings, *args)
        else:
            compare(demo_cell, settings, *args)


def test_latest_alignment_is_left_to_the_streaming_estimator(demo_cell, demo_config):
    run = simulate(demo_cell, make_scenario("paper-step"), seed=1)
    settings = dataclasses.replace(estimator_settings(demo_config), alignment="latest")
    with pytest.raises(BatchUnsupportedError, match="latest"):
        estimate_batch(demo_cell, settings, *streams(run))


def test_keo_estimate_writes_what_the_streaming_estimator_gives(demo_cell, demo_config, tmp_path):
    """The command end to end (files in, file out) against the per-sample estimator."""
    run = simulate(demo_cell, make_scenario("path", {"duration_s": "8"}), seed=4)
    enc_t, enc_q, trk_t, trk_p, quat = _faulty(run)
    write_tracker(tmp_path / "tracker.csv", TrackerData(trk_t, trk_p, quat))
    write_encoder(tmp_path / "encoder.csv", EncoderData(enc_t, enc_q))
    res = keo(
        "estimate",
        "--config",
        str(DEMO),
        "--encoder",
        str(tmp_path / "encoder.csv"),
        "--tracker",
        str(tmp_path / "tracker.csv"),
        "--out",
        str(tmp_path / "e.csv"),
        "--json",
    )
    assert res.returncode == 0, res.stderr
    summary = json.loads(res.stdout)
    assert summary["path"] == "batch"
    table = read_estimates(tmp_path / "e.csv")
    est = Estimator(demo_cell, estimator_settings(demo_config))
    reference = run_offline(est, enc_t, enc_q, trk_t, trk_p, quat)
    assert table.t.size == len(reference)
    assert summary["counters"] == dict(est.counters)
    want_meas = np.array(
        [r.measured if r.measured is not None else [np.nan] * 6 for r in reference]
    )
    assert np.array_equal(np.isnan(table.measured), np.isnan(want_meas))
    ok = ~np.isnan(want_meas)
    assert np.max(np.abs(table.measured[ok] - want_meas[ok])) < TOL
    assert np.max(np.abs(table.estimate - np.array([r.estimate for r in reference]))) < TOL
    assert table.flags == ["|".join(r.flags) for r in reference]
    # as docs/design.md writes them: a held row's measured values and a row without flags empty
    rows = (tmp_path / "e.csv").read_text().splitlines()[1:]
    assert "nan" not in "".join(rows).lower()
    for line, r in zip(rows, reference, strict=True):
        fields = line.split(",")
        assert (fields[1:7] == [""] * 6) == (r.measured is None), line
        assert fields[-1] == "|".join(r.flags), line


def test_more_rejects_than_messages_kept_give_the_same_newest_messages(demo_cell, demo_config):
    """Every reject is counted; only the newest 32 are put in words, interleaved across the
    two streams in arrival order as the streaming estimator keeps them."""
    run = simulate(demo_cell, make_scenario("path", {"duration_s": "6"}), seed=7)
    enc_t, enc_q, trk_t, trk_p, quat = (a.copy() for a in streams(run))
    enc_q[5::6, 1] = np.nan  # one encoder row in 6
    trk_p[3::9, 0] = np.inf  # one tracker row in 9
    batch, _ = compare(demo_cell, estimator_settings(demo_config), enc_t, enc_q, trk_t, trk_p, quat)
    assert batch.counters["rejected"] > 64
    assert len(batch.messages) == 32
    assert any(m.startswith("encoder") for m in batch.messages)
    assert any(m.startswith("tracker") for m in batch.messages)


def test_keo_estimate_reports_the_encoder_files_error_first(demo_config, demo_cell, tmp_path):
    """The tracker file is read on a worker thread while the encoder file is read: which
    error the user sees must not depend on which read finishes first."""
    from keo_service.core.errors import DataFormatError
    from keo_service.offline.estimate import estimate_files

    run = simulate(demo_cell, make_scenario("path", {"duration_s": "2"}), seed=4)
    good_encoder, good_tracker = tmp_path / "encoder.csv", tmp_path / "tracker.csv"
    write_encoder(good_encoder, run.encoder)
    write_tracker(good_tracker, run.tracker)
    bad_encoder, bad_tracker = tmp_path / "bad_encoder.csv", tmp_path / "bad_tracker.csv"
    bad_encoder.write_text("time,a,b\n1,2,3\n")
    bad_tracker.write_text("when,where\n1,2\n")
    with pytest.raises(DataFormatError, match=r"bad_encoder\.csv"):
        estimate_files(demo_config, bad_encoder, bad_tracker)
    with pytest.raises(DataFormatError, match=r"bad_tracker\.csv"):
        estimate_files(demo_config, good_encoder, bad_tracker)
    result = estimate_files(demo_config, good_encoder, good_tracker)
    assert result.path == "batch"
    assert result.table.stamp.size == run.tracker.t.size


@pytest.mark.parametrize("start", ["zero", "first"])
def test_unequal_gains_and_held_rows_equal_the_streaming_estimator(demo_cell, demo_config, start):
    # the recursion's factors per channel (not the one shared by equal gains), on rows with
    # held ones among them (faults and a dropout in both streams)
    run = simulate(demo_cell, make_scenario("path", {"duration_s": "10"}), seed=7)
    settings = dataclasses.replace(
        estimator_settings(demo_config), gains=(0.5, 1.0, 2.0, 4.0, 8.0, 3.0), start=start
    )
    batch, _ = compare(demo_cell, settings, *_faulty(run))
    assert batch.counters["estimates"] > 100
    assert batch.counters.get("held_encoder_gap", 0) > 0
