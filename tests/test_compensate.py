"""keo compensate: on simulated stop-and-measure data with effects the config does not declare,
`keo analyze` then `keo compensate`, judged by the simulator's truth; the flags; the refusals.

The truth is the simulator's real arm (perturbed placements, joint offsets, a true sensor
mount, gravity compliance and an angle ripple on joints 2 and 3). The targets live in the
robot base frame as the identified model defines it: the tracker frame carried by the model's
registration (a user's targets reach keo that way; the first joint's placement and the
tracker registration cannot be told apart, see test_analysis), so the true tool pose is taken
through the real tracker frame and the model's registration.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pinocchio as pin
import polars as pl
import pytest

from keo_service.core.compensation import compensate
from keo_service.core.kinematics import flange_pose, se3_from_xyz_rpy, tool_pose
from keo_service.io.cell import cell_from_config
from keo_service.io.config import load_config
from keo_service.sim.simulate import angle_ripple, make_scenario, simulate, write_run
from tests.conftest import DEMO, keo

SETS = {
    "poses": "120",
    "ripple_rad": "0.0005",
    "ripple_period_rad": "0.3",
    "compliance_rad_per_nm": "2e-7",
}
SEED = 3
JOINTS = [f"q{i + 1}" for i in range(6)]


class Truth:
    def __init__(self, cell, scenario, run, model_config):
        self.cell, self.scenario, self.true = cell, scenario, run.true_robot
        self.gravity = cell.robot.model.createData()
        # base frame as the model defines it: model registration after the real tracker frame
        T_bk_model = se3_from_xyz_rpy(model_config.tracker.xyz, model_config.tracker.rpy)
        self.T_model_base = T_bk_model * self.true.T_bk.inverse()
        self.T_nt = se3_from_xyz_rpy(model_config.tool.xyz, model_config.tool.rpy)
        self.nominal = cell.robot.create_data()

    def tool(self, q):
        """The real tool (sensor) pose at joints q, as the simulator makes it."""
        q = np.asarray(q, dtype=float)
        tau = pin.computeGeneralizedGravity(self.cell.robot.model, self.gravity, q)
        extra = self.scenario.compliance_rad_per_nm * tau + angle_ripple(self.scenario, q)
        return self.T_model_base * self.true.sensor_pose(q, extra)

    def nominal_tool(self, q):
        return flange_pose(self.cell.robot, self.nominal, np.asarray(q, dtype=float)) * self.T_nt


def errors(goals, poses):
    """Position (mm) and rotation (mrad) of each pose from its goal."""
    pos, rot = [], []
    for goal, pose in zip(goals, poses, strict=True):
        d = goal.actInv(pose)
        pos.append(np.linalg.norm(d.translation) * 1e3)
        rot.append(np.linalg.norm(pin.log3(d.rotation)) * 1e3)
    return np.array(pos), np.array(rot)


def rms(v):
    return float(np.sqrt(np.mean(np.square(v))))


@pytest.fixture(scope="module")
def analyzed(tmp_path_factory):
    """One simulated session, analysed once by the real `keo analyze` (about 20 s)."""
    tmp = tmp_path_factory.mktemp("comp")
    cell = cell_from_config(load_config(DEMO))
    scenario = make_scenario("static-poses", SETS)
    run = simulate(cell, scenario, seed=SEED)
    write_run(run, tmp / "sim")
    res = keo(
        "analyze",
        "--config",
        str(DEMO),
        "--encoder",
        str(tmp / "sim" / "encoder.csv"),
        "--tracker",
        str(tmp / "sim" / "tracker.csv"),
        "--out",
        str(tmp / "an"),
        "--json",
    )
    assert res.returncode == 0, res.stderr[-2000:]
    report = json.loads(res.stdout)
    model_path = tmp / "an" / "model.toml"
    model_config = load_config(model_path)
    # new targets the analysis never saw: poses of another seed (same workspace)
    program = simulate(
        cell, make_scenario("static-poses", {"poses": "30", "geometric_errors": "false"}), seed=11
    ).encoder.q
    return {
        "tmp": tmp,
        "cell": cell,
        "report": report,
        "model_path": model_path,
        "model_config": model_config,
        "truth": Truth(cell, scenario, run, model_config),
        "program": program,
    }


def write_csv(path: Path, header: list[str], rows: list[list[object]]) -> Path:
    path.write_text(
        ",".join(header) + "\n" + "".join(",".join(str(v) for v in r) + "\n" for r in rows)
    )
    return path


class Result:
    def __init__(self, returncode, stdout, stderr):
        self.returncode, self.stdout, self.stderr = returncode, stdout, stderr


def compensate_in_process(capsys, config, targets: Path, out: Path):
    """`keo compensate` through the CLI's own entry point, in this process (fast)."""
    from keo_service.cli import main

    capsys.readouterr()
    code = main(
        [
            "compensate",
            "--config",
            str(config),
            "--targets",
            str(targets),
            "--out",
            str(out),
            "--json",
        ]
    )
    captured = capsys.readouterr()
    return Result(code, captured.out, captured.err)


