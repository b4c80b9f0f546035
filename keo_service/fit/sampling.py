"""Long motion recordings: which samples carry information for `keo analyze`. No I/O.

At 1 kHz a robot moving at 1 rad/s changes each joint by a milliradian between samples:
neighbouring samples measure nearly the same configuration, and what the analysis can learn
from ten minutes is bounded by how many distinct configurations the robot passed through, not
by the sample count. So samples are binned by joint configuration (a grid of CELL_RAD on every
joint, plus the direction of motion of each joint, which backlash depends on) and one sample
per occupied cell is kept, the first in time; if more cells than `max_rows` are occupied, every
k-th kept sample in time order. Time order is preserved, so the held-out blocks still follow
time (drift).
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
    """Indices (increasing) of one sample per occupied configuration cell, thinned evenly in
    time to at most `max_rows`."""
    n = q.shape[0]
    if n <= max_rows:
        return np.arange(n)
    keys = np.floor(q / cell_rad).astype(np.int64)
    if direction is not None:
        keys = np.hstack([keys, np.sign(direction).astype(np.int64)])
    _cells, first = np.unique(keys, axis=0, return_index=True)
    rows = np.sort(first)
    if rows.size > max_rows:
        rows = rows[np.linspace(0, rows.size - 1, max_rows).round().astype(int)]
    return rows


def selection_report(recorded: int, rows: np.ndarray, cell_rad: float = CELL_RAD) -> dict[str, Any]:
    return {
        "recorded": int(recorded),
        "used": int(rows.size),
        "how": (
            f"one sample per {cell_rad:g} rad cell of the joint configuration (and direction of "
            "motion), the first in time; thinned evenly in time if more"
            if rows.size < recorded
            else "all samples"
        ),
    }
