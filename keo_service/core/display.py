"""Geometry for drawing a cell: the robot as capsules along its links, the measured error
as a magnified arrow, the tool speed, and a camera that frames robot and tracker.

Pure math over the kinematics (no drawing library): the Rerun sink in `keo_service.live`
turns these numbers into entities.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from keo_service.core.kinematics import Cell, RobotModel

LINK_RADIUS_PER_REACH = 0.03  # a link's radius as a share of the robot's reach
HUB_RADIUS = 1.25  # a joint's hub: radius and half length, in link radii
MIN_SEGMENT_M = 1e-6  # shorter joint offsets are not drawn as links


def reach(robot: RobotModel) -> float:
    """Sum of the joint offsets of the chain (m): the robot's size, for radii and views."""
    model = robot.model
    return float(
        sum(np.linalg.norm(model.jointPlacements[j].translation) for j in range(1, model.njoints))
    )


def link_radius(robot: RobotModel) -> float:
    return LINK_RADIUS_PER_REACH * max(reach(robot), 0.1)


def _joint_axis(robot: RobotModel, j: int) -> np.ndarray:
    """Joint j's rotation axis in its own frame (Z for joints that are not revolute)."""
    joint = robot.model.joints[j]
    name = joint.shortname()
    for suffix, axis in (("RX", (1.0, 0.0, 0.0)), ("RY", (0.0, 1.0, 0.0)), ("RZ", (0.0, 0.0, 1.0))):
        if name.endswith(suffix):
            return np.array(axis)
    inner = joint.extract()
    if hasattr(inner, "axis"):
        return np.asarray(inner.axis, dtype=float)
    return np.array([0.0, 0.0, 1.0])


def _z_to(direction: np.ndarray) -> np.ndarray:
    """Quaternion (x, y, z, w) that turns +Z onto `direction`."""
    q = pin.Quaternion.FromTwoVectors(np.array([0.0, 0.0, 1.0]), np.asarray(direction, dtype=float))
    return np.asarray(q.coeffs(), dtype=float)


@dataclass(frozen=True)
class Capsules:
    """Capsules as a drawing library takes them: each starts at `starts[i]` and runs
    `lengths[i]` along the +Z axis turned by `quaternions[i]` (x, y, z, w)."""

    starts: np.ndarray  # (n, 3)
    quaternions: np.ndarray  # (n, 4)
    lengths: np.ndarray  # (n,)
    radii: np.ndarray  # (n,)
    kinds: tuple[str, ...]  # "link", "hub" (a joint's motor), "tool"


def robot_capsules(cell: Cell, data: pin.Data, q: np.ndarray, T_bt: pin.SE3) -> Capsules:
    """The robot at joints q as capsules in its base frame: one per joint offset (the links,
    the pedestal first), one across each joint along its axis (the hubs), and the tool from
    the flange to the nominal tool point `T_bt` (thinner)."""
    robot = cell.robot
    model = robot.model
    pin.forwardKinematics(model, data, q)
    pin.updateFramePlacement(model, data, robot.flange_frame_id)
    T_ob = data.oMf[robot.base_frame_id] if robot.base_frame_id else pin.SE3.Identity()
    r = link_radius(robot)
    starts, quats, lengths, radii, kinds = [], [], [], [], []

    def add(start: np.ndarray, end: np.ndarray, radius: float, kind: str) -> None:
        d = end - start
        n = float(np.linalg.norm(d))
        if n < MIN_SEGMENT_M:
            return
        starts.append(start)
        quats.append(_z_to(d / n))
        lengths.append(n)
        radii.append(radius)
        kinds.append(kind)

    def in_base(p: np.ndarray) -> np.ndarray:
        return np.asarray(T_ob.actInv(p), dtype=float)

    for j in range(1, model.njoints):
        parent = model.parents[j]
        add(in_base(data.oMi[parent].translation), in_base(data.oMi[j].translation), r, "link")
    flange = in_base(data.oMf[robot.flange_frame_id].translation)
    add(
        in_base(data.oMi[model.frames[robot.flange_frame_id].parentJoint].translation),
        flange,
        r,
        "link",
    )
    for j in range(1, model.njoints):
        axis = T_ob.rotation.T @ data.oMi[j].rotation @ _joint_axis(robot, j)
        centre = in_base(data.oMi[j].translation)
        half = HUB_RADIUS * r
        add(centre - half * axis, centre + half * axis, HUB_RADIUS * r, "hub")
    add(flange, np.asarray(T_bt.translation, dtype=float), 0.4 * r, "tool")
    return Capsules(
        np.asarray(starts, dtype=float).reshape(-1, 3),
        np.asarray(quats, dtype=float).reshape(-1, 4),
        np.asarray(lengths, dtype=float),
        np.asarray(radii, dtype=float),
        tuple(kinds),
    )


