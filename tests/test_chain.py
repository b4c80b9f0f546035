"""The vectorised chain and rotations that `keo analyze` fits with, against Pinocchio and
scipy one pose at a time (independent implementations)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pinocchio as pin
import pytest
from scipy.spatial.transform import Rotation

from keo_service.core.chain import Chain
from keo_service.core.kinematics import flange_pose, load_robot
from keo_service.core.model_corrections import ModelCorrections
from keo_service.core.rotations import log3_many
from keo_service.fit.analysis import EFFECTS, ROT_WEIGHT, Data, Model
from tests.conftest import CONFIGS


def _robot(urdf: str):
    return load_robot(CONFIGS / "robots" / urdf, "base_link", "tool0")


def _poses(robot, n, seed):
    rng = np.random.default_rng(seed)
    lower = np.maximum(robot.lower, -2 * np.pi)
    upper = np.minimum(robot.upper, 2 * np.pi)
    return rng.uniform(lower, upper, size=(n, robot.nq)), rng


def _corrections(nq, rng):
    """Every joint-angle effect and a geometry error on every joint, at sizes a real arm has."""
    corr = ModelCorrections(nq=nq)
    return dataclasses.replace(
        corr,
        joint_offsets=rng.normal(0, 1e-3, nq),
        compliance=rng.normal(0, 2e-6, nq),
        backlash=rng.normal(0, 2e-4, nq),
        cyclic=rng.normal(0, 1e-4, (nq, 2, 2)),
        placement=rng.normal(0, 1e-3, (nq, 6)),
    )


def _pinocchio_with_geometry(robot, placement):
    """A copy of the robot's model with each joint placement M_j -> M_j exp6(delta_j)."""
    model = robot.model.copy()
    for j in range(1, model.njoints):
        d = placement[j - 1]
        model.jointPlacements[j] = model.jointPlacements[j] * pin.exp6(pin.Motion(d[:3], d[3:]))
    return dataclasses.replace(robot, model=model)


@pytest.mark.parametrize("urdf", ["mh180.urdf", "ur10.urdf"])
def test_corrected_flange_frames_equal_pinocchio_on_the_corrected_model(urdf):
    robot = _robot(urdf)
    q, rng = _poses(robot, 500, seed=11)
    corr = _corrections(robot.nq, rng)
    chain = Chain(robot)
    tau = chain.gravity_torques(q)
    direction = rng.choice([-1.0, 0.0, 1.0], size=q.shape)
    tail = pin.SE3(pin.exp3(np.array([0.1, -0.2, 0.3])), np.array([0.01, 0.02, 0.15]))
    R, p = chain.flange_frames(q, tail=tail.homogeneous, corr=corr, tau=tau, direction=direction)
    poses = chain.flange_poses(q, corr, tau, direction)

    bent = _pinocchio_with_geometry(robot, corr.placement)
    data = bent.create_data()
    q_eff = corr.joint_angles(q, tau, direction)
    for k in range(q.shape[0]):
        T = flange_pose(bent, data, q_eff[k])
        assert np.max(np.abs(poses[k] - T.homogeneous)) < 1e-12
        T = T * tail
        assert np.max(np.abs(R[:, :, k] - T.rotation)) < 1e-12
        assert np.max(np.abs(p[:, k] - T.translation)) < 1e-12


def test_uncorrected_flange_frames_are_the_nominal_chain():
    robot = _robot("ur10.urdf")
    q, _rng = _poses(robot, 200, seed=2)
    chain = Chain(robot)
    R, p = chain.flange_frames(q, corr=ModelCorrections(nq=robot.nq))
    data = robot.create_data()
    for k in range(q.shape[0]):
        T = flange_pose(robot, data, q[k])
        assert np.max(np.abs(R[:, :, k] - T.rotation)) < 1e-12
        assert np.max(np.abs(p[:, k] - T.translation)) < 1e-12


def test_log3_many_equals_scipy_from_tiny_angles_to_a_half_turn():
    rng = np.random.default_rng(5)
    axes = rng.normal(size=(4000, 3))
    axes /= np.linalg.norm(axes, axis=1)[:, None]
    angles = np.concatenate(
        [
            np.zeros(10),
            10.0 ** rng.uniform(-12, -3, 1000),  # the errors keo sees
            rng.uniform(1e-3, 2.5, 1990),
            rng.uniform(2.5, np.pi - 1e-9, 1000),  # the far branch
        ]
    )
    rotvec = axes * angles[:, None]
    matrices = Rotation.from_rotvec(rotvec).as_matrix()
    got = log3_many(np.ascontiguousarray(matrices.transpose(1, 2, 0)))
    assert np.max(np.abs(got - rotvec)) < 1e-9
    small = angles < 1e-3
    # near zero the error is relative to the angle (what a sub-microradian fit relies on)
    rel = np.linalg.norm(got[small] - rotvec[small], axis=1) / np.maximum(angles[small], 1e-300)
    assert np.max(rel[angles[small] > 0]) < 1e-9
    assert np.all(got[angles == 0] == 0.0)


