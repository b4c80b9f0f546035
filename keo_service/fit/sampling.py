"""Long motion recordings: which samples carry information for `keo analyze`. No I/O.

At 1 kHz neighbouring samples measure nearly the same configuration, so a long recording is
thinned to `max_rows` samples evenly spaced in time: the recording as it was, fast motion,
slow stretches and rests each as often as they occur, so the fit and its held-out error weigh
them as all samples would. Thinning can step over configurations the robot passed quickly;
those are added back: the first sample of every occupied configuration cell (a grid of
CELL_RAD on every joint, plus each joint's direction of motion, which backlash depends on)
that no evenly spaced sample falls in, for at most MISSED_SHARE of the rows (thinned evenly
if more: those samples are fast motion, and a larger share would weigh it above its time
again). Selecting one sample per cell alone over-weighted fast motion (more cells a second),
where timing errors are largest. docs/analyze.md gives what each choice measured.

Time order is preserved, so the held-out blocks still follow time (drift).
"""

from __future__ import annotations

from typing import Any

import numpy as np

CELL_RAD = 0.01  # rad: configurations closer than this on every joint count as one
MAX_ROWS = 10_000  # rows the analysis keeps of a long motion recording
MISSED_SHARE = 0.05  # of those rows at most, the configurations the even spacing misses


def informative_rows(
    q: np.ndarray,
    direction: np.ndarray | None = None,
    max_rows: int = MAX_ROWS,
    cell_rad: float = CELL_RAD,
) -> np.ndarray:
    """Indices (increasing, at most `max_rows`) of samples evenly spaced in time, plus the
    first sample of each configuration cell none of them falls in (at most MISSED_SHARE)."""
    n = q.shape[0]
    if n <= max_rows:
        return np.arange(n)
    keys = np.floor(q / cell_rad).astype(np.int64)
    if direction is not None:
        keys = np.hstack([keys, np.sign(direction).astype(np.int64)])
    _cells, first, cell_of = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    cell_of = cell_of.ravel()
    covered = np.zeros(first.size, dtype=bool)
    covered[cell_of[_even(n, max_rows)]] = True
    missed = np.sort(first[~covered])
    most = int(MISSED_SHARE * max_rows)
    if missed.size > most:
        missed = missed[_even(missed.size, most)]
    rows: np.ndarray = np.union1d(_even(n, max_rows - missed.size), missed)  # <= max_rows
    return rows


def _even(n: int, k: int) -> np.ndarray:
    """k indices of 0..n-1 evenly spaced (both ends included)."""
    out: np.ndarray = np.linspace(0, n - 1, k).round().astype(int)
    return out


def selection_report(recorded: int, rows: np.ndarray, cell_rad: float = CELL_RAD) -> dict[str, Any]:
    return {
        "recorded": int(recorded),
        "used": int(rows.size),
        "how": (
            "evenly spaced in time, plus the first sample of each "
            f"{cell_rad:g} rad cell of the joint configuration (and direction of motion) that "
            f"none of them falls in (at most {100 * MISSED_SHARE:g} % of the rows)"
            if rows.size < recorded
            else "all samples"
        ),
    }