def error_arrow(
    T_bt: pin.SE3, measured: np.ndarray, factor: float
) -> tuple[np.ndarray, np.ndarray, float]:
    """The measured position error as an arrow in the base frame: from the nominal tool
    point, the vector to the measured sensor point magnified by `factor`, and the error's
    true length (m). `measured[:3]` is the sensor's position in the nominal tool frame."""
    offset = np.asarray(T_bt.rotation, dtype=float) @ np.asarray(measured[:3], dtype=float)
    return (
        np.asarray(T_bt.translation, dtype=float).copy(),
        factor * offset,
        float(np.linalg.norm(offset)),
    )


def speeds(t: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """Speed (m/s) between successive positions (n, 3) at times t (n,): n - 1 values, at
    the later time of each pair; a pair without elapsed time gives NaN."""
    t = np.asarray(t, dtype=float)
    step = np.linalg.norm(np.diff(np.asarray(positions, dtype=float), axis=0), axis=1)
    dt = np.diff(t)
    out = np.full(dt.shape, np.nan)
    np.divide(step, dt, out=out, where=dt > 0)
    return out


def framing_camera(
    points: np.ndarray, up: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """An eye position and a look target that show all `points` (n, 3): the target at the
    centre of their bounding box, the eye back along a diagonal from above, far enough for
    a field of view of about 60 degrees."""
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    centre = (lo + hi) / 2.0
    radius = max(float(np.linalg.norm(hi - lo)) / 2.0, 0.5)
    up_v = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, dtype=float)
    # look across the longest horizontal extent, from the side and a little above
    span = hi - lo
    span = span - up_v * float(span @ up_v)
    side = np.cross(up_v, span) if np.linalg.norm(span) > 1e-9 else np.array([1.0, 0.0, 0.0])
    side = side / np.linalg.norm(side)
    direction = side + 0.35 * up_v + 0.25 * span / max(float(np.linalg.norm(span)), 1e-9)
    direction = direction / np.linalg.norm(direction)
    eye = centre + direction * radius * 1.3
    return eye, centre


@dataclass(frozen=True)
class Mesh:
    """A visual mesh of the URDF: its file, scale, and the joint it moves with."""

    name: str
    path: str
    scale: np.ndarray
    joint: int
    placement: pin.SE3  # in the joint's frame


MESH_SUFFIXES = (".obj", ".stl", ".glb", ".gltf")  # what the viewer loads as an asset


def visual_meshes(robot: RobotModel, urdf: str, package_dirs: list[str]) -> list[Mesh]:
    """The URDF's visual meshes in formats a viewer loads (its other visuals are left out);
    empty when it has none or cannot be read."""
    try:
        geom = pin.buildGeomFromUrdf(
            robot.model, urdf, pin.GeometryType.VISUAL, package_dirs=package_dirs
        )
    except (RuntimeError, ValueError):
        return []
    out = []
    for obj in geom.geometryObjects:
        path = str(obj.meshPath)
        if path.lower().endswith(MESH_SUFFIXES):
            out.append(
                Mesh(
                    obj.name,
                    path,
                    np.asarray(obj.meshScale, dtype=float),
                    int(obj.parentJoint),
                    pin.SE3(obj.placement),
                )
            )
    return out


def mesh_poses(cell: Cell, data: pin.Data, meshes: list[Mesh]) -> list[pin.SE3]:
    """Each mesh's pose in the base frame, after forward kinematics on `data` (as
    `robot_capsules` leaves it)."""
    robot = cell.robot
    T_ob = data.oMf[robot.base_frame_id] if robot.base_frame_id else pin.SE3.Identity()
    return [T_ob.actInv(data.oMi[m.joint] * m.placement) for m in meshes]


def arrow_factor(robot: RobotModel, share: float = 0.1) -> float:
    """A round magnification (1, 2 or 5 times a power of ten) that draws a 1 mm error at
    about `share` of the robot's reach, at least that long."""
    want = share * max(reach(robot), 0.1) / 1e-3
    decade = 10.0 ** np.floor(np.log10(want))
    for step in (1.0, 2.0, 5.0, 10.0):
        if step * decade >= want * 0.999:
            return float(step * decade)
    return float(10.0 * decade)


def away_from(vector: np.ndarray, distance: float) -> np.ndarray:
    """The point `distance` from the origin opposite to `vector` (straight up for a zero
    vector): where a label goes so that it does not sit on an arrow drawn along `vector`."""
    v = np.asarray(vector, dtype=float)
    n = float(np.linalg.norm(v))
    if n == 0.0:
        return np.array([0.0, 0.0, distance])
    return -v * (distance / n)
