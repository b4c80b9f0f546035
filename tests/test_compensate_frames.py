"""Compensation a user can check (issue 47): the identified model in the nominal robot's
frames, so that a correction is the kinematic error the model found and not a rigid motion the
tracker registration absorbed; the TCP is the user's [tool], the probe a measurement frame;
model.toml travels.

Expected values come from outside the code under test: a model whose every error is a rigid
motion of the base or the flange must correct nothing (the registration and the probe mount
take such motions whole); adding such motions to a model must not change its corrections; on
the real UR10 data the corrections must be of the size the report gives for the nominal
robot's error (held out, with its own registration fitted).
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pinocchio as pin
import polars as pl
import pytest

from keo_service.core.compensation import (
    CompensationLimits,
    CorrectionFilter,
    ToolModel,
    compensate,
    pinning,
)
from keo_service.core.kinematics import load_robot, se3_from_xyz_rpy
from keo_service.core.model_corrections import ModelCorrections
from keo_service.io.cell import cell_from_config, probe_in_tool
from keo_service.io.config import load_config
from tests.conftest import CONFIGS, REPO, UR10_DATA, keo

UR10 = CONFIGS / "robots" / "ur10.urdf"
JOINTS = [f"q{i + 1}" for i in range(6)]


def ur10():
    return load_robot(str(UR10), "base_link", "tool0")


def calibration_joints(robot, n=200, seed=1):
    rng = np.random.default_rng(seed)
    lo, hi = np.maximum(robot.lower, -np.pi), np.minimum(robot.upper, np.pi)
    return lo + (hi - lo) * rng.uniform(0.2, 0.8, (n, robot.nq))


def pinned_model(robot, corr, q, T_nt):
    """The model as keo analyze writes it: pinned over the calibration joints q."""
    T_np = se3_from_xyz_rpy([0.0, 0.0, 0.093], [0.0, 0.0, -1.5708]).homogeneous
    p = pinning(robot, corr, q, np.eye(4), T_np)
    return ToolModel(robot, corr, T_nt, p.base, p.flange)


def compensate_program(model, q):
    R, p = model.poses(q, identified=False)
    return compensate(model, R, p, q, seeds_are_nominal=True)


TOOL = se3_from_xyz_rpy([0.0, 0.0, 0.109], [0.0, 0.0, 0.0]).homogeneous


def test_a_model_that_only_moves_base_and_flange_rigidly_corrects_nothing():
    """A joint-1 offset turns the whole arm about the base z axis; a joint-6 offset turns the
    flange about its own axis; a constant map value is an offset. A tracker registration and
    a probe mount take each whole, so compensating by them (as the unpinned model did: 6.1
    mm / 14 mrad on the UR10 data) moves the tool by a motion nobody measured."""
    robot = ur10()
    q = calibration_joints(robot)
    offsets = np.array([9e-3, 0.0, 0.0, 0.0, 0.0, -12e-3])
    maps = tuple(
        (np.array([-np.pi, np.pi]), np.full(2, v)) for v in (0.004, 0.0, 0.0, 0.0, 0.0, 0.002)
    )
    corr = ModelCorrections(robot.nq, joint_offsets=offsets, maps=maps)
    unpinned = ToolModel(robot, corr, TOOL)
    before = compensate_program(unpinned, q[:20])
    assert np.sqrt(np.mean(before.correction_rad**2)) > 10e-3  # what the issue saw
    model = pinned_model(robot, corr, q, TOOL)
    after = compensate_program(model, q[:20])
    assert np.max(after.correction_m) < 1e-8
    assert np.max(after.correction_rad) < 1e-8
    assert all(not f for f in after.flags)


def test_rigid_motions_added_to_a_model_leave_its_corrections_unchanged():
    """A genuine error (joint 2 and 3 offsets, a placement error of joint 4) with and without
    the rigid motions a registration absorbs: the same corrections, and each correction the
    model's predicted deviation from the nominal robot (at the corrected joints exactly, at
    the target's joints to the deviation's own variation)."""
    robot = ur10()
    q = calibration_joints(robot)
    placement = np.zeros((6, 6))
    placement[3] = [0.4e-3, -0.3e-3, 0.2e-3, 0.5e-3, 0.0, -0.3e-3]
    genuine = ModelCorrections(
        robot.nq, joint_offsets=np.array([0.0, 1e-3, -0.8e-3, 0.0, 0.0, 0.0]), placement=placement
    )
    gauge = ModelCorrections(
        robot.nq,
        joint_offsets=genuine.joint_offsets + np.array([7e-3, 0, 0, 0, 0, -5e-3]),
        placement=placement,
    )
    a = compensate_program(pinned_model(robot, genuine, q, TOOL), q[:25])
    model_b = pinned_model(robot, gauge, q, TOOL)
    b = compensate_program(model_b, q[:25])
    assert np.allclose(a.correction_m, b.correction_m, atol=1e-9)
    assert np.allclose(a.correction_rad, b.correction_rad, atol=1e-9)
    assert 0.05e-3 < np.sqrt(np.mean(b.correction_m**2)) < 5e-3
    at_corrected, rot_corrected = model_b.predicted_errors(b.q)
    assert np.allclose(b.correction_m, np.linalg.norm(at_corrected, axis=1), atol=1e-9)
    assert np.allclose(b.correction_rad, np.linalg.norm(rot_corrected, axis=1), atol=1e-9)
    assert b.predicted_m is not None
    assert np.allclose(b.correction_m, b.predicted_m, rtol=0.02, atol=1e-6)


def test_the_measured_error_is_the_probes_and_the_correction_lands_the_users_tcp(tmp_path):
    """With the probe elsewhere than the TCP, the measured error compares the sensor with the
    nominal probe (zero for a robot that is nominal), and the correction built from a probe
    error E_p puts the TCP on its goal: the real tool is T_bt T_tp E_p T_tp^-1."""
    cfg = tmp_path / "cell.toml"
    cfg.write_text(
        f'[robot]\nurdf = "{UR10.as_posix()}"\n[tool]\nxyz = [0.0, 0.0, 0.109]\n'
        "[tracker]\nprobe_xyz = [0.01, 0.0, 0.093]\nprobe_rpy = [0.0, 0.0, -1.5708]\n"
    )
    config = load_config(cfg)
    cell = cell_from_config(config)
    q = np.array([0.3, -1.2, 1.1, -0.7, 1.4, 0.2])
    from keo_service.core.kinematics import flange_pose, measured_error, quat_wxyz

    data = cell.robot.create_data()
    T_bn = flange_pose(cell.robot, data, q)
    T_bs = T_bn * se3_from_xyz_rpy([0.01, 0.0, 0.093], [0.0, 0.0, -1.5708])
    e = measured_error(cell, data, q, T_bs.translation, quat_wxyz(T_bs.rotation))
    assert np.allclose(e, 0.0, atol=1e-12)
    T_tp = probe_in_tool(config)
    assert T_tp is not None
    filt = CorrectionFilter(CompensationLimits(1.0, 1.0, 1e6), None, T_tp)
    filt.step(0.0, [0.0] * 6, None)
    rng = np.random.default_rng(2)
    for k in range(4):
        E_p = pin.SE3(pin.exp3(rng.normal(0, 2e-3, 3)), rng.normal(0, 2e-3, 3))
        c = filt.step(1.0 + k, [*E_p.translation, *pin.log3(E_p.rotation)], None)
        C = pin.SE3(pin.exp3(c.rotation), c.translation)
        E_t = pin.SE3(T_tp) * E_p * pin.SE3(T_tp).inverse()
        goal = pin.SE3(pin.exp3(rng.normal(0, 1, 3)), rng.normal(0, 1, 3))
        landed = goal * C * E_t
        assert np.linalg.norm(landed.translation - goal.translation) < 1e-12
        assert np.linalg.norm(pin.log3(goal.rotation.T @ landed.rotation)) < 1e-12


@pytest.fixture(scope="module")
def ur10_b(tmp_path_factory):
    """Series B imported and analysed once by the real commands (about a minute)."""
    tmp = tmp_path_factory.mktemp("ur10b")
    source = UR10_DATA / "Series_B" / "measurements_joint_configurations.csv"
    res = keo("import", "ur10-lasertracker", str(source), "--out", str(tmp))
    assert res.returncode == 0, res.stderr
    cfg = REPO / "configs" / "ur10_lasertracker.toml"
    res = keo(
        "analyze",
        *("--config", str(cfg), "--encoder", str(tmp / "encoder.csv")),
        *("--tracker", str(tmp / "tracker.csv"), "--out", str(tmp / "an"), "--json"),
        timeout=600,
    )
    assert res.returncode == 0, res.stderr
    return {"tmp": tmp, "report": json.loads(res.stdout), "config": cfg}


@pytest.mark.e2e
@pytest.mark.slow  # the analysis of Series B behind it takes a minute or more on two cores
def test_corrections_on_the_real_ur10_data_are_the_size_of_the_nominal_error(ur10_b, tmp_path):
    """60 joint rows of Series B itself, compensated with the model.toml moved to another
    folder (it travels): corrections within 1.5x of the nominal model's held-out error, the
    figure the report gives for how far the nominal robot is off (before: 6.1 mm / 14 mrad
    against 1.06 mm / 1.48 mrad)."""
    tmp = ur10_b["tmp"]
    elsewhere = tmp_path / "moved"
    shutil.copytree(tmp / "an", elsewhere)
    text = (elsewhere / "model.toml").read_text()
    assert str(REPO) not in text.split("\n", 3)[3]  # no path of this checkout below the header
    assert "protocol" not in text  # the input config gave neither
    assert "port" not in text
    assert "ur10_lasertracker.toml" in text.splitlines()[0]  # the comment naming its source
    model = load_config(elsewhere / "model.toml")
    user = load_config(ur10_b["config"])
    assert model.tool.xyz == user.tool.xyz  # the TCP, as the user gave it
    assert model.tool.rpy == user.tool.rpy
    assert model.tracker.probe_xyz is not None  # the identified probe, beside it
    assert 0.08 < model.tracker.probe_xyz[2] < 0.1
    rows = pl.read_csv(tmp / "encoder.csv")[1::25].head(60).rename({"t": "id"})
    rows.write_csv(tmp_path / "targets.csv")
    res = keo(
        "compensate",
        *("--config", str(elsewhere / "model.toml"), "--targets", str(tmp_path / "targets.csv")),
        *("--out", str(tmp_path / "out.csv"), "--json", "--accuracy"),
    )
    assert res.returncode == 0, res.stderr
    summary = json.loads(res.stdout)
    nominal = ur10_b["report"]["baseline"]["validation"]
    pos, rot = summary["correction_mm"]["rms"], summary["correction_mrad"]["rms"]
    print(
        f"corrections {pos:.3f} mm / {rot:.3f} mrad RMS; nominal held out "
        f"{nominal['pos_rms_mm']:.3f} mm / {nominal['rot_rms_mrad']:.3f} mrad"
    )
    assert nominal["pos_rms_mm"] / 1.5 < pos < 1.5 * nominal["pos_rms_mm"]
    assert nominal["rot_rms_mrad"] / 1.5 < rot < 1.5 * nominal["rot_rms_mrad"]
    out = pl.read_csv(tmp_path / "out.csv")
    assert {"predicted_mm", "accuracy_mm", "outside_region_mm"} <= set(out.columns)
    assert np.allclose(out["correction_mm"], out["predicted_mm"], rtol=0.05, atol=2e-3)
    assert summary["calibrated_region"]["tool_boxes_m"]  # printed and in the summary
    assert summary["outside_region"]["targets"] == 0  # its own calibration poses
    # a tool pointing straight down, which Series B never did: said so, with how far
    down = tmp_path / "down.csv"
    down.write_text("x,y,z,qw,qx,qy,qz\n0.0,-0.6,0.9,0.0,1.0,0.0,0.0\n")
    res = keo(
        "compensate",
        *("--config", str(elsewhere / "model.toml"), "--targets", str(down)),
        *("--out", str(tmp_path / "down_out.csv"), "--accuracy"),
    )
    assert res.returncode == 0, res.stderr
    assert "outside the calibrated region" in res.stdout
    assert "a tool orientation no calibration pose had" in res.stdout
    row = pl.read_csv(tmp_path / "down_out.csv").row(0, named=True)
    assert row["outside_region_mm"] == float("inf")
    assert row["accuracy_mm"] is None or np.isnan(row["accuracy_mm"])


@pytest.mark.e2e
@pytest.mark.slow  # Series B analysed (the shared fixture) and carried to Series A: minutes
def test_stated_accuracy_covers_the_error_met_in_another_session(ur10_b, tmp_path):
    """Series B's model compensates Series A's held-out poses (another day, another tracker
    station): the error met there is Series A's measurement against B's model with only the
    tracker registration and the probe mount fitted on A's training rows. The accuracy
    `keo compensate` states per target (with the between-session term) must hold about 95 %
    of those errors within its 95 % band; the same-session figure alone held 81 % when this
    was written (docs/analyze.md)."""
    from keo_service.core.chain import Chain
    from keo_service.fit.accuracy import BAND_95
    from keo_service.fit.analysis import analyze, split_data
    from keo_service.io.analysis_report import saved_model
    from keo_service.io.cell import robot_from_config
    from keo_service.offline.analyze import load_data
    from keo_service.offline.compensate import compensate as compensate_file

    series_a = tmp_path / "a"
    source = UR10_DATA / "Series_A" / "measurements_grid.csv"
    res = keo("import", "ur10-lasertracker", str(source), "--out", str(series_a))
    assert res.returncode == 0, res.stderr
    model = load_config(ur10_b["tmp"] / "an" / "model.toml")
    assert model.model.accuracy_session_mm > 0.0
    robot = robot_from_config(model)
    data, position_only = load_data(model, series_a / "encoder.csv", series_a / "tracker.csv")
    carried = analyze(
        robot, data, position_only, fixed_model=saved_model(model, Chain(robot), position_only)
    )
    held = data.subset(split_data(data)[1])
    width = 3 if position_only else 6
    tau = carried.model.chain.gravity_torques(held.q)
    r = carried.model.residuals(carried.x, held, tau).reshape(-1, width)
    error_mm = np.linalg.norm(r[:, :3], axis=1) * 1e3
    header = ",".join(f"q{i + 1}" for i in range(held.q.shape[1]))
    targets = tmp_path / "targets.csv"
    np.savetxt(targets, held.q, delimiter=",", header=header, comments="")
    found = compensate_file(model, targets)
    stated = np.isfinite(found.accuracy_mm)
    assert stated.mean() > 0.9  # stated outside the calibrated region too (not seen: none)
    later = float(np.mean(error_mm[stated] <= BAND_95 * found.accuracy_mm[stated]))
    same = found.accuracy_same_session_mm
    assert same is not None
    within = float(np.mean(error_mm[stated] <= BAND_95 * same[stated]))
    print(
        f"B's model at {int(stated.sum())} of A's {error_mm.size} held-out poses: measured "
        f"{np.sqrt(np.mean(error_mm[stated] ** 2)):.3f} mm RMS; within the 95 % band "
        f"{100 * later:.1f} % (same-session figure {100 * within:.1f} %)"
    )
    assert later >= 0.9
    assert later > within
