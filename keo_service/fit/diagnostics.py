"""What a metrologist asks of an identification besides its numbers: how repeatable the data
itself is, and which parameters the poses cannot tell apart. No I/O."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

SAME_POSE_RAD = 2e-4  # joint vectors this close on every joint: one pose measured again
MIN_REPEATED_POSES = 5  # fewer repeated poses say little about a repeatability
OUTLIER_FACTOR = 5.0  # a repeated pose this far above the median pose's scatter is no repeat
MAX_PAIRS = 2_000_000  # neighbour pairs searched at most; beyond, poses are grouped by cells
COUPLING_SHARE = 0.2  # a parameter takes part in a combination above this share of its largest


@dataclass(frozen=True)
class Repeatability:
    """Scatter of repeated measurements of the same pose: the pooled RMS distance of each
    measurement from its pose's mean position (degrees of freedom: measurements - poses).
    A pose whose own scatter exceeds OUTLIER_FACTOR x the median pose's is left out and
    counted (real data hold equal joint readings far apart: not a repeat)."""

    poses: int  # poses measured more than once (kept)
    measurements: int  # measurements of those poses
    rms_mm: float
    left_out: int  # repeated poses left out as outliers
    # per row, the repeated pose it belongs to (-1: measured once, or left out)
    groups: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=int), compare=False)

    def as_dict(self) -> dict[str, Any]:
        return {
            "poses": self.poses,
            "measurements": self.measurements,
            "rms_mm": self.rms_mm,
            "left_out_poses": self.left_out,
        }


def repeatability(
    q: np.ndarray, p: np.ndarray, tol_rad: float = SAME_POSE_RAD
) -> Repeatability | None:
    """From rows whose joints agree within `tol_rad` on every joint (chained: the connected
    groups of such pairs; two readings of one commanded pose differ by encoder counts,
    distinct poses by far more). None below MIN_REPEATED_POSES. `p` in metres, any fixed frame (a
    rigid change of frame keeps distances)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    q = np.asarray(q, dtype=float)
    # equal joint vectors are one group before any search: motion data standing still hold
    # tens of thousands of equal rows, whose pairs (n^2 / 2 of them) took 24 GB at 60k rows
    distinct, first_of = np.unique(q, axis=0, return_inverse=True)
    first_of = first_of.ravel()
    m = distinct.shape[0]
    tree = cKDTree(distinct)
    if tree.count_neighbors(tree, tol_rad, p=np.inf) - m > 2 * MAX_PAIRS:
        # still too many neighbours (slow motion at a high rate): cells of tol_rad instead
        cells = np.floor(distinct / tol_rad).astype(np.int64)
        _cells, cell_group = np.unique(cells, axis=0, return_inverse=True)
        group = cell_group.ravel()[first_of]
    else:
        pairs = tree.query_pairs(tol_rad, p=np.inf, output_type="ndarray")
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(m, m))
        _count, distinct_group = connected_components(graph, directed=False)
        group = distinct_group[first_of]
    # labels in order of each group's first row (as a search over all rows numbers them)
    _labels, first_row, dense = np.unique(group, return_index=True, return_inverse=True)
    rank = np.empty(first_row.size, dtype=np.int64)
    rank[np.argsort(first_row)] = np.arange(first_row.size)
    group = rank[dense.ravel()]
    counts = np.bincount(group)
    if not np.any(counts > 1):
        return None
    pts = np.asarray(p, dtype=float)
    sums = np.zeros((counts.size, 3))
    np.add.at(sums, group, pts)
    means = sums / counts[:, None]
    sq = np.zeros(counts.size)
    np.add.at(sq, group, np.sum((pts - means[group]) ** 2, axis=1))
    repeated = np.flatnonzero(counts > 1)
    spread = np.sqrt(sq[repeated] / (counts[repeated] - 1))
    keep = repeated[spread <= OUTLIER_FACTOR * np.median(spread)]
    if keep.size < MIN_REPEATED_POSES:
        return None
    m = int(counts[keep].sum())
    rms = float(np.sqrt(sq[keep].sum() / (m - keep.size)))
    labels = np.where(np.isin(group, keep), group, -1)
    return Repeatability(int(keep.size), m, rms * 1e3, int(repeated.size - keep.size), labels)


def describe_null_space(null: np.ndarray, labels: Sequence[str]) -> list[dict[str, Any]]:
    """Each direction the poses cannot see (a column of `null`, in the effect's parameters)
    as the parameters taking part and a sentence: one parameter alone cannot be told apart
    from the registration; several move the tool alike and only other combinations of them
    are identified."""
    out = []
    for direction in _sparse_basis(np.asarray(null, dtype=float)).T:
        v = direction / np.max(np.abs(direction))
        idx = [int(i) for i in np.argsort(-np.abs(v)) if abs(v[i]) >= COUPLING_SHARE]
        members = [{"parameter": labels[i], "weight": float(v[i])} for i in idx]
        if len(idx) == 1:
            text = (
                f"{labels[idx[0]]}: not identifiable here (the tracker registration or the "
                "sensor mount absorbs it, or these poses do not excite it); held at zero"
            )
        else:
            combo = " ".join(f"{v[i]:+.2f} x {labels[i]}" for i in idx)
            text = (
                f"coupled: {', '.join(labels[i] for i in idx)} move the tool alike; the "
                f"combination {combo} is invisible in these poses and held at zero"
            )
        out.append({"members": members, "text": text})
    return out


def _sparse_basis(null: np.ndarray) -> np.ndarray:
    """The same null space in a basis that names few parameters each: pivot parameters by
    column-pivoted QR, then each direction holds one pivot at 1 and the others at 0 (a
    reduced echelon form), so a parameter the registration absorbs alone shows alone."""
    if null.size == 0:
        return null
    from scipy.linalg import qr

    _q, _r, pivots = qr(null.T, pivoting=True)
    chosen = pivots[: null.shape[1]]
    basis = null @ np.linalg.inv(null[chosen, :])
    basis[np.abs(basis) < 1e-9] = 0.0
    return basis


def residual_components(pos_mm: np.ndarray) -> dict[str, float]:
    """RMS of the signed position residual per base-frame component (mm)."""
    r = np.asarray(pos_mm, dtype=float)
    return {axis: float(np.sqrt(np.mean(r[:, k] ** 2))) for k, axis in enumerate("xyz")}
