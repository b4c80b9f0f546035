"""Robot models: Pinocchio FK against independent numpy versions of the published geometry."""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import pytest

from keo_service.core.kinematics import flange_pose, load_robot
from tests.conftest import CONFIGS


def rot(axis: str, a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    m = {
        "x": [[1, 0, 0], [0, c, -s], [0, s, c]],
        "y": [[c, 0, s], [0, 1, 0], [-s, 0, c]],
        "z": [[c, -s, 0], [s, c, 0], [0, 0, 1]],
    }[axis]
    T = np.eye(4)
    T[:3, :3] = m
    return T


def trans(x: float, y: float, z: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = [x, y, z]
    return T


def mh180_numpy(q: np.ndarray) -> np.ndarray:
    """docs/design.md §7 joint table, written out by hand."""
    T = trans(0, 0, 0.650) @ rot("z", q[0])
    T = T @ trans(0.325, 0, 0) @ rot("y", q[1])
    T = T @ trans(0, 0, 1.150) @ rot("y", -q[2])
    T = T @ trans(0, 0, 0.300) @ rot("x", -q[3])
    T = T @ trans(1.225, 0, 0) @ rot("y", -q[4])
    T = T @ trans(0.225, 0, 0) @ rot("x", -q[5])
    # tool0: rpy (pi, -pi/2, 0) = Rz(0) Ry(-pi/2) Rx(pi)
    return T @ rot("y", -math.pi / 2) @ rot("x", math.pi)


UR10_DH = [
    (0.0, 0.1273, math.pi / 2),
    (-0.612, 0.0, 0.0),
    (-0.5723, 0.0, 0.0),
    (0.0, 0.163941, math.pi / 2),
    (0.0, 0.1157, -math.pi / 2),
    (0.0, 0.0922, 0.0),
]


def ur10_numpy(q: np.ndarray) -> np.ndarray:
    """Rz(180 deg) * prod DH(a, alpha, d, q): standard DH, Rz(theta) Tz(d) Tx(a) Rx(alpha)."""
    T = rot("z", math.pi)
    for (a, d, alpha), qi in zip(UR10_DH, q, strict=True):
        T = T @ rot("z", qi) @ trans(0, 0, d) @ trans(a, 0, 0) @ rot("x", alpha)
    return T


@pytest.mark.parametrize(
    ("urdf", "reference"), [("mh180.urdf", mh180_numpy), ("ur10.urdf", ur10_numpy)]
)
def test_fk_matches_published_geometry(urdf, reference):
    robot = load_robot(CONFIGS / "robots" / urdf)
    data = robot.create_data()
    rng = np.random.default_rng(42)
    for _ in range(1000):
        q = rng.uniform(robot.lower, robot.upper)
        T = flange_pose(robot, data, q)
        ref = reference(q)
        assert np.max(np.abs(T.translation - ref[:3, 3])) < 1e-9
        dR = T.rotation.T @ ref[:3, :3]
        assert np.linalg.norm(pin.log3(dR)) < 1e-9


def test_mh180_zero_pose_matches_design():
    robot = load_robot(CONFIGS / "robots" / "mh180.urdf")
    T = flange_pose(robot, robot.create_data(), np.zeros(6))
    assert np.allclose(
        T.translation, [0.325 + 1.225 + 0.225, 0.0, 0.650 + 1.150 + 0.300], atol=1e-12
    )
    assert np.allclose(T.rotation[:, 0], [0, 0, 1], atol=1e-12)  # X up
    assert np.allclose(T.rotation[:, 2], [1, 0, 0], atol=1e-12)  # Z out of the flange


def _wrist_centre_radius(robot, data, q):
    pin.forwardKinematics(robot.model, data, q)
    b_axis = robot.model.getJointId("joint_5_b")
    p = data.oMi[b_axis].translation
    return math.hypot(p[0], p[1])


def test_mh180_reach_is_2702_mm():
    robot = load_robot(CONFIGS / "robots" / "mh180.urdf")
    data = robot.create_data()
    limit_l = float(robot.upper[1])
    assert limit_l == pytest.approx(math.radians(76), abs=1e-12)
    forearm_tilt = math.atan2(0.300, 1.225)
    q = np.array([0.3, limit_l, limit_l - forearm_tilt, 0.0, 0.0, 0.0])
    expected = 0.325 + 1.150 * math.sin(limit_l) + math.hypot(1.225, 0.300)
    assert expected == pytest.approx(2.702, abs=5e-4)
    assert _wrist_centre_radius(robot, data, q) == pytest.approx(expected, abs=1e-9)
    assert np.all(q >= robot.lower)
    assert np.all(q <= robot.upper)
    rng = np.random.default_rng(1)
    radii = [
        _wrist_centre_radius(robot, data, rng.uniform(robot.lower, robot.upper))
        for _ in range(5000)
    ]
    assert max(radii) <= expected + 1e-9


@pytest.mark.parametrize("urdf", ["mh180.urdf", "ur10.urdf"])
def test_models_have_limits_and_inertia_for_gravity_torques(urdf):
    robot = load_robot(CONFIGS / "robots" / urdf)
    assert robot.nq == 6
    assert np.all(robot.upper > robot.lower)
    assert np.all(robot.velocity_limit > 0)
    assert all(inertia.mass > 0 for inertia in list(robot.model.inertias)[1:])
    data = robot.create_data()
    tau = pin.computeGeneralizedGravity(robot.model, data, np.array([0, 0.3, 0.2, 0, 0.4, 0]))
    assert np.all(np.isfinite(tau))
    assert abs(tau[1]) > 1.0
