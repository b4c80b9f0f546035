"""The delay's level and rate (a small Kalman filter) and the choice between a steady and a
moving view of the fits, checked against least squares and against walks we made up."""

from __future__ import annotations

import math

import numpy as np
import pytest

from keo_service.fit.delay_online import DelayMeasurement, DelayRefused, OnlineDelayTracker
from keo_service.fit.delay_trend import LevelAndRate, SteadyOrMoving


def test_without_process_noise_the_filter_is_the_least_squares_line():
    """No walk, a rate prior too wide to matter: the level at the newest time is the weighted
    least-squares line through the measurements (numpy's polyfit, weights 1/sigma)."""
    rng = np.random.default_rng(1)
    t = np.sort(rng.uniform(0.0, 20.0, 9))
    sigma = rng.uniform(1.0, 4.0, t.size)
    y = 3.0 - 0.7 * t + rng.normal(0.0, 1.0, t.size) * sigma
    f = LevelAndRate(level_walk=0.0, rate_walk=0.0, rate_relax_s=math.inf, rate_prior=1e3)
    for ti, yi, si in zip(t, y, sigma, strict=True):
        f.update(float(yi), float(si) ** 2, float(ti))
    slope, intercept = np.polyfit(t, y, 1, w=1.0 / sigma)
    level, variance = f.predict(float(t[-1]))
    assert level == pytest.approx(intercept + slope * t[-1], abs=1e-6)
    assert f.rate == pytest.approx(slope, abs=1e-6)
    # and its variance is that of the line's value there
    a = np.vstack([np.ones_like(t), t - t[-1]]).T / sigma[:, None]
    assert variance == pytest.approx(np.linalg.inv(a.T @ a)[0, 0], rel=1e-6)


def test_a_stale_rate_relaxes_instead_of_running_on():
    f = LevelAndRate(level_walk=0.0, rate_walk=0.0, rate_relax_s=10.0, rate_prior=1.0)
    for k in range(6):
        f.update(2.0 * k, 0.01, float(k))  # 2 per second
    assert f.rate > 1.0  # (below 2: the model expects a rate to relax)
    here, _ = f.predict(5.0)
    # a day later the level has gained rate * relax time, not rate * a day
    level, _ = f.predict(5.0 + 86400.0)
    assert level == pytest.approx(here + f.rate * 10.0, rel=1e-9)


def _views() -> SteadyOrMoving:
    return SteadyOrMoving(
        LevelAndRate(25e-12, 0.0, 30.0, 0.0), LevelAndRate(4e-12, 1e-12, 30.0, 2e-6)
    )


def test_scattering_fits_are_seen_as_steady_and_a_steady_walk_as_moving():
    rng = np.random.default_rng(7)
    t = np.arange(0.0, 40.0, 2.5)
    scatter = _views()
    for ti in t:
        scatter.update(50e-6 + rng.normal(0.0, 30e-6), (30e-6) ** 2, float(ti))
    assert scatter.chosen == "steady"
    walk = _views()
    for ti in t:
        walk.update(50e-6 + 4e-6 * ti + rng.normal(0.0, 1e-6), (2e-6) ** 2, float(ti))
    assert walk.chosen == "moving"
    level, variance = walk.predict(float(t[-1]))
    assert abs(level - (50e-6 + 4e-6 * t[-1])) < 3 * math.sqrt(variance)
    assert abs(level - (50e-6 + 4e-6 * t[-1])) < 3e-6


def test_the_delay_in_use_follows_a_steady_walk(demo_cell):
    """The delay the stamps need walking at 4 us/s (the device-clock test measured 3-5 us/s
    over 10-20 s), fitted every 2.5 s to 1 us: the estimate at each stretch's end stays
    within 4 us of the walk from the tenth fit on (before it, the fits' consensus: the delay
    is found, settles at the third fit, and the filter starts from it). (The mean of recent
    fits weighted by age, the version before, lagged it by 15-20 us: a fit describes its
    stretch's middle and the mean its recent past.)"""
    tracker = OnlineDelayTracker(demo_cell)
    rng = np.random.default_rng(5)
    errors = []
    for k in range(24):
        end = 2.5 * (k + 1)
        middle = end - 1.25
        value = 500e-6 + 4e-6 * middle + rng.normal(0.0, 1e-6)
        tracker.combine(DelayMeasurement(value, 1e-6, 0.3, end, math.nan, middle))
        assert tracker.estimate is not None
        errors.append(tracker.estimate - (500e-6 + 4e-6 * end))
    assert np.max(np.abs(errors[10:])) < 4e-6, np.round(np.array(errors) * 1e6, 1)
    assert "moving" in tracker.last_result


def test_rough_fits_lengthen_the_stretch_and_precise_ones_shorten_it(demo_cell):
    tracker = OnlineDelayTracker(demo_cell)  # stretches of 2.5 s, up to 10 s
    assert tracker._span() == 2.5
    for k in range(3):  # se * speed = 30 um: rough
        tracker.combine(DelayMeasurement(28e-3, 100e-6, 0.3, 10.0 * (k + 1)))
    assert tracker._span() == 10.0
    tracker.combine(DelayMeasurement(28e-3, 1e-6, 0.3, 40.0))  # 0.3 um
    assert tracker._span() == 5.0
    tracker.combine(DelayMeasurement(28e-3, 1e-6, 0.3, 45.0))
    assert tracker._span() == 2.5
    # a stretch too short to separate a delay at all counts as a rough fit (a robot with
    # geometric errors, from delay_s = 0: 2.5 s stretches were never identifiable, and the
    # delay stayed 28 ms off)
    tracker.combine(DelayRefused("fits_not_identifiable", "a test", 50.0))
    assert tracker._span() == 5.0
    tracker.combine(DelayRefused("fits_without_data", "a test", 55.0))
    assert tracker._span() == 5.0


def test_a_delay_that_jumped_is_taken_once_the_fits_after_it_are_the_consensus(demo_cell):
    """A settled 500 us, then the delay jumps to 640 us: the first two fits after the jump are
    outnumbered by the five before (no consensus against the delay in use), the third makes
    them the majority of the recent five: changed, as a step."""
    tracker = OnlineDelayTracker(demo_cell)
    for k in range(6):
        tracker.combine(DelayMeasurement(500e-6, 1e-6, 0.3, 2.5 * (k + 1)))
    assert tracker.settled
    assert tracker.delay_now() == pytest.approx(500e-6, abs=1e-6)
    assert tracker.combine(DelayMeasurement(640e-6, 1e-6, 0.3, 17.5)) is None
    assert tracker.combine(DelayMeasurement(640e-6, 1e-6, 0.3, 20.0)) is None
    taken = tracker.combine(DelayMeasurement(640e-6, 1e-6, 0.3, 22.5))
    assert taken == pytest.approx(640e-6, abs=1e-6), tracker.last_result
    assert tracker.step
