"""Whose angle error is it: the maps' variance inflation tells poses that separate two joints'
angle errors from poses that cannot (docs/analyze.md, "What A's data determine")."""

from __future__ import annotations

import numpy as np

from keo_service.fit.angle_maps import _Linearized, knots_for, variance_inflation

POSES = 2000
WIDTH = 6
REGISTRATION = 6


def _linearized(coupled_angles: bool, same_effect: bool, seed: int = 3):
    """Two joints' residual derivatives and a registration Jacobian, all random (about a
    metre per radian), with joint 2's angle equal to joint 1's (`coupled_angles`) and its
    derivative equal to joint 1's (`same_effect`: an angle error of either moves the sensor
    the same way, as two parallel axes through the same point would)."""
    rng = np.random.default_rng(seed)
    q1 = rng.uniform(0.0, 2.0, POSES)
    q2 = q1.copy() if coupled_angles else rng.uniform(0.0, 2.0, POSES)
    g1 = rng.normal(size=(POSES, WIDTH))
    g2 = g1.copy() if same_effect else rng.normal(size=(POSES, WIDTH))
    J = rng.normal(size=(POSES * WIDTH, REGISTRATION)) * 0.1
    lin = _Linearized(np.zeros((POSES, WIDTH)), [g1, g2], J)
    q = np.column_stack([q1, q2])
    return lin, q, knots_for(q, 0.05)


def test_joints_that_move_apart_are_not_inflated():
    lin, q, knots = _linearized(coupled_angles=False, same_effect=False)
    inflation = variance_inflation(lin, q, knots, 1.0, REGISTRATION)
    assert all(v is not None and 1.0 - 1e-9 <= v < 1.1 for v in inflation), inflation


def test_joints_moved_together_with_the_same_effect_cannot_be_told_apart():
    lin, q, knots = _linearized(coupled_angles=True, same_effect=True)
    inflation = variance_inflation(lin, q, knots, 1.0, REGISTRATION)
    # any map on joint 1 is matched exactly by its negative on joint 2: only the smoothing
    # holds the split, so each value's variance grows far beyond the one-joint figure
    assert all(v is not None and v > 50.0 for v in inflation), inflation


def test_moving_together_alone_does_not_confound_where_the_errors_show_differently():
    lin, q, knots = _linearized(coupled_angles=True, same_effect=False)
    inflation = variance_inflation(lin, q, knots, 1.0, REGISTRATION)
    assert all(v is not None and v < 1.1 for v in inflation), inflation


def test_a_joint_without_a_map_has_no_figure():
    lin, q, knots = _linearized(coupled_angles=False, same_effect=False)
    knots = (knots[0], np.empty(0))
    inflation = variance_inflation(lin, q, knots, 1.0, REGISTRATION)
    assert inflation[1] is None
    assert inflation[0] is not None
