"""The robot's kinematic chain, vectorized over many configurations, with the corrections
`keo analyze` identifies. No I/O.

The chain is read from the Pinocchio model (fixed placement, then a rotation about the joint's
own axis, per joint). ModelCorrections:
    joint angle:   q_eff = q + offsets + compliance * tau_gravity(q) + backlash * direction
                         + sum over harmonics (a sin(h q_j) + b cos(h q_j))
    geometry:      each joint placement M_j -> M_j exp6(delta_j)   (delta_j: 6-vector)
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from keo_service.core.kinematics import RobotModel
from keo_service.core.model_corrections import ModelCorrections


def _skew(axis: np.ndarray) -> np.ndarray:
    x, y, z = (float(v) for v in axis)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def _frame_with_z(axis: np.ndarray) -> np.ndarray:
    """A rotation S whose third column is the unit `axis` (so R_axis(q) = S Rz(q) S^T)."""
    a = axis / np.linalg.norm(axis)
    helper = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(helper, a)
    u /= np.linalg.norm(u)
    return np.column_stack([u, np.cross(a, u), a])


def _times_constant(T: np.ndarray, M: np.ndarray) -> np.ndarray:
    """(N, 4, 4) @ (4, 4) as one matrix product over the stacked rows (a single BLAS call
    instead of N small ones)."""
    out: np.ndarray = (T.reshape(-1, 4) @ M).reshape(T.shape)
    return out


def times_constant_frames(R: np.ndarray, p: np.ndarray, C: np.ndarray) -> None:
    """In place: the frames (R (3, 3, N), p (3, N)) followed by the constant 4x4 C."""
    for i in range(3):
        p[i] += C[:3, 3] @ R[i]
        R[i] = C[:3, :3].T @ R[i]


class Chain:
    """Vectorized forward kinematics of a RobotModel's base -> flange chain."""

    def __init__(self, robot: RobotModel) -> None:
        model = robot.model
        self.robot = robot
        self.nq = model.nq
        data = model.createData()
        q0 = pin.neutral(model)
        pin.computeJointJacobians(model, data, q0)
        self.placements = [
            model.jointPlacements[j].homogeneous.copy() for j in range(1, model.njoints)
        ]
        self.axes = []
        for j in range(1, model.njoints):
            J = pin.getJointJacobian(model, data, j, pin.LOCAL)
            self.axes.append(J[3:, model.joints[j].idx_v].copy())
        # Rodrigues: R(a) = I + sin(a) K + (1 - cos(a)) K^2 about each joint's unit axis
        self._K = [_skew(a) for a in self.axes]
        self._K2 = [K @ K for K in self._K]
        # for `flange_frames`: each joint as a constant then a rotation about z
        self._axis_frames = []
        for axis in self.axes:
            S = np.eye(4)
            S[:3, :3] = _frame_with_z(axis)
            self._axis_frames.append(S)
        self._steps, self._carried = self._z_steps(self.placements)
        flange = model.frames[robot.flange_frame_id]
        if flange.parentJoint != model.njoints - 1:
            raise ValueError("the flange must hang on the last joint of a serial chain")
        self.flange = flange.placement.homogeneous.copy()
        base = model.frames[robot.base_frame_id]
        self.base_inv = (
            np.linalg.inv(data.oMf[robot.base_frame_id].homogeneous)
            if base.parentJoint == 0
            else np.eye(4)
        )
        self._model = model
        self._data = data

    def _z_steps(self, placements: list[np.ndarray]) -> tuple[list[np.ndarray], np.ndarray]:
        """Each joint's constant before its rotation about z, and the constant left after the
        last joint: a step absorbs the previous joint's axis frame (S_j R_z(q) S_j^T, with
        S_j^T carried on to the next placement)."""
        steps = []
        carried = np.eye(4)
        for M, S in zip(placements, self._axis_frames, strict=True):
            steps.append(carried @ M @ S)
            carried = np.eye(4)
            carried[:3, :3] = S[:3, :3].T
        return steps, carried

    def corrected_placements(self, corr: ModelCorrections | None) -> list[np.ndarray]:
        """Each joint's placement with the geometry correction: M_j exp6(delta_j)."""
        if corr is None or not np.any(corr.placement):
            return self.placements
        return [
            M @ pin.exp6(pin.Motion(d[:3], d[3:])).homogeneous if np.any(d) else M
            for M, d in zip(self.placements, corr.placement, strict=True)
        ]

    def gravity_torques(self, q: np.ndarray) -> np.ndarray:
        """(N, nq) joint torques from gravity with the URDF's (estimated) inertias."""
        return np.array([pin.computeGeneralizedGravity(self._model, self._data, qi) for qi in q])

    def effective_joints(
        self,
        q: np.ndarray,
        corr: ModelCorrections,
        tau: np.ndarray | None = None,
        direction: np.ndarray | None = None,
    ) -> np.ndarray:
        if tau is None and np.any(corr.compliance):
            tau = self.gravity_torques(q)
        return corr.joint_angles(q, tau, direction)

    def flange_poses(
        self,
        q: np.ndarray,
        corr: ModelCorrections | None = None,
        tau: np.ndarray | None = None,
        direction: np.ndarray | None = None,
    ) -> np.ndarray:
        """(N, 4, 4) base -> flange for joints q (N, nq)."""
        q = np.atleast_2d(q)
        n = q.shape[0]
        if corr is not None:
            q = self.effective_joints(q, corr, tau, direction)
        T = np.broadcast_to(self.base_inv, (n, 4, 4)).copy()
        for j, M in enumerate(self.corrected_placements(corr)):
            T = _times_constant(T, M)
            # the joint's rotation: A R(q) = A + sin(q) (A K) + 2 sin^2(q/2) (A K^2)
            A = T[:, :3, :3]
            rows = A.reshape(-1, 3)
            AK = (rows @ self._K[j]).reshape(A.shape)
            AK2 = (rows @ self._K2[j]).reshape(A.shape)
            half = np.sin(0.5 * q[:, j])
            T[:, :3, :3] = (
                A + np.sin(q[:, j])[:, None, None] * AK + (2.0 * half * half)[:, None, None] * AK2
            )
        flange: np.ndarray = _times_constant(T, self.flange)
        return flange

    def flange_frames(
        self,
        q: np.ndarray,
        head: np.ndarray | None = None,
        tail: np.ndarray | None = None,
        corr: ModelCorrections | None = None,
        tau: np.ndarray | None = None,
        direction: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """head @ (base -> flange) @ tail for joints q (N, nq), with constant 4x4 `head` (e.g.
        tracker <- base) and `tail` (e.g. the tool), as
        rotations (3, 3, N) and positions (3, N): component-major, so that every step is a
        3x3 matrix product over contiguous rows or a mix of two columns by cos and sin. The
        fast form of `flange_poses` (the same corrections)."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        n = q.shape[0]
        steps, carried = self._steps, self._carried
        if corr is not None:
            q = self.effective_joints(q, corr, tau, direction)
            if np.any(corr.placement):
                steps, carried = self._z_steps(self.corrected_placements(corr))
        start = self.base_inv if head is None else head @ self.base_inv
        R = np.empty((3, 3, n))
        R[...] = start[:3, :3, None]
        p = np.empty((3, n))
        p[...] = start[:3, 3:]

        for j in range(self.nq):
            times_constant_frames(R, p, steps[j])
            c, s = np.cos(q[:, j]), np.sin(q[:, j])
            x, y = R[:, 0, :].copy(), R[:, 1, :]
            R[:, 0, :] = x * c + y * s
            R[:, 1, :] = y * c - x * s
        last = carried @ self.flange
        times_constant_frames(R, p, last if tail is None else last @ tail)
        return R, p


_SHARED: dict[int, tuple[RobotModel, Chain]] = {}
SHARED_CHAINS = 8  # robots whose chain `shared_chain` keeps (bounded)


def shared_chain(robot: RobotModel) -> Chain:
    """One `Chain` per robot model, built once and kept (the newest few robots): building
    one reads the whole model through Pinocchio, which cost the online delay fits more than
    some of their rounds' kinematics. For `flange_frames` without corrections, which keep no
    state between calls (`gravity_torques` writes the chain's Pinocchio data: not for
    threads sharing a chain)."""
    hit = _SHARED.get(id(robot))
    if hit is None or hit[0] is not robot:
        if len(_SHARED) >= SHARED_CHAINS:
            _SHARED.clear()
        hit = _SHARED[id(robot)] = (robot, Chain(robot))
    return hit[1]
