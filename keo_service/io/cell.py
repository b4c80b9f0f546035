"""The core's objects built from a config: robot model, cell, corrections, estimator settings
and delay model. The one place where config keys meet the math's types."""

from __future__ import annotations

import dataclasses

import numpy as np
import pinocchio as pin

from keo_service.core.compensation import CalibratedRegion, RegionBand, ToolModel
from keo_service.core.errors import ConfigError
from keo_service.core.kinematics import Cell, RobotModel, load_robot, se3_from_xyz_rpy
from keo_service.core.model_corrections import ModelCorrections
from keo_service.core.settings import EstimatorSettings
from keo_service.core.timing import DelayModel
from keo_service.io.config import Config, ModelConfig, TimingConfig


def robot_from_config(config: Config) -> RobotModel:
    """The nominal robot of a config (errors name the config key)."""
    return load_robot(
        config.robot.urdf, config.robot.base_frame, config.robot.flange_frame, source=config.source
    )


def probe_frame(config: Config) -> pin.SE3:
    """The tracker's probe in the flange frame: `[tracker] probe_xyz/probe_rpy`, else the
    config's [tool] (a config whose tool is the probe)."""
    t = config.tracker
    if t.probe_xyz is None and t.probe_rpy is None:
        return se3_from_xyz_rpy(config.tool.xyz, config.tool.rpy)
    return se3_from_xyz_rpy(t.probe_xyz or [0.0, 0.0, 0.0], t.probe_rpy or [0.0, 0.0, 0.0])


def probe_in_tool(config: Config) -> np.ndarray | None:
    """T_tp (4x4): the probe seen from the user's TCP, None when they are one frame (the
    measured error is the probe's; this carries it to the tool)."""
    T_tp = se3_from_xyz_rpy(config.tool.xyz, config.tool.rpy).actInv(probe_frame(config))
    if np.allclose(T_tp.homogeneous, np.eye(4), atol=1e-15):
        return None
    out: np.ndarray = T_tp.homogeneous
    return out


def pinning_frames(config: Config) -> tuple[np.ndarray | None, np.ndarray | None]:
    """`[model] base_xyz/rpy` and `flange_xyz/rpy` as 4x4 (None where not given)."""
    m = config.model
    out: list[np.ndarray | None] = []
    for key, xyz, rpy in (("base", m.base_xyz, m.base_rpy), ("flange", m.flange_xyz, m.flange_rpy)):
        if not xyz and not rpy:
            out.append(None)
            continue
        if len(xyz) != 3 or len(rpy) != 3:
            raise ConfigError(
                config.source, f"model.{key}_xyz", f"{key}_xyz and {key}_rpy: 3 numbers each"
            )
        out.append(se3_from_xyz_rpy(xyz, rpy).homogeneous)
    return out[0], out[1]


def cell_from_config(config: Config) -> Cell:
    """The cell of a config: robot (with identified geometry and the model's pinned base and
    flange applied), the measurement frame (the probe) and tracker registration, and the
    identified corrections of its [model] section. The measured error is the probe's: the
    sensor compared with where the model puts the probe (`probe_in_tool` carries it to the
    user's TCP).

    Args:
        config: a loaded config (`load_config`).

    Returns:
        The `Cell` the estimator computes the error with (lengths m, angles rad).

    Raises:
        ConfigError: the URDF or a frame named in the config is missing or unusable.
    """
    robot = robot_from_config(config)
    corrections = corrections_from_config(config.model, robot.nq, config.source)
    base, flange = pinning_frames(config)
    nominal = None
    if corrections is not None:
        nominal = robot.model
        if corrections.placement is not None and np.any(corrections.placement):
            robot = _with_placement_corrections(robot, corrections.placement)
    if base is not None or flange is not None:
        nominal = robot.model if nominal is None else nominal
        robot = _with_pinning(robot, base, flange)
    return Cell(
        robot=robot,
        T_nt=probe_frame(config),
        T_bk=se3_from_xyz_rpy(config.tracker.xyz, config.tracker.rpy),
        corrections=corrections,
        nominal_model=nominal,
        gravity_data=None if nominal is None else nominal.createData(),
    )


def _with_placement_corrections(robot: RobotModel, placement: np.ndarray) -> RobotModel:
    model = pin.Model(robot.model)
    for j in range(1, model.njoints):
        delta = placement[j - 1]
        model.jointPlacements[j] = model.jointPlacements[j] * pin.exp6(
            pin.Motion(delta[:3], delta[3:])
        )
    return dataclasses.replace(robot, model=model)