def compensate_cli(analyzed, targets: Path, out: Path):
    """`keo compensate` as a real process."""
    return keo(
        "compensate",
        "--config",
        str(analyzed["model_path"]),
        "--targets",
        str(targets),
        "--out",
        str(out),
        "--json",
    )


def test_a_joint_program_lands_within_the_models_held_out_error(analyzed, tmp_path):
    truth, program = analyzed["truth"], analyzed["program"]
    targets = write_csv(
        tmp_path / "program.csv",
        ["id", *JOINTS],
        [[f"P{i}", *map(float, q)] for i, q in enumerate(program)],
    )
    res = compensate_cli(analyzed, targets, tmp_path / "out.csv")
    assert res.returncode == 0, res.stderr
    summary = json.loads(res.stdout)
    assert summary["targets"] == len(program)
    out = pl.read_csv(tmp_path / "out.csv")
    assert out.columns == [
        "id",
        *JOINTS,
        "x",
        "y",
        "z",
        "qw",
        "qx",
        "qy",
        "qz",
        "correction_mm",
        "correction_mrad",
        "residual_um",
        "flags",
    ]
    assert out["id"].to_list() == [f"P{i}" for i in range(len(program))]
    corrected = out.select(JOINTS).to_numpy()
    goals = [truth.nominal_tool(q) for q in program]
    before = errors(goals, [truth.tool(q) for q in program])
    after = errors(goals, [truth.tool(q) for q in corrected])
    held_out = analyzed["report"]["final"]["validation"]
    print(
        f"true tool error, RMS over {len(program)} targets: uncompensated {rms(before[0]):.3f} "
        f"mm / {rms(before[1]):.3f} mrad, compensated {rms(after[0]):.3f} mm / "
        f"{rms(after[1]):.3f} mrad; model held out {held_out['pos_rms_mm']:.3f} mm / "
        f"{held_out['rot_rms_mrad']:.3f} mrad"
    )
    assert rms(after[0]) <= 1.5 * held_out["pos_rms_mm"]
    assert rms(after[1]) <= 1.5 * held_out["rot_rms_mrad"]
    assert rms(before[0]) > 5 * rms(after[0])  # the uncompensated error, beside it
    # the pose to command is the nominal tool pose at the corrected joints (Pinocchio's own
    # forward kinematics here, not the chain the solver uses)
    for row, q in zip(out.iter_rows(named=True), corrected, strict=True):
        cmd = truth.nominal_tool(q)
        assert np.allclose([row["x"], row["y"], row["z"]], cmd.translation, atol=1e-12)
        quat = pin.Quaternion(cmd.rotation)
        sign = 1.0 if quat.w >= 0 else -1.0
        assert np.allclose(
            [row["qw"], row["qx"], row["qy"], row["qz"]],
            sign * np.array([quat.w, quat.x, quat.y, quat.z]),
            atol=1e-12,
        )
    assert np.all(out["residual_um"].to_numpy() < 1e-3)  # 1e-9 m
    # the size of the change: the commanded pose against the target
    cmd_err = errors(goals, [truth.nominal_tool(q) for q in corrected])
    assert np.allclose(out["correction_mm"].to_numpy(), cmd_err[0], atol=1e-9)
    assert np.allclose(out["correction_mrad"].to_numpy(), cmd_err[1], atol=1e-6)


