"""Long motion recordings: one sample per configuration cell, in time order, at most
max_rows."""

from __future__ import annotations

import numpy as np

from keo_service.fit.sampling import informative_rows, selection_report


def test_dwelling_samples_collapse_and_the_limit_holds():
    # 1 kHz for 20 s: a sweep of joint 1 over 2 rad in 10 s, then 10 s standing still
    t = np.arange(20_000) / 1000.0
    q = np.zeros((t.size, 6))
    q[:, 0] = np.minimum(t, 10.0) * 0.2
    rows = informative_rows(q, max_rows=5000, cell_rad=0.01)
    assert np.all(np.diff(rows) > 0)  # time order
    # 2 rad / 0.01 rad: 200 cells on the sweep (201 with the end), the standstill adds none
    assert 200 <= rows.size <= 202
    assert rows.max() <= 10_001
    assert np.all(np.diff(q[rows, 0]) > 0.009)  # one sample a cell (cell edges in floats)
    # a finer grid gives more cells than allowed: thinned evenly to the limit
    fine = informative_rows(q, max_rows=100, cell_rad=0.001)
    assert fine.size == 100
    assert np.all(np.diff(fine) > 0)
    # short recordings are kept whole
    assert informative_rows(q[:50], max_rows=100).size == 50
    assert selection_report(20_000, rows)["used"] == rows.size
