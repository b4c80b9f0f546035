"""Long motion recordings: one sample per configuration cell, in time order, at most
max_rows."""

from __future__ import annotations

import numpy as np
import pytest

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
    # thinned to 200 rows, the evenly spaced ones miss cells: those are added back, for at
    # most MISSED_SHARE of the rows
    coarse = informative_rows(q, max_rows=200, cell_rad=0.01)
    assert coarse.size <= 200
    assert np.all(np.diff(coarse) > 0)
    assert coarse.size >= 195
    # 190 evenly spaced (about 95 in the standstill, one cell, covered) and 10 added on the
    # sweep, whose 200 cells 95 evenly spaced samples cannot cover
    assert 92 <= np.sum(coarse >= 10_001) <= 97
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


def test_the_fit_for_many_rows_reaches_the_exact_solvers_minimum(demo_cell, monkeypatch):
    """Above LARGE_ROWS the robust fit steps on the normal equations. On a problem scipy's
    exact trust-region solver also solves (registration and joint offsets of a robot whose
    geometry differs from the nominal by millimetres, a few 2 mm outliers), it reaches the same
    minimum where the Huber threshold is wide (1 mm noise: the cost to 1e-8) and one
    at least as low where most rows lie beyond it (20 um: the robust cost, which scipy's
    solver stops above)."""
    from scipy.spatial.transform import Rotation

    from keo_service.core.chain import Chain
    from keo_service.core.model_corrections import approach_directions
    from keo_service.fit import model as fit_model
    from keo_service.fit.effects import EFFECTS
    from keo_service.fit.model import Data, Model, fit, initial_registration
    from keo_service.sim.simulate import make_scenario, simulate

    run = simulate(demo_cell, make_scenario("static-poses", {"poses": "300"}), seed=11)
    p = run.tracker.p.copy()
    p[::50] += 0.002
    R = Rotation.from_quat(run.tracker.quat, scalar_first=True).as_matrix()
    data = Data(run.encoder.q, p, R, run.tracker.t, {}, approach_directions(run.encoder.q))
    chain = Chain(demo_cell.robot)
    tau = chain.gravity_torques(data.q)
    effect = EFFECTS["joint_offsets"]
    reg = initial_registration(chain, data, None, False)
    x0 = np.concatenate([reg, np.zeros(effect.size(chain.nq))])
    for noise in (1e-3, 20e-6):
        residuals, costs = [], []
        for large_rows in (10**9, 100):  # scipy's exact solver, then the normal equations
            monkeypatch.setattr(fit_model, "LARGE_ROWS", large_rows)
            model = Model(chain, False, [effect], x0.copy())
            x = fit(model, data, tau, x0, noise).x
            assert np.abs(x - x0).max() > 1e-4  # the fit moved
            residuals.append(model.residuals(x, data, tau))
            costs.append(fit_model._robust_cost(residuals[-1], 3 * noise, None))
        if noise == 1e-3:  # the same minimum (up to weakly determined directions)
            assert costs[1] == pytest.approx(costs[0], rel=1e-8)
            assert np.sqrt(np.mean((residuals[1] - residuals[0]) ** 2)) < 1e-5
        assert costs[1] <= costs[0] * (1 + 1e-8)
