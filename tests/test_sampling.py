"""Long motion recordings: one sample per configuration cell, in time order, at most
max_rows."""

from __future__ import annotations

import numpy as np

from keo_service.fit.sampling import informative_rows, selection_report


def test_every_configuration_and_the_time_spent_are_kept():
    # 1 kHz for 20 s: a sweep of joint 1 over 2 rad in 10 s, then 10 s standing still
    t = np.arange(20_000) / 1000.0
    q = np.zeros((t.size, 6))
    q[:, 0] = np.minimum(t, 10.0) * 0.2
    rows = informative_rows(q, max_rows=5000, cell_rad=0.01)
    assert np.all(np.diff(rows) > 0)  # time order
    assert rows.size <= 5000
    # every 0.01 rad cell of the sweep has a kept sample
    cells = np.floor(q[:, 0] / 0.01)
    assert set(np.floor(q[rows, 0] / 0.01)) == set(cells)
    # and the samples follow time: the standstill (half the recording) has half the rows
    assert 0.48 <= np.mean(rows >= 10_001) <= 0.52
    # thinned to 100 rows, the evenly spaced ones miss cells: those are added back, for at
    # most a quarter of the rows
    coarse = informative_rows(q, max_rows=100, cell_rad=0.01)
    assert coarse.size <= 100
    assert np.all(np.diff(coarse) > 0)
    assert coarse.size >= 95
    # 75 evenly spaced (about 37 in the standstill, one cell, covered) and 25 added on the
    # sweep, whose 200 cells 38 evenly spaced samples cannot cover
    assert 35 <= np.sum(coarse >= 10_001) <= 40
    # short recordings are kept whole
    assert informative_rows(q[:50], max_rows=100).size == 50
    assert selection_report(20_000, rows)["used"] == rows.size


def test_repeatability_of_motion_standing_still_is_bounded():
    """Motion data standing still: 40 000 equal rows (their pairs would be 8e8) and a slow
    creep; the repeatability is found in well under a second, the rows grouped as equal."""
    import time

    from keo_service.fit.diagnostics import repeatability

    rng = np.random.default_rng(1)
    q = np.zeros((50_000, 6))
    q[40_000:, 0] = 1.0 + np.arange(10_000) * 1e-3  # 10 rad at 1 mrad a row: no repeats
    p = rng.normal(scale=20e-6, size=(q.shape[0], 3))
    start = time.process_time()
    rep = repeatability(q, p)
    assert time.process_time() - start < 5.0
    assert rep is None  # one pose measured again and again: fewer than 5 repeated poses
    q[:40_000, 1] = np.repeat(np.arange(5), 8_000) * 0.5  # five poses, 8 000 rows each
    rep = repeatability(q, p)
    assert rep is not None
    assert rep.poses == 5
    assert rep.measurements == 40_000
    assert abs(rep.rms_mm - 0.020 * np.sqrt(3)) < 0.002  # 20 um per coordinate
