"""`keo compensate` over files, and the compensation objects built from a config.

Targets (docs/design.md §6): CSV with a header, either `q1..qN` (a joint program: each target
is the nominal tool pose at those joints) or `x,y,z,qw,qx,qy,qz` (tool pose in the robot base
frame, m, scalar first) optionally followed by `q1..qN` as seeds; an optional first column
`id` or `t` is carried through as written. Output: that column, then `q1..qN` (corrected
joints), `x,y,z,qw,qx,qy,qz` (the nominal-model pose to command), `correction_mm`,
`correction_mrad`, `residual_um` and `flags` (`|`-separated, empty when none).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import polars as pl
from scipy.spatial.transform import Rotation

from keo_service.core.compensation import FLAGS, Compensated, ToolModel, compensate
from keo_service.core.correction import CompensationLimits
from keo_service.core.corrections import approach_directions
from keo_service.core.errors import ConfigError, DataFormatError
from keo_service.core.kinematics import se3_from_xyz_rpy
from keo_service.io.cell import corrections_from_config, robot_from_config
from keo_service.io.config import Config

POSE_COLUMNS = ("x", "y", "z", "qw", "qx", "qy", "qz")
CARRIED = ("id", "t")
MAX_LINES_NAMED = 10


def tool_model(config: Config, require_effects: bool = False) -> ToolModel:
    """The nominal robot, the [model] section's corrections and the tool of a config."""
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
    T_nt = se3_from_xyz_rpy(config.tool.xyz, config.tool.rpy).homogeneous
    return ToolModel(robot, corrections, T_nt)


def compensation_limits(config: Config, max_age_s: float = 0.1) -> CompensationLimits:
    c = config.compensation
    return CompensationLimits.from_config_values(c.max_mm, c.max_mrad, c.max_rate_mm_s, max_age_s)


@dataclass
class Targets:
    carried: pl.Series | None  # the `id` or `t` column as written
    q: np.ndarray | None  # (N, nq) joints: the program, or the seeds of a pose list
    p: np.ndarray | None  # (N, 3) goal positions of a pose list
    quat: np.ndarray | None  # (N, 4) scalar first
    lines: np.ndarray  # (N,) the file line of each row

    @property
    def is_program(self) -> bool:
        return self.p is None


def _joint_names(n: int) -> list[str]:
    return [f"q{i + 1}" for i in range(n)]


def read_targets(path: str | Path, nq: int) -> Targets:
    """The targets of a file; DataFormatError (exit 2) for columns that fit neither form, a
    cell that is not a number, and rows with non-finite values (counted, lines named)."""
    path = Path(path)
    try:
        frame = pl.read_csv(path, infer_schema=False, comment_prefix=None)
    except FileNotFoundError:
        raise DataFormatError(str(path), 0, "-", "no such file") from None
    except (pl.exceptions.PolarsError, OSError, ValueError) as exc:
        raise DataFormatError(str(path), 1, "-", f"not a CSV file with a header ({exc})") from None
    header = [c.strip() for c in frame.columns]
    frame.columns = header
    joints = _joint_names(nq)
    rest = header[1:] if header and header[0] in CARRIED else header
    if rest == joints:
        form = "program"
    elif rest == list(POSE_COLUMNS) or rest == [*POSE_COLUMNS, *joints]:
        form = "poses"
    else:
        raise DataFormatError(
            str(path),
            1,
            "-",
            f"the columns {','.join(header)} fit neither form: {','.join(joints)} (a joint "
            f"program) or x,y,z,qw,qx,qy,qz optionally followed by {','.join(joints)} (tool "
            "poses in the base frame, m, scalar-first quaternions), each optionally after a "
            "first column id or t",
        )
    if frame.height == 0:
        raise DataFormatError(str(path), 2, "-", "no targets (a header only)")
    values = np.empty((frame.height, len(rest)))
    lines = np.arange(frame.height) + 2
    for k, name in enumerate(rest):
        text = frame[name].str.strip_chars()
        numbers = text.cast(pl.Float64, strict=False)
        bad = numbers.is_null()
        if bad.any():
            i = int(np.flatnonzero(bad.to_numpy())[0])
            raise DataFormatError(
                str(path), int(lines[i]), name, f"'{text[i] or ''}' is not a number"
            )
        values[:, k] = numbers.to_numpy()
    finite = np.all(np.isfinite(values), axis=1)
    if not finite.all():
        bad_lines = lines[~finite]
        named = ", ".join(str(int(n)) for n in bad_lines[:MAX_LINES_NAMED])
        more = f" and {bad_lines.size - MAX_LINES_NAMED} more" if bad_lines.size > 10 else ""
        raise DataFormatError(
            str(path),
            int(bad_lines[0]),
            "-",
            f"{bad_lines.size} row(s) with non-finite values (nan or inf), on lines "
            f"{named}{more}: every target must be a finite number in every column",
        )
    carried = frame[header[0]] if header[0] in CARRIED else None
    if form == "program":
        return Targets(carried, values, None, None, lines)
    quat = values[:, 3:7]
    norm = np.linalg.norm(quat, axis=1)
    if np.any(norm < 1e-9):
        i = int(np.flatnonzero(norm < 1e-9)[0])
        raise DataFormatError(str(path), int(lines[i]), "qw", "the quaternion is zero")
    q = values[:, 7:] if values.shape[1] > 7 else None
    return Targets(carried, q, values[:, :3], quat / norm[:, None], lines)


