"""Long motion recordings: which samples carry information for `keo analyze`. No I/O.

At 1 kHz a robot moving at 1 rad/s changes each joint by a milliradian between samples:
neighbouring samples measure nearly the same configuration, and what the analysis can learn
from ten minutes is bounded by how many distinct configurations the robot passed through, not
by the sample count. So the kept rows are two sets, in time order:

- one sample per occupied configuration cell (a grid of CELL_RAD on every joint, plus the
  direction of motion of each joint, which backlash depends on), the first in time, thinned
  evenly to at most half of `max_rows`: every distinct configuration is seen;
- the rest of `max_rows` evenly spaced in time: the recording as it was, slow stretches and
  rests as often as they occur. One sample per cell alone over-weights fast motion (more cells
  a second), where timing errors are largest: on a 60 s simulated recording it gave 4.22 mm
  held out against 2.43 mm from all samples.

Time order is preserved, so the held-out blocks still follow time (drift).
"""

from __future__ import annotations

from typing import Any

import numpy as np

CELL_RAD = 0.01  # rad: configurations closer than this on every joint count as one
MAX_ROWS = 20_000  # rows the analysis keeps of a long motion recording


def informative_rows(
    q: np.ndarray,
    direction: np.ndarray | None = None,
    max_rows: int = MAX_ROWS,
    cell_rad: float = CELL_RAD,
) -> np.ndarray:
    """Indices (increasing, at most `max_rows`) of one sample per occupied configuration cell
    (at most half of them) and samples evenly spaced in time (the rest)."""
    n = q.shape[0]
    if n <= max_rows:
        return np.arange(n)
    keys = np.floor(q / cell_rad).astype(np.int64)
    if direction is not None:
        keys = np.hstack([keys, np.sign(direction).astype(np.int64)])
    _cells, first = np.unique(keys, axis=0, return_index=True)
    cells = np.sort(first)
    if cells.size > max_rows // 2:
        cells = cells[np.linspace(0, cells.size - 1, max_rows // 2).round().astype(int)]
    even = np.linspace(0, n - 1, max_rows - cells.size).round().astype(int)
    rows: np.ndarray = np.union1d(cells, even)  # at most max_rows
    return rows


def selection_report(recorded: int, rows: np.ndarray, cell_rad: float = CELL_RAD) -> dict[str, Any]:
    return {
        "recorded": int(recorded),
        "used": int(rows.size),
        "how": (
            f"one sample per {cell_rad:g} rad cell of the joint configuration (and direction of "
            "motion), the first in time, for at most half the rows; the rest evenly spaced in "
            "time"
            if rows.size < recorded
            else "all samples"
        ),
    }
