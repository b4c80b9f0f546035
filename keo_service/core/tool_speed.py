"""The tool's speed that every live estimate message carries (`tool_speed_m_s`).

A delay that is off by d shows in the measured error as the tool's speed times d, so a client
judging an estimate (or the delay's standard error) needs the speed at that moment: `keo
analyze` gives it offline, and the live messages give it too. It is taken off the per-sample
path (the service's status cycle samples the newest estimate; a forward kinematics per
estimate would cost the hot path a real share): the nominal tool point of each sampled
estimate's joints, through the forward kinematics, and a quadratic fitted by least squares to
the points of the last `WINDOW_S`, whose slope is the speed at the stamp asked for.

Why a fit over several points, not the step between two: joints stamped on receipt (a MotoROS
controller sends every 25 +/- 3 ms and leaves its time at 0) are placed a few milliseconds off
in time, so each tool point is off by the speed times that, and a late-delivered frame by tens
of milliseconds; over one 0.1 s step that was a speed tens of mm/s off, and 20-40 % high at
peaks. A fit over about six points averages the stamps' scatter, and a point far off the
others' curve is left out. Why a quadratic, not a line: the speed of a line over the window is
the speed at its middle, a quarter of a second behind a tool that speeds up or slows down; the
quadratic's slope is taken where it is asked, up to `AHEAD_S` past the newest point (the status
cycle samples every 0.1 s). Measured errors: docs/timing-delay.md.
"""

from __future__ import annotations

import collections
import math

import numpy as np

from keo_service.core.estimator import Estimate
from keo_service.core.kinematics import Cell, tool_pose

STEP_S = 0.05  # sampled points at least this far apart (stream time)
WINDOW_S = 0.6  # the fit's span: the points of the last this many seconds
MIN_POINTS = 4  # a quadratic through fewer would average nothing
AHEAD_S = 0.1  # the slope is taken at most this far past the newest point (one status cycle)
MAX_STEP_S = 1.0  # a longer step (a pause, a gap, a restart) starts the points anew
STALE_S = 1.0  # a speed older than this (stream time) is no longer the tool's at a new estimate
OUTLIER = 3.0  # a point this many times the median distance off the fit is left out ...
OUTLIER_MIN_M = 0.2e-3  # ... when it is that far off at all (the tool's own noise is below)


class ToolSpeed:
    """The nominal tool point's speed from the estimates' joints, sampled now and then.

    `sample(estimate)` (the service's status cycle, with the estimator's newest estimate)
    computes the tool point once per call when the estimate is new and at least `STEP_S` after
    the one before, and fits the window anew; `at(stamp)` gives the speed for an estimate at
    that stream time, or None (fewer than `MIN_POINTS` points yet, or the fit is stale)."""

    def __init__(self, cell: Cell) -> None:
        self.cell = cell
        self._data = cell.robot.create_data()
        self._points: collections.deque[tuple[float, np.ndarray]] = collections.deque()
        # the fit, about the newest point's stamp: (stamp, velocity there, acceleration), m/s
        self._fit: tuple[float, tuple[float, ...], tuple[float, ...]] | None = None
        self.speed: float | None = None  # at the newest point, m/s

    def sample(self, estimate: Estimate | None) -> None:
        """Take the tool point of this estimate, and fit the speed anew."""
        if estimate is None or estimate.joints is None or estimate.held:
            return
        t = estimate.stamp
        points = self._points
        if points:
            step = t - points[-1][0]
            if 0.0 <= step < STEP_S:
                return  # the same estimate again, or too close to the last one
            if not 0.0 < step <= MAX_STEP_S:  # a pause, or stamps went back (a restart)
                points.clear()
                self._fit, self.speed = None, None
        p = np.array(tool_pose(self.cell, self._data, estimate.joints).translation, dtype=float)
        points.append((t, p))
        while points[0][0] < t - WINDOW_S - 1e-9:
            points.popleft()
        if len(points) >= MIN_POINTS:
            self._refit(t)

    def _refit(self, t: float) -> None:
        """The quadratic through the window's points (about the newest, at `t`), once more
        without the point farthest off it when that one is an outlier."""
        x = np.array([s - t for s, _ in self._points])
        y = np.array([p for _, p in self._points])
        design = np.column_stack([np.ones_like(x), x, x * x])
        coef = np.linalg.lstsq(design, y, rcond=None)[0]
        if x.size > MIN_POINTS:
            off = np.linalg.norm(y - design @ coef, axis=1)
            worst = int(np.argmax(off))
            if off[worst] > max(OUTLIER * float(np.median(off)), OUTLIER_MIN_M):
                keep = np.arange(x.size) != worst
                coef = np.linalg.lstsq(design[keep], y[keep], rcond=None)[0]
        velocity = tuple(float(c) for c in coef[1])
        acceleration = tuple(2.0 * float(c) for c in coef[2])
        self._fit = (t, velocity, acceleration)
        self.speed = math.sqrt(sum(v * v for v in velocity))

    def at(self, stamp: float) -> float | None:
        """The speed for an estimate at this stream time, m/s (None: not known, or stale).
        Per published estimate: a few float operations."""
        fit = self._fit
        if fit is None:
            return None
        t, v, a = fit
        dt = stamp - t
        if not abs(dt) <= STALE_S:
            return None
        dt = min(max(dt, -WINDOW_S), AHEAD_S)
        return math.sqrt(
            (v[0] + a[0] * dt) ** 2 + (v[1] + a[1] * dt) ** 2 + (v[2] + a[2] * dt) ** 2
        )
