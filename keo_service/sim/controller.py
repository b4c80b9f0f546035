"""What a robot controller does with a Cartesian correction in the tool frame (KUKA RSI's
absolute TCP correction, ABB EGM's pose correction): it moves the joints so that its nominal
model puts the tool at the programmed pose times the correction. Used by the controller mocks.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pinocchio as pin

from keo_service.core.kinematics import Cell, flange_pose

MAX_ITERATIONS = 8
TOLERANCE = 1e-10  # m and rad


def tool_corrector(cell: Cell) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """`correct(q, c)`: joints q' with T_bt(q') = T_bt(q) * exp(c), c = [x y z (m), rotation
    vector (rad)] in the tool frame, on the nominal model (Gauss-Newton from q)."""
    robot = cell.robot
    data = robot.create_data()

    def tool(q: np.ndarray) -> pin.SE3:
        return flange_pose(robot, data, q) * cell.T_nt

    def correct(q: np.ndarray, c: np.ndarray) -> np.ndarray:
        target = tool(q) * pin.SE3(pin.exp3(np.asarray(c[3:], float)), np.asarray(c[:3], float))
        q_new = np.array(q, dtype=float)
        for _ in range(MAX_ITERATIONS):
            T = tool(q_new)
            err = pin.log6(T.actInv(target)).vector  # in the current tool frame
            if np.max(np.abs(err)) < TOLERANCE:
                break
            pin.computeJointJacobians(robot.model, data, q_new)
            J_flange = pin.getFrameJacobian(
                robot.model, data, robot.flange_frame_id, pin.ReferenceFrame.LOCAL
            )
            J_tool = cell.T_nt.inverse().toActionMatrix() @ J_flange
            q_new = q_new + np.linalg.lstsq(J_tool, err, rcond=None)[0]
        return q_new

    return correct
