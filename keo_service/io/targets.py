"""The targets file of `keo compensate` and its output file (the run is
`keo_service.offline.compensate`).

Targets (docs/design.md §6): CSV with a header, either `q1..qN` (a joint program: each target
is the nominal tool pose at those joints) or `x,y,z,qw,qx,qy,qz` (the user's TCP, `[tool]`,
in the robot base frame: m, scalar-first quaternion) optionally followed by `q1..qN` as seeds;
an optional first column `id` or `t` is carried through as written. Output: that column, then
`q1..qN` (corrected joints, rad), `x,y,z,qw,qx,qy,qz` (the nominal-model tool pose to command),
`correction_mm`, `correction_mrad` (the commanded pose against the target), `residual_um` (of
the model solve), with `--accuracy` `predicted_mm`, `predicted_mrad` (the model's predicted
deviation from the nominal robot at the target), `accuracy_mm` (the model's predicted
accuracy there in a later session, its between-session term included; NaN outside the
calibrated range or region), `accuracy_same_session_mm` (the same without that term) and
`outside_region_mm` (how far
the target lies outside the box the calibration poses' tool swept in its orientation band, inf
for a band none had), and `flags` (`|`-separated, empty when none; each with its detail: which
joint and how far outside).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import polars as pl

from keo_service.core.compensation import Compensated
from keo_service.core.errors import DataFormatError
from keo_service.core.kinematics import quat_wxyz

POSE_COLUMNS = ("x", "y", "z", "qw", "qx", "qy", "qz")
CARRIED = ("id", "t")
MAX_LINES_NAMED = 10


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


# complexity (C901): one refusal per way a target file can be wrong, each with its own message
def read_targets(path: str | Path, nq: int) -> Targets:  # noqa: C901
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


def write_compensated(
    path: str | Path,
    targets: Targets,
    result: Compensated,
    accuracy: np.ndarray | None = None,
    same_session: np.ndarray | None = None,
) -> None:
    """The output file (columns: see the module); `accuracy`: the predicted accuracy per
    target (mm): with it, the columns predicted_mm, predicted_mrad and accuracy_mm;
    `same_session`: the accuracy without the between-session term (accuracy_same_session_mm)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    columns: list[pl.Series] = []
    if targets.carried is not None:
        columns.append(targets.carried)
    nq = result.q.shape[1]
    for j, name in enumerate(_joint_names(nq)):
        columns.append(pl.Series(name, result.q[:, j]))
    pose = np.column_stack([result.p_command, [quat_wxyz(R) for R in result.R_command]])
    for k, name in enumerate(POSE_COLUMNS):
        columns.append(pl.Series(name, pose[:, k]))
    columns.append(pl.Series("correction_mm", result.correction_m * 1e3))
    columns.append(pl.Series("correction_mrad", result.correction_rad * 1e3))
    columns.append(pl.Series("residual_um", result.residual_m * 1e6))
    if accuracy is not None and result.predicted_m is not None:
        assert result.predicted_rad is not None
        columns.append(pl.Series("predicted_mm", result.predicted_m * 1e3))
        columns.append(pl.Series("predicted_mrad", result.predicted_rad * 1e3))
        columns.append(pl.Series("accuracy_mm", accuracy))
        if same_session is not None:
            columns.append(pl.Series("accuracy_same_session_mm", same_session))
        if result.outside_region_m is not None:
            columns.append(pl.Series("outside_region_mm", result.outside_region_m * 1e3))
    details = result.details or result.flags
    columns.append(pl.Series("flags", ["|".join(f) for f in details], dtype=pl.String))
    pl.DataFrame(columns).write_csv(path)
