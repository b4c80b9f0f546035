"""Rotations over many samples at once, component-major ((3, 3, N) matrices): what the
batch estimator, the delay fit and the residual analysis share. No I/O."""

from __future__ import annotations

import numpy as np

__all__ = ["log3_many", "quaternion_matrices", "transposed_times"]


def quaternion_matrices(wxyz: np.ndarray) -> np.ndarray:
    """(3, 3, N) rotation matrices of quaternions (N, 4), scalar first, normalised here (as
    Pinocchio does per sample)."""
    w, x, y, z = (wxyz / np.sqrt(np.einsum("ij,ij->i", wxyz, wxyz))[:, None]).T
    R = np.empty((3, 3, wxyz.shape[0]))
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz, wx, wy, wz = x * y, x * z, y * z, w * x, w * y, w * z
    R[0, 0] = 1.0 - 2.0 * (yy + zz)
    R[0, 1] = 2.0 * (xy - wz)
    R[0, 2] = 2.0 * (xz + wy)
    R[1, 0] = 2.0 * (xy + wz)
    R[1, 1] = 1.0 - 2.0 * (xx + zz)
    R[1, 2] = 2.0 * (yz - wx)
    R[2, 0] = 2.0 * (xz - wy)
    R[2, 1] = 2.0 * (yz + wx)
    R[2, 2] = 1.0 - 2.0 * (xx + yy)
    return R


def log3_many(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (N, 3) of rotations (3, 3, N): angle atan2(sin, cos) from the skew
    part and the trace, exact near zero (the errors keo sees); within 0.45 rad of a half
    turn, where the skew part vanishes, scipy's quaternion route takes over."""
    v = 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    sin = np.sqrt(np.einsum("in,in->n", v, v))
    cos = 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)
    angle = np.arctan2(sin, cos)
    scale = np.ones_like(angle)
    moving = sin > 0.0
    scale[moving] = angle[moving] / sin[moving]
    out: np.ndarray = (v * scale).T
    far = cos < -0.9
    if far.any():
        from scipy.spatial.transform import Rotation  # rare: kept off the import path

        out[far] = Rotation.from_matrix(np.moveaxis(R[:, :, far], 2, 0)).as_rotvec()
    return out


def transposed_times(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """A_n^T B_n for every sample of two (3, 3, N) stacks (views of other layouts are fine),
    as nine sums of three products over contiguous rows: the relative rotation of B from A."""
    out = np.empty(B.shape)
    for i in range(3):
        for k in range(3):
            out[i, k] = A[0, i] * B[0, k] + A[1, i] * B[1, k] + A[2, i] * B[2, k]
    return out
