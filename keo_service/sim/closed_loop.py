"""A compensated cell that knows the truth: a UR-style controller that follows a tool path
and adds the latest correction it received (as a URScript program reading RTDE input
registers does: `servoj(get_inverse_kin(pose_trans(path_pose, correction)))`), the real arm
that differs from the nominal one, and the tracker that sees where the real tool went.

The controller and the tracker share the arm: the tracker measures the joints the
controller actually turned to, so corrections move what the tracker sees. Every controller
sample logs the true tool error against the path, and what it would have been without any
correction (the same path, no correction): the numbers `keo demo --compensate` prints and the
closed-loop tests judge.
"""

from __future__ import annotations

import collections
import math
import threading
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from keo_service.core.compensation import ToolModel
from keo_service.core.kinematics import Cell, quat_wxyz
from keo_service.sim.simulate import Scenario, angle_ripple, make_true_robot, motion_for
from keo_service.sim.trajectories import solve_ik

PATH_RATE_HZ = 200.0  # the path's joints are solved on this grid, interpolated between
HISTORY = 4096  # controller samples the tracker can look back on (8 s at 500 Hz)


@dataclass
class ErrorLog:
    """Per controller sample: scenario time, |position| (m) and |rotation| (rad) of the true
    tool error against the path, with and without the correction, and the correction."""

    t: list[float]
    pos: list[float]
    rot: list[float]
    pos_uncompensated: list[float]
    rot_uncompensated: list[float]
    applied: list[bool]


