"""The estimator's rules (`core.rules`): each scalar form (what the streaming estimator asks
per sample) against its array form (what the batch path asks per recording), on streams with
faults of every kind, plus hand-worked cases for each rule."""

from __future__ import annotations

import dataclasses
import math
from collections import deque

import numpy as np
import pytest

from keo_service.core.model_corrections import ModelCorrections
from keo_service.core.rules import (
    CAP_MIN_INTERVALS,
    HELD_REASONS,
    RECENT_INTERVALS,
    CalibratedRanges,
    cap_is_due,
    direction_update,
    directions,
    encoder_reject,
    encoder_verdicts,
    first_beyond,
    held_reason,
    held_reasons,
    sensor_values,
    step_cap,
    step_caps,
    tracker_stamp_problem,
    tracker_verdicts,
    waits_for_encoder,
)
from keo_service.core.settings import EstimatorSettings, encoder_capacity
from keo_service.core.timing import EncoderBuffer


def _faulty_encoder(rng: np.random.Generator, n: int = 400) -> tuple[np.ndarray, np.ndarray]:
    t = np.cumsum(rng.uniform(0.002, 0.006, n))
    q = rng.normal(size=(n, 6))
    late = rng.choice(np.arange(5, n), 15, replace=False)
    t[late] = t[late - rng.integers(0, 4, 15)]  # duplicates and older stamps
    t[rng.choice(n, 5)] = np.inf
    t[rng.choice(n, 5)] = np.nan
    q[rng.choice(n, 8), rng.integers(0, 6, 8)] = np.nan
    return t, q


@pytest.mark.parametrize("seed", range(4))
def test_encoder_rejects_per_sample_equal_the_whole_stream(seed):
    t, q = _faulty_encoder(np.random.default_rng(seed))
    verdicts = encoder_verdicts(t, q)
    newest = -math.inf
    names = []
    for k in range(t.size):
        refused = encoder_reject(float(t[k]), q[k].tolist(), newest)
        names.append(None if refused is None else refused[0])
        assert (refused is None) == bool(verdicts.ok[k])
        assert newest == verdicts.newest[k]
        if refused is None:
            newest = float(t[k])
    assert {"encoder_non_finite", "encoder_duplicate", "encoder_out_of_order"} <= set(names)
    assert [n == "encoder_non_finite" for n in names] == (~verdicts.finite).tolist()
    assert [n == "encoder_duplicate" for n in names] == verdicts.duplicate.tolist()
    assert [n == "encoder_out_of_order" for n in names] == verdicts.out_of_order.tolist()


@pytest.mark.parametrize("seed", range(4))
def test_tracker_rejects_per_sample_equal_the_whole_stream(seed):
    rng = np.random.default_rng(seed)
    n = 400
    t = np.cumsum(rng.uniform(0.001, 0.002, n))
    p = rng.normal(size=(n, 3))
    quat = rng.normal(size=(n, 4))
    quat /= np.linalg.norm(quat, axis=1)[:, None]
    late = rng.choice(np.arange(5, n), 15, replace=False)
    t[late] = t[late - rng.integers(0, 4, 15)]  # duplicates and older stamps
    t[rng.choice(n, 4)] = np.nan
    p[rng.choice(n, 6), rng.integers(0, 3, 6)] = np.inf
    quat[rng.choice(n, 6)] *= 1.01  # not unit
    quat[rng.choice(n, 3)] *= 1.00001  # within the tolerance: accepted, normalised
    verdicts = tracker_verdicts(t, p, quat)
    last = -math.inf
    counted: dict[str, list[bool]] = {"non_finite": [], "dup": [], "old": [], "unit": []}
    for k in range(n):
        name = None
        if not last < t[k] < math.inf:
            name = tracker_stamp_problem(float(t[k]), last)[0]
        else:
            values = sensor_values(p[k], quat[k])
            if isinstance(values, tuple):
                name = values[0]
        assert (name is None) == bool(verdicts.accepted[k]), k
        if name is None:
            last = float(t[k])
        counted["non_finite"].append(name == "tracker_non_finite")
        counted["dup"].append(name == "tracker_duplicate")
        counted["old"].append(name == "tracker_out_of_order")
        counted["unit"].append(name == "tracker_not_unit_quaternion")
    assert counted["non_finite"] == verdicts.non_finite.tolist()
    assert counted["dup"] == verdicts.duplicate.tolist()
    assert counted["old"] == verdicts.out_of_order.tolist()
    assert counted["unit"] == verdicts.not_unit.tolist()
    assert [k for k, v in counted.items() if not any(v)] == []


def test_sensor_values_by_hand():
    assert sensor_values([1, 2, 3], None) == [1, 2, 3]
    assert sensor_values([1, 2], None)[0] == "tracker_wrong_length"
    assert sensor_values([1, 2, 3], [0.5, 0.5, 0.5, 0.5]) == [1, 2, 3, 0.5, 0.5, 0.5, 0.5]
    assert sensor_values([1, 2, 3], [2.0, 0, 0, 0]) == (
        "tracker_not_unit_quaternion",
        "quaternion norm 2, expected 1",
    )
    assert sensor_values([1, float("nan"), 3], None)[0] == "tracker_non_finite"
    assert sensor_values([1, "x", 3], None)[0] == "tracker_non_finite"


@pytest.mark.parametrize("limit", [0.003, 0.01, 0.5])
def test_waiting_per_sample_equals_the_first_sample_beyond(limit):
    """A sample waits (encoder behind) while the newest tracker stamp is within `limit` of it:
    the first tracker sample after which it no longer waits is `first_beyond`'s answer."""
    rng = np.random.default_rng(5)
    t = 1000.0 + np.cumsum(rng.uniform(0.0005, 0.004, 2000))
    got = first_beyond(t, limit)
    for a in range(t.size):
        b = a + 1
        while b < t.size and waits_for_encoder(-math.inf, 0.0, t[b] - t[a], limit):
            b += 1
        assert got[a] == b, a
    assert not waits_for_encoder(2.0, 1.0, 0.0, limit)  # the encoder is there: no wait


