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
