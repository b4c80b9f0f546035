"""The measured error e_m: log map accuracy and exact recovery of known perturbations."""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from keo_service.core.kinematics import (
    Cell,
    fold_frames,
    log3,
    measured_error,
    measured_error_folded,
    quat_wxyz,
    se3_from_xyz_quat,
    tool_pose,
)

unit = st.lists(st.floats(-1, 1), min_size=3, max_size=3).filter(lambda v: np.linalg.norm(v) > 0.1)
angles = st.floats(0.0, math.pi - 1e-6)


def rotation(axis, angle) -> np.ndarray:
    axis = np.asarray(axis) / np.linalg.norm(axis)
    return np.asarray(pin.exp3(axis * angle))


@given(unit, angles)
def test_exp_log_roundtrip(axis, angle):
    R = rotation(axis, angle)
    assert np.allclose(pin.exp3(log3(R)), R, atol=1e-14)


@given(unit)
def test_log_accurate_near_zero_and_pi(axis):
    axis = np.asarray(axis) / np.linalg.norm(axis)
    for angle in (1e-9, math.pi - 1e-9):
        w = axis * angle
        R = Rotation.from_rotvec(w).as_matrix()  # an independent exp
        got = log3(R)
        if angle > 3:  # at pi the sign of the axis is not defined by R; choose w's
            got = got if got @ w > 0 else -got
        assert np.linalg.norm(got - w) <= 1e-12 * angle


poses = st.tuples(
    st.lists(st.floats(-0.01, 0.01), min_size=3, max_size=3),
    st.lists(st.floats(-0.02, 0.02), min_size=3, max_size=3),
)


def joints(seed: int, cell: Cell) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform(cell.robot.lower, cell.robot.upper)


def homogeneous(T: pin.SE3) -> np.ndarray:
    return np.asarray(T.homogeneous)


@settings(max_examples=200, deadline=None)
@given(poses, st.integers(0, 10_000))
def test_known_tool_perturbation_is_recovered(demo_cell, perturbation, seed):
    p_err, r_err = (np.asarray(v) for v in perturbation)
    q = joints(seed, demo_cell)
    data = demo_cell.robot.create_data()
    T_bt = tool_pose(demo_cell, data, q)
    T_bs = T_bt * pin.SE3(Rotation.from_rotvec(r_err).as_matrix(), p_err)
    T_ks = demo_cell.T_bk.inverse() * T_bs
    e = measured_error(demo_cell, data, q, T_ks.translation, quat_wxyz(T_ks.rotation))
    assert np.allclose(e[:3], p_err, atol=1e-12)
    assert np.allclose(e[3:], r_err, atol=1e-12)


@settings(max_examples=200, deadline=None)
@given(poses, st.integers(0, 10_000))
def test_registration_change_moves_error_as_predicted(demo_cell, change, seed):
    """With tracker data fixed, T_bk -> T_bk D gives T_ts' = T_bt^-1 T_bk D T_ks (numpy)."""
    q = joints(seed, demo_cell)
    data = demo_cell.robot.create_data()
    T_bt = tool_pose(demo_cell, data, q)
    T_ks = (
        demo_cell.T_bk.inverse()
        * T_bt
        * pin.SE3(
            Rotation.from_rotvec([1e-3, -2e-3, 5e-4]).as_matrix(), np.array([1e-3, 2e-3, -1e-3])
        )
    )
    D = pin.SE3(Rotation.from_rotvec(change[1]).as_matrix(), np.asarray(change[0]))
    moved = Cell(robot=demo_cell.robot, T_nt=demo_cell.T_nt, T_bk=demo_cell.T_bk * D)
    e = measured_error(moved, data, q, T_ks.translation, quat_wxyz(T_ks.rotation))
    M = (
        np.linalg.inv(homogeneous(T_bt))
        @ homogeneous(demo_cell.T_bk)
        @ homogeneous(D)
        @ homogeneous(T_ks)
    )
    assert np.allclose(e[:3], M[:3, 3], atol=1e-11)
    assert np.allclose(e[3:], Rotation.from_matrix(M[:3, :3]).as_rotvec(), atol=1e-11)


def test_position_only_error_is_reflector_in_tool_frame(demo_cell):
    q = joints(3, demo_cell)
    data = demo_cell.robot.create_data()
    T_bt = tool_pose(demo_cell, data, q)
    offset = np.array([1e-3, -0.5e-3, 2e-3])
    p_bs = T_bt.act(offset)
    p_ks = demo_cell.T_bk.actInv(p_bs)
    e = measured_error(demo_cell, data, q, p_ks, None)
    assert e.shape == (3,)
    assert np.allclose(e, offset, atol=1e-12)


@given(
    st.lists(st.floats(-10, 10), min_size=4, max_size=4).filter(
        lambda q: math.sqrt(sum(v * v for v in q)) > 1e-3
    ),
    st.lists(st.floats(-5, 5), min_size=3, max_size=3),
)
def test_pose_from_position_and_quaternion_matches_scipy(q_wxyz, p):
    """Scalar-first wire order, any scale (normalised), against scipy's scalar-last rotation."""
    w, x, y, z = q_wxyz
    expected = Rotation.from_quat([x, y, z, w]).as_matrix()
    pose = se3_from_xyz_quat(p, q_wxyz)
    assert np.allclose(pose.rotation, expected, atol=1e-12)
    assert np.allclose(pose.translation, p, atol=0)


def test_folded_measured_error_equals_the_frame_by_frame_one(demo_cell):
    """The hot path's measured error (constant frames folded into the model, the rotation
    vector from a quaternion) against the definition evaluated frame by frame with Pinocchio,
    its rotation vector from scipy; for poses, half turns included, and a single reflector."""
    frames = fold_frames(demo_cell)
    assert frames is not None
    model, data = demo_cell.robot.model, frames.model.createData()
    rng = np.random.default_rng(3)
    for k in range(300):
        q = pin.randomConfiguration(model)
        T_bt = tool_pose(demo_cell, demo_cell.robot.create_data(), q)
        p = rng.uniform(-2.0, 2.0, 3)
        if k % 3 == 0:  # the sensor turned 3.1-pi rad from the nominal tool
            axis = rng.normal(size=3)
            angle = rng.uniform(3.1, math.pi)
            R_bs = (
                T_bt.rotation
                @ Rotation.from_rotvec(angle * axis / np.linalg.norm(axis)).as_matrix()
            )
            R_ks = demo_cell.T_bk.rotation.T @ R_bs
            wxyz = Rotation.from_matrix(R_ks).as_quat(scalar_first=True)
        else:
            wxyz = Rotation.random(random_state=rng).as_quat(scalar_first=True)
        sensor = [*p, wxyz[1], wxyz[2], wxyz[3], wxyz[0]]
        T_ts = T_bt.actInv(demo_cell.T_bk * se3_from_xyz_quat(p, wxyz))
        want = np.r_[T_ts.translation, Rotation.from_matrix(T_ts.rotation).as_rotvec()]
        got = np.array(measured_error_folded(frames, data, q, sensor))
        assert np.max(np.abs(got - want)) < 1e-12, (k, got, want)
        want3 = measured_error(demo_cell, demo_cell.robot.create_data(), q, p, None)
        got3 = np.array(measured_error_folded(frames, data, q, p.tolist()))
        assert np.max(np.abs(got3 - want3)) < 1e-12