@pytest.mark.parametrize("seed", range(3))
def test_held_reasons_per_sample_equal_the_array_form(seed):
    """The buffer's verdicts (too old, stale, gap) with `held_reason`, against `held_reasons`
    from the number of encoder samples buffered, at many times and buffer fillings."""
    rng = np.random.default_rng(seed)
    settings = EstimatorSettings(buffer_s=0.03, max_gap_s=0.012)
    capacity = encoder_capacity(settings)
    steps = rng.uniform(0.002, 0.006, 3 * capacity)
    steps[rng.choice(steps.size, 20)] = 0.02  # gaps beyond max_gap_s
    E = np.cumsum(steps)
    have = rng.integers(0, E.size + 1, 600)
    target = rng.uniform(-0.01, E[-1] + 0.01, have.size)
    target[:50] = E[rng.integers(0, E.size, 50)]  # on a stamp, also just after a gap
    first_cover = np.searchsorted(E, target, side="left")
    g = np.minimum(first_cover, E.size - 1)
    g0 = np.maximum(g - 1, 0)
    bracket = (E[g0], E[g], E[g] == target)
    want = held_reasons(settings, E, have, target, bracket)
    seen = set()
    for k in np.argsort(have, kind="stable"):
        buffer = EncoderBuffer(1, capacity)
        for i in range(int(have[k])):
            buffer.push(float(E[i]), np.zeros(1))
        verdict = buffer.interpolate(float(target[k]), settings.max_gap_s)
        reason = held_reason(verdict, float(target[k]), buffer.newest_t, settings.buffer_s)
        assert (reason or "") == HELD_REASONS[want[k]], (k, have[k], target[k])
        seen.add(reason)
    assert seen == {None, "encoder_stale", "encoder_too_old", "encoder_gap"}


def test_step_caps_as_cached_equal_the_array_form():
    """The streaming estimator's cap after each interval (recomputed as `cap_is_due` says)
    against `step_caps`, with a gap in the middle and fewer intervals than the window."""
    rng = np.random.default_rng(2)
    intervals = rng.uniform(0.001, 0.0015, 500)
    intervals[200:230] = 0.05  # a burst of long intervals moves the median
    settings = EstimatorSettings(max_dt_s=0.1)
    recent: deque[float] = deque(maxlen=RECENT_INTERVALS)
    cap = None
    want = []
    for seen in range(1, intervals.size + 1):
        recent.append(float(intervals[seen - 1]))
        if len(recent) < CAP_MIN_INTERVALS:
            want.append(settings.max_dt_s)
            continue
        if cap_is_due(seen, cap):
            cap = step_cap(settings, recent)
        want.append(cap)
    got = step_caps(settings, intervals, np.arange(1, intervals.size + 1))
    assert got.tolist() == want
    assert len(set(want)) > 5


def test_step_cap_by_hand():
    settings = EstimatorSettings(max_dt_s=0.25, sample_rate_hz=40.0)
    assert step_cap(settings, [0.01] * 7) == 0.25  # too few intervals
    assert step_cap(settings, [0.01] * 4 + [0.02] * 5) == pytest.approx(0.06)  # 3 x median
    assert step_cap(settings, [1.0] * 9) == 0.25  # at most max_dt_s
    latest = dataclasses.replace(settings, alignment="latest")
    assert step_cap(latest, [0.001] * 9) == pytest.approx(3 / 40)  # never below its period


def test_directions_per_sample_equal_the_array_form():
    rng = np.random.default_rng(4)
    t = np.cumsum(rng.uniform(0.002, 0.006, 300))
    q = np.cumsum(rng.normal(0, 1e-3, (300, 6)), axis=0)
    q[100:140, 2] = q[99, 2]  # a joint at rest keeps its last direction
    got = directions(t, q)
    direction = np.zeros(6)
    for k in range(t.size):
        if k:
            direction_update(direction, q[k - 1], q[k], float(t[k] - t[k - 1]))
        assert got[k].tolist() == direction.tolist(), k


def test_direction_by_hand():
    direction = np.zeros(3)
    # in 0.01 s: +1e-3 rad (moved), -1e-3 rad (moved), 5e-7 rad (below 1e-4 rad/s: kept)
    direction_update(direction, np.zeros(3), np.array([1e-3, -1e-3, 5e-7]), 0.01)
    assert direction.tolist() == [1.0, -1.0, 0.0]
    direction_update(direction, np.zeros(3), np.array([-1e-3, 0.0, 0.0]), 0.01)
    assert direction.tolist() == [-1.0, -1.0, 0.0]


def test_calibrated_ranges_per_row_equal_the_array_form():
    nq = 6
    knots = np.linspace(-0.5, 0.5, 5)
    maps = [(np.empty(0), np.empty(0))] * nq
    maps[1] = (knots, np.zeros(5))
    maps[4] = (knots + 1.0, np.zeros(5))
    ranges = CalibratedRanges(ModelCorrections(nq, maps=tuple(maps)))
    assert ranges.joints == [1, 4]
    q = np.random.default_rng(0).uniform(-1.0, 2.0, (500, nq))
    rows = ranges.outside_rows(q)
    assert rows.tolist() == [ranges.outside(row) for row in q]
    assert 0 < rows.sum() < rows.size
    inside = np.zeros(nq)
    inside[4] = 1.0
    assert not ranges.outside(inside)
    inside[1] = 0.51
    assert ranges.outside(inside)
    assert not CalibratedRanges(None)
