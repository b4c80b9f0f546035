"""Compensation: turning the known error into a tool that lands where it is told. No I/O.

One home for both uses of the identified model: the live correction (the command transform,
its limits and filter) and the offline solve (`keo compensate`). "Correction" here always
means the transform applied to a commanded tool pose; the identified model's own parameters
are `keo_service.core.model_corrections.ModelCorrections`.

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
correction: the loop does not integrate, the correction follows the observer.

Pinned frames. A tracker sees the tool only up to the rigid motions its registration and the
probe mount absorb: a model that moved the whole arm by a rigid motion G of the base (or H at
the flange) predicts the same tracker readings with a registration moved by G (a probe by H).
The identified model is therefore stated in the nominal robot's frames: `pinning` finds the G
and H that best carry the nominal robot onto the identified one over the calibration poses,
and the model's tool pose is `base * chain(q) * flange * T_nt` with base = G^-1 and
flange = H^-1 (`[model] base_xyz/rpy, flange_xyz/rpy`). F(q), and so every correction, is then
the kinematic error the model found and nothing the registration already took.

The TCP T_nt is the user's `[tool]`; the tracker's probe (`[tracker] probe_xyz/rpy`) is a
measurement frame only: it enters the measured error, never the frame targets refer to.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol

import numpy as np

from keo_service.core.model_corrections import ModelCorrections
from keo_service.core.rotations import log3_many

if TYPE_CHECKING:
    from keo_service.core.kinematics import RobotModel

# Importing this module loads numpy only (a controller interface and the config reader import
# it); the model's kinematics (Pinocchio) load when a ToolModel is built.

# a received correction older than this is not applied (the controller interfaces' limit);
# the default of `[compensation] max_age_s`
DEFAULT_MAX_AGE_S = 0.1
# metres per radian when position and orientation errors are weighed together, as keo
# analyze's fit weighs them (20 um of position ~ 40 urad of orientation)
ROT_WEIGHT_M = 0.5

# ---- the model's tool pose and its error ---------------------------------------------------


def se3_matrix(xyz: Sequence[float], rotvec: Sequence[float]) -> np.ndarray:
    """4x4 of a translation and a rotation vector."""
    T = np.eye(4)
    T[:3, :3] = exp3(np.asarray(rotvec, dtype=float))
    T[:3, 3] = np.asarray(xyz, dtype=float)
    return T


def _apply(
    T: np.ndarray, R: np.ndarray, p: np.ndarray, right: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """T @ (R, p) @ right for stacks R (N, 3, 3), p (N, 3)."""
    if right is not None:
        p = p + np.einsum("nij,j->ni", R, right[:3, 3])
        R = np.einsum("nij,jk->nik", R, right[:3, :3])
    R2 = np.einsum("ij,njk->nik", T[:3, :3], R)
    p2 = p @ T[:3, :3].T + T[:3, 3]
    return R2, p2


class ToolModel:
    """The tool pose of the nominal robot and of the identified model, for many joint
    configurations at once: the `Chain` over the nominal URDF, with the identified
    `ModelCorrections` (joint offsets, placement, compliance, backlash, cyclic terms, joint maps)
    applied exactly as `keo analyze` fitted them, the pinning (`base`, `flange`: 4x4, see the
    module text) and the flange -> tool transform T_nt (the user's TCP)."""

    def __init__(
        self,
        robot: RobotModel,
        corrections: ModelCorrections | None,
        T_nt: np.ndarray,
        base: np.ndarray | None = None,
        flange: np.ndarray | None = None,
        region: CalibratedRegion | None = None,
    ) -> None:
        from keo_service.core.chain import Chain

        self.robot = robot
        self.chain = Chain(robot)
        self.corrections = corrections
        self.T_nt = np.asarray(T_nt, dtype=float)
        self.base = np.eye(4) if base is None else np.asarray(base, dtype=float)
        self.flange = np.eye(4) if flange is None else np.asarray(flange, dtype=float)
        self.region = region
        self.nq = robot.nq

    def poses(
        self, q: np.ndarray, identified: bool, direction: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Rotations (N, 3, 3) and positions (N, 3) of the tool in the base frame."""
        if not identified:
            R, p = self.chain.flange_frames(np.atleast_2d(q), tail=self.T_nt)
        else:
            R, p = self.chain.flange_frames(
                np.atleast_2d(q),
                head=self.base,
                tail=self.flange @ self.T_nt,
                corr=self.corrections,
                direction=direction if self.corrections is not None else None,
            )
        return np.ascontiguousarray(R.transpose(2, 0, 1)), np.ascontiguousarray(p.T)

    def predicted_errors(
        self, q: np.ndarray, direction: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """F(q) = T_bt(q)^-1 T_bt_model(q) for joints q (N, nq): the model's error in the
        nominal tool frame, as translations (N, 3) m and rotation vectors (N, 3) rad."""
        q2 = np.atleast_2d(np.asarray(q, dtype=float))
        d2 = None if direction is None else np.atleast_2d(direction)
        Rn, pn = self.poses(q2, identified=False)
        Rm, pm = self.poses(q2, identified=True, direction=d2)
        p = np.einsum("nji,nj->ni", Rn, pm - pn)
        r = log3_many(np.einsum("nji,njk->ikn", Rn, Rm))
        return p, r

    def predicted_error(
        self, q: np.ndarray, direction: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """F(q) at one joint configuration (the live feedforward)."""
        p, r = self.predicted_errors(q, direction)
        return p[0], r[0]

    def calibrated_ranges(self) -> list[tuple[float, float] | None]:
        """Each joint's calibrated range: its map's knots, beyond which the map fades out;
        for a joint without a map the calibration poses' range widened by the fade the model
        uses (its `map_taper`, `[model] map_taper_rad`; `MAP_TAPER_RAD` without corrections),
        beyond which nothing identified there was seen (None: neither is known, the model is
        taken as defined everywhere). The same fade as the maps', so a flag and the stated
        accuracy's rise start where the model's corrections stop being trusted."""
        from keo_service.core.model_corrections import MAP_TAPER_RAD

        if self.corrections is None:
            maps: list[tuple[float, float] | None] = [None] * self.nq
            taper = MAP_TAPER_RAD
        else:
            maps = self.corrections.map_ranges()
            taper = float(self.corrections.map_taper)
        if self.region is None or self.region.q_min.size != self.nq:
            return maps
        return [
            rng
            if rng is not None
            else (float(self.region.q_min[j]) - taper, float(self.region.q_max[j]) + taper)
            for j, rng in enumerate(maps)
        ]

    def beyond_ranges(self, q: np.ndarray) -> list[list[tuple[int, float]]]:
        """Per row of q (N, nq): each joint outside its calibrated range and by how far (rad,
        signed: below the range negative)."""
        q = np.atleast_2d(q)
        out: list[list[tuple[int, float]]] = [[] for _ in range(q.shape[0])]
        for j, rng in enumerate(self.calibrated_ranges()):
            if rng is None:
                continue
            below, above = q[:, j] - rng[0], q[:, j] - rng[1]
            for i in np.flatnonzero((below < 0) | (above > 0)):
                out[i].append((j, float(below[i] if below[i] < 0 else above[i])))
        return out

    def outside_calibrated_range(self, q: np.ndarray) -> np.ndarray:
        """Per row of q (N, nq): a joint leaves its calibrated range."""
        return np.array([bool(b) for b in self.beyond_ranges(q)], dtype=bool)


# ---- pinning: the identified model in the nominal robot's frames -----------------------------


def _exp6(x: np.ndarray) -> np.ndarray:
    import pinocchio as pin

    out: np.ndarray = pin.exp6(pin.Motion(x[:3], x[3:])).homogeneous
    return out


def rigid_alignment(
    R_a: np.ndarray,
    p_a: np.ndarray,
    R_b: np.ndarray,
    p_b: np.ndarray,
    position_only: bool = False,
    rot_weight: float = ROT_WEIGHT_M,
) -> tuple[np.ndarray, np.ndarray]:
    """The rigid motions G (left, 4x4) and K (right) for which G A_i K is closest to B_i
    over all poses (positions m, orientations weighed `rot_weight` m per rad; with
    `position_only` only the positions, and K's rotation, which moves no point of A's
    origin, stays identity). Gauss-Newton on (log G, log K) from identity."""
    from scipy.optimize import least_squares  # kept off the live import path

    def residual(x: np.ndarray) -> np.ndarray:
        G = _exp6(x[:6])
        K = _exp6(np.concatenate([x[6:9], np.zeros(3)]) if position_only else x[6:])
        R, p = _apply(G, R_a, p_a, K)
        dp: np.ndarray = (p_b - p).ravel()
        if position_only:
            return dp
        dr = log3_many(np.einsum("nji,njk->ikn", R, R_b)).ravel()
        return np.concatenate([dp, rot_weight * dr])

    n = 9 if position_only else 12
    sol = least_squares(residual, np.zeros(n), method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    x = sol.x
    K = _exp6(np.concatenate([x[6:9], np.zeros(3)]) if position_only else x[6:])
    return _exp6(x[:6]), K


# a stated probe mount this close to the one identified on the nominal-best arm is taken as
# true (a measured mount); farther, it was a planning offset and the arm pins the flange
STATED_MOUNT_TOLERANCE_M = 3e-3
STATED_MOUNT_TOLERANCE_RAD = 10e-3


@dataclass(frozen=True)
class Pinning:
    """The identified model in the nominal robot's frames: `base` (4x4) before the chain,
    `flange` after it (`ToolModel`), and what the registration and the probe become so that
    every tracker reading is predicted as before; `flange_by`: "probe" when the stated probe
    mount pinned the flange, "arm" when the nominal-best arm did."""

    base: np.ndarray
    flange: np.ndarray
    T_bk: np.ndarray  # base -> tracker, in the pinned base frame
    T_np: np.ndarray  # flange -> probe, on the pinned flange
    flange_by: str = "arm"


def pinning(
    robot: RobotModel,
    corrections: ModelCorrections | None,
    q: np.ndarray,
    T_bk: np.ndarray,
    T_np: np.ndarray,
    position_only: bool = False,
    stated_probe: np.ndarray | None = None,
) -> Pinning:
    """From the calibration joints q (N, nq) and the registration (T_bk) and probe (T_np) the
    fit found with the raw chain: G and H with chain_model(q) ~ G chain_nominal(q) H, judged
    at the probe as the tracker saw it, and the model restated with base = G^-1,
    flange = H^-1, T_bk' = G^-1 T_bk and T_np' = H T_np (the same predicted readings).

    The flange's rigid motion H is what the tracker cannot tell from the probe mount. When the
    config states the mount (`stated_probe`, 4x4) and the mount on the nominal-best arm is
    within STATED_MOUNT_TOLERANCE of it, the statement is taken as true: H puts the probe
    exactly there, and the arm keeps the rest as kinematic error (a tool that is the probe
    then lands where the probe is sent)."""
    from keo_service.core.chain import Chain

    chain = Chain(robot)
    q = np.atleast_2d(np.asarray(q, dtype=float))
    Rn, pn = chain.flange_frames(q, tail=T_np)
    Rm, pm = chain.flange_frames(q, tail=T_np, corr=corrections)
    G, K = rigid_alignment(Rn.transpose(2, 0, 1), pn.T, Rm.transpose(2, 0, 1), pm.T, position_only)
    H = T_np @ K @ np.linalg.inv(T_np)
    by = "arm"
    if stated_probe is not None:
        gap = np.linalg.inv(stated_probe) @ H @ T_np
        angle = float(np.linalg.norm(log3_many(gap[:3, :3, None])[0]))
        if np.linalg.norm(gap[:3, 3]) <= STATED_MOUNT_TOLERANCE_M and (
            position_only or angle <= STATED_MOUNT_TOLERANCE_RAD
        ):
            H = stated_probe @ np.linalg.inv(T_np)
            if position_only:  # the probe's orientation was never seen: keep the arm's
                H[:3, :3] = (T_np @ K @ np.linalg.inv(T_np))[:3, :3]
                H[:3, 3] = stated_probe[:3, 3] - H[:3, :3] @ T_np[:3, 3]
            by = "probe"
    G_inv, H_inv = np.linalg.inv(G), np.linalg.inv(H)
    return Pinning(base=G_inv, flange=H_inv, T_bk=G_inv @ T_bk, T_np=H @ T_np, flange_by=by)


# ---- where the model is valid: the calibrated region -----------------------------------------

# tool orientation bands: the angle between the tool's z axis and the base's -z (pointing down)
BANDS = (("down", 0.0, 45.0), ("side", 45.0, 135.0), ("up", 135.0, 180.0))


def orientation_band(R: np.ndarray) -> list[str]:
    """The band of each tool orientation (N, 3, 3): "down", "side" or "up" (its z axis within
    45 degrees of the base's -z, within 45 degrees of horizontal, or within 45 of +z)."""
    tilt = np.degrees(np.arccos(np.clip(-R[:, 2, 2], -1.0, 1.0)))
    out = []
    for a in tilt:
        out.append(next(name for name, lo, hi in BANDS if lo <= a <= hi))
    return out


@dataclass(frozen=True)
class RegionBand:
    band: str
    poses: int
    lower: np.ndarray  # (3,) m, base frame
    upper: np.ndarray


@dataclass(frozen=True)
class CalibratedRegion:
    """Where the calibration poses took the tool (the user's TCP on the nominal robot): the
    box of its positions in the base frame per orientation band, and each joint's range."""

    q_min: np.ndarray
    q_max: np.ndarray
    bands: tuple[RegionBand, ...]

    def beyond(self, R: np.ndarray, p: np.ndarray) -> list[tuple[str, float] | None]:
        """Per pose: None inside its band's box, else (band, distance m outside the box; inf
        when no calibration pose had that orientation)."""
        out: list[tuple[str, float] | None] = []
        boxes = {b.band: b for b in self.bands}
        for band, pos in zip(orientation_band(R), p, strict=True):
            box = boxes.get(band)
            if box is None:
                out.append((band, math.inf))
                continue
            gap = np.maximum(box.lower - pos, 0.0) + np.maximum(pos - box.upper, 0.0)
            d = float(np.linalg.norm(gap))
            out.append(None if d == 0.0 else (band, d))
        return out


def calibrated_region(model: ToolModel, q: np.ndarray) -> CalibratedRegion:
    """The region of calibration joints q (N, nq) for `model`'s tool."""
    q = np.atleast_2d(np.asarray(q, dtype=float))
    R, p = model.poses(q, identified=False)
    names = np.array(orientation_band(R))
    bands = []
    for name, _lo, _hi in BANDS:
        rows = names == name
        if rows.any():
            bands.append(
                RegionBand(name, int(rows.sum()), p[rows].min(axis=0), p[rows].max(axis=0))
            )
    return CalibratedRegion(q.min(axis=0), q.max(axis=0), tuple(bands))


# ---- live: the correction to send now, its limits and filter ---------------------------------
def exp3(r: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (Rodrigues; exact for small angles too)."""
    theta = math.sqrt(float(r @ r))
    K = np.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
    if theta < 1e-8:  # series: sin(t)/t ~ 1 - t^2/6, (1 - cos t)/t^2 ~ 1/2 - t^2/24
        a, b = 1.0 - theta * theta / 6.0, 0.5 - theta * theta / 24.0
    else:
        a, b = math.sin(theta) / theta, (1.0 - math.cos(theta)) / (theta * theta)
    out: np.ndarray = np.eye(3) + a * K + b * (K @ K)
    return out


def invert(translation: np.ndarray, rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The inverse of the transform (p, r): (-R^T p, -r), with R^T p by Rodrigues on plain
    floats, p - a (r x p) + b r x (r x p) (the terms of `exp3`, transposed): no 3x3 matrix
    is built, a live correction takes one per estimate (docs/performance.md)."""
    px, py, pz = np.asarray(translation, dtype=float).tolist()
    r = np.asarray(rotation, dtype=float)
    rx, ry, rz = r.tolist()
    t2 = rx * rx + ry * ry + rz * rz
    if t2 < 1e-16:  # theta < 1e-8: exp3's series
        a, b = 1.0 - t2 / 6.0, 0.5 - t2 / 24.0
    else:
        theta = math.sqrt(t2)
        a, b = math.sin(theta) / theta, (1.0 - math.cos(theta)) / t2
    cx, cy, cz = ry * pz - rz * py, rz * px - rx * pz, rx * py - ry * px  # r x p
    dx, dy, dz = ry * cz - rz * cy, rz * cx - rx * cz, rx * cy - ry * cx  # r x (r x p)
    back = np.array([px - a * cx + b * dx, py - a * cy + b * dy, pz - a * cz + b * dz])
    return -back, -r


def compose(
    a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """A * B for transforms given as (translation, rotation vector)."""
    Ra, Rb = exp3(a[1]), exp3(b[1])
    return a[0] + Ra @ b[0], log3_many((Ra @ Rb)[:, :, None])[0]


@dataclass(frozen=True)
class CompensationLimits:
    """[compensation] in SI units, and how old a received correction may be when applied."""

    max_m: float = 5e-3
    max_rad: float = 5e-3
    max_rate_m_s: float = 0.05  # the rotation's rate is limited at the same number in rad/s
    max_age_s: float = DEFAULT_MAX_AGE_S

    @classmethod
    def from_config_values(
        cls, max_mm: float, max_mrad: float, max_rate_mm_s: float, max_age_s: float
    ) -> CompensationLimits:
        return cls(max_mm * 1e-3, max_mrad * 1e-3, max_rate_mm_s * 1e-3, max_age_s)


def _clamp_norm(v: np.ndarray, limit: float) -> tuple[np.ndarray, bool]:
    # the same sqrt(v . v) that `np.linalg.norm` takes for a vector, on plain floats (four
    # calls per live correction: a fifth of its cost, docs/performance.md)
    x, y, z = v.tolist()
    size = math.sqrt(x * x + y * y + z * z)
    if size > limit:
        return v * (limit / size), True
    return v, False


class CorrectionLike(Protocol):
    """What `correction_to_send` reads of a received correction (keo's CorrectionMessage)."""

    @property
    def host_ns(self) -> int: ...
    @property
    def translation(self) -> Sequence[float]: ...
    @property
    def rotation(self) -> Sequence[float]: ...
    @property
    def valid(self) -> bool: ...


def correction_to_send(
    latest: CorrectionLike | None, limits: CompensationLimits, now_ns: int
) -> tuple[list[float], list[float]]:
    """For a controller interface that sends a correction with every reply (UR registers,
    KUKA RSI, ABB EGM): the translation (m) and rotation vector (rad) to send now, in the
    tool frame and meant for the right of the commanded tool pose (T_cmd = T_goal * C, see
    the module text). Zero when there is none, when it is not valid, or when it is older than
    `limits.max_age_s` (host clock, ns since the epoch); never larger than the limits."""
    zero = [0.0, 0.0, 0.0]
    if latest is None or not latest.valid:
        return zero, list(zero)
    if (now_ns - latest.host_ns) * 1e-9 > limits.max_age_s:
        return zero, list(zero)
    p = np.asarray(latest.translation, dtype=float)
    r = np.asarray(latest.rotation, dtype=float)
    finite = bool(np.all(np.isfinite(p)) and np.all(np.isfinite(r)))
    if p.shape != (3,) or r.shape != (3,) or not finite:
        return zero, list(zero)
    p, _ = _clamp_norm(p, limits.max_m)
    r, _ = _clamp_norm(r, limits.max_rad)
    return p.tolist(), r.tolist()


@dataclass
class LiveCorrection:
    """One correction: total = feedback then feedforward (each (translation, rotation)),
    zero when not valid."""

    translation: np.ndarray
    rotation: np.ndarray
    feedback: tuple[np.ndarray, np.ndarray]
    feedforward: tuple[np.ndarray, np.ndarray]
    valid: bool
    reason: str = ""
    clamped: bool = False


def feedback_part(
    estimate: Sequence[float] | np.ndarray, probe_in_tool: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """C_fb = T_ts^-1 from the estimate [p_ts; r_ts] (3 numbers for a single reflector: no
    rotation known, none corrected). The estimate is the probe's error E_p; with the probe
    elsewhere than the TCP (`probe_in_tool` = T_tp, 4x4) the tool's is T_tp E_p T_tp^-1."""
    e = np.asarray(estimate, dtype=float)
    p, r = e[:3], (e[3:6] if e.size >= 6 else np.zeros(3))
    if probe_in_tool is not None:
        R_tp, d = probe_in_tool[:3, :3], probe_in_tool[:3, 3]
        r = R_tp @ r
        p = R_tp @ p + d - exp3(r) @ d
    return invert(p, r)


class FeedforwardModel(Protocol):
    """What the filter needs of a model (`ToolModel`)."""

    def predicted_error(
        self, q: np.ndarray, direction: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]: ...

    def outside_calibrated_range(self, q: np.ndarray) -> np.ndarray: ...


class CorrectionFilter:
    """The live correction from each estimate: validity, the feedforward of a model, and the
    [compensation] limits on size and rate of change (clamps counted in `counters`)."""

    def __init__(
        self,
        limits: CompensationLimits,
        model: FeedforwardModel | None = None,
        probe_in_tool: np.ndarray | None = None,
    ) -> None:
        self.limits = limits
        self.model = model
        self.probe_in_tool = probe_in_tool  # T_tp: the estimate is the probe's error
        self.counters: dict[str, int] = {
            "corrections": 0,
            "corrections_invalid": 0,
            "corrections_clamped_size": 0,
            "corrections_clamped_rate": 0,
        }
        self._last: tuple[float, np.ndarray, np.ndarray] | None = None  # t, p, r sent

    def step(
        self,
        t: float,
        estimate: Sequence[float] | np.ndarray,
        joints: np.ndarray | None,
        invalid_reason: str = "",
        direction: np.ndarray | None = None,
    ) -> LiveCorrection:
        """`t`: stream time (s) of the estimate; `invalid_reason` non-empty for a held step,
        stale input or joints outside the calibrated range (the caller's flags)."""
        self.counters["corrections"] += 1
        zero = np.zeros(3)
        values = np.asarray(estimate, dtype=float)
        if not invalid_reason and not np.isfinite(values).all():
            invalid_reason = "non_finite_estimate"
        if not invalid_reason and self.model is not None and joints is None:
            invalid_reason = "no_joints"
        if invalid_reason:
            self.counters["corrections_invalid"] += 1
            self._last = (t, zero, zero)
            return LiveCorrection(zero, zero, (zero, zero), (zero, zero), False, invalid_reason)
        fb = feedback_part(values, self.probe_in_tool)
        ff: tuple[np.ndarray, np.ndarray] = (zero, zero)
        if self.model is not None and joints is not None:
            if self.model.outside_calibrated_range(np.asarray(joints))[0]:
                self.counters["corrections_invalid"] += 1
                self._last = (t, zero, zero)
                return LiveCorrection(
                    zero, zero, (zero, zero), (zero, zero), False, "outside_calibrated_range"
                )
            ff = invert(*self.model.predicted_error(np.asarray(joints), direction))
        p, r = compose(fb, ff) if self.model is not None else fb
        p, size_p = _clamp_norm(p, self.limits.max_m)
        r, size_r = _clamp_norm(r, self.limits.max_rad)
        clamped = size_p or size_r
        if clamped:
            self.counters["corrections_clamped_size"] += 1
        if self._last is None:  # nothing applied before: ramp up from zero
            self._last = (t, zero, zero)
        dt = t - self._last[0]
        step_limit = self.limits.max_rate_m_s * max(dt, 0.0)
        dp, rate_p = _clamp_norm(p - self._last[1], step_limit)
        dr, rate_r = _clamp_norm(r - self._last[2], step_limit)
        if rate_p or rate_r:
            self.counters["corrections_clamped_rate"] += 1
            clamped = True
            p, r = self._last[1] + dp, self._last[2] + dr
        self._last = (t, p, r)
        return LiveCorrection(p, r, fb, ff, True, "", clamped)


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
    # each flag with its detail, as the output file writes it: which joint and how far
    # outside its calibrated range, which orientation band and how far outside its box
    details: list[list[str]] = field(default_factory=list)
    # the model's predicted deviation from the nominal robot at q_goal (F), m and rad
    predicted_m: np.ndarray | None = None
    predicted_rad: np.ndarray | None = None
    # how far each goal lies outside the box the calibration poses' tool swept in its
    # orientation band (m; 0 inside, inf for a band no calibration pose had); None: the
    # model states no region
    outside_region_m: np.ndarray | None = None


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
    beyond = model.beyond_ranges(sol.q)
    region = None if model.region is None else model.region.beyond(R_goal, p_goal)
    names = model.robot.joint_names
    robot = model.robot
    beyond_limits = np.any((sol.q < robot.lower - 1e-12) | (sol.q > robot.upper + 1e-12), axis=1)
    flags: list[list[str]] = []
    details: list[list[str]] = []
    for i in range(sol.q.shape[0]):
        row: list[str] = []
        text: list[str] = []
        if beyond[i]:
            row.append("outside_calibrated_range")
            text.append(
                "outside_calibrated_range("
                + ", ".join(f"{names[j]} {d:+.3f} rad" for j, d in beyond[i])
                + ")"
            )
        far = sol.residual_m[i] > UNREACHABLE_M or sol.residual_rad[i] > UNREACHABLE_M
        if far or beyond_limits[i] or not nominal_ok[i]:
            row.append("unreachable")
            text.append("unreachable")
        elif not sol.converged[i]:
            row.append("not_converged")
            text.append("not_converged")
        if ratio[i] < SINGULAR_RATIO:
            row.append("near_singular")
            text.append("near_singular")
        flags.append(row)
        details.append(text)
    pred_p, pred_r = model.predicted_errors(start, direction)
    return Compensated(
        q=sol.q,
        R_command=R_cmd,
        p_command=p_cmd,
        correction_m=np.linalg.norm(p_cmd - p_goal, axis=1),
        correction_rad=corr_rad,
        residual_m=sol.residual_m,
        residual_rad=sol.residual_rad,
        flags=flags,
        details=details,
        predicted_m=np.linalg.norm(pred_p, axis=1),
        predicted_rad=np.linalg.norm(pred_r, axis=1),
        outside_region_m=None
        if region is None
        else np.array([0.0 if r is None else r[1] for r in region]),
    )
