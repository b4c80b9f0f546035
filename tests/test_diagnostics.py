"""Repeatability and the words for what the poses cannot separate, on constructed data."""

from __future__ import annotations

import numpy as np

from keo_service.fit.diagnostics import describe_null_space, repeatability, residual_components


def test_repeatability_of_repeated_poses_matches_the_injected_noise():
    rng = np.random.default_rng(4)
    sigma = 10e-6  # per axis, metres
    poses = rng.uniform(-2, 2, size=(300, 6))
    q = np.repeat(poses, 4, axis=0) + rng.normal(0, 2e-5, size=(1200, 6))  # encoder jitter
    truth = rng.uniform(-1, 1, size=(300, 3))
    p = np.repeat(truth, 4, axis=0) + rng.normal(0, sigma, size=(1200, 3))
    # poses visited once do not count, whatever their scatter
    q = np.vstack([q, rng.uniform(-2, 2, size=(200, 6))])
    p = np.vstack([p, rng.uniform(-1, 1, size=(200, 3))])
    rep = repeatability(q, p)
    assert rep is not None
    # 3-D distance from the pose's mean, dof-corrected: sqrt(3) sigma
    assert abs(rep.rms_mm - np.sqrt(3) * sigma * 1e3) < 0.05 * np.sqrt(3) * sigma * 1e3
    assert rep.measurements == 1200
    assert rep.poses == 300
    assert rep.left_out == 0


def test_a_pose_measured_far_apart_is_no_repeat():
    """Equal joint readings 2 mm apart (seen in the UR10 data) would dominate the RMS."""
    rng = np.random.default_rng(6)
    poses = rng.uniform(-2, 2, size=(50, 6))
    q = np.repeat(poses, 2, axis=0)
    p = np.repeat(rng.uniform(-1, 1, size=(50, 3)), 2, axis=0) + rng.normal(0, 10e-6, (100, 3))
    p[1] += [0.002, 0.0, 0.0]  # the first pose's second measurement: 2 mm off
    rep = repeatability(q, p)
    assert rep is not None
    assert rep.left_out == 1
    assert rep.poses == 49
    assert abs(rep.rms_mm - np.sqrt(3) * 0.010) < 0.25 * np.sqrt(3) * 0.010


def test_no_repeated_pose_no_repeatability():
    rng = np.random.default_rng(5)
    assert repeatability(rng.uniform(-2, 2, size=(100, 6)), rng.normal(size=(100, 3))) is None


def test_null_space_in_words():
    labels = ["joint_1 link x", "joint_2 link x", "joint_2 link z"]
    null = np.array([[1.0, 0.0], [-0.98, 0.0], [0.0, 1.0]])
    null = null / np.linalg.norm(null, axis=0)
    words = describe_null_space(null, labels)
    coupled = next(w for w in words if len(w["members"]) == 2)
    alone = next(w for w in words if len(w["members"]) == 1)
    assert [m["parameter"] for m in coupled["members"]] == ["joint_1 link x", "joint_2 link x"]
    assert abs(coupled["members"][1]["weight"] + 0.98) < 1e-12
    assert "coupled" in coupled["text"]
    assert "+1.00 x joint_1 link x -0.98 x joint_2 link x" in coupled["text"]
    assert alone["members"] == [{"parameter": "joint_2 link z", "weight": 1.0}]
    assert "not identifiable" in alone["text"]


def test_a_mixed_null_basis_is_put_back_into_few_parameters_each():
    """SVD returns any rotation of the unseen directions; the words must not depend on it."""
    labels = [f"p{i}" for i in range(5)]
    clean = np.array([[1.0, 0, 0, 0, 0], [0, 1.0, -0.5, 0, 0]]).T  # p0 alone; p1 with p2
    rotation = np.array([[0.6, -0.8], [0.8, 0.6]])
    words = describe_null_space(clean @ rotation, labels)
    members = sorted(sorted(m["parameter"] for m in w["members"]) for w in words)
    assert members == [["p0"], ["p1", "p2"]]


def test_residual_components_are_signed_rms_per_axis():
    r = np.array([[1.0, -2.0, 0.0], [-1.0, 2.0, 0.0]])
    assert residual_components(r) == {"x": 1.0, "y": 2.0, "z": 0.0}