def test_the_identified_model_puts_the_tool_on_the_target_to_a_nanometre(analyzed):
    """Pinocchio's forward kinematics on the model as `keo run` builds it (not the solver's
    chain) at the corrected joints."""
    model_config, program = analyzed["model_config"], analyzed["program"][:10]
    cell = cell_from_config(model_config)
    from keo_service.io.cell import tool_model

    model = tool_model(model_config)
    R, p = model.poses(program, identified=False)
    result = compensate(model, R, p, program, seeds_are_nominal=True)
    data = cell.robot.create_data()
    for q, Rg, pg in zip(result.q, R, p, strict=True):
        T = tool_pose(cell, data, q)
        assert np.linalg.norm(T.translation - pg) < 1e-9
        assert np.linalg.norm(pin.log3(Rg.T @ T.rotation)) < 1e-9


def test_a_pose_list_with_and_without_seeds(analyzed, tmp_path, capsys):
    truth, program = analyzed["truth"], analyzed["program"][:12]
    goals = [truth.nominal_tool(q) for q in program]
    rows_plain, rows_seeded = [], []
    for i, (goal, q) in enumerate(zip(goals, program, strict=True)):
        quat = pin.Quaternion(goal.rotation)
        pose = [*goal.translation.tolist(), quat.w, quat.x, quat.y, quat.z]
        rows_plain.append([float(i), *pose])
        rows_seeded.append([*pose, *(q + 0.05).tolist()])  # seeds near, not at, the answer
    pose_cols = ["x", "y", "z", "qw", "qx", "qy", "qz"]
    plain = write_csv(tmp_path / "poses.csv", ["t", *pose_cols], rows_plain)
    seeded = write_csv(tmp_path / "seeded.csv", [*pose_cols, *JOINTS], rows_seeded)
    held_out = analyzed["report"]["final"]["validation"]["pos_rms_mm"]
    for targets, name in ((plain, "plain"), (seeded, "seeded")):
        out_path = tmp_path / f"out_{name}.csv"
        res = compensate_in_process(capsys, analyzed["model_path"], targets, out_path)
        assert res.returncode == 0, res.stderr
        out = pl.read_csv(out_path)
        if name == "plain":
            assert out.columns[0] == "t"
            assert out["t"].to_list() == [float(i) for i in range(len(program))]
        corrected = out.select(JOINTS).to_numpy()
        after = errors(goals, [truth.tool(q) for q in corrected])
        before = errors(goals, [truth.tool(q) for q in program])
        with capsys.disabled():
            print(
                f"{name}: uncompensated {rms(before[0]):.3f} mm, compensated {rms(after[0]):.3f} mm"
            )
        assert rms(after[0]) <= 1.5 * held_out
        assert not any(out["flags"].fill_null("").to_list())


def test_flags(analyzed):
    from keo_service.io.cell import tool_model

    model = tool_model(analyzed["model_config"])
    base = analyzed["program"][0]
    _lo, hi = model.calibrated_ranges()[1]  # joint 2: its map's knots, or the poses' range
    outside = base.copy()
    outside[1] = hi + 0.05
    singular = base.copy()
    singular[4] = 1e-5  # MH180: B at zero lines up the R and T axes
    program = np.array([base, outside, singular])
    R, p = model.poses(program, identified=False)
    # a goal 20 m away cannot be reached
    p_far = p.copy()
    p_far[0] += 20.0
    result = compensate(model, R, p, program, seeds_are_nominal=True)
    assert result.flags[0] == []
    assert "outside_calibrated_range" in result.flags[1]
    assert "near_singular" in result.flags[2]
    far = compensate(model, R[:1], p_far[:1], None)
    assert "unreachable" in far.flags[0]
    slow = compensate(model, R[:1], p[:1], program[:1] + 0.3, max_iterations=1)
    assert slow.flags[0] == ["not_converged"]


