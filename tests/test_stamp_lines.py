"""Mapped stamps carried onto their clock mapping's newest line (fit/stamp_lines.py): a delay
fitted under one line per stream, and followed as the lines move, without waiting for a fit.

The truth here is a simulation's: each sample's true instant is known, the device clocks run
at a known rate, and the mapping's lines are set by the test (an offset that jumps, as the
median transport floor does)."""

from __future__ import annotations

import numpy as np
import pytest

from keo_service.fit.delay_online import DelayMeasurement, OnlineDelayTracker
from keo_service.fit.stamp_lines import Anchor, moved
from keo_service.sim.simulate import make_scenario, simulate

DELAY = 0.028  # the simulation's delay between the streams (s)
ENC_CLOCK = (1000.0, 80e-6)  # device time at stream time 0, rate error: runs 80 ppm fast
TRK_CLOCK = (2000.0, -40e-6)


def test_an_anchor_carries_device_stamps_onto_its_line():
    """Analytic: under (stamp 100 s at device 10 s, drift 50 ppm) device 12 s maps to
    100 + 2 * (1 + 50e-6) s; a newer anchor on a line 30 us later at its own device time has
    moved by 30 us, whatever its drift."""
    old = Anchor(100.0, 10.0, 50e-6)
    assert old.at(np.array([12.0]))[0] == pytest.approx(102.0001, abs=1e-9)
    newer = Anchor(float(old.at(np.array([14.0]))[0]) + 30e-6, 14.0, 52e-6)
    assert newer.moved_since(old) == pytest.approx(30e-6, abs=1e-9)
    assert moved(newer, None) == moved(None, old) == 0.0
    # lines whose drifts differ (100 ppm): 30 us apart at device 14 s, -170 us at 12 s
    turned = Anchor(104.0 + 30e-6, 14.0, 100e-6)
    flat = Anchor(100.0, 10.0, 0.0)
    assert turned.moved_since(flat) == pytest.approx(30e-6, abs=1e-9)
    assert turned.moved_since(flat, at=102.0) == pytest.approx(-170e-6, abs=0.1e-6)


def _line(t_true, clock, jump_at, jump_s, slope=(0.0, 0.0)):
    """Device stamps of a clock (start, rate error) and their mapped stamps under a line that
    is exact (the inverse rate) but for an offset `jump_s` from `jump_at` on and a slope
    error (s/s, and the instant where the line is right); the drift the mapping's line has."""
    start, rate = clock
    device = start + t_true * (1.0 + rate)
    error, right_at = slope
    drift = (1.0 + error) / (1.0 + rate) - 1.0  # host seconds per device second, minus one
    stamps = t_true + np.where(t_true >= jump_at, jump_s, 0.0) + error * (t_true - right_at)
    return device, stamps, drift


def _feed(
    tracker, run, lo, hi, enc_jump=(0.0, 0.0), trk_jump=(0.0, 0.0), lines=True, trk_slope=(0, 0)
):
    enc = (run.encoder.t >= lo) & (run.encoder.t < hi)
    trk = (run.tracker.t >= lo) & (run.tracker.t < hi)
    e_dev, e_t, e_drift = _line(run.encoder.t[enc], ENC_CLOCK, *enc_jump)
    k_dev, k_t, k_drift = _line(run.tracker.t[trk], TRK_CLOCK, *trk_jump, slope=trk_slope)
    for t, q, d in zip(e_t, run.encoder.q[enc], e_dev, strict=True):
        tracker.add_encoder(
            float(t),
            q,
            device_stamp=float(d) if lines else None,
            clock_drift=e_drift if lines else None,
        )
    for t, p, quat, d in zip(k_t, run.tracker.p[trk], run.tracker.quat[trk], k_dev, strict=True):
        tracker.add_tracker(
            float(t),
            p,
            quat,
            device_stamp=float(d) if lines else None,
            clock_drift=k_drift if lines else None,
        )


@pytest.fixture(scope="module")
def run(demo_cell):
    sets = {
        "duration_s": "12",
        "encoder_rate_hz": "500",  # a fit precise to microseconds (at 40 Hz: 0.16 ms)
        "encoder_rate_std_hz": "0",
        "tracker_rate_std_hz": "0",
        "delay_jitter_s": "0",
        "tool_error_only": "true",
        "position_noise_m": "0",
        "rotation_noise_rad": "0",
        "drop_probability": "0",
    }
    return simulate(demo_cell, make_scenario("path", sets), seed=2)


@pytest.mark.parametrize("lines", [True, False])
def test_a_stretch_is_fitted_under_its_newest_lines(demo_cell, run, lines):
    """The tracker's line moves 60 us later half-way through a 2.5 s stretch (its median
    floor changed): the stamps after the move need a delay 60 us longer. Fitted under the
    newest line (the samples carry their device stamps and the line's drift), the stretch
    gives that delay (measured 60.0 us more than the same stretch without the move, within
    its 7 us standard error of the truth); from the stamps as they were mapped (no lines:
    the version before), a mix that fits badly (measured 55 +/- 339 us off)."""
    tracker = OnlineDelayTracker(demo_cell, span_s=2.5, young_span_s=2.5)
    _feed(tracker, run, 4.0, 6.6, trk_jump=(5.2, 60e-6), lines=lines)
    assert tracker.due()
    found = tracker.measure(tracker.snapshot(), DELAY)
    assert isinstance(found, DelayMeasurement), found
    if lines:
        assert found.se_s < 10e-6
        assert found.delay_s == pytest.approx(DELAY + 60e-6, abs=10e-6)
    else:
        assert abs(found.delay_s - (DELAY + 60e-6)) > 15e-6


