"""Robot models and the measured kinematic error (docs/design.md §1). No I/O beyond the URDF.

Pinocchio style: a `Cell` is data (robot model, tool and tracker registration); the
algorithms are free functions over `(cell, data, ...)`.

Frames: b robot base, n flange, t nominal tool, k tracker, s sensor (measured).
    T_bt(q) = T_bn(q) T_nt,   T_bs = T_bk T_ks,   T_ts = T_bt^-1 T_bs
    e_m = [p_ts ; log3(R_ts)]            (6 channels; metres, radians)
A single-reflector tracker measures only p_ks; then e_m = R_bt^T (p_bs - p_bt) (3 channels).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pinocchio as pin

from keo_service.core.errors import ConfigError
from keo_service.core.model_corrections import ModelCorrections

POSE_CHANNELS = ("px", "py", "pz", "rx", "ry", "rz")
POSITION_CHANNELS = ("px", "py", "pz")


def rpy_matrix(rpy: Sequence[float]) -> np.ndarray:
    """URDF convention: R = Rz(yaw) Ry(pitch) Rx(roll)."""
    return np.asarray(pin.rpy.rpyToMatrix(float(rpy[0]), float(rpy[1]), float(rpy[2])))


def se3_from_xyz_rpy(xyz: Sequence[float], rpy: Sequence[float]) -> pin.SE3:
    return pin.SE3(rpy_matrix(rpy), np.asarray(xyz, dtype=float))


def se3_from_xyz_quat(
    p: Sequence[float] | np.ndarray, q_wxyz: Sequence[float] | np.ndarray
) -> pin.SE3:
    """Pose from a position and a unit quaternion, scalar first (the wire and file order)."""
    w, x, y, z = q_wxyz.tolist() if isinstance(q_wxyz, np.ndarray) else q_wxyz
    norm = math.sqrt(w * w + x * x + y * y + z * z) or 1.0
    # one Pinocchio call (x, y, z, qx, qy, qz, qw): a quarter of Quaternion -> matrix -> SE3
    xyzquat = [p[0], p[1], p[2], x / norm, y / norm, z / norm, w / norm]
    return pin.XYZQUATToSE3(np.array(xyzquat, dtype=float))


def quat_wxyz(rotation: np.ndarray) -> np.ndarray:
    """Unit quaternion, scalar first, with w >= 0."""
    x, y, z, w = pin.Quaternion(np.asarray(rotation)).coeffs()
    q = np.array([w, x, y, z])
    return -q if w < 0 else q


@dataclass(frozen=True)
class RobotModel:
    """A kinematic chain loaded from URDF, with the two frames keo measures between."""

    model: pin.Model
    base_frame_id: int
    flange_frame_id: int
    joint_names: tuple[str, ...]
    lower: np.ndarray
    upper: np.ndarray
    velocity_limit: np.ndarray

    @property
    def nq(self) -> int:
        return int(self.model.nq)

    def create_data(self) -> pin.Data:
        return self.model.createData()


def load_robot(
    urdf: str | Path,
    base_frame: str = "base_link",
    flange_frame: str = "tool0",
    source: str = "<config>",
) -> RobotModel:
    """Load a URDF with Pinocchio; frame names are checked and reported by config key."""
    try:
        model = pin.buildModelFromUrdf(str(urdf))
    except (RuntimeError, ValueError) as exc:
        raise ConfigError(source, "robot.urdf", f"not a loadable URDF ({exc})") from None
    if model.nq != model.nv:
        raise ConfigError(
            source,
            "robot.urdf",
            "continuous (unbounded) joints are not supported; use revolute joints",
        )
    frames = [f.name for f in model.frames]
    for key, name in (("robot.base_frame", base_frame), ("robot.flange_frame", flange_frame)):
        if name not in frames:
            raise ConfigError(
                source, key, f"frame '{name}' is not in the URDF; frames: " + ", ".join(frames)
            )
    names = tuple(model.names[i] for i in range(1, model.njoints))
    return RobotModel(
        model=model,
        base_frame_id=model.getFrameId(base_frame),
        flange_frame_id=model.getFrameId(flange_frame),
        joint_names=names,
        lower=np.array(model.lowerPositionLimit, dtype=float),
        upper=np.array(model.upperPositionLimit, dtype=float),
        velocity_limit=np.array(model.velocityLimit, dtype=float),
    )


@dataclass(frozen=True)
class Cell:
    """Everything needed to turn joints and a tracker pose into the measured error.

    Built from a config by `cell_from_config`; lengths in m, angles in rad.

    Attributes:
        robot: the kinematic chain (URDF) and the base and flange frames keo measures between.
        T_nt: the measurement frame (the probe) in the flange frame.
        T_bk: the tracker's frame in the robot's base frame (the registration).
        corrections: the identified model of `keo analyze` (joint offsets, compliance,
            backlash, maps, ...), or None for the nominal robot.
        nominal_model: the nominal robot, for the gravity torques of the compliance
            correction when `robot.model` carries identified geometry.
        gravity_data: scratch data for those torques (not used per sample).
    """

    robot: RobotModel
    T_nt: pin.SE3  # flange -> nominal tool
    T_bk: pin.SE3  # base -> tracker
    corrections: ModelCorrections | None = None  # an identified model (keo analyze), if any
    nominal_model: pin.Model | None = None  # for gravity torques when robot.model is corrected
    gravity_data: pin.Data | None = None  # scratch for those torques (not per sample)


def flange_pose(robot: RobotModel, data: pin.Data, q: np.ndarray) -> pin.SE3:
    """T_bn(q): flange in the base frame."""
    pin.framesForwardKinematics(robot.model, data, q)
    T_on = data.oMf[robot.flange_frame_id]
    if robot.base_frame_id == 0:
        return pin.SE3(T_on)
    return data.oMf[robot.base_frame_id].actInv(T_on)


def tool_pose(
    cell: Cell, data: pin.Data, q: np.ndarray, direction: np.ndarray | None = None
) -> pin.SE3:
    """T_bt(q) = T_bn(q) T_nt, on the identified model when the cell has one (`direction`:
    each joint's direction of its last move, for backlash)."""
    if cell.corrections is not None:
        q = corrected_joints(cell, q, direction)
    robot = cell.robot
    pin.framesForwardKinematics(robot.model, data, q)
    T_on = data.oMf[robot.flange_frame_id]  # a view into data: used before the next call
    if robot.base_frame_id == 0:
        return T_on * cell.T_nt
    return data.oMf[robot.base_frame_id].actInv(T_on) * cell.T_nt


def corrected_joints(cell: Cell, q: np.ndarray, direction: np.ndarray | None = None) -> np.ndarray:
    corr = cell.corrections
    assert corr is not None
    tau = None
    if np.any(corr.compliance) and cell.nominal_model is not None:
        tau = np.asarray(pin.computeGeneralizedGravity(cell.nominal_model, cell.gravity_data, q))
    return np.asarray(corr.joint_angles(np.asarray(q, dtype=float), tau, direction))


def log3(R: np.ndarray) -> np.ndarray:
    """Axis-angle vector of a rotation matrix; exact near 0 and near pi (Pinocchio's log3)."""
    return np.asarray(pin.log3(R))


def pose_error(T_bt: pin.SE3, T_bs: pin.SE3) -> np.ndarray:
    """e_m = [p_ts ; log3(R_ts)] for T_ts = T_bt^-1 T_bs."""
    T_ts = T_bt.actInv(T_bs)
    out = np.empty(6)
    out[:3] = T_ts.translation
    out[3:] = pin.log3(T_ts.rotation)
    return out


def position_error(T_bt: pin.SE3, p_bs: np.ndarray) -> np.ndarray:
    """Reflector position in the nominal tool frame: R_bt^T (p_bs - p_bt)."""
    return np.asarray(T_bt.actInv(np.asarray(p_bs, dtype=float)))


def measured_error(
    cell: Cell,
    data: pin.Data,
    q: np.ndarray,
    p_ks: Sequence[float] | np.ndarray,
    q_ks: Sequence[float] | np.ndarray | None,
    direction: np.ndarray | None = None,
) -> np.ndarray:
    """The measured error for joints q and a tracker measurement in the tracker frame.

    `q_ks` is the sensor orientation as a unit quaternion (w, x, y, z), or None for a
    single-reflector tracker: then only the 3 position channels are returned.
    """
    T_bt = tool_pose(cell, data, q, direction)
    if q_ks is None:
        return position_error(T_bt, cell.T_bk.act(np.asarray(p_ks, dtype=float)))
    return pose_error(T_bt, cell.T_bk * se3_from_xyz_quat(p_ks, q_ks))


@dataclass(frozen=True)
class FoldedFrames:
    """The cell's constant transforms folded into a copy of the robot model, so that one
    measured error costs one forward kinematics, one frame placement and one SE3 product:
    the copy's origin is the tracker frame k (its root joint placed by T_ko = (T_ob T_bk)^-1)
    and its flange frame carries the nominal tool (placement times T_nt), so the frame
    placement it computes is T_kt(q) and T_ts = T_kt^-1 T_ks."""

    model: pin.Model
    tool_frame_id: int


def fold_frames(cell: Cell) -> FoldedFrames | None:
    """None when the base frame moves with a joint (then only `measured_error` applies)."""
    robot = cell.robot
    if robot.model.frames[robot.base_frame_id].parentJoint != 0:
        return None
    data = robot.create_data()
    pin.framesForwardKinematics(robot.model, data, pin.neutral(robot.model))
    T_ko = (data.oMf[robot.base_frame_id] * cell.T_bk).inverse()
    model = pin.Model(robot.model)
    for joint in range(1, model.njoints):
        if model.parents[joint] == 0:
            model.jointPlacements[joint] = T_ko * model.jointPlacements[joint]
    tool = model.frames[robot.flange_frame_id]
    tool.placement = tool.placement * cell.T_nt
    model.frames[robot.flange_frame_id] = tool
    return FoldedFrames(model, robot.flange_frame_id)


def measured_error_folded(
    frames: FoldedFrames, data: pin.Data, q: np.ndarray, sensor: list[float]
) -> list[float]:
    """`measured_error` for joints q (already corrected, if the cell has corrections) and the
    sensor as [x, y, z, qx, qy, qz, qw] (Pinocchio's order, unit quaternion) or [x, y, z];
    `data` is `frames.model`'s. Plain floats out: the observer steps on them.

    Three native calls (kinematics, frame placement, T_kt as position and quaternion); the
    error transform T_ts = T_kt^-1 T_ks is formed on plain floats: in the service each
    sample wakes a cold CPU, where a native call costs several times a line of float
    arithmetic (docs/performance.md times both)."""
    pin.forwardKinematics(frames.model, data, q)
    T_kt = pin.updateFramePlacement(frames.model, data, frames.tool_frame_id)
    tx, ty, tz, ax, ay, az, aw = pin.SE3ToXYZQUAT(T_kt).tolist()
    # p_ts = R_kt^T (p_ks - p_kt): d rotated by the conjugate quaternion (-a, aw), as
    # d + 2 aw (u x d) + 2 u x (u x d) with u = -a
    dx, dy, dz = sensor[0] - tx, sensor[1] - ty, sensor[2] - tz
    cx, cy, cz = az * dy - ay * dz, ax * dz - az * dx, ay * dx - ax * dy  # u x d
    ex, ey, ez = az * cy - ay * cz, ax * cz - az * cx, ay * cx - ax * cy  # u x (u x d)
    px = dx + 2.0 * (aw * cx + ex)
    py = dy + 2.0 * (aw * cy + ey)
    pz = dz + 2.0 * (aw * cz + ez)
    if len(sensor) == 3:
        return [px, py, pz]
    bx, by, bz, bw = sensor[3], sensor[4], sensor[5], sensor[6]
    # the quaternion of R_ts = R_kt^T R_ks: conj(a) * b
    qw = aw * bw + ax * bx + ay * by + az * bz
    qx = aw * bx - ax * bw - ay * bz + az * by
    qy = aw * by + ax * bz - ay * bw - az * bx
    qz = aw * bz - ax * by + ay * bx - az * bw
    # log3 from the quaternion (axis times angle, the angle in [0, pi]): exact near a half
    # turn, where the matrix route loses digits
    s = math.sqrt(qx * qx + qy * qy + qz * qz)  # |sin(angle / 2)|
    k = 2.0 * math.atan2(s, abs(qw)) / s if s > 0.0 else 2.0
    if qw < 0.0:  # q and -q are one rotation: the short way round
        k = -k
    return [px, py, pz, k * qx, k * qy, k * qz]


def sensor_pose_from_error(T_bt: pin.SE3, error: np.ndarray) -> pin.SE3:
    """Inverse of pose_error: the sensor pose T_bs that produces `error` at tool pose T_bt."""
    T_ts = pin.SE3(pin.exp3(np.asarray(error[3:], dtype=float)), np.asarray(error[:3], dtype=float))
    return T_bt * T_ts


def channels_for(position_only: bool) -> tuple[str, ...]:
    return POSITION_CHANNELS if position_only else POSE_CHANNELS


def error_as_pose(error: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """An error 6-vector [p; r] as a pose: position [m] and the unit quaternion of exp(r),
    scalar first; a 3-vector (single reflector) has no orientation (None)."""
    p = np.array(error[:3], dtype=float)
    if len(error) < 6:
        return p, None
    return p, quat_wxyz(pin.exp3(np.asarray(error[3:6], dtype=float)))
