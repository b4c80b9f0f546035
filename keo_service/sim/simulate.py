"""A simulator that knows the truth: a "true" robot that differs from the nominal model, the
streams real devices would produce from it, and the true error at every tracker sample.

Scenarios are seeded; `--set key=value` overrides any Scenario field. No network.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

from keo_service.core.errors import ConfigError
from keo_service.core.kinematics import (
    Cell,
    channels_for,
    flange_pose,
    pose_error,
    position_error,
    quat_wxyz,
)
from keo_service.core.model_corrections import approach_directions
from keo_service.io.interchange import (
    EncoderData,
    TrackerData,
    write_encoder,
    write_tracker,
    write_truth,
)
from keo_service.sim.trajectories import (
    Segment,
    Trajectory,
    cartesian_line_moves,
    piecewise_joint_moves,
    sinusoid_path,
    solve_ik,
)

SCENARIOS = ("paper-step", "paper-vertical", "workspace", "path", "static-poses")


@dataclass(frozen=True)
class Scenario:
    name: str
    duration_s: float = 0.0  # 0: the motion's own length
    encoder_rate_hz: float = 39.5
    encoder_rate_std_hz: float = 6.0
    tracker_rate_hz: float = 99.6
    tracker_rate_std_hz: float = 15.5
    delay_s: float = 0.028  # tracker stamps lag the encoder's by this much on average
    delay_jitter_s: float = 0.003  # std of the delay's random part
    drift_ppm: float = 0.0  # tracker clock runs fast by this much relative to the encoder's
    delay_change_s: float = 0.0  # the delay grows by this much half-way (a changed path)
    position_noise_m: float = 20e-6
    rotation_noise_rad: float = 50e-6
    drop_probability: float = 0.005
    geometric_errors: bool = True
    tool_error_only: bool = False  # of the geometric errors only the tool's: a constant error
    path_speed: float = 1.0  # path: the motion played this many times faster
    error_drift_m_per_s: float = 0.0  # slow drift of the true error (e.g. thermal growth)
    position_only: bool = False
    speed_m_s: float = 0.1  # paper-vertical
    stroke_m: float = 1.0  # paper-vertical
    dwell_s: float = 4.0  # paper-vertical
    moves: int = 8  # workspace
    poses: int = 400  # static-poses: stop-and-measure poses over the workspace
    # effects of the real arm beyond geometry (for keo analyze to find)
    compliance_rad_per_nm: float = 0.0  # every joint deflects this much per N m of gravity
    backlash_rad: float = 0.0  # every joint lags by this much behind its direction of motion
    cyclic_rad: float = 0.0  # 1st-harmonic error of joints 2 and 3 (a gear's runout)
    # angle ripple (an encoder or gear transmission error): amplitude and period in the joint's
    # own angle, on the joints listed (1-based, comma-separated, e.g. "2,3")
    ripple_rad: float = 0.0
    ripple_period_rad: float = 0.3
    ripple_joints: str = "2,3"
    thermal_m_per_c: float = 0.0  # the sensor drifts along base x with temperature
    tracker_scale_ppm: float = 0.0  # a tracker distance-scale error (geometry absorbs it)
    periodic_drift_m: float = 0.0  # the sensor wanders along base x, 3 cycles per recording
    # (a cyclic disturbance in time that no effect in keo's library models)


def make_scenario(name: str, overrides: dict[str, str] | None = None) -> Scenario:
    if name not in SCENARIOS:
        raise ConfigError(
            "--scenario", "scenario", f"unknown scenario '{name}'; known: " + ", ".join(SCENARIOS)
        )
    base = Scenario(name=name)
    if name == "paper-step":
        base = dataclasses.replace(base, duration_s=12.0)
    elif name in ("workspace", "path"):
        base = dataclasses.replace(base, duration_s=60.0 if name == "path" else 0.0)
    return apply_overrides(base, overrides or {})


def apply_overrides(scenario: Scenario, overrides: dict[str, str]) -> Scenario:
    fields = {f.name: f for f in dataclasses.fields(Scenario)}
    changes: dict[str, Any] = {}
    for key, text in overrides.items():
        if key not in fields or key == "name":
            raise ConfigError(
                "--set",
                key,
                "unknown scenario parameter; known: " + ", ".join(k for k in fields if k != "name"),
            )
        kind = type(getattr(scenario, key))
        try:
            if kind is bool:
                if text.lower() not in ("true", "false", "1", "0"):
                    raise ValueError
                value: object = text.lower() in ("true", "1")
            else:
                value = kind(text)
        except ValueError:
            raise ConfigError("--set", key, f"'{text}' is not a {kind.__name__}") from None
        if isinstance(value, float) and not math.isfinite(value):
            raise ConfigError("--set", key, "must be finite")
        changes[key] = value
    return dataclasses.replace(scenario, **changes)


@dataclass
class TrueRobot:
    """The real arm: perturbed joint placements, joint zero offsets, a true sensor mount."""

    model: pin.Model
    data: pin.Data
    flange_frame_id: int
    joint_offsets: np.ndarray
    T_ns: pin.SE3  # flange -> real sensor frame
    T_bk: pin.SE3  # base -> real tracker frame
    parameters: dict[str, list[float]] = field(default_factory=dict)

    def sensor_pose(self, q: np.ndarray, extra: np.ndarray | None = None) -> pin.SE3:
        q_true = q + self.joint_offsets + (0.0 if extra is None else extra)
        pin.framesForwardKinematics(self.model, self.data, q_true)
        return self.data.oMf[self.flange_frame_id] * self.T_ns


def make_true_robot(
    cell: Cell, rng: np.random.Generator, geometric_errors: bool, tool_only: bool = False
) -> TrueRobot:
    model = pin.Model(cell.robot.model)
    nq = model.nq
    offsets = np.zeros(nq)
    params: dict[str, list[float]] = {}
    T_ns = cell.T_nt
    if geometric_errors:
        for j in range(1, model.njoints):
            dp = rng.uniform(0.1e-3, 1.0e-3, 3) * rng.choice([-1.0, 1.0], 3)
            dr = rng.uniform(0.01, 0.05, 3) * math.pi / 180.0 * rng.choice([-1.0, 1.0], 3)
            if not tool_only:
                model.jointPlacements[j] = model.jointPlacements[j] * pin.exp6(pin.Motion(dp, dr))
                params[f"joint{j}_placement_error"] = [*dp.tolist(), *dr.tolist()]
        offsets = rng.uniform(0.01, 0.05, nq) * math.pi / 180.0 * rng.choice([-1.0, 1.0], nq)
        if tool_only:
            offsets = np.zeros(nq)
        params["joint_zero_offsets_rad"] = offsets.tolist()
        tool = pin.exp6(pin.Motion(rng.normal(0, 0.2e-3, 3), rng.normal(0, 0.2e-3, 3)))
        T_ns = cell.T_nt * tool
        params["tool_error"] = [*tool.translation.tolist(), *pin.log3(tool.rotation).tolist()]
    return TrueRobot(
        model=model,
        data=model.createData(),
        flange_frame_id=cell.robot.flange_frame_id,
        joint_offsets=offsets,
        T_ns=T_ns,
        T_bk=cell.T_bk,
        parameters=params,
    )


# ---- scenario motions ------------------------------------------------------------------------


def _mh_style_home(cell: Cell) -> np.ndarray:
    """A pose with the flange pointing down in front of the robot (any 6-joint arm)."""
    robot = cell.robot
    q = np.clip(np.zeros(robot.nq), robot.lower, robot.upper)
    if robot.joint_names[:3] == ("joint_1_s", "joint_2_l", "joint_3_u"):
        # L - U - B = pi/2 turns the flange's Z straight down (docs/design.md §7 axes)
        q[:6] = [0.0, 0.35, 0.05, 0.0, 0.35 - 0.05 - math.pi / 2, 0.0]
    else:
        q[:6] = [0.0, -1.9, 1.9, -1.57, -1.57, 0.0]
    return q


def motion_for(
    scenario: Scenario, cell: Cell, rng: np.random.Generator
) -> tuple[Trajectory, float]:
    robot = cell.robot
    home = _mh_style_home(cell)
    if scenario.name == "paper-step":
        return piecewise_joint_moves([], home), scenario.duration_s
    if scenario.name == "paper-vertical":
        data = robot.create_data()
        start = flange_pose(robot, data, home)
        if robot.joint_names[0] == "joint_1_s":
            # MH180: flange 1.6 m out and 2.2 m up, so two 1 m strokes down stay in reach
            start = pin.SE3(start.rotation, np.array([1.6, 0.0, 2.2]))
            home = solve_ik(robot, data, start, home)
        p0 = start.translation
        down = np.array([0.0, 0.0, -scenario.stroke_m])
        traj, total = cartesian_line_moves(
            robot,
            home,
            [p0 + down, p0 + 2 * down],
            speed=scenario.speed_m_s,
            accel=0.5,
            dwell=scenario.dwell_s,
        )
        return traj, scenario.duration_s or total
    if scenario.name == "workspace":
        span = 0.6 * np.minimum(robot.upper - robot.lower, 2 * math.pi) / 2
        centre = np.clip(home, robot.lower + span, robot.upper - span)
        vmax = 0.5 * robot.velocity_limit
        amax = 2.0 * vmax
        segments, q_prev, t = [], home.copy(), 1.0
        data = robot.create_data()
        for _ in range(scenario.moves):
            for _attempt in range(100):
                q_next = centre + rng.uniform(-1, 1, robot.nq) * span
                if flange_pose(robot, data, q_next).translation[2] > 0.3:
                    break
            dq = np.abs(q_next - q_prev)
            accel_time = float(np.max(vmax / amax))
            duration = float(np.max(dq / vmax)) + accel_time
            duration = max(duration, 2 * accel_time, float(np.max(2 * np.sqrt(dq / amax))))
            segments.append(Segment(t, duration, accel_time, q_prev, q_next))
            t += duration + 1.0
            q_prev = q_next
        return piecewise_joint_moves(segments, home), scenario.duration_s or t
    # path: continuous smooth motion on all joints, within half the speed limits
    k = 3
    freq = rng.uniform(0.03, 0.15, (robot.nq, k))
    amp = rng.uniform(0.05, 0.25, (robot.nq, k))
    vmax = 0.5 * robot.velocity_limit
    scale = np.minimum(1.0, vmax / np.sum(2 * np.pi * freq * amp, axis=1))
    amp = amp * scale[:, None]
    phase = rng.uniform(0, 2 * np.pi, (robot.nq, k))
    freq = freq * scenario.path_speed
    return sinusoid_path(home, amp, freq, phase), scenario.duration_s or 60.0


# ---- streams -----------------------------------------------------------------------------------


def _sample_times(
    rng: np.random.Generator, rate: float, rate_std: float, duration: float
) -> np.ndarray:
    period = 1.0 / rate
    period_std = rate_std / (rate * rate)
    n = int(duration * rate * 1.5) + 10
    periods = np.clip(rng.normal(period, period_std, n), 0.3 * period, 3.0 * period)
    times = np.cumsum(periods) - periods[0] * rng.uniform()
    kept: np.ndarray = times[(times >= 0) & (times <= duration)]
    return kept


def _monotonic(t: np.ndarray, min_step: float = 1e-4) -> np.ndarray:
    out = t.copy()
    for i in range(1, out.size):
        if out[i] <= out[i - 1]:
            out[i] = out[i - 1] + min_step
    return out


@dataclass
class SimulatedRun:
    scenario: Scenario
    encoder: EncoderData
    tracker: TrackerData
    truth_t: np.ndarray
    truth: np.ndarray  # true error at each tracker row (the instant it measured)
    channels: tuple[str, ...]
    true_robot: TrueRobot
    physical_t: np.ndarray  # the instant each tracker row measured (encoder clock)
    moving: np.ndarray  # per tracker row: the robot was moving then


def simulate(cell: Cell, scenario: Scenario, seed: int = 0) -> SimulatedRun:
    if scenario.name == "static-poses":
        return simulate_static(cell, scenario, seed)
    rng = np.random.default_rng(seed)
    true_robot = make_true_robot(cell, rng, scenario.geometric_errors, scenario.tool_error_only)
    trajectory, duration = motion_for(scenario, cell, rng)
    nominal_data = cell.robot.create_data()

    # encoder: stamped on receipt; the encoder clock is the reference clock
    t_enc = _sample_times(rng, scenario.encoder_rate_hz, scenario.encoder_rate_std_hz, duration)
    t_enc = t_enc[rng.uniform(size=t_enc.size) >= scenario.drop_probability]
    q_enc = trajectory(t_enc)

    # tracker: measures at tau, its stamp arrives late by delay + jitter, on a drifting clock
    tau = _sample_times(rng, scenario.tracker_rate_hz, scenario.tracker_rate_std_hz, duration)
    tau = tau[rng.uniform(size=tau.size) >= scenario.drop_probability]
    stamps = (
        tau * (1.0 + scenario.drift_ppm * 1e-6)
        + scenario.delay_s
        + rng.normal(0.0, scenario.delay_jitter_s, tau.size)
    )
    if scenario.delay_change_s:
        stamps = stamps + np.where(tau > duration / 2, scenario.delay_change_s, 0.0)
    keep = np.argsort(stamps, kind="stable")
    tau, stamps = tau[keep], _monotonic(stamps[keep])
    q_phys = trajectory(tau)

    n = tau.size
    p = np.empty((n, 3))
    quat = np.empty((n, 4))
    channels = channels_for(scenario.position_only)
    truth = np.empty((n, len(channels)))
    T_kb = true_robot.T_bk.inverse()
    for i in range(n):
        T_bs = true_robot.sensor_pose(q_phys[i])
        if scenario.error_drift_m_per_s:
            T_bs = pin.SE3(
                T_bs.rotation,
                T_bs.translation
                + np.array([1.0, 0.0, 0.0]) * scenario.error_drift_m_per_s * tau[i],
            )
        T_bt = flange_pose(cell.robot, nominal_data, q_phys[i]) * cell.T_nt
        T_bs_seen = cell.T_bk * (T_kb * T_bs)  # what the config's registration makes of it
        if scenario.position_only:
            truth[i] = position_error(T_bt, T_bs_seen.translation)
        else:
            truth[i] = pose_error(T_bt, T_bs_seen)
        T_ks = T_kb * T_bs
        noise_rot = pin.exp3(rng.normal(0.0, scenario.rotation_noise_rad, 3))
        p[i] = T_ks.translation + rng.normal(0.0, scenario.position_noise_m, 3)
        quat[i] = quat_wxyz(T_ks.rotation @ noise_rot)

    tracker = TrackerData(t=stamps, p=p, quat=None if scenario.position_only else quat)
    q_ahead = trajectory(tau + 1e-3)
    moving = np.max(np.abs(q_ahead - q_phys), axis=1) > 1e-7
    return SimulatedRun(
        scenario=scenario,
        encoder=EncoderData(t=t_enc, q=q_enc),
        tracker=tracker,
        truth_t=stamps,
        truth=truth,
        channels=channels,
        true_robot=true_robot,
        physical_t=tau,
        moving=moving,
    )


def _static_poses(cell: Cell, scenario: Scenario, rng: np.random.Generator) -> np.ndarray:
    robot = cell.robot
    data = robot.create_data()
    home = _mh_style_home(cell)
    span = 0.45 * np.minimum(robot.upper - robot.lower, 2 * math.pi) / 2
    centre = np.clip(home, robot.lower + span, robot.upper - span)
    poses: list[np.ndarray] = []
    while len(poses) < scenario.poses:
        q = centre + rng.uniform(-1, 1, robot.nq) * span
        if flange_pose(robot, data, q).translation[2] > 0.3:
            poses.append(q)
    return np.array(poses)


def angle_ripple(scenario: Scenario, q: np.ndarray) -> np.ndarray:
    """The injected angle ripple at joints q (nq,): zero unless `ripple_rad` is set."""
    out = np.zeros_like(q)
    if scenario.ripple_rad:
        for j in (int(k) - 1 for k in scenario.ripple_joints.split(",") if k.strip()):
            out[j] = scenario.ripple_rad * math.sin(2 * math.pi * q[j] / scenario.ripple_period_rad)
    return out


def simulate_static(cell: Cell, scenario: Scenario, seed: int = 0) -> SimulatedRun:
    """Stop-and-measure: one encoder row and one tracker row per pose, at the same t."""
    rng = np.random.default_rng(seed)
    true_robot = make_true_robot(cell, rng, scenario.geometric_errors, scenario.tool_error_only)
    q = _static_poses(cell, scenario, rng)
    n = q.shape[0]
    t = np.arange(n, dtype=float) * 10.0
    direction = approach_directions(q)
    model, gdata = cell.robot.model, cell.robot.model.createData()
    temperature = 22.0 + np.cumsum(rng.normal(0, 0.05, n))
    T_kb = true_robot.T_bk.inverse()
    p, quat = np.empty((n, 3)), np.empty((n, 4))
    nominal = cell.robot.create_data()
    truth = np.empty((n, 3 if scenario.position_only else 6))
    for i in range(n):
        extra = np.zeros(cell.robot.nq)
        if scenario.compliance_rad_per_nm:
            tau = pin.computeGeneralizedGravity(model, gdata, q[i])
            extra += scenario.compliance_rad_per_nm * tau
        extra += scenario.backlash_rad * direction[i]
        if scenario.cyclic_rad:
            extra[1:3] += scenario.cyclic_rad * np.sin(q[i, 1:3])
        extra += angle_ripple(scenario, q[i])
        T_bs = true_robot.sensor_pose(q[i], extra)
        if scenario.periodic_drift_m:
            wander = scenario.periodic_drift_m * math.sin(6 * math.pi * t[i] / t[-1])
            T_bs = pin.SE3(T_bs.rotation, T_bs.translation + np.array([wander, 0.0, 0.0]))
        if scenario.thermal_m_per_c:
            T_bs = pin.SE3(
                T_bs.rotation,
                T_bs.translation
                + np.array([scenario.thermal_m_per_c * (temperature[i] - 22.0), 0.0, 0.0]),
            )
        T_ks = T_kb * T_bs
        p_k = T_ks.translation * (1.0 + scenario.tracker_scale_ppm * 1e-6)
        T_bt = flange_pose(cell.robot, nominal, q[i]) * cell.T_nt
        seen = cell.T_bk * T_ks
        truth[i] = (
            position_error(T_bt, seen.translation)
            if scenario.position_only
            else pose_error(T_bt, seen)
        )
        p[i] = p_k + rng.normal(0.0, scenario.position_noise_m, 3)
        quat[i] = quat_wxyz(T_ks.rotation @ pin.exp3(rng.normal(0, scenario.rotation_noise_rad, 3)))
    tracker = TrackerData(
        t=t,
        p=p,
        quat=None if scenario.position_only else quat,
        extra={"temperature_c": temperature},
    )
    return SimulatedRun(
        scenario=scenario,
        encoder=EncoderData(t=t, q=q),
        tracker=tracker,
        truth_t=t,
        truth=truth,
        channels=channels_for(scenario.position_only),
        true_robot=true_robot,
        physical_t=t,
        moving=np.zeros(n, dtype=bool),
    )


def write_run(run: SimulatedRun, out_dir: str | Path) -> None:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_encoder(out / "encoder.csv", run.encoder)
    write_tracker(out / "tracker.csv", run.tracker)
    write_truth(out / "truth.csv", run.truth_t, run.truth, run.channels)
