"""Issue 45 (review): every live estimate message carries the tool's speed (`tool_speed_m_s`),
as `keo analyze` does offline. Judged against the speed of a simulated motion at constant
joint velocity, from the robot's Jacobian (pinocchio's, at the flange, with the tool's lever
arm): an independent computation of what the service takes from the forward kinematics."""

from __future__ import annotations

import numpy as np
import pinocchio as pin
import pytest

from keo_service.core.estimator import Estimate
from keo_service.core.tool_speed import ToolSpeed


def _analytic_speed(cell, q, qdot):
    """|v_tool| = |J_v qdot + (J_w qdot) x (p_tool - p_flange)| in the base frame."""
    robot = cell.robot
    model, data = robot.model, robot.model.createData()
    pin.computeJointJacobians(model, data, q)
    pin.framesForwardKinematics(model, data, q)
    fid = robot.flange_frame_id
    J = pin.getFrameJacobian(model, data, fid, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED)
    v, w = J[:3] @ qdot, J[3:] @ qdot
    T_of = data.oMf[fid]
    lever = T_of.rotation @ cell.T_nt.translation
    # the base frame is the world frame rotated (or the same): a speed does not change
    return float(np.linalg.norm(v + np.cross(w, lever)))


def _estimate(t, q):
    return Estimate(t, [0.0] * 3, [0.0] * 3, (), t - 0.03, ("px", "py", "pz"), q)


@pytest.mark.parametrize("rate_hz", [100.0, 1000.0])
def test_the_speed_of_a_constant_joint_velocity_motion(demo_cell, rate_hz):
    """Six joints at constant velocities (0.05-0.2 rad/s), estimates at the tracker's rate,
    the speed sampled every 0.1 s as the status cycle does: within 1 % of the Jacobian's."""
    nq = demo_cell.robot.model.nq
    q0 = np.array([0.3, -0.4, 0.5, 0.2, -0.6, 0.4])[:nq]
    qdot = np.array([0.2, -0.1, 0.15, 0.05, 0.1, -0.2])[:nq]
    speed = ToolSpeed(demo_cell)
    checked = 0
    for k in range(int(3.0 * rate_hz)):
        t = 10.0 + k / rate_hz
        est = _estimate(t, q0 + qdot * (t - 10.0))
        if k % int(0.1 * rate_hz) == 0:
            speed.sample(est)
        got = speed.at(t)
        if k > 0.25 * rate_hz:
            # the speed over the newest step (<= 0.1 s before): the analytic speed there
            assert got is not None
            lo = _analytic_speed(demo_cell, q0 + qdot * (t - 10.2), qdot)
            hi = _analytic_speed(demo_cell, q0 + qdot * (t - 10.0), qdot)
            assert min(lo, hi) * 0.99 <= got <= max(lo, hi) * 1.01, (t, got, lo, hi)
            checked += 1
    assert checked > 2.5 * rate_hz
    assert speed.speed is not None
    assert speed.speed > 0.05  # the motion is not a crawl


def test_no_speed_before_two_estimates_after_a_pause_or_when_stale(demo_cell):
    nq = demo_cell.robot.model.nq
    q = np.full(nq, 0.2)
    speed = ToolSpeed(demo_cell)
    speed.sample(None)
    speed.sample(_estimate(1.0, q))
    assert speed.at(1.0) is None  # one point is no speed
    speed.sample(_estimate(1.1, q + 0.01))
    assert speed.at(1.1) is not None
    assert speed.at(5.0) is None  # a speed from 4 s before is not the tool's now
    speed.sample(_estimate(9.0, q + 0.5))  # a pause: a chord over 8 s is no speed
    assert speed.at(9.0) is None
    held = Estimate(9.2, None, [0.0] * 3, ("encoder_stale",), None, ("px", "py", "pz"), None)
    speed.sample(held)  # a held step has no joints
    assert speed.at(9.2) is None
