"""Accuracy against a known truth: shared by the paper tables, benchmarks and tests. No I/O."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from keo_service.core.estimator import Estimate, Estimator, run_offline
from keo_service.core.kinematics import Cell
from keo_service.core.settings import EstimatorSettings


@dataclass(frozen=True)
class Series:
    """`Estimate`s' `stamp`, `measured` and `estimate` as columns (what the studies score)."""

    stamp: np.ndarray
    measured: np.ndarray  # NaN rows where held
    estimate: np.ndarray


def as_series(estimates: Sequence[Estimate]) -> Series:
    n = len(estimates)
    k = len(estimates[0].estimate) if n else 0
    meas = np.full((n, k), np.nan)
    for i, e in enumerate(estimates):
        if e.measured is not None:
            meas[i] = e.measured
    return Series(
        np.array([e.stamp for e in estimates]),
        meas,
        np.array([e.estimate for e in estimates]).reshape(n, k),
    )


def truth_at(t: np.ndarray, truth_t: np.ndarray, truth: np.ndarray) -> np.ndarray:
    return np.column_stack([np.interp(t, truth_t, truth[:, k]) for k in range(truth.shape[1])])


def rms(x: np.ndarray) -> float:
    x = x[np.all(np.isfinite(x), axis=1)] if x.ndim == 2 else x[np.isfinite(x)]
    return (
        float(np.sqrt(np.mean(np.sum(x * x, axis=1))))
        if x.ndim == 2
        else float(np.sqrt(np.mean(x * x)))
    )


def window_mask(t: np.ndarray, windows: Sequence[tuple[float, float]]) -> np.ndarray:
    mask = np.zeros(t.size, dtype=bool)
    for a, b in windows:
        mask |= (t >= a) & (t <= b)
    return mask


def estimate_error_rms(
    series: Series, truth_t: np.ndarray, truth: np.ndarray, mask: np.ndarray
) -> tuple[float, float]:
    """RMS norm of (estimate - truth) over the rows in `mask`: (position m, orientation rad)."""
    err = series.estimate - truth_at(series.stamp, truth_t, truth)
    pos = rms(err[mask, :3])
    rot = rms(err[mask, 3:6]) if err.shape[1] >= 6 else float("nan")
    return pos, rot


def estimate_run(cell: Cell, settings: EstimatorSettings, run: Any) -> Series:
    """The estimator over a SimulatedRun's streams, in stamp order."""
    return as_series(
        run_offline(
            Estimator(cell, settings),
            run.encoder.t,
            run.encoder.q,
            run.tracker.t,
            run.tracker.p,
            run.tracker.quat,
        )
    )
