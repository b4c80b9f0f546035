"""The recording interchange (docs/design.md §5): encoder.csv, tracker.csv, truth.csv and
estimate files. Plain CSV with a header row; SI units; quaternions scalar first.

Readers check the format and raise DataFormatError naming file, line and column. Values that
parse but are not finite are kept as NaN: the estimator skips and counts them.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

import numpy as np
import polars as pl

from keo_service.core.errors import DataFormatError

TRACKER_POSE_COLUMNS = ("t", "x", "y", "z", "qw", "qx", "qy", "qz")
TRACKER_POSITION_COLUMNS = ("t", "x", "y", "z")


@dataclass
class EncoderData:
    t: np.ndarray  # (n,)
    q: np.ndarray  # (n, nq)


@dataclass
class TrackerData:
    t: np.ndarray  # (n,)
    p: np.ndarray  # (n, 3)
    quat: np.ndarray | None  # (n, 4) scalar first, or None for a single reflector
    extra: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def position_only(self) -> bool:
        return self.quat is None


def _read_table(path: Path) -> tuple[list[str], np.ndarray]:
    """Header and numbers (rows, columns) of a CSV file. Polars parses a well-formed file (in
    native code, several times faster than numpy's loadtxt: docs/performance.md) into one
    column-major array: each column is contiguous, and the callers' column groups are views
    of it, not copies (a copy of a recording costs more in fresh pages than in arithmetic).
    A file it refuses goes to numpy, and one numpy refuses too is parsed again cell by cell
    only to say which line and column is wrong."""
    try:
        with path.open(encoding="utf-8", newline="") as f:
            first = f.readline()
    except OSError as exc:
        raise DataFormatError(str(path), 0, "-", f"cannot open: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise _not_utf8(path) from None
    if not first.strip():
        raise DataFormatError(str(path), 1, "-", "empty file, expected a header row")
    header = [h.strip() for h in next(csv.reader([first]), [])]
    if len(set(header)) != len(header):
        raise DataFormatError(str(path), 1, "-", f"repeated column names in {header}")
    table = _read_fast(path, header)
    if table is not None:
        return header, table
    try:
        body = path.read_text(encoding="utf-8").splitlines()[1:]
    except UnicodeDecodeError:
        raise _not_utf8(path) from None
    if not any(line.strip() for line in body):
        return header, np.empty((0, len(header)))
    try:
        data = np.loadtxt(body, delimiter=",", dtype=float, ndmin=2, comments=None)
    except ValueError:
        data = None
    if data is None or data.shape[1] != len(header):
        data = _parse_cells(path, header, body)
    return header, data


def _not_utf8(path: Path) -> DataFormatError:
    """The line of the first byte that is not UTF-8 (found fuzzing: it escaped as a
    UnicodeDecodeError)."""
    data = path.read_bytes()
    try:
        data.decode("utf-8")
        start = len(data)
    except UnicodeDecodeError as exc:
        start = exc.start
    line = data[:start].count(b"\n") + 1
    return DataFormatError(str(path), line, "-", f"byte {start} is not UTF-8 text")


def _read_fast(path: Path, header: list[str]) -> np.ndarray | None:
    """All numbers of a well-formed file, or None for anything unusual (a bad cell, an empty
    cell, a ragged row, a blank line) which the careful path then reads or reports."""
    schema = {f"c{i}": pl.Float64 for i in range(len(header))}
    try:
        frame = pl.read_csv(path, schema=schema, has_header=False, skip_rows=1, comment_prefix=None)
    except (pl.exceptions.PolarsError, OSError, ValueError):
        return None
    except pl.exceptions.PanicException:  # polars 2.1 panics on a lone '"' (found fuzzing)
        return None
    if frame.height == 0 or any(frame.null_count().row(0)):
        return None
    table: np.ndarray = frame.to_numpy(order="fortran")  # one copy out of polars' chunks
    return table


def _parse_cells(path: Path, header: list[str], body: list[str]) -> np.ndarray:
    rows: list[list[float]] = []
    for line_no, row in enumerate(csv.reader(body), start=2):
        if not row or all(not c.strip() for c in row):
            continue
        if len(row) != len(header):
            raise DataFormatError(
                str(path),
                line_no,
                "-",
                f"{len(row)} fields, expected {len(header)} as in the header",
            )
        values = []
        for name, cell in zip(header, row, strict=True):
            try:
                values.append(float(cell))
            except ValueError:
                raise DataFormatError(
                    str(path), line_no, name, f"'{cell}' is not a number"
                ) from None
        rows.append(values)
    return np.array(rows, dtype=float).reshape(len(rows), len(header))


def read_encoder(path: str | Path, nq: int | None = None) -> EncoderData:
    path = Path(path)
    header, table = _read_table(path)
    if not header or header[0] != "t":
        raise DataFormatError(
            str(path), 1, header[0] if header else "-", "first column must be 't'"
        )
    joints = header[1:]
    expected = [f"q{i + 1}" for i in range(len(joints))]
    if joints != expected or not joints:
        raise DataFormatError(
            str(path), 1, "-", f"columns must be t,q1,...,qN; got {','.join(header)}"
        )
    if nq is not None and len(joints) != nq:
        raise DataFormatError(
            str(path), 1, joints[-1], f"{len(joints)} joint columns, the robot model has {nq}"
        )
    return EncoderData(t=table[:, 0], q=table[:, 1:])


def read_tracker(path: str | Path) -> TrackerData:
    path = Path(path)
    header, table = _read_table(path)
    if tuple(header[:8]) == TRACKER_POSE_COLUMNS:
        core, quat = 8, table[:, 4:8]
    elif tuple(header[:4]) == TRACKER_POSITION_COLUMNS and not {"qw", "qx", "qy", "qz"} & set(
        header
    ):
        core, quat = 4, None
    else:
        raise DataFormatError(
            str(path),
            1,
            "-",
            "columns must start with t,x,y,z,qw,qx,qy,qz "
            f"(6-DoF) or t,x,y,z (single reflector); got {','.join(header)}",
        )
    extra = {name: table[:, i] for i, name in enumerate(header) if i >= core}
    return TrackerData(t=table[:, 0], p=table[:, 1:4], quat=quat, extra=extra)


def _fmt(value: float) -> str:
    return repr(float(value)) if math.isfinite(value) else "nan"


def _write_rows(path: Path, header: Sequence[str], rows: Iterable[Sequence[float]]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", encoding="utf-8", newline="") as f:
        f.write(",".join(header) + "\n")
        for row in rows:
            f.write(",".join(_fmt(v) for v in row) + "\n")


def write_encoder(path: str | Path, data: EncoderData) -> None:
    header = ["t"] + [f"q{i + 1}" for i in range(data.q.shape[1])]
    _write_rows(Path(path), header, np.column_stack([data.t, data.q]).tolist())


def write_tracker(path: str | Path, data: TrackerData) -> None:
    cols: list[np.ndarray] = [data.t[:, None], data.p]
    header = list(TRACKER_POSITION_COLUMNS)
    if data.quat is not None:
        cols.append(data.quat)
        header = list(TRACKER_POSE_COLUMNS)
    for name, values in data.extra.items():
        cols.append(values[:, None])
        header.append(name)
    _write_rows(Path(path), header, np.hstack(cols).tolist())


def error_columns(prefix: str, channels: Sequence[str]) -> list[str]:
    return [f"{prefix}_{c}" for c in channels]


def write_truth(
    path: str | Path, t: np.ndarray, error: np.ndarray, channels: Sequence[str]
) -> None:
    _write_rows(
        Path(path), ["t", *error_columns("true", channels)], np.column_stack([t, error]).tolist()
    )


def read_truth(path: str | Path) -> tuple[np.ndarray, np.ndarray, list[str]]:
    path = Path(path)
    header, table = _read_table(path)
    if header[0] != "t" or not all(h.startswith("true_") for h in header[1:]):
        raise DataFormatError(str(path), 1, "-", "columns must be t,true_px,...")
    return table[:, 0], table[:, 1:], [h[5:] for h in header[1:]]


class EstimateWriter:
    """Streams estimates to CSV: t, meas_*, est_*, flags. Held steps leave meas_* empty."""

    def __init__(self, handle: TextIO, channels: Sequence[str]) -> None:
        self._f = handle
        self._n = len(channels)
        handle.write(
            ",".join(
                ["t", *error_columns("meas", channels), *error_columns("est", channels), "flags"]
            )
            + "\n"
        )

    def write(
        self, t: float, measured: np.ndarray | None, estimate: np.ndarray, flags: Sequence[str]
    ) -> None:
        meas = [""] * self._n if measured is None else [repr(float(v)) for v in measured]
        est = [repr(float(v)) for v in estimate]
        self._f.write(",".join([repr(float(t)), *meas, *est, "|".join(flags)]) + "\n")


def write_estimate_table(
    path: str | Path,
    t: np.ndarray,
    measured: np.ndarray,
    estimate: np.ndarray,
    flags: Sequence[str] | np.ndarray,
    channels: Sequence[str],
) -> None:
    """The whole estimate file at once, the same columns as `EstimateWriter` (held rows: NaN
    measured values are written empty). Polars formats the numbers in native code with the
    shortest text that reads back to the same float, as repr() does."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    columns = [pl.Series("t", np.asarray(t, dtype=float))]
    for prefix, values in (("meas", measured), ("est", estimate)):
        for name, column in zip(error_columns(prefix, channels), np.asarray(values).T, strict=True):
            # NaN (a held row's measured error) is written empty
            columns.append(pl.Series(name, np.asarray(column, dtype=float), nan_to_null=True))
    flag_texts = flags.tolist() if isinstance(flags, np.ndarray) else flags
    columns.append(pl.Series("flags", flag_texts, dtype=pl.String))
    frame = pl.DataFrame(columns).with_columns(pl.col("flags").replace("", None))
    # opened once here: polars given the path opens it twice, truncating each time, and a
    # truncation to empty makes ext4 start writing the whole file back in close()
    with path.open("wb") as file:
        frame.write_csv(file)


@dataclass
class EstimateTable:
    t: np.ndarray
    measured: np.ndarray  # NaN where held
    estimate: np.ndarray
    flags: list[str]
    channels: list[str]


def read_estimates(path: str | Path) -> EstimateTable:
    path = Path(path)
    with path.open(encoding="utf-8", newline="") as f:
        reader = csv.reader(f)
        header = next(reader)
        n = (len(header) - 2) // 2
        channels = [h[len("meas_") :] for h in header[1 : 1 + n]]
        t, meas, est, flags = [], [], [], []
        for row in reader:
            t.append(float(row[0]))
            meas.append([float(v) if v else math.nan for v in row[1 : 1 + n]])
            est.append([float(v) for v in row[1 + n : 1 + 2 * n]])
            flags.append(row[-1])
    return EstimateTable(
        np.array(t), np.array(meas).reshape(-1, n), np.array(est).reshape(-1, n), flags, channels
    )