def _quat_wxyz(R: np.ndarray) -> np.ndarray:
    q = Rotation.from_matrix(R).as_quat(scalar_first=True)
    q[q[:, 0] < 0] *= -1.0  # w >= 0, as keo writes quaternions everywhere
    out: np.ndarray = q
    return out


def write_compensated(path: str | Path, targets: Targets, result: Compensated) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    columns: list[pl.Series] = []
    if targets.carried is not None:
        columns.append(targets.carried)
    nq = result.q.shape[1]
    for j, name in enumerate(_joint_names(nq)):
        columns.append(pl.Series(name, result.q[:, j]))
    pose = np.column_stack([result.p_command, _quat_wxyz(result.R_command)])
    for k, name in enumerate(POSE_COLUMNS):
        columns.append(pl.Series(name, pose[:, k]))
    columns.append(pl.Series("correction_mm", result.correction_m * 1e3))
    columns.append(pl.Series("correction_mrad", result.correction_rad * 1e3))
    columns.append(pl.Series("residual_um", result.residual_m * 1e6))
    columns.append(pl.Series("flags", ["|".join(f) for f in result.flags], dtype=pl.String))
    pl.DataFrame(columns).write_csv(path)


def compensate_targets(model: ToolModel, targets: Targets) -> Compensated:
    """The goals of the targets and their compensation. Backlash (a direction-dependent
    effect) takes each joint's approach direction from the row order, as a program runs."""
    seeds: np.ndarray | None = targets.q
    if targets.is_program:
        assert seeds is not None
        R_goal, p_goal = model.poses(seeds, identified=False)
        nominal = True
    else:
        assert targets.p is not None
        assert targets.quat is not None
        R_goal = Rotation.from_quat(targets.quat, scalar_first=True).as_matrix()
        p_goal, nominal = targets.p, False
    direction = None
    corr = model.corrections
    if corr is not None and np.any(corr.backlash) and seeds is not None:
        direction = approach_directions(seeds)
    return compensate(model, R_goal, p_goal, seeds, direction, seeds_are_nominal=nominal)


def run_compensate(config: Config, targets_path: Path, out: Path) -> dict[str, Any]:
    """`keo compensate`: read, solve, write; the summary for the command's output."""
    model = tool_model(config, require_effects=True)
    targets = read_targets(targets_path, model.nq)
    result = compensate_targets(model, targets)
    write_compensated(out, targets, result)
    counts = dict.fromkeys(FLAGS, 0)
    for row in result.flags:
        for f in row:
            counts[f] += 1
    ok = np.array([not ({"unreachable", "not_converged"} & set(f)) for f in result.flags])
    return {
        "out": str(out),
        "targets": int(result.q.shape[0]),
        "form": "joint program" if targets.is_program else "tool poses",
        "flags": counts,
        "correction_mm": {
            "rms": float(np.sqrt(np.mean((result.correction_m * 1e3) ** 2))),
            "max": float(np.max(result.correction_m) * 1e3),
        },
        "correction_mrad": {
            "rms": float(np.sqrt(np.mean((result.correction_rad * 1e3) ** 2))),
            "max": float(np.max(result.correction_rad) * 1e3),
        },
        "residual_um_max": float(np.max(result.residual_m[ok]) * 1e6) if ok.any() else None,
        "residual_urad_max": float(np.max(result.residual_rad[ok]) * 1e6) if ok.any() else None,
    }