class ClosedLoopCell:
    def __init__(
        self,
        cell: Cell,
        scenario: Scenario,
        seed: int = 0,
        tool_error: tuple[float, ...] | None = None,
        joint_offsets: tuple[float, ...] | None = None,
    ) -> None:
        """`tool_error`: a constant error of the real tool (x, y, z m, rotation vector rad,
        in the tool frame, T = [exp(r), p]) on top of the scenario's; `joint_offsets` (rad):
        the real arm's joint zero offsets instead of the scenario's."""
        self.cell, self.scenario = cell, scenario
        rng = np.random.default_rng(seed)
        self.true = make_true_robot(cell, rng, scenario.geometric_errors)
        if tool_error is not None:
            e = np.asarray(tool_error, dtype=float)
            self.true.T_ns = self.true.T_ns * pin.SE3(pin.exp3(e[3:]), e[:3])
        if joint_offsets is not None:
            self.true.joint_offsets = np.asarray(joint_offsets, dtype=float)
        trajectory, self.duration = motion_for(scenario, cell, rng)
        self.grid = np.arange(0.0, self.duration + 1.0, 1.0 / PATH_RATE_HZ)
        self.q_grid = trajectory(self.grid)
        self.nominal = ToolModel(cell.robot, None, cell.T_nt.homogeneous)
        self._T_kb = self.true.T_bk.inverse()
        self._T_tn = cell.T_nt.inverse()
        self._ik_data = cell.robot.create_data()
        self._noise = np.random.default_rng(seed + 1)
        self._lock = threading.Lock()
        self._history: collections.deque[tuple[float, np.ndarray]] = collections.deque(
            maxlen=HISTORY
        )
        self.log = ErrorLog([], [], [], [], [], [])
        self.loop_closed_at: float | None = None  # scenario time of the first correction

    def path_joints(self, t: float) -> np.ndarray:
        return np.array([np.interp(t, self.grid, c) for c in self.q_grid.T])

    def true_tool(self, q: np.ndarray) -> pin.SE3:
        return self.true.sensor_pose(q, angle_ripple(self.scenario, q))

    def joints(self, t: float, correction: tuple[float, ...] | None) -> np.ndarray:
        """The controller at scenario time t: the path's tool pose times the correction
        (translation m, rotation vector rad; tool frame), to joints by the nominal inverse."""
        q_path = self.path_joints(t)
        R, p = self.nominal.poses(q_path[None], identified=False)
        applied = correction is not None and any(v != 0.0 for v in correction)
        q = q_path
        if applied:
            assert correction is not None
            c = np.asarray(correction, dtype=float)
            C = pin.SE3(pin.exp3(c[3:]), c[:3])  # a UR pose: translation, rotation vector
            flange = pin.SE3(R[0], p[0]) * C * self._T_tn
            q = solve_ik(self.cell.robot, self._ik_data, flange, q_path, tol=1e-12)
            if self.loop_closed_at is None:
                self.loop_closed_at = t
        goal_pose = pin.SE3(R[0], p[0])
        err = goal_pose.actInv(self.true_tool(q))
        err0 = err if not applied else goal_pose.actInv(self.true_tool(q_path))
        with self._lock:
            self._history.append((t, q.copy()))
            log = self.log
            log.t.append(t)
            log.pos.append(float(np.linalg.norm(err.translation)))
            log.rot.append(float(np.linalg.norm(pin.log3(err.rotation))))
            log.pos_uncompensated.append(float(np.linalg.norm(err0.translation)))
            log.rot_uncompensated.append(float(np.linalg.norm(pin.log3(err0.rotation))))
            log.applied.append(applied)
        return q

    def sensor(self, stamp: float) -> tuple[np.ndarray, np.ndarray] | None:
        """The tracker's measurement stamped `stamp` (it measured `delay_s` earlier): the
        sensor position (m) and scalar-first quaternion in the tracker frame, at the joints
        the controller had then; None before the controller moved at all."""
        tau = stamp - self.scenario.delay_s
        with self._lock:
            if not self._history:
                return None
            times = np.array([h[0] for h in self._history])
            k = int(np.searchsorted(times, tau))
            if k <= 0:
                q = self._history[0][1]
            elif k >= len(times):
                q = self._history[-1][1]
            else:
                (t0, q0), (t1, q1) = self._history[k - 1], self._history[k]
                w = 0.0 if t1 <= t0 else (tau - t0) / (t1 - t0)
                q = q0 + w * (q1 - q0)
        T_ks = self._T_kb * self.true_tool(q)
        s = self.scenario
        p = T_ks.translation + self._noise.normal(0.0, s.position_noise_m, 3)
        rot = T_ks.rotation @ pin.exp3(self._noise.normal(0.0, s.rotation_noise_rad, 3))
        return p, quat_wxyz(rot)

    def series(self) -> dict[str, list[float]]:
        """The log as lists (scenario time s, error mm / mrad, compensated and not)."""
        with self._lock:
            log = self.log
            return {
                "t": list(log.t),
                "pos_mm": [v * 1e3 for v in log.pos],
                "rot_mrad": [v * 1e3 for v in log.rot],
                "pos_uncompensated_mm": [v * 1e3 for v in log.pos_uncompensated],
                "rot_uncompensated_mrad": [v * 1e3 for v in log.rot_uncompensated],
            }

    def summary(self, settle_s: float = 5.0) -> dict[str, float | None]:
        """RMS and max of the true error along the path (mm, mrad): uncompensated over the
        whole run, compensated from `settle_s` after the loop closed."""
        with self._lock:
            t = np.array(self.log.t)
            pos, rot = np.array(self.log.pos), np.array(self.log.rot)
            pos0, rot0 = np.array(self.log.pos_uncompensated), np.array(self.log.rot_uncompensated)
        out: dict[str, float | None] = {
            "uncompensated_pos_rms_mm": _rms(pos0) * 1e3,
            "uncompensated_pos_max_mm": float(pos0.max()) * 1e3 if pos0.size else math.nan,
            "uncompensated_rot_rms_mrad": _rms(rot0) * 1e3,
            "loop_closed_at_s": self.loop_closed_at,
        }
        if self.loop_closed_at is not None:
            after = t >= self.loop_closed_at + settle_s
            out["compensated_pos_rms_mm"] = _rms(pos[after]) * 1e3
            out["compensated_pos_max_mm"] = (
                float(pos[after].max()) * 1e3 if after.any() else math.nan
            )
            out["compensated_rot_rms_mrad"] = _rms(rot[after]) * 1e3
            out["compensated_rot_max_mrad"] = (
                float(rot[after].max()) * 1e3 if after.any() else math.nan
            )
        return out


def _rms(v: np.ndarray) -> float:
    return float(np.sqrt(np.mean(v * v))) if v.size else math.nan
