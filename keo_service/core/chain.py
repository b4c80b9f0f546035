"""The robot's kinematic chain, vectorized over many configurations, with the corrections
`keo analyze` identifies. No I/O.

The chain is read from the Pinocchio model (fixed placement, then a rotation about the joint's
own axis, per joint). Corrections:
    joint angle:   q_eff = q + offsets + compliance * tau_gravity(q) + backlash * direction
                         + sum over harmonics (a sin(h q_j) + b cos(h q_j))
    geometry:      each joint placement M_j -> M_j exp6(delta_j)   (delta_j: 6-vector)
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin
from scipy.spatial.transform import Rotation

from keo_service.core.corrections import Corrections
from keo_service.core.kinematics import RobotModel


def _rot(axis: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations about a unit axis."""
    rotations: np.ndarray = Rotation.from_rotvec(angles[:, None] * axis[None, :]).as_matrix()
    return rotations


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

    def gravity_torques(self, q: np.ndarray) -> np.ndarray:
        """(N, nq) joint torques from gravity with the URDF's (estimated) inertias."""
        return np.array([pin.computeGeneralizedGravity(self._model, self._data, qi) for qi in q])

    def effective_joints(
        self,
        q: np.ndarray,
        corr: Corrections,
        tau: np.ndarray | None = None,
        direction: np.ndarray | None = None,
    ) -> np.ndarray:
        if tau is None and np.any(corr.compliance):
            tau = self.gravity_torques(q)
        return corr.joint_angles(q, tau, direction)

    def flange_poses(
        self,
        q: np.ndarray,
        corr: Corrections | None = None,
        tau: np.ndarray | None = None,
        direction: np.ndarray | None = None,
    ) -> np.ndarray:
        """(N, 4, 4) base -> flange for joints q (N, nq)."""
        q = np.atleast_2d(q)
        n = q.shape[0]
        if corr is not None:
            q = self.effective_joints(q, corr, tau, direction)
        T = np.broadcast_to(self.base_inv, (n, 4, 4)).copy()
        for j in range(self.nq):
            M = self.placements[j]
            if corr is not None and np.any(corr.placement[j]):
                M = (
                    M
                    @ pin.exp6(pin.Motion(corr.placement[j][:3], corr.placement[j][3:])).homogeneous
                )
            T = T @ M
            R = _rot(self.axes[j], q[:, j])
            T[:, :3, :3] = T[:, :3, :3] @ R
        flange: np.ndarray = T @ self.flange
        return flange
