"""`keo import`: outside data sets to the interchange files (docs/design.md §5).

ur10-lasertracker (data/ur10_lasertracker): static stop-and-measure poses of a UR10 with
a Leica 6-DoF probe. `;`-separated, decimal comma; positions in mm, orientation as intrinsic
XYZ Euler angles in degrees (R = Rx(rx) Ry(ry) Rz(rz)). Each pose becomes one encoder row and
one tracker row at the same t; temperature is kept as an extra tracker column, and where the
file carries the tracker's standard deviation of each coordinate (`measurement_std_x,y,z`, mm;
Series B) it becomes the optional sx, sy, sz columns (m) that `keo analyze` takes its floor
from.
"""

from __future__ import annotations

import csv
import datetime as dt
import math
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from keo_service.core.errors import DataFormatError
from keo_service.io.interchange import EncoderData, TrackerData, write_encoder, write_tracker

JOINTS = (
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
)


def _number(text: str, path: Path, line: int, column: str) -> float:
    try:
        return float(text.replace(",", "."))
    except ValueError:
        raise DataFormatError(str(path), line, column, f"'{text}' is not a number") from None


# complexity (C901, PLR0915): one branch per optional column group of the vendor's files
def read_ur10_lasertracker(  # noqa: C901, PLR0915
    path: str | Path,
) -> tuple[EncoderData, TrackerData, dict[str, str]]:
    path = Path(path)
    with path.open(encoding="utf-8", newline="") as f:
        rows = list(csv.reader(f, delimiter=";"))
    if not rows:
        raise DataFormatError(str(path), 1, "-", "empty file")
    header = rows[0]
    need = [
        "Timestamp",
        *JOINTS,
        "measurement_temperature",
        "measurement_x",
        "measurement_y",
        "measurement_z",
        "measurement_rx",
        "measurement_ry",
        "measurement_rz",
    ]
    missing = [c for c in need if c not in header]
    if missing:
        raise DataFormatError(str(path), 1, missing[0], "column missing from the header")
    col = {name: header.index(name) for name in header}
    std_cols = [f"measurement_std_{a}" for a in "xyz"]
    has_std = all(c in col for c in std_cols)
    stamps, q, p, quat, temp, std = [], [], [], [], [], []
    timestamps_usable = True
    for line, row in enumerate(rows[1:], start=2):
        if not row or all(not c.strip() for c in row):
            continue
        raw = row[col["Timestamp"]]
        try:
            stamp = dt.datetime.strptime(raw, "%Y%m%d%H%M%S").replace(tzinfo=dt.UTC).timestamp()
        except ValueError:
            timestamps_usable = False  # Series B: damaged by a spreadsheet export
            stamp = math.nan
        stamps.append(stamp)
        q.append([_number(row[col[j]], path, line, j) for j in JOINTS])
        p.append(
            [
                _number(row[col[f"measurement_{a}"]], path, line, f"measurement_{a}") * 1e-3
                for a in "xyz"
            ]
        )
        angles = [
            _number(row[col[f"measurement_r{a}"]], path, line, f"measurement_r{a}") for a in "xyz"
        ]
        x, y, z, w = Rotation.from_euler("XYZ", angles, degrees=True).as_quat()
        quat.append([w, x, y, z] if w >= 0 else [-w, -x, -y, -z])
        temp.append(
            _number(row[col["measurement_temperature"]], path, line, "measurement_temperature")
        )
        if has_std:
            std.append([_number(row[col[c]], path, line, c) * 1e-3 for c in std_cols])
    n = len(q)
    if timestamps_usable:
        t = np.array(stamps)
        order = np.argsort(t, kind="stable")  # rows are not in time order
        t = t[order] - t[order][0]
        # 1 s resolution: poses within the same second are spread by 1 ms to stay distinct
        for i in range(1, n):
            if t[i] <= t[i - 1]:
                t[i] = t[i - 1] + 1e-3
        note = "t: seconds since the first measurement (file time stamps, 1 s resolution)"
    else:
        order = np.arange(n)
        t = order.astype(float)
        note = "t: row number (the file's time stamps are damaged)"
    q_arr, p_arr = np.array(q)[order], np.array(p)[order]
    quat_arr, temp_arr = np.array(quat)[order], np.array(temp)[order]
    enc = EncoderData(t=t, q=q_arr)
    extra = {"temperature_c": temp_arr}
    if has_std:
        std_arr = np.array(std)[order]
        extra.update({name: std_arr[:, k] for k, name in enumerate(("sx", "sy", "sz"))})
    trk = TrackerData(t=t.copy(), p=p_arr, quat=quat_arr, extra=extra)
    return enc, trk, {"rows": str(n), "time": note}


def import_dataset(kind: str, source: Path, out: Path) -> dict[str, str]:
    if kind != "ur10-lasertracker":
        raise DataFormatError(str(source), 0, "-", f"unknown data set kind '{kind}'")
    enc, trk, info = read_ur10_lasertracker(source)
    write_encoder(out / "encoder.csv", enc)
    write_tracker(out / "tracker.csv", trk)
    return {**info, "out": str(out)}
