"""The pooled fit's bookkeeping in the online delay tracker, one measurement at a time: which
pooled fit may be in use and when (issue 45's review of the pooled fit). The measurements are
written out here, so each case states exactly what the tracker was told."""

from __future__ import annotations

import math

from keo_service.fit.delay_online import DelayMeasurement, DelayRefused, OnlineDelayTracker


def _fit(value: float, se: float, t: float, pooled: tuple[float, float] | None = None):
    """A stretch's fit at 0.2 m/s ending at `t`, with a pooled fit when given."""
    extra = {} if pooled is None else {"pooled_s": pooled[0], "pooled_se_s": pooled[1]}
    return DelayMeasurement(value, se, 0.2, t, t_mid=t - 2.5, **extra)


def test_a_pooled_fit_is_not_taken_again_after_a_measurement_without_one(demo_cell):
    """A pooled fit is of the pool it was measured on: once a later measurement comes without
    one, it is not in use again under that later time (its source time would say it is new)."""
    tracker = OnlineDelayTracker(demo_cell)
    tracker.combine(_fit(0.030, 300e-6, 10.0, pooled=(0.0301, 80e-6)))
    assert tracker.applied is not None
    assert tracker.source_t == 10.0
    tracker.combine(_fit(0.036, 900e-6, 15.0))
    assert tracker.pooled is None
    for t in (40.0, 70.0):
        tracker.combine(DelayRefused("fits_not_identifiable", "the motion", t))
        assert tracker.source_t <= 15.0, tracker.source


def test_no_pooled_fit_is_kept_once_settled(demo_cell):
    """Stretches agreeing to well within `settle_m` at their speed settle the delay; the
    pooled fit that came with them is dropped then (it is for an unsettled delay only)."""
    tracker = OnlineDelayTracker(demo_cell)
    for k in range(12):
        tracker.combine(_fit(0.030 + (-1) ** k * 5e-6, 20e-6, 5.0 * (k + 1), (0.030, 15e-6)))
        if tracker.settled:
            break
    assert tracker.settled
    assert tracker.pooled is None


def test_a_refusal_without_a_time_takes_no_pooled_fit(demo_cell):
    """A measurement whose stretch's time is not known says nothing about when its pooled fit
    describes: it is not taken (the source would read 'fit at nan s')."""
    tracker = OnlineDelayTracker(demo_cell)
    tracker.combine(DelayRefused("fits_without_data", "no data", pooled_s=0.03, pooled_se_s=1e-4))
    assert tracker.applied is None
    assert "nan" not in tracker.source


def test_an_imprecise_stretch_does_not_block_a_fresh_pooled_fit(demo_cell):
    """Every way a measurement is folded in ends at the same place: a stretch whose own fit
    is unusable still brings a usable pooled fit into use (as a refused stretch does)."""
    tracker = OnlineDelayTracker(demo_cell)
    tracker.combine(_fit(math.nan, math.nan, 10.0, pooled=(0.0302, 90e-6)))
    assert tracker.counters["fits_refused_imprecise"] == 1
    assert tracker.applied is not None
    assert abs(tracker.applied - 0.0302) < 1e-9
    assert tracker.source_t == 10.0


def test_a_reload_drops_a_fit_in_flight(demo_cell):
    """The service folds a fit in only when the tracker's restart count is what it was when
    the stretch was taken: a reload (the delay set by hand) counts too, so a fit of samples
    from before it, pooled fit included, is dropped."""
    tracker = OnlineDelayTracker(demo_cell)
    before = tracker.counters["restarts"]
    tracker.forget(0.0)
    assert tracker.counters["restarts"] == before + 1
    tracker.restart(5.0, "the encoder time base started anew")
    assert tracker.counters["restarts"] == before + 2


def test_a_pool_the_fit_cannot_use_is_counted_and_the_stretch_stands(demo_cell):
    """A pool whose joints the fit cannot take (a non-finite joint row: its least squares
    fail) gives no pooled fit; the stretch's own fit comes back as without a pool, and the
    tracker counts the pool (`pools_unusable`, beside its other counters: the service's
    status shows them as `delay_pools_unusable`), where before it was dropped unsaid."""
    import numpy as np

    from keo_service.fit.delay_online import pool_arrays, stretch_arrays
    from keo_service.sim.delay_study import StreamCase, case_streams
    from tests.test_delay_buffers import stretches_taken

    streams = case_streams(demo_cell, StreamCase("motoros", "line100", "all_slow", seconds=12.0))
    tracker = OnlineDelayTracker(demo_cell)
    stretch = None
    for stretch in stretches_taken(tracker, streams):
        if stretch.pool is not None:  # the second stretch: a pool of two
            break
        tracker.combine(tracker.measure(stretch_arrays(stretch), 0.0, 0.0))
    assert stretch is not None
    pool = pool_arrays(stretch)
    assert pool is not None
    window = stretch_arrays(stretch)
    alone = tracker.measure(window, 0.0, 0.0)
    assert isinstance(alone, DelayMeasurement)
    joints = pool[1].copy()
    joints[len(joints) // 2, 2] = math.nan
    found = tracker.measure(window, 0.0, 0.0, pool=(pool[0], joints, *pool[2:]))
    assert found.pool_unusable
    assert math.isnan(found.pooled_s)
    assert found.delay_s == alone.delay_s  # the stretch's own fit stands
    assert found.se_s == alone.se_s
    tracker.combine(found)
    assert tracker.counters["pools_unusable"] == 1
    assert tracker.pooled is None
    # a usable pool is not counted
    assert not tracker.measure(window, 0.0, 0.0, pool=pool).pool_unusable
    assert np.isfinite(tracker.measure(window, 0.0, 0.0, pool=pool).pooled_s)