def _with_pinning(
    robot: RobotModel, base: np.ndarray | None, flange: np.ndarray | None
) -> RobotModel:
    """The robot with the model's base before its first joint and flange after its flange
    frame (`keo_service.core.compensation.pinning`)."""
    model = pin.Model(robot.model)
    if base is not None:
        data = model.createData()
        pin.framesForwardKinematics(model, data, pin.neutral(model))
        T_ob = data.oMf[robot.base_frame_id]
        shift = T_ob * pin.SE3(base) * T_ob.inverse()  # base, stated in the base frame
        for j in range(1, model.njoints):
            if model.parents[j] == 0:
                model.jointPlacements[j] = shift * model.jointPlacements[j]
    if flange is not None:
        frame = model.frames[robot.flange_frame_id]
        frame.placement = frame.placement * pin.SE3(flange)
        model.frames[robot.flange_frame_id] = frame
    return dataclasses.replace(robot, model=model)


def corrections_from_config(model: ModelConfig, nq: int, source: str) -> ModelCorrections | None:
    """The [model] section as ModelCorrections (None when empty); lengths checked per key."""
    sizes = {
        "joint_offsets": nq,
        "compliance": nq,
        "backlash": nq,
        "cyclic": 4 * nq,
        "placement": 6 * nq,
    }
    values: dict[str, np.ndarray | None] = {}
    for key, n in sizes.items():
        v = list(getattr(model, key))
        if v and len(v) != n:
            raise ConfigError(
                source, f"model.{key}", f"{len(v)} numbers, expected {n} for this {nq}-joint robot"
            )
        values[key] = np.asarray(v, dtype=float) if v else None
    maps = _maps_from_config(model, nq, source)
    couplings = _couplings_from_config(model, nq, source)
    ripple = _ripple_from_config(model, nq, source)
    if all(v is None for v in values.values()) and not maps and not couplings and not ripple:
        return None
    shapes = {"cyclic": (nq, 2, 2), "placement": (nq, 6)}
    given = {k: v.reshape(shapes.get(k, (nq,))) for k, v in values.items() if v is not None}
    taper = float(model.map_taper_rad)
    if not (np.isfinite(taper) and taper >= 0):
        raise ConfigError(source, "model.map_taper_rad", "a distance in rad, 0 or more")
    return ModelCorrections(
        nq, **given, maps=maps, couplings=couplings, ripple=ripple, map_taper=taper
    )


def _ripple_from_config(
    model: ModelConfig, nq: int, source: str
) -> tuple[tuple[int, float, float, float], ...]:
    n = len(model.ripple_joints)
    lengths = (len(model.ripple_periods_rad), len(model.ripple_sin), len(model.ripple_cos))
    if any(m != n for m in lengths):
        raise ConfigError(
            source,
            "model.ripple_joints",
            "one entry per term in ripple_joints, ripple_periods_rad, ripple_sin and ripple_cos",
        )
    out = []
    for i, (j, period, a, b) in enumerate(
        zip(
            model.ripple_joints,
            model.ripple_periods_rad,
            model.ripple_sin,
            model.ripple_cos,
            strict=True,
        )
    ):
        if not 0 <= j < nq:
            raise ConfigError(source, f"model.ripple_joints[{i}]", f"a joint 0..{nq - 1}")
        if not period > 0:
            raise ConfigError(source, f"model.ripple_periods_rad[{i}]", "a period > 0 (rad)")
        out.append((int(j), float(period), float(a), float(b)))
    return tuple(out)


def _couplings_from_config(
    model: ModelConfig, nq: int, source: str
) -> tuple[tuple[int, int, float, np.ndarray, np.ndarray], ...]:
    n = len(model.coupling_joints)
    lengths = (len(model.coupling_slopes), len(model.coupling_knots), len(model.coupling_values))
    if any(m != n for m in lengths):
        raise ConfigError(
            source,
            "model.coupling_joints",
            "one entry per coupling in coupling_joints, coupling_slopes, coupling_knots and "
            "coupling_values",
        )
    out = []
    for i, (pair, slope, knots, values) in enumerate(
        zip(
            model.coupling_joints,
            model.coupling_slopes,
            model.coupling_knots,
            model.coupling_values,
            strict=True,
        )
    ):
        k, v = np.asarray(knots, dtype=float), np.asarray(values, dtype=float)
        if len(pair) != 2 or not all(0 <= p < nq for p in pair) or pair[0] == pair[1]:
            raise ConfigError(
                source, f"model.coupling_joints[{i}]", f"two different joints 0..{nq - 1}"
            )
        if k.size != v.size or (k.size and (k.size < 2 or np.any(np.diff(k) <= 0))):
            raise ConfigError(
                source,
                f"model.coupling_knots[{i}]",
                "at least two increasing knots, as many as coupling_values",
            )
        out.append((int(pair[0]), int(pair[1]), float(slope), k, v))
    return tuple(out)


