"""Joint trajectories for the simulator: functions of time returning joint angles. No I/O."""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from keo_service.core.kinematics import RobotModel, flange_pose

Trajectory = Callable[[np.ndarray], np.ndarray]  # times (n,) -> joints (n, nq)


def trapezoid_profile(t: np.ndarray, duration: float, accel_time: float) -> np.ndarray:
    """Normalized position s(t) in [0, 1]: constant acceleration, cruise, deceleration."""
    ta = min(accel_time, duration / 2.0)
    v = 1.0 / (duration - ta)  # cruise speed
    a = v / ta
    t = np.clip(t, 0.0, duration)
    s = np.where(
        t < ta,
        0.5 * a * t * t,
        np.where(
            t <= duration - ta,
            0.5 * a * ta * ta + v * (t - ta),
            1.0 - 0.5 * a * (duration - t) ** 2,
        ),
    )
    return s


@dataclass(frozen=True)
class Segment:
    start: float
    duration: float
    accel_time: float
    q0: np.ndarray
    q1: np.ndarray


def piecewise_joint_moves(segments: list[Segment], q_initial: np.ndarray) -> Trajectory:
    """Point-to-point synchronized joint moves; holds between and after them."""

    def q_of_t(times: np.ndarray) -> np.ndarray:
        times = np.asarray(times, dtype=float)
        out = np.repeat(q_initial[None, :], times.size, axis=0)
        for seg in segments:
            after = times >= seg.start
            s = trapezoid_profile(times[after] - seg.start, seg.duration, seg.accel_time)
            out[after] = seg.q0 + s[:, None] * (seg.q1 - seg.q0)
        return out

    return q_of_t


def solve_ik(
    robot: RobotModel,
    data: pin.Data,
    target: pin.SE3,
    q_guess: np.ndarray,
    tol: float = 1e-13,
    max_iter: int = 100,
) -> np.ndarray:
    """Flange pose IK by damped Gauss-Newton on log6 in the local frame (warm-started).

    The base frame is fixed, so the flange's LOCAL Jacobian serves for any base frame.
    """
    q = q_guess.copy()
    for _ in range(max_iter):
        current = flange_pose(robot, data, q)
        err = pin.log6(current.actInv(target)).vector
        if np.linalg.norm(err) < tol:
            return q
        pin.computeJointJacobians(robot.model, data, q)
        J = pin.getFrameJacobian(robot.model, data, robot.flange_frame_id, pin.LOCAL)
        JJt = J @ J.T + 1e-12 * np.eye(6)
        q = q + J.T @ np.linalg.solve(JJt, err)
    raise RuntimeError(f"IK did not converge (residual {np.linalg.norm(err):.3g})")


def cartesian_line_moves(
    robot: RobotModel,
    q_start: np.ndarray,
    waypoints: list[np.ndarray],
    speed: float,
    accel: float,
    dwell: float,
) -> tuple[Trajectory, float]:
    """Straight flange moves between position waypoints at constant orientation.

    Dwell `dwell` seconds at the start and after every move. Returns (q(t), total duration).
    """
    data = robot.create_data()
    start_pose = flange_pose(robot, data, q_start)
    rotation = start_pose.rotation.copy()
    points = [start_pose.translation.copy(), *waypoints]
    moves = []
    t = dwell
    accel_time = speed / accel
    for p0, p1 in itertools.pairwise(points):
        length = float(np.linalg.norm(p1 - p0))
        duration = length / speed + accel_time
        moves.append((t, duration, p0, p1))
        t += duration + dwell
    total = t

    def position(times: np.ndarray) -> np.ndarray:
        out = np.repeat(points[0][None, :], times.size, axis=0)
        for start, duration, p0, p1 in moves:
            after = times >= start
            s = trapezoid_profile(times[after] - start, duration, accel_time)
            out[after] = p0 + s[:, None] * (p1 - p0)
        return out

    def q_of_t(times: np.ndarray) -> np.ndarray:
        times = np.asarray(times, dtype=float)
        order = np.argsort(times, kind="stable")
        pos = position(times[order])
        out = np.empty((times.size, robot.nq))
        q = q_start.copy()
        for i, k in enumerate(order):
            q = solve_ik(robot, data, pin.SE3(rotation, pos[i]), q)
            out[k] = q
        return out

    return q_of_t, total


def sinusoid_path(
    q_center: np.ndarray, amplitude: np.ndarray, freq: np.ndarray, phase: np.ndarray
) -> Trajectory:
    """Continuous smooth motion of every joint: a sum of sinusoids (amplitude/freq (nq, k))."""

    def q_of_t(times: np.ndarray) -> np.ndarray:
        times = np.asarray(times, dtype=float)
        arg = 2 * np.pi * freq[None, :, :] * times[:, None, None] + phase[None, :, :]
        # ramp in over 1 s so the motion starts from rest
        x = np.clip(times, 0.0, 1.0)[:, None]
        ramp = x * x * (3.0 - 2.0 * x)
        q: np.ndarray = q_center + ramp * np.sum(amplitude[None, :, :] * np.sin(arg), axis=2)
        return q

    return q_of_t
