"""The floor `keo analyze` judges what remains against: the tracker's per-point uncertainty,
its specification (keo's default marked as assumed), the repeatability of repeated
stop-and-measure poses (never of motion), and the ISO 9283 figures."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from keo_service.core.model_corrections import approach_directions
from keo_service.fit.analysis import Data, analyze, split
from keo_service.fit.uncertainty import TrackerUncertainty, iso_path_figures, iso_pose_figures
from keo_service.sim.simulate import make_scenario, simulate


def _clean_run(cell, poses=600, seed=5, **sets):
    """Stop-and-measure poses of a robot without errors, measured without noise: the tests
    add noise they know."""
    scenario = make_scenario(
        "static-poses",
        {
            "poses": str(poses),
            "geometric_errors": "false",
            "position_noise_m": "0",
            "rotation_noise_rad": "0",
            **sets,
        },
    )
    return simulate(cell, scenario, seed=seed)


def _data(run, p, sigma=None, velocity=None):
    R = Rotation.from_quat(run.tracker.quat, scalar_first=True).as_matrix()
    q = run.encoder.q
    return Data(q, p, R, run.tracker.t, {}, approach_directions(q), velocity, sigma)


def test_floor_from_per_point_uncertainties_and_the_verdict(demo_cell):
    """Each point measured with its own known standard deviation (10-60 um per coordinate):
    the floor is what that noise gives on the held-out poses (within 5 %), a perfect model
    reaches it, and the verdict says so."""
    run = _clean_run(demo_cell)
    rng = np.random.default_rng(1)
    n = run.tracker.p.shape[0]
    sigma = rng.uniform(10e-6, 60e-6, size=(n, 3))
    p = run.tracker.p + sigma * rng.standard_normal((n, 3))
    result = analyze(demo_cell.robot, _data(run, p, sigma), False, candidates=())
    floor = result.report["floor"]
    assert floor["source"].startswith("per-point standard deviations")
    assert not floor["assumed"]
    _train, val = split(n)
    noise_only = float(np.sqrt(np.mean(np.sum(sigma[val] ** 2, axis=1)))) * 1e3
    assert floor["pos_rms_mm"] == pytest.approx(noise_only, rel=0.05)
    assert floor["pos_rms_mm"] >= noise_only  # the fitted parameters only add
    final = result.report["final"]["validation"]["pos_rms_mm"]
    assert 0.85 < final / floor["pos_rms_mm"] < 1.15, (final, floor)
    assert floor["ratio"] == pytest.approx(final / floor["pos_rms_mm"])
    assert "consistent with noise" in result.report["unexplained"]


def test_an_error_above_the_floor_is_not_called_noise(demo_cell):
    """20 um of noise per coordinate, stated as the tracker's specification, and a robot whose
    geometry is wrong while no effect may take it up: the verdict states the excess in mm."""
    run = simulate(
        demo_cell, make_scenario("static-poses", {"poses": "400", "geometric_errors": "true"}), 5
    )
    spec = TrackerUncertainty(20.0, 0.0, assumed=False)
    result = analyze(
        demo_cell.robot, _data(run, run.tracker.p), False, candidates=(), uncertainty=spec
    )
    floor = result.report["floor"]
    assert floor["source"].startswith("tracker specification 20 um + 0 um/m")
    # 20 um per coordinate: 34.6 um RMS of the 3D norm, plus the registration's share
    assert floor["pos_rms_mm"] == pytest.approx(0.0346, rel=0.05)
    final = result.report["final"]["validation"]["pos_rms_mm"]
    assert final > 3 * floor["pos_rms_mm"]
    text = result.report["unexplained"]
    assert "consistent with noise" not in text
    excess = np.sqrt(final**2 - floor["pos_rms_mm"] ** 2)
    assert f"{excess:.4f} mm" in text
    assert f"{final / floor['pos_rms_mm']:.2f}x the floor" in text


def test_the_default_uncertainty_is_marked_assumed(demo_cell):
    run = _clean_run(demo_cell, poses=300)
    result = analyze(demo_cell.robot, _data(run, run.tracker.p), False, candidates=())
    floor = result.report["floor"]
    assert floor["assumed"]
    assert "assumed" in floor["source"]
    assert "15 um + 6 um/m" in floor["source"]
    assert "15 um + 6 um/m, assumed" in result.report["unexplained"]
    # 15 um + 6 um/m x the distance from the tracker, per coordinate, at the held-out poses
    _train, val = split(run.tracker.p.shape[0])
    d = np.linalg.norm(run.tracker.p[val], axis=1)
    expected = float(np.sqrt(np.mean(3 * ((15 + 6 * d) * 1e-3) ** 2)))
    assert floor["pos_rms_mm"] == pytest.approx(expected, rel=0.05)


def test_repeatability_is_a_floor_only_for_repeated_stops(demo_cell):
    """Every pose measured twice: as stop-and-measure data the scatter is the repeatability
    and the floor; the same rows labelled as motion are angles passed twice, reported with
    what was found and not used."""
    run = _clean_run(demo_cell, poses=200)
    rng = np.random.default_rng(4)
    twice = np.repeat(np.arange(200), 2)
    p = run.tracker.p[twice] + 25e-6 * rng.standard_normal((400, 3))
    R = Rotation.from_quat(run.tracker.quat, scalar_first=True).as_matrix()[twice]
    q = run.encoder.q[twice]
    t = np.arange(400.0)
    static = Data(q, p, R, t, {}, approach_directions(q))
    result = analyze(demo_cell.robot, static, False, candidates=())
    rep = result.report["repeatability"]
    assert rep["used_as_floor"]
    assert rep["poses"] == 200
    # the scatter of two measurements about their mean: 25 um per coordinate -> 43 um 3D
    assert rep["rms_mm"] == pytest.approx(0.0433, rel=0.1)
    assert result.report["floor"]["source"].startswith("repeatability")
    moving = Data(q, p, R, t, {}, approach_directions(q), np.full(q.shape, 0.1))
    result = analyze(demo_cell.robot, moving, False, candidates=())
    rep = result.report["repeatability"]
    assert not rep["used_as_floor"]
    assert "not repeats of one commanded pose" in rep["note"]
    assert not result.report["floor"]["source"].startswith("repeatability")


def test_iso_9283_pose_and_path_figures_by_hand():
    # two poses measured three times each (mm): the barycentres and distances by hand
    pts = np.array([[0, 0, 0], [2, 0, 0], [1, 3, 0], [10, 0, 0], [10, 4, 0], [10, 2, 0]]) * 1e-3
    groups = np.array([0, 0, 0, 1, 1, 1])
    resid = np.zeros((6, 3))
    resid[:3] = [1e-3, 0, 0]  # the model misses pose 0 by 1 mm in x
    resid[3:] = [[0, 0, 1e-3], [0, 0, 3e-3], [0, 0, 2e-3]]  # pose 1 by 2 mm in z on average
    fig = iso_pose_figures(groups, pts, {"before": resid, "after": resid * 0.5})
    assert fig is not None
    assert fig["poses"] == 2
    assert fig["AP_mm"]["before"]["mean"] == pytest.approx(1.5)
    assert fig["AP_mm"]["before"]["max"] == pytest.approx(2.0)
    assert fig["AP_mm"]["after"]["max"] == pytest.approx(1.0)
    # pose 0: barycentre (1, 1, 0), distances sqrt2, sqrt2, 2; pose 1: (10, 2, 0): 2, 2, 0
    l0 = np.array([np.sqrt(2), np.sqrt(2), 2.0])
    l1 = np.array([2.0, 2.0, 0.0])
    rp = [lv.mean() + 3 * np.std(lv, ddof=1) for lv in (l0, l1)]
    assert fig["RP_mm"]["max"] == pytest.approx(max(rp))
    assert fig["RP_mm"]["mean"] == pytest.approx(np.mean(rp))
    assert iso_pose_figures(np.full(6, -1), pts, {"before": resid}) is None
    path = iso_path_figures({"before": resid, "after": resid * 0.5})
    assert path["AT_mm"] == {"before": pytest.approx(3.0), "after": pytest.approx(1.5)}