def test_the_delay_in_use_follows_the_lines_without_a_fit(demo_cell, run):
    """After a fit was applied, each line's move changes the delay to use by as much, at once
    (a tracker stamp moved later needs a longer delay, an encoder stamp a shorter one): the
    delay in use lagged such moves by a stretch and its fit before (15-40 us in the
    device-clock test). The running estimate moves with them: the next fit, under the
    moved lines, is combined with the first as it is now, not as it was fitted."""
    tracker = OnlineDelayTracker(
        demo_cell, span_s=2.5, young_span_s=2.5, young_s=0.0, prior_s=DELAY, prior_se_s=5e-6
    )
    _feed(tracker, run, 4.0, 6.6)
    found = tracker.measure(tracker.snapshot(), DELAY)
    assert isinstance(found, DelayMeasurement)
    assert found.delay_s == pytest.approx(DELAY, abs=10e-6)
    assert tracker.combine(found) is None  # agrees with the configured delay: kept
    applied = tracker.delay_now()
    assert applied == pytest.approx(DELAY, abs=1e-12)
    _feed(tracker, run, 6.6, 7.0, trk_jump=(6.7, 40e-6))
    assert tracker.delay_now() == pytest.approx(applied + 40e-6, abs=0.5e-6)
    _feed(tracker, run, 7.0, 7.5, enc_jump=(7.0, 25e-6), trk_jump=(0.0, 40e-6))
    assert tracker.delay_now() == pytest.approx(applied + 15e-6, abs=0.5e-6)
    # the next fit, under the moved lines, finds what the delay already is; combined with
    # the first carried along (measured: 1.2 us off applied + 15 us; combined with the first
    # as it was fitted, 8.2 us)
    _feed(tracker, run, 7.5, 9.6, enc_jump=(0.0, 25e-6), trk_jump=(0.0, 40e-6))
    assert tracker.due()
    again = tracker.measure(tracker.snapshot(), tracker.delay_now())
    tracker.combine(again)
    assert isinstance(again, DelayMeasurement)
    assert again.delay_s == pytest.approx(applied + 15e-6, abs=3e-6)
    consensus = tracker.consensus()
    assert consensus is not None
    assert consensus[0] == pytest.approx(applied + 15e-6, abs=3e-6), tracker.last_result
    assert tracker.delay_now() == pytest.approx(applied + 15e-6, abs=0.5e-6)


def test_streams_without_lines_change_nothing(demo_cell, run):
    """Shared-clock or receipt stamps come without a line: the delay applied stays as it
    was fitted."""
    tracker = OnlineDelayTracker(demo_cell, span_s=2.5, young_span_s=2.5, prior_s=DELAY)
    tracker.forget(DELAY, 5e-6)
    _feed(tracker, run, 4.0, 6.6, lines=False)
    tracker.combine(tracker.measure(tracker.snapshot(), DELAY))
    applied = tracker.delay_now()
    assert applied is not None
    _feed(tracker, run, 6.6, 7.5, trk_jump=(6.7, 40e-6), lines=False)
    assert tracker.delay_now() == applied


def test_a_turned_line_carries_the_estimate_where_it_describes(demo_cell, run):
    """While a mapping's drift converges its line turns. Here the tracker's line runs 20 ppm
    fast during the first stretch (right at its middle, 26 us off at its ends; the fit is
    rough: 27990 +/- 37 us, kept but not applied) and right from then on: both stretches
    need the same delay where each is fitted. Carried onto the new line where it describes
    (its stretch, 5.3 s), the first fit agrees with the second; carried where the lines were
    compared (9.2 s, the newest sample, 78 us apart there) it pulls the estimate off
    (measured: 0.7 us off the truth, that version 16.1 us)."""
    tracker = OnlineDelayTracker(demo_cell, span_s=2.5, young_span_s=2.5, young_s=0.0)
    _feed(tracker, run, 4.0, 6.6, trk_slope=(20e-6, 5.3))
    first = tracker.measure(tracker.snapshot(), DELAY)
    tracker.combine(first)
    assert isinstance(first, DelayMeasurement)
    assert first.delay_s == pytest.approx(DELAY, abs=15e-6), tracker.last_result
    _feed(tracker, run, 6.6, 9.2)
    tracker.combine(tracker.measure(tracker.snapshot(), DELAY))
    assert tracker.counters["fits_accepted"] == 2, tracker.last_result
    # the two fits, the first carried onto the new line where it describes, agree on it
    assert tracker.delay_now() == pytest.approx(DELAY, abs=8e-6), tracker.last_result