def test_analysis_residuals_equal_a_pose_by_pose_reference():
    """Model.residuals with every effect and a 6-DoF probe, against Pinocchio and scipy pose
    by pose: position in the base frame, then ROT_WEIGHT x the rotation vector of
    R_meas^T R_pred."""
    robot = _robot("mh180.urdf")
    q, rng = _poses(robot, 300, seed=21)
    chain = Chain(robot)
    tau = chain.gravity_torques(q)
    direction = rng.choice([-1.0, 1.0], size=q.shape)
    names = ["joint_offsets", "geometry", "compliance", "backlash", "cyclic"]
    model = Model(chain, False, [EFFECTS[n] for n in names], np.zeros(0))
    corr = _corrections(robot.nq, rng)
    reg = np.concatenate([[1.5, -0.4, 0.2], [0.1, 0.2, -2.5], [0.01, -0.02, 0.2], [0.3, -0.1, 0.2]])
    x = np.concatenate(
        [
            reg,
            corr.joint_offsets,
            corr.placement.ravel(),
            corr.compliance,
            corr.backlash,
            corr.cyclic.ravel(),
        ]
    )
    T_bk = pin.SE3(Rotation.from_rotvec(reg[3:6]).as_matrix(), reg[:3])
    T_ns = pin.SE3(Rotation.from_rotvec(reg[9:12]).as_matrix(), reg[6:9])
    # measurements: the true sensor pose seen from the tracker, plus a small error
    bent = _pinocchio_with_geometry(robot, corr.placement)
    pdata = bent.create_data()
    q_eff = corr.joint_angles(q, tau, direction)
    T_bs = [flange_pose(bent, pdata, qk) * T_ns for qk in q_eff]
    wobble = [pin.SE3(pin.exp3(rng.normal(0, 1e-4, 3)), rng.normal(0, 1e-4, 3)) for _ in q]
    T_ks = [T_bk.inverse() * T * w for T, w in zip(T_bs, wobble, strict=True)]
    data = Data(
        q,
        np.array([T.translation for T in T_ks]),
        np.array([T.rotation for T in T_ks]),
        np.arange(q.shape[0], dtype=float),
        {},
        direction,
    )
    got = model.residuals(x, data, tau).reshape(-1, 6)
    for k in range(q.shape[0]):
        T_meas = T_bk * T_ks[k]
        assert np.max(np.abs(got[k, :3] - (T_bs[k].translation - T_meas.translation))) < 1e-12
        rot = Rotation.from_matrix(T_meas.rotation.T @ T_bs[k].rotation).as_rotvec()
        assert np.max(np.abs(got[k, 3:] - ROT_WEIGHT * rot)) < 1e-12


def test_residuals_reuse_the_chain_only_while_corrections_and_data_stay(monkeypatch):
    """Moving a registration parameter (what a finite-difference Jacobian does first) reuses
    the chain; a changed correction or other data recomputes it; the values are always those
    of a model without any history."""
    robot = _robot("ur10.urdf")
    q, rng = _poses(robot, 200, seed=8)
    chain = Chain(robot)
    tau = chain.gravity_torques(q)
    R_ks = Rotation.from_rotvec(rng.normal(0, 0.3, (q.shape[0], 3))).as_matrix()
    data = Data(q, rng.normal(0, 1, (q.shape[0], 3)), R_ks, np.arange(q.shape[0], dtype=float))
    other = data.subset(np.arange(0, q.shape[0], 2))
    tau_other = tau[::2]
    x = np.concatenate([rng.normal(0, 0.1, 12), rng.normal(0, 1e-3, robot.nq)])
    calls = []
    evaluate = chain.flange_frames

    def counted(*args, **kwargs):
        calls.append(1)
        return evaluate(*args, **kwargs)

    monkeypatch.setattr(chain, "flange_frames", counted)
    model = Model(chain, False, [EFFECTS["joint_offsets"]], x)

    def fresh(x_now, d, t):
        return Model(chain, False, [EFFECTS["joint_offsets"]], x_now).residuals(x_now, d, t)

    steps = []
    for k in range(12):  # the registration, one parameter at a time
        xk = x.copy()
        xk[k] += 1e-6
        steps.append((xk, data, tau))
    moved = x.copy()
    moved[12] += 1e-4  # a joint offset: the chain changes
    steps += [(moved, data, tau), (moved, other, tau_other), (x, data, tau)]
    for xk, d, t in [(x, data, tau), *steps]:
        got = model.residuals(xk, d, t)
        np.testing.assert_array_equal(got, fresh(xk, d, t))
    # 1 for x, 0 for the 12 registration steps, 1 each for the offset, other data, back
    # (and 1 for each fresh model)
    assert len(calls) == 4 + 1 + len(steps)
