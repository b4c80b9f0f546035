"""Compensation: turning the known error into a tool that lands where it is told. No I/O.

Frames (docs/design.md §1). The controller moves its *nominal* model: commanded tool pose
T_cmd, it turns the joints to q with T_bt(q) = T_cmd, and the real tool lands at
T_bt(q) T_ts, where T_ts is the error transform keo estimates (tool frame). To land on a goal
T_goal the controller must be commanded T_goal T_ts^-1. So the correction is applied on the
right of the commanded tool pose, i.e. expressed in the tool frame:

    T_cmd = T_goal * C,    C = T_ts^-1                  (URScript: pose_trans(goal, C))

With an identified model, keo's estimate is the error left *after* the model: the real tool is
T_bt(q) F(q) T_ts with F(q) = T_bt(q)^-1 T_bt_model(q) the model's predicted error (its
tool pose seen from the nominal tool frame). Then C = T_ts^-1 F(q)^-1: a feedback part
C_fb = T_ts^-1 (the live estimate) followed by a feedforward part C_ff = F(q)^-1 (the model).
Applying the correction moves the joints, and the estimate is measured against the nominal
model at the joints the robot actually has, so the estimate itself is unaffected by the
correction: the loop does not integrate, the correction follows the observer. The live
correction (limits, validity) is `keo_service.core.correction`; this module holds the model's
tool poses (`ToolModel`, also the live feedforward) and the offline solve.

Offline (`keo compensate`): the joints at which the identified model puts the tool on a
target, by damped Gauss-Newton on the model's forward kinematics (the same `Chain` with the
same `Corrections` that `keo analyze` fits and the estimator applies), each target on its own.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from keo_service.core.chain import Chain
from keo_service.core.correction import log3
from keo_service.core.corrections import Corrections
from keo_service.core.kinematics import RobotModel
from keo_service.core.rotations import log3_many

# ---- the model's tool pose and its error ---------------------------------------------------


class ToolModel:
    """The tool pose of the nominal robot and of the identified model, for many joint
    configurations at once: the `Chain` over the nominal URDF, with the identified
    `Corrections` (joint offsets, placement, compliance, backlash, cyclic terms, joint maps)
    applied exactly as `keo analyze` fitted them, and the flange -> tool transform T_nt."""

    def __init__(
        self, robot: RobotModel, corrections: Corrections | None, T_nt: np.ndarray
    ) -> None:
        self.robot = robot
        self.chain = Chain(robot)
        self.corrections = corrections
        self.T_nt = np.asarray(T_nt, dtype=float)
        self.nq = robot.nq

    def poses(
        self, q: np.ndarray, identified: bool, direction: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Rotations (N, 3, 3) and positions (N, 3) of the tool in the base frame."""
        corr = self.corrections if identified else None
        R, p = self.chain.flange_frames(
            np.atleast_2d(q), tail=self.T_nt, corr=corr, direction=direction if corr else None
        )
        return np.ascontiguousarray(R.transpose(2, 0, 1)), np.ascontiguousarray(p.T)

    def predicted_error(
        self, q: np.ndarray, direction: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """F(q) = T_bt(q)^-1 T_bt_model(q) at one joint configuration: the model's error in
        the nominal tool frame, as (translation m, rotation vector rad)."""
        q2 = np.atleast_2d(np.asarray(q, dtype=float))
        d2 = None if direction is None else np.atleast_2d(direction)
        Rn, pn = self.poses(q2, identified=False)
        Rm, pm = self.poses(q2, identified=True, direction=d2)
        return Rn[0].T @ (pm[0] - pn[0]), log3(Rn[0].T @ Rm[0])

    def calibrated_ranges(self) -> list[tuple[float, float] | None]:
        return [None] * self.nq if self.corrections is None else self.corrections.map_ranges()

    def outside_calibrated_range(self, q: np.ndarray) -> np.ndarray:
        """Per row of q (N, nq): a joint leaves its map's knot range."""
        q = np.atleast_2d(q)
        out = np.zeros(q.shape[0], dtype=bool)
        for j, rng in enumerate(self.calibrated_ranges()):
            if rng is not None:
                out |= (q[:, j] < rng[0]) | (q[:, j] > rng[1])
        return out


# ---- offline: joints that put the modelled tool on targets ----------------------------------

TOLERANCE_M = 1e-9
TOLERANCE_RAD = 1e-9
UNREACHABLE_M = 1e-3  # a solve that ends farther than this (or 1 mrad) did not reach the target
SINGULAR_RATIO = 5e-3  # smallest / largest singular value of the Jacobian below: near_singular
FLAGS = ("outside_calibrated_range", "not_converged", "unreachable", "near_singular")


@dataclass
class Solution:
    q: np.ndarray  # (N, nq)
    converged: np.ndarray  # (N,) bool
    residual_m: np.ndarray  # (N,) position residual
    residual_rad: np.ndarray  # (N,) rotation residual
    iterations: np.ndarray  # (N,)


def pose_residual(
    R: np.ndarray, p: np.ndarray, R_goal: np.ndarray, p_goal: np.ndarray
) -> np.ndarray:
    """(N, 6): the goal seen from the current pose, in the base frame: p_goal - p and
    log3(R_goal R^T) (so that a small joint step dq moves the pose by J dq toward it)."""
    out = np.empty((p.shape[0], 6))
    out[:, :3] = p_goal - p
    rel = np.einsum("nij,nkj->nik", R_goal, R)  # R_goal R^T
    out[:, 3:] = log3_many(rel.transpose(1, 2, 0))
    return out


def jacobian(
    model: ToolModel,
    q: np.ndarray,
    identified: bool,
    direction: np.ndarray | None,
    step: float = 1e-6,
) -> np.ndarray:
    """(N, 6, nq) of the tool pose by central differences (position m/rad, rotation in the
    base frame rad/rad), all 2 nq perturbations of all rows in one chain evaluation. A
    numeric Jacobian keeps every effect of the model in (maps, compliance, cyclic terms)
    without a derivative of each; Newton's answer is set by the residual, which is exact."""
    n, nq = q.shape
    shifted = np.repeat(q[None], 2 * nq, axis=0)  # (2 nq, N, nq)
    for j in range(nq):
        shifted[2 * j, :, j] += step
        shifted[2 * j + 1, :, j] -= step
    d = None if direction is None else np.tile(direction, (2 * nq, 1))
    R, p = model.poses(shifted.reshape(-1, nq), identified, d)
    R = R.reshape(2 * nq, n, 3, 3)
    p = p.reshape(2 * nq, n, 3)
    J = np.empty((n, 6, nq))
    for j in range(nq):
        J[:, :3, j] = (p[2 * j] - p[2 * j + 1]) / (2 * step)
        rel = np.einsum("nij,nkj->nik", R[2 * j], R[2 * j + 1])
        J[:, 3:, j] = log3_many(rel.transpose(1, 2, 0)) / (2 * step)
    return J


def _cost(e: np.ndarray) -> np.ndarray:
    out: np.ndarray = np.einsum("ni,ni->n", e, e)  # m^2 + rad^2 (1 m per rad)
    return out


def solve(
    model: ToolModel,
    R_goal: np.ndarray,
    p_goal: np.ndarray,
    seeds: np.ndarray,
    identified: bool,
    direction: np.ndarray | None = None,
    max_iterations: int = 60,
) -> Solution:
    """Joints q with model pose = goal, each row on its own: Levenberg-Marquardt damped
    Gauss-Newton from `seeds`, a step kept only when it lowers the residual (otherwise the
    damping grows tenfold), to TOLERANCE_M / TOLERANCE_RAD."""
    q = np.array(seeds, dtype=float, copy=True)
    n, nq = q.shape
    lam = np.full(n, 1e-9)
    iterations = np.zeros(n, dtype=int)
    R, p = model.poses(q, identified, direction)
    e = pose_residual(R, p, R_goal, p_goal)
    cost = _cost(e)

    def done_rows() -> np.ndarray:
        out: np.ndarray = (np.linalg.norm(e[:, :3], axis=1) <= TOLERANCE_M) & (
            np.linalg.norm(e[:, 3:], axis=1) <= TOLERANCE_RAD
        )
        return out

    active = ~done_rows()
    for _ in range(max_iterations):
        rows = np.flatnonzero(active)
        if rows.size == 0:
            break
        d = None if direction is None else direction[rows]
        J = jacobian(model, q[rows], identified, d)
        JT = J.transpose(0, 2, 1)
        A = JT @ J
        g = np.einsum("nji,nj->ni", J, e[rows])
        scale = np.trace(A, axis1=1, axis2=2) / nq
        A = A + (lam[rows] * scale)[:, None, None] * np.eye(nq)
        dq = np.linalg.solve(A, g[:, :, None])[:, :, 0]
        big = np.max(np.abs(dq), axis=1)
        dq *= np.minimum(1.0, 0.5 / np.maximum(big, 1e-300))[:, None]  # at most 0.5 rad a step
        trial = q[rows] + dq
        Rt, pt = model.poses(trial, identified, d)
        et = pose_residual(Rt, pt, R_goal[rows], p_goal[rows])
        ct = _cost(et)
        better = ct < cost[rows]
        keep = rows[better]
        q[keep], e[keep], cost[keep] = trial[better], et[better], ct[better]
        lam[keep] = np.maximum(lam[keep] * 0.1, 1e-12)
        worse = rows[~better]
        lam[worse] *= 10.0
        iterations[rows] += 1
        active = ~done_rows() & (lam < 1e8)
    return Solution(
        q=q,
        converged=done_rows(),
        residual_m=np.linalg.norm(e[:, :3], axis=1),
        residual_rad=np.linalg.norm(e[:, 3:], axis=1),
        iterations=iterations,
    )


def singular_ratio(
    model: ToolModel, q: np.ndarray, identified: bool, direction: np.ndarray | None = None
) -> np.ndarray:
    """Smallest over largest singular value of each row's Jacobian (position rows per metre
    of a 1 m arm, rotation rows per radian): near zero at a singular configuration."""
    s = np.linalg.svd(jacobian(model, q, identified, direction), compute_uv=False)
    out: np.ndarray = s[:, -1] / np.maximum(s[:, 0], 1e-300)
    return out


def seed_candidates(robot: RobotModel, count: int = 24) -> np.ndarray:
    """Deterministic starting joints spread over the joint ranges (within +-pi), for a
    nominal inverse with no seed given."""
    lo = np.maximum(robot.lower, -math.pi)
    hi = np.minimum(robot.upper, math.pi)
    rng = np.random.default_rng(20261124)
    out: np.ndarray = lo + (hi - lo) * rng.uniform(0.15, 0.85, (count, robot.nq))
    return out


def nominal_inverse(
    model: ToolModel, R_goal: np.ndarray, p_goal: np.ndarray, seeds: np.ndarray | None
) -> Solution:
    """Joints at which the nominal robot puts its tool on each goal: from the given seeds,
    else from each of `seed_candidates` in turn for the rows without a good answer yet. A
    good answer converged within the joint limits and, when the model has joint maps, within
    their calibrated range (another branch of the inverse may be); a solution beyond the
    joint limits is no solution."""
    if seeds is not None:
        return solve(model, R_goal, p_goal, seeds, identified=False)
    robot = model.robot

    def rank(sol: Solution) -> np.ndarray:
        within = np.all((sol.q >= robot.lower) & (sol.q <= robot.upper), axis=1)
        solved = sol.converged & within
        out: np.ndarray = 2 * solved + (solved & ~model.outside_calibrated_range(sol.q))
        return out

    n = p_goal.shape[0]
    best: Solution | None = None
    best_rank = np.zeros(n, dtype=int)
    for seed in seed_candidates(model.robot):
        todo = np.arange(n) if best is None else np.flatnonzero(best_rank < 3)
        if todo.size == 0:
            break
        sol = solve(
            model, R_goal[todo], p_goal[todo], np.tile(seed, (todo.size, 1)), identified=False
        )
        r = rank(sol)
        if best is None:
            best, best_rank = sol, r
            continue
        better = (r > best_rank[todo]) | (
            (r == best_rank[todo]) & (r == 0) & (sol.residual_m < best.residual_m[todo])
        )
        rows = todo[better]
        best_rank[rows] = r[better]
        for name in ("q", "converged", "residual_m", "residual_rad", "iterations"):
            getattr(best, name)[rows] = getattr(sol, name)[better]
    assert best is not None
    best.converged &= best_rank >= 2
    return best


@dataclass
class Compensated:
    q: np.ndarray  # (N, nq) corrected joints
    R_command: np.ndarray  # (N, 3, 3) the nominal tool pose at q: what to command
    p_command: np.ndarray  # (N, 3)
    correction_m: np.ndarray  # (N,) |p_command - p_goal|
    correction_rad: np.ndarray  # (N,) angle between R_command and R_goal
    residual_m: np.ndarray  # (N,) of the model solve
    residual_rad: np.ndarray
    flags: list[list[str]] = field(default_factory=list)


def compensate(
    model: ToolModel,
    R_goal: np.ndarray,
    p_goal: np.ndarray,
    seeds: np.ndarray | None,
    direction: np.ndarray | None = None,
    seeds_are_nominal: bool = False,
    max_iterations: int = 60,
) -> Compensated:
    """For every goal pose: the nominal inverse (from `seeds` when given; `seeds_are_nominal`
    when the seeds already are that inverse, as for a joint program), then the joints at which
    the identified model puts the tool on the goal, and the nominal tool pose there (the pose
    to command a controller that uses its nominal model). Flags per row, see FLAGS."""
    if seeds is not None and seeds_are_nominal:
        start = np.asarray(seeds, dtype=float)
        nominal_ok = np.ones(start.shape[0], dtype=bool)
    else:
        nom = nominal_inverse(model, R_goal, p_goal, seeds)
        start, nominal_ok = nom.q, nom.residual_m < UNREACHABLE_M
    sol = solve(model, R_goal, p_goal, start, True, direction, max_iterations)
    R_cmd, p_cmd = model.poses(sol.q, identified=False)
    corr_rad = np.linalg.norm(pose_residual(R_cmd, p_cmd, R_goal, p_goal)[:, 3:], axis=1)
    ratio = singular_ratio(model, sol.q, True, direction)
    outside = model.outside_calibrated_range(sol.q)
    robot = model.robot
    beyond_limits = np.any((sol.q < robot.lower - 1e-12) | (sol.q > robot.upper + 1e-12), axis=1)
    flags: list[list[str]] = []
    for i in range(sol.q.shape[0]):
        row: list[str] = []
        if outside[i]:
            row.append("outside_calibrated_range")
        far = sol.residual_m[i] > UNREACHABLE_M or sol.residual_rad[i] > UNREACHABLE_M
        if far or beyond_limits[i] or not nominal_ok[i]:
            row.append("unreachable")
        elif not sol.converged[i]:
            row.append("not_converged")
        if ratio[i] < SINGULAR_RATIO:
            row.append("near_singular")
        flags.append(row)
    return Compensated(
        q=sol.q,
        R_command=R_cmd,
        p_command=p_cmd,
        correction_m=np.linalg.norm(p_cmd - p_goal, axis=1),
        correction_rad=corr_rad,
        residual_m=sol.residual_m,
        residual_rad=sol.residual_rad,
        flags=flags,
    )