def _maps_from_config(
    model: ModelConfig, nq: int, source: str
) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
    if not model.map_knots and not model.map_values:
        return ()
    if len(model.map_knots) != nq or len(model.map_values) != nq:
        raise ConfigError(
            source, "model.map_knots", f"one list per joint ({nq}) in map_knots and map_values"
        )
    maps = []
    for j, (knots, values) in enumerate(zip(model.map_knots, model.map_values, strict=True)):
        k, v = np.asarray(knots, dtype=float), np.asarray(values, dtype=float)
        if k.size != v.size or (k.size and (k.size < 2 or np.any(np.diff(k) <= 0))):
            raise ConfigError(
                source,
                f"model.map_knots[{j}]",
                "at least two increasing knots, as many as map_values",
            )
        maps.append((k, v))
    return tuple(maps)


def delay_model(timing: TimingConfig) -> DelayModel:
    """The [timing] section's delay: delay_s at drift_ref_s, drifting by drift_ppm."""
    return DelayModel(
        offset_s=timing.delay_s, drift=timing.drift_ppm * 1e-6, t_ref=timing.drift_ref_s
    )


def delay_prior(timing: TimingConfig) -> tuple[float, float | None]:
    """The configured delay and its standard uncertainty, the online tracker's prior; None
    when nothing is known (delay_s = 0, the default)."""
    return timing.delay_s, None if timing.delay_s == 0.0 else timing.delay_se_s


def estimator_settings(config: Config) -> EstimatorSettings:
    """The estimator's settings from [observer] and [timing].

    Args:
        config: a loaded config (`load_config`).

    Returns:
        `EstimatorSettings`: gains (1/s), delay (s, with drift), alignment, rates (Hz) and
        the buffer and gap limits (s).
    """
    timing, obs = config.timing, config.observer
    return EstimatorSettings(
        gains=tuple(obs.gain),
        max_dt_s=obs.max_dt_s,
        delay=delay_model(timing),
        alignment=timing.alignment,
        sample_rate_hz=timing.sample_rate_hz,
        buffer_s=timing.buffer_s,
        max_gap_s=timing.max_gap_s,
        stale_after_s=timing.stale_after_s,
    )


def calibrated_region_of(config: Config) -> CalibratedRegion | None:
    """`[model] calibrated_q_min/max` and `calibrated_region` (None when not written)."""
    m = config.model
    if not m.calibrated_q_min and not m.calibrated_region:
        return None
    if len(m.calibrated_q_min) != len(m.calibrated_q_max):
        raise ConfigError(
            config.source, "model.calibrated_q_min", "as many numbers as calibrated_q_max"
        )
    bands = tuple(
        RegionBand(b.band, b.poses, np.asarray(b.lower, dtype=float), np.asarray(b.upper))
        for b in m.calibrated_region
    )
    return CalibratedRegion(
        np.asarray(m.calibrated_q_min, dtype=float), np.asarray(m.calibrated_q_max), bands
    )


def tool_model(config: Config, require_effects: bool = False) -> ToolModel:
    """The nominal robot, the [model] section's corrections and pinning, and the user's TCP
    ([tool]) of a config: the tool poses compensation works with."""
    robot = robot_from_config(config)
    corrections = corrections_from_config(config.model, robot.nq, config.source)
    if corrections is not None and corrections.is_zero:
        corrections = None
    if require_effects and corrections is None:
        raise ConfigError(
            config.source,
            "model",
            "no identified effects of the robot (joint offsets, geometry, compliance, backlash, "
            "cyclic, joint maps) to compensate: pass the model.toml that `keo analyze` wrote",
        )
    base, flange = pinning_frames(config)
    region = calibrated_region_of(config)
    if region is not None and region.q_min.size != robot.nq:
        raise ConfigError(
            config.source, "model.calibrated_q_min", f"{robot.nq} numbers, one per joint"
        )
    T_nt = se3_from_xyz_rpy(config.tool.xyz, config.tool.rpy).homogeneous
    return ToolModel(robot, corrections, T_nt, base, flange, region)
