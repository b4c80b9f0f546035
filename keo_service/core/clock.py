"""A device's clock mapped onto the host's, from (device time, host receipt time) pairs. No I/O.

Model: a sample the device stamped `d` (its clock) reaches the host at

    r = d + offset + drift * (d - d_ref) + latency,     latency >= floor >= 0

where latency carries the TCP and scheduling jitter (milliseconds, in bursts when the host or
the network stalls). The stamps the device gives are far more regular than the receipt times,
so the mapped stamp `d + offset + drift * (d - d_ref)` keeps the device's regularity on the
host's clock. The lower envelope of `r - d` against `d` is the line `offset + drift * (d -
d_ref)` shifted up by the latency floor: per block of `block_s` device seconds we keep the
sample that waited least, and fit a line through the block minima of the last `window_s`
seconds, refitted without blocks far above it (a block delivered late as a whole). The floor
itself (the shortest transport time) cannot be seen from the host and stays in the offset.

A device clock that steps (controller restart, resync) shows as samples arriving earlier than
the line allows (more than `step_threshold_s`) or device time going backwards: after
`step_confirm` such samples in a row the mapper forgets the old line and learns anew (a first
offset at once, a drift after two blocks). Late samples never count as a step: a stalled host
delays them, and their mapped stamps are what removes the stall. (A host clock stepping
forward looks like lateness: the line follows it once the old minima leave the window.)
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass

import numpy as np

__all__ = ["ClockMapper", "ClockState", "ReceiptStamps"]

MIN_STEP_S = 1e-6


@dataclass(frozen=True)
class ClockState:
    offset_s: float  # host minus device time at the reference device time (incl. the floor)
    drift_ppm: float  # how much faster the host clock runs than the device's, in ppm
    residual_s: float  # RMS of the block minima about the fitted line
    blocks: int  # block minima in the current fit
    steps: int  # clock steps detected and re-learned
    held_back: int  # stamps moved just after the previous one so that none goes back


class ClockMapper:
    def __init__(
        self,
        block_s: float = 0.25,
        window_s: float = 10.0,
        step_threshold_s: float = 0.05,
        step_confirm: int = 3,
    ) -> None:
        self.block_s = block_s
        self.step_threshold_s = step_threshold_s
        self.step_confirm = step_confirm
        self._blocks: collections.deque[tuple[float, float]] = collections.deque(
            maxlen=max(2, math.ceil(window_s / block_s))
        )
        self.steps = 0
        self.held_back = 0
        self._last_out = -math.inf  # the host clock does not step with the device's
        self._reset()

    def _reset(self) -> None:
        self._blocks.clear()
        self._block_index: int | None = None
        self._block_min = (math.inf, math.inf)  # (host - device, device) of the least-late sample
        self._ref = 0.0
        self._offset: float | None = None
        self._drift = 0.0
        self._residual = 0.0
        self._last_device = -math.inf
        self._outliers = 0

    def predict(self, device_t: float) -> float:
        """Host time of a device stamp under the current fit (device time itself if none)."""
        if self._offset is None:
            return device_t
        return device_t + self._offset + self._drift * (device_t - self._ref)

    def map(self, device_t: float, host_t: float) -> float:
        """Learn from one sample and return its stamp on the host clock. A sample far off the
        line (a step not yet confirmed, or one glitch) is not learned from and keeps its
        receipt time."""
        if self._is_step(device_t, host_t):
            self.steps += 1
            self._reset()
        elif self._outliers:
            return self._monotonic(host_t)
        self._last_device = max(self._last_device, device_t)
        lag = host_t - device_t
        index = math.floor(device_t / self.block_s)
        if self._block_index is None:
            self._block_index = index
        if index != self._block_index:
            self._blocks.append((self._block_min[1], self._block_min[0]))
            self._block_index = index
            self._block_min = (lag, device_t)
            self._fit()
        elif lag < self._block_min[0]:
            self._block_min = (lag, device_t)
        if len(self._blocks) < 2:
            # before a line: the least-late sample so far gives the offset, no drift
            best = min([self._block_min[0], *(y for _d, y in self._blocks)])
            self._offset, self._drift, self._ref = best, 0.0, device_t
        return self._monotonic(self.predict(device_t))

    def _monotonic(self, t: float) -> float:
        """Stamps never go back: while the fit learns (the first samples of a connection
        wait longest, so the offset drops as faster ones arrive) a stamp that would fall
        before the previous one is placed just after it, and counted."""
        if t <= self._last_out:
            t = self._last_out + MIN_STEP_S
            self.held_back += 1
        self._last_out = t
        return t

    def _is_step(self, device_t: float, host_t: float) -> bool:
        if self._offset is None:
            return False
        gone_back = device_t < self._last_device - self.step_threshold_s
        # early beyond the threshold is impossible without a step (latency is never negative);
        # late is only a stalled host or network, which the mapping is there to remove
        early = host_t < self.predict(device_t) - self.step_threshold_s
        if not (gone_back or early):
            self._outliers = 0
            return False
        self._outliers += 1
        return self._outliers >= self.step_confirm

    def _fit(self) -> None:
        if len(self._blocks) < 2:
            return
        d = np.fromiter((b[0] for b in self._blocks), float, len(self._blocks))
        y = np.fromiter((b[1] for b in self._blocks), float, len(self._blocks))
        ref = float(d.mean())
        keep = np.ones(d.size, dtype=bool)
        for _ in range(2):  # the envelope: refit without blocks that arrived late as a whole
            slope, intercept = np.polyfit(d[keep] - ref, y[keep], 1)
            resid = y - (intercept + slope * (d - ref))
            spread = 1.4826 * float(np.median(np.abs(resid[keep]))) + 1e-6
            new_keep = resid < 3.0 * spread
            if new_keep.sum() < 2 or np.array_equal(new_keep, keep):
                break
            keep = new_keep
        self._ref, self._offset, self._drift = ref, float(intercept), float(slope)
        self._residual = float(np.sqrt(np.mean(resid[keep] ** 2)))

    def state(self) -> ClockState:
        return ClockState(
            offset_s=0.0 if self._offset is None else self._offset,
            drift_ppm=self._drift * 1e6,
            residual_s=self._residual,
            blocks=len(self._blocks),
            steps=self.steps,
            held_back=self.held_back,
        )


class ReceiptStamps:
    """Host stamps for a device that gives none (MotoROS leaves its time at 0): receipt time.

    Frames that reach the host in one read share a receipt time, yet were sent apart: the
    earlier ones arrived somewhere after the previous read, so they are spread evenly between
    the previous stamp and this receipt (the last frame keeps the receipt time). A stamp never
    repeats or goes back (a host clock stepped back): it is placed just after its
    predecessor, and counted."""

    def __init__(self) -> None:
        self._last = -math.inf
        self.held_back = 0

    def place(self, receipt_t: float, count: int) -> list[float]:
        """Stamps for `count` frames received together at `receipt_t`, oldest first."""
        if count <= 0:
            return []
        last = self._last
        if receipt_t <= last:
            self.held_back += 1
            receipt_t = last + MIN_STEP_S * count
        start = last if math.isfinite(last) else receipt_t - MIN_STEP_S * count
        step = (receipt_t - start) / count
        stamps = [start + step * (i + 1) for i in range(count - 1)] + [receipt_t]
        self._last = receipt_t
        return stamps
