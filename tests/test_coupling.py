"""Effects across joints: a coupling injected in simulation (joint 5's angle error moving with
joint 4's angle) is proposed from the residual's correlation, found, named in words, and takes
the held-out error to the floor; data without one get none."""

from __future__ import annotations

import numpy as np
import pytest

from keo_service.core.chain import Chain
from keo_service.core.model_corrections import approach_directions
from keo_service.fit.analysis import KEEP_MARGIN, Data, analyze, split
from keo_service.fit.angle_maps import try_maps
from keo_service.fit.coupling import try_couplings
from keo_service.fit.uncertainty import TrackerUncertainty
from keo_service.sim.simulate import make_scenario, simulate

SLOPE = 3e-4  # rad of joint 5 per rad of joint 4
RIPPLE = 2e-4  # rad, a period of 1 rad of joint 4's angle
NOISE = 20e-6  # m per coordinate


def _measured(cell, coupled: bool, seed: int = 7):
    """Poses of the simulator; the tracker's positions computed here from the nominal chain
    at the angles the coupling makes (independent of keo's coupling code), plus noise."""
    scenario = make_scenario(
        "static-poses",
        {"poses": "900", "geometric_errors": "false", "position_noise_m": "0"},
    )
    run = simulate(cell, scenario, seed=seed)
    q = run.encoder.q
    q_true = q.copy()
    if coupled:
        qk = q[:, 3]
        q_true[:, 4] += SLOPE * (qk - qk.mean()) + RIPPLE * np.sin(2 * np.pi * qk / 1.0)
    T_bn = Chain(cell.robot).flange_poses(q_true)
    p_b = T_bn[:, :3, :3] @ cell.T_nt.translation + T_bn[:, :3, 3]
    R_bk, t_bk = cell.T_bk.rotation, cell.T_bk.translation
    p_k = (p_b - t_bk) @ R_bk
    rng = np.random.default_rng(seed)
    p_k = p_k + NOISE * rng.standard_normal(p_k.shape)
    return Data(q, p_k, None, run.tracker.t, {}, approach_directions(q))


def _analysed(cell, data):
    spec = TrackerUncertainty(NOISE * 1e6, 0.0, assumed=False)
    result = analyze(cell.robot, data, True, candidates=(), uncertainty=spec)
    train, val = split(data.n)
    names = cell.robot.joint_names
    try_maps(result, data, train, val, KEEP_MARGIN, names)
    try_couplings(result, data, train, val, KEEP_MARGIN, names)
    return result


def test_a_coupling_is_found_named_and_reaches_the_floor(demo_cell):
    data = _measured(demo_cell, coupled=True)
    result = _analysed(demo_cell, data)
    report = result.report
    names = demo_cell.robot.joint_names
    entry = next(e for e in report["effects"] if e["name"] == "couplings")
    rec = entry["parameters"]["records"][0]
    assert (rec["joint"], rec["with"]) == (names[4], names[3])
    # the map carries no mean and no slope over its knots (those are the offset and the
    # linear term): the slope to expect is the injected error's straight-line part there
    knots = np.array(rec["knots"])
    injected = SLOPE * knots + RIPPLE * np.sin(2 * np.pi * knots / 1.0)
    expected = np.polyfit(knots, injected, 1)[0]
    assert rec["value"] == pytest.approx(expected, abs=max(4 * rec["se"], 0.1 * SLOPE))
    assert rec["text"].startswith(f"{names[4]}'s angle moves with {names[3]}: +0.")
    assert "mrad per rad" in rec["text"]
    final = report["final"]["validation"]["pos_rms_mm"]
    assert final < 1.5 * report["floor"]["pos_rms_mm"], (final, report["floor"])
    assert entry["band_split"]["improvement_pct"] > 100 * KEEP_MARGIN


def test_the_live_estimator_applies_the_coupling_from_model_toml(demo_cell, demo_config):
    from keo_service.core.kinematics import corrected_joints
    from keo_service.io.analysis_report import model_config
    from keo_service.io.cell import cell_from_config

    data = _measured(demo_cell, coupled=True, seed=8)
    result = _analysed(demo_cell, data)
    assert "couplings" in result.model.names
    cell = cell_from_config(model_config(result, demo_config))
    assert len(cell.corrections.couplings) == 1
    _T_bk, _T_ns, corr = result.model.unpack(result.x)
    for i in range(0, data.n, 97):
        q = data.q[i]
        live = corrected_joints(cell, q, data.direction[i])
        tau = result.model.chain.gravity_torques(q[None, :])
        expected = corr.joint_angles(q[None, :], tau, data.direction[i][None, :])[0]
        assert np.max(np.abs(live - expected)) < 1e-9
        # and the coupling is in it: joint 5 moved against the uncoupled angles
        assert live[4] != pytest.approx(q[4], abs=1e-7)


def test_no_coupling_without_one(demo_cell):
    result = _analysed(demo_cell, _measured(demo_cell, coupled=False))
    assert all(e["name"] != "couplings" for e in result.report["effects"])
