"""The tool's speed that every live estimate message carries (`tool_speed_m_s`).

A delay that is off by d shows in the measured error as the tool's speed times d, so a client
judging an estimate (or the delay's standard error) needs the speed at that moment: `keo
analyze` gives it offline, and the live messages give it too. It is the nominal tool point's
displacement between two of the estimator's newest estimates, at least `STEP_S` of stream time
apart, over that time: the joints each estimate was computed with, through the forward
kinematics. It is taken off the per-sample path (the service's status cycle samples the newest
estimate; a forward kinematics per estimate would cost the hot path a real share), so each
message carries the speed over the newest step before it.
"""

from __future__ import annotations

import math

import numpy as np

from keo_service.core.estimator import Estimate
from keo_service.core.kinematics import Cell, tool_pose

STEP_S = 0.05  # the step the speed is taken over, at least (stream time)
MAX_STEP_S = 1.0  # a longer step (a pause, a gap, a restart) gives no speed: a chord is no speed
STALE_S = 1.0  # a speed older than this (stream time) is no longer the tool's at a new estimate


class ToolSpeed:
    """The nominal tool point's speed from the estimates' joints, sampled now and then.

    `sample(estimate)` (the service's status cycle, with the estimator's newest estimate)
    computes the tool point once per call when the estimate is new and at least `STEP_S` after
    the one before; `at(stamp)` gives the newest speed for an estimate at that stream time, or
    None (no two estimates with joints yet, or the speed is stale)."""

    def __init__(self, cell: Cell) -> None:
        self.cell = cell
        self._data = cell.robot.create_data()
        self._last: tuple[float, np.ndarray] | None = None  # (stamp, tool point)
        self.speed: float | None = None  # m/s
        self._speed_t = -math.inf  # the stamp the speed was taken at

    def sample(self, estimate: Estimate | None) -> None:
        """Take the tool point of this estimate, and the speed since the one before."""
        if estimate is None or estimate.joints is None or estimate.held:
            return
        t = estimate.stamp
        last = self._last
        if last is not None and 0.0 <= t - last[0] < STEP_S:
            return  # the same estimate again, or too close to the last one
        p = np.array(tool_pose(self.cell, self._data, estimate.joints).translation, dtype=float)
        self._last = (t, p)
        if last is None or not 0.0 < t - last[0] <= MAX_STEP_S:
            return  # the first, or after a pause or a restart (stamps went back)
        self.speed = float(np.linalg.norm(p - last[1])) / (t - last[0])
        self._speed_t = t

    def at(self, stamp: float) -> float | None:
        """The speed for an estimate at this stream time (None: not known, or stale)."""
        if self.speed is None or not abs(stamp - self._speed_t) <= STALE_S:
            return None
        return self.speed