def test_the_stated_accuracy_per_target_carries_the_between_session_term(analyzed, tmp_path):
    """A program is compensated on a day after the calibration: each target's accuracy_mm is
    the model's held-out RMS with the between-session term of model.toml added in quadrature
    (the rule `keo analyze` judges a carried model by), accuracy_same_session_mm the same
    without it; expected values from the numbers model.toml states, not from the code."""
    import msgspec

    from keo_service.offline.compensate import compensate as compensate_file

    config = analyzed["model_config"]
    m = config.model
    assert m.accuracy_mm > 0.0
    assert m.calibrated_q_min
    stated = msgspec.structs.replace(
        config,
        model=msgspec.structs.replace(m, accuracy_session_mm=0.3, accuracy_session_source="test"),
    )
    lo, hi = np.asarray(m.calibrated_q_min), np.asarray(m.calibrated_q_max)
    program = np.asarray(analyzed["program"], dtype=float)
    inside = np.all((program > lo + 0.02) & (program < hi - 0.02), axis=1)
    assert inside.sum() >= 5
    base = program[np.flatnonzero(inside)[0]]
    near, far = base.copy(), base.copy()
    near[1] = hi[1] + 0.05  # within the maps' fade length: between the two stated figures
    far[1] = hi[1] + 0.5  # far beyond it: the extrapolation figure
    rows = np.vstack([program[inside], near, far])
    targets = write_csv(tmp_path / "program.csv", JOINTS, [list(map(float, q)) for q in rows])
    found = compensate_file(stated, targets, tmp_path / "out.csv", accuracy_columns=True)
    n = int(inside.sum())
    region = found.result.outside_region_m
    judged = np.arange(n) if region is None else np.flatnonzero(np.isfinite(region[:n]))
    assert judged.size >= 5
    same = found.accuracy_same_session_mm
    assert same is not None
    assert np.allclose(same[judged], m.accuracy_mm, rtol=1e-9)
    assert np.allclose(found.accuracy_mm[judged], np.hypot(m.accuracy_mm, 0.3), rtol=1e-9)
    if region is None or np.isfinite(region[n]):
        top = max(m.accuracy_outside_mm, m.accuracy_mm)
        assert m.accuracy_mm <= same[n] <= top
        assert found.accuracy_mm[n] == pytest.approx(np.hypot(same[n], 0.3), rel=1e-9)
    if region is None or np.isfinite(region[n + 1]):
        top = max(m.accuracy_outside_mm, m.accuracy_mm)
        assert same[n + 1] == pytest.approx(top, rel=1e-9)
        assert found.accuracy_mm[n + 1] == pytest.approx(np.hypot(top, 0.3), rel=1e-9)
    assert found.summary["accuracy_session_mm"] == 0.3
    assert found.summary["accuracy_session_source"] == "test"
    out = pl.read_csv(tmp_path / "out.csv")
    assert out.columns.index("accuracy_same_session_mm") == out.columns.index("accuracy_mm") + 1
    assert np.allclose(out["accuracy_mm"].to_numpy()[judged], found.accuracy_mm[judged])


def test_refusals_exit_2_with_a_clear_message(analyzed, tmp_path, capsys):
    def compensate_cli(analyzed, targets, out):
        return compensate_in_process(capsys, analyzed["model_path"], targets, out)

    ok = write_csv(tmp_path / "ok.csv", JOINTS, [[0.1, 0.3, 0.1, 0.0, -1.0, 0.0]])
    # a config with no identified effects
    res = compensate_in_process(capsys, DEMO, ok, tmp_path / "o")
    assert res.returncode == 2
    assert "model" in res.stderr
    assert "no identified effects" in res.stderr
    # columns that fit neither form
    for header in (["q1", "q2", "q3"], ["x", "y", "z"], ["name", *JOINTS]):
        bad = write_csv(tmp_path / "bad.csv", header, [[0.0] * len(header)])
        res = compensate_cli(analyzed, bad, tmp_path / "o.csv")
        assert res.returncode == 2, header
        assert "fit neither form" in res.stderr
    # non-finite rows: counted and named by line
    rows = [[0.1, 0.3, 0.1, 0.0, -1.0, 0.0] for _ in range(5)]
    rows[1][2] = math.nan
    rows[3][0] = math.inf
    bad = write_csv(tmp_path / "nonfinite.csv", JOINTS, rows)
    res = compensate_cli(analyzed, bad, tmp_path / "o.csv")
    assert res.returncode == 2
    assert "2 row(s) with non-finite values" in res.stderr
    assert "lines 3, 5" in res.stderr
    assert not (tmp_path / "o.csv").exists()
    # a cell that is not a number, named by line and column
    text = write_csv(
        tmp_path / "text.csv", JOINTS, [[0.1, 0.3, 0.1, 0.0, -1.0, 0.0], [1, 2, "x", 4, 5, 6]]
    )
    res = compensate_cli(analyzed, text, tmp_path / "o.csv")
    assert res.returncode == 2
    assert ":3: column 'q3'" in res.stderr
