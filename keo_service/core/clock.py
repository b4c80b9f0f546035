"""A device's clock mapped onto the host's, from (device time, host receipt time) pairs. No I/O.

Model: a sample the device stamped `d` (its clock) reaches the host at

    r = d + offset + drift * (d - d_ref) + latency,     latency >= floor >= 0

where latency carries the TCP and scheduling jitter (milliseconds, in bursts when the host or
the network stalls, and rises lasting seconds when the host is loaded). The stamps the device
gives are far more regular than the receipt times, so the mapped stamp `d + offset + drift *
(d - d_ref)` keeps the device's regularity on the host's clock. The line is a low envelope of
`r - d` against `d`: per block of `block_s` device seconds we keep the sample that waited
least, and

- the drift is the median of the slopes between pairs of block minima over the last
  `drift_window_s` seconds (Theil and Sen's estimator; pairs closer than a quarter of
  `min_drift_span_s` are left out): blocks above the line, for seconds at a time, do not
  move it;
- the offset puts the line, at that slope, through the `offset_quantile` (the median) of the
  block minima of the last `window_s` seconds: a change in latency lasting seconds (a loaded
  host, or one that answers faster for a while) leaves it nearly alone, one lasting more than
  half of `window_s` is a new floor and the line follows it.

Not through the lowest blocks: the least latency of a block varies by a hundred microseconds
from block to block (whether the receiving process happened to be awake), with rare "lucky"
samples far below the rest and stretches of seconds when the host answers faster; a line
through the lowest (a lower convex hull, tried) jumps whenever one enters or leaves the
window and tilts between them, and the mean of the lowest half (the version before) follows
each faster stretch, which the delay between the streams then has to follow. The median
does neither (docs/timing-delay.md, "The clock mapping", has the measurements). So the mapped
stamps carry the stream's usual shortest transport time (which cannot be seen from the host
and stays in the offset) and little else.

A drift needs a span of device time to be resolved: until the blocks span `min_drift_span_s`
(and `min_drift_blocks` of them), the drift is held at its prior, the drift the mapper had
before it re-learned (or zero for a new mapper, or the `prior_drift` given), and the offset is
taken from the newest blocks only (`hold_s` seconds), so a wrong prior costs about
`drift * hold_s / 2`. (A drift fitted from two blocks, as the first version did, turns one
slow block after a restart into a steep slope: docs/timing-delay.md.)

A device clock that steps (controller restart, resync) shows as device time going backwards,
or as samples arriving earlier than any block of the window allowed (more than
`step_threshold_s` below the lowest block minimum, not below the median line) where the lag
fell at once from one sample to the next: after `step_confirm` such samples in a row the mapper
forgets the old line and learns anew (a first offset at once, the drift held at the previous
one until the span supports a new one). A backlog clearing is none of these: a host that fell
behind for seconds (a loaded CI machine, a busy cell PC) delivers late samples whose lag falls
back by at most one sample period per sample, to where it had been before. Late samples never
count as a step: a stalled host delays them, and their mapped stamps are what removes the
stall. (A host clock stepping forward looks like lateness: the line follows it once the old
minima leave the window.)

A device's oscillator does not change when its connection does: a new connection (or a
restarted adapter, from the mapping it saved: `export` / `resume`) continues the mapping it
had, block minima and all, so the stamps go on on the same line and the drift is not learned
again from a few seconds of blocks (which leaves it off and swings the stamps while it
converges: docs/timing.md). The continued line is checked: until a whole block of the new
data has come, a sample late beyond `step_threshold_s` counts like an early one, and a first
block whose least lag is more than `step_threshold_s` off the line either way is a step (the
device restarted, or another device answers at that address): the mapping starts anew.
"""

from __future__ import annotations

import collections
import itertools
import math
from dataclasses import dataclass

import numpy as np

__all__ = [
    "RECEIPT_GAP_FACTOR",
    "RECEIPT_GAP_MIN_S",
    "ClockMapper",
    "ClockState",
    "ReceiptStamps",
    "pairwise_median_slope",
]

MIN_STEP_S = 1e-6
# the offset's quantile of the newest blocks while the drift is held (see ClockMapper._fit)
HELD_QUANTILE = 0.25


@dataclass(frozen=True)
class ClockState:
    offset_s: float  # host minus device time at the reference device time (incl. the floor)
    drift_ppm: float  # how much faster the host clock runs than the device's, in ppm
    residual_s: float  # RMS of the block minima above the line (the recent window)
    blocks: int  # block minima in the recent window
    steps: int  # clock steps detected and re-learned
    held_back: int  # stamps moved just after the previous one so that none goes back
    drift_held: bool = False  # the span does not support a drift yet: the prior is used
    span_s: float = 0.0  # device seconds the drift fit spans
    continued: int = 0  # times a mapping was continued (a reconnect, a restarted adapter)


def pairwise_median_slope(d: np.ndarray, y: np.ndarray, min_dd: float) -> float:
    """The median of the slopes between all pairs of points at least `min_dd` apart in d
    (Theil and Sen's estimator: a third of the points may lie anywhere without moving it)."""
    i, j = np.triu_indices(d.size, k=1)
    dd = d[j] - d[i]
    far = dd >= min_dd
    if not far.any():
        return 0.0
    return float(np.median((y[j] - y[i])[far] / dd[far]))


class ClockMapper:
    def __init__(
        self,
        block_s: float = 0.25,
        window_s: float = 20.0,
        step_threshold_s: float = 0.05,
        step_confirm: int = 3,
        drift_window_s: float = 60.0,
        min_drift_span_s: float = 4.0,
        min_drift_blocks: int = 12,
        hold_s: float = 1.0,
        prior_drift: float = 0.0,
        offset_quantile: float = 0.5,
        max_drift: float = 1e-3,
    ) -> None:
        self.block_s = block_s
        self.window_s = window_s
        self.step_threshold_s = step_threshold_s
        self.step_confirm = step_confirm
        self.drift_window_s = max(drift_window_s, window_s)
        self.min_drift_span_s = min_drift_span_s
        self.min_drift_blocks = min_drift_blocks
        self.hold_s = hold_s
        self.prior_drift = prior_drift
        self.offset_quantile = offset_quantile
        self.max_drift = max_drift
        self._recent = max(1, math.ceil(window_s / block_s))
        self._blocks: collections.deque[tuple[float, float]] = collections.deque(
            maxlen=max(2, math.ceil(max(drift_window_s, window_s) / block_s))
        )
        self.steps = 0
        self.held_back = 0
        self.continued = 0
        self._checking = False  # a continued line not yet confirmed by a block of new data
        self._last_out = -math.inf  # the host clock does not step with the device's
        self.on_line = False  # whether the newest stamp mapped lies on the line (`predict`)
        self._reset()

    def _reset(self) -> None:
        self._blocks.clear()
        self._block_index: int | None = None
        self._block_min = (math.inf, math.inf)  # (host - device, device) of the least-late sample
        self._ref = 0.0
        self._offset: float | None = None
        self._drift = self.prior_drift
        self._held = True
        self._span = 0.0
        self._residual = 0.0
        self._last_device = -math.inf
        self._outliers = 0
        self._checking = False
        self._floor_gap = 0.0  # the line's offset above the window's lowest block minimum
        self._last_residual: float | None = None  # the previous sample's lag above the line

    @property
    def drift(self) -> float:
        """The drift of the line stamps are mapped with now (s/s): a stamp lies on
        `stamp - device_stamp = drift * device_stamp + const` until the line moves."""
        return self._drift

    @property
    def learning(self) -> bool:
        """True while the drift is held (a new or re-learned clock): stamps are less sure."""
        return self._held

    @property
    def checking(self) -> bool:
        """True while a continued line waits for the first block of new data to confirm it."""
        return self._checking

    def export(self) -> dict[str, object]:
        """What a later mapper of the same device clock needs to continue this one (JSON
        numbers only): the block minima, the drift (and whether it was held), the newest
        device time."""
        blocks = [[d, y] for d, y in self._blocks]
        return {
            "blocks": blocks,
            "drift": self._drift,
            "held": self._held,
            "last_device": self._last_device if math.isfinite(self._last_device) else None,
        }

    def reconnect(self) -> None:
        """A new connection to the same device: continue the line, to be confirmed by the
        first block of the new data (see the module's docstring)."""
        if self._offset is None:
            return
        self._block_index = None
        self._block_min = (math.inf, math.inf)
        self._outliers = 0
        if not self._checking:
            self.continued += 1
        self._checking = True

    def resume(self, saved: dict[str, object]) -> bool:
        """Continue the mapping `export` gave (a restarted adapter, the same device): the
        line goes on from those blocks, to be confirmed by the first block of new data.
        False (and nothing changed) when `saved` is not such a mapping."""
        try:
            raw = saved["blocks"]
            assert isinstance(raw, list)
            blocks = [(float(d), float(y)) for d, y in raw]
            drift = float(saved["drift"])  # type: ignore[arg-type]
            held = bool(saved["held"])
            last = saved.get("last_device")
            last_device = -math.inf if last is None else float(last)  # type: ignore[arg-type]
        except (KeyError, TypeError, ValueError, AssertionError):
            return False
        finite = all(math.isfinite(d) and math.isfinite(y) for d, y in blocks)
        ordered = all(b[0] > a[0] for a, b in itertools.pairwise(blocks))
        if not (blocks and finite and ordered and math.isfinite(drift)):
            return False
        if abs(drift) > self.max_drift:
            return False
        self._reset()
        if not held:
            self.prior_drift = drift
        self._blocks.extend(blocks)
        self._last_device = max(last_device, blocks[-1][0])
        self._fit()
        self.reconnect()
        return True

    def predict(self, device_stamp: float) -> float:
        """Host time of a device stamp under the current fit (device time itself if none)."""
        if self._offset is None:
            return device_stamp
        return device_stamp + self._offset + self._drift * (device_stamp - self._ref)

    def map(self, device_stamp: float, host_t: float) -> float:
        """Learn from one sample and return its stamp on the host clock. A sample far off the
        line (a step not yet confirmed, or one glitch) is not learned from and keeps its
        receipt time."""
        if self._is_step(device_stamp, host_t):
            self.steps += 1
            if not self._held:
                self.prior_drift = self._drift  # the same oscillator after a restart
            self._reset()
        elif self._outliers:
            return self._monotonic(host_t, on_line=False)
        self._last_device = max(self._last_device, device_stamp)
        lag = host_t - device_stamp
        index = math.floor(device_stamp / self.block_s)
        if self._block_index is None:
            self._block_index = index
        if index != self._block_index:
            if self._checking and not self._confirm(*self._block_min):
                return self.map(device_stamp, host_t)  # the line did not hold: learn anew
            self._blocks.append((self._block_min[1], self._block_min[0]))
            self._block_index = index
            self._block_min = (lag, device_stamp)
            self._fit()
        elif lag < self._block_min[0]:
            self._block_min = (lag, device_stamp)
            if not self._blocks:
                self._fit()  # the first block: the least-late sample so far gives the offset
        return self._monotonic(self.predict(device_stamp))

    def _confirm(self, lag: float, device_stamp: float) -> bool:
        """The first block of new data under a continued line: is its least lag on the
        line? If not, a step: the mapping starts anew (its drift is kept as the prior)."""
        self._checking = False
        if abs(device_stamp + lag - self.predict(device_stamp)) <= self.step_threshold_s:
            return True
        self.steps += 1
        if not self._held:
            self.prior_drift = self._drift
        self._reset()
        return False

    def _monotonic(self, t: float, on_line: bool = True) -> float:
        """Stamps never go back: while the fit learns (the first samples of a connection
        wait longest, so the offset drops as faster ones arrive) a stamp that would fall
        before the previous one is placed just after it, and counted. `on_line` says whether
        the stamp returned lies on the line (`predict`)."""
        if t <= self._last_out:
            t = self._last_out + MIN_STEP_S
            self.held_back += 1
            on_line = False
        self._last_out = t
        self.on_line = on_line
        return t

    def _is_step(self, device_stamp: float, host_t: float) -> bool:
        if self._offset is None:
            return False
        gone_back = device_stamp < self._last_device - self.step_threshold_s
        residual = host_t - self.predict(device_stamp)
        fell = self._last_residual
        self._last_residual = residual
        if self._checking:
            # a continued line is not trusted yet: far late is as suspect as far early
            early = residual < -self.step_threshold_s
            late = residual > self.step_threshold_s
        else:
            # earlier than the lowest block of the window by more than the threshold is
            # impossible without a step (latency is never negative); the line itself is a
            # median and sits above the floor while the host runs behind
            early = residual < -self._floor_gap - self.step_threshold_s
            if early and self._outliers == 0 and fell is not None:
                # a step starts where the lag falls at once; a backlog clearing falls by at
                # most one sample period per sample
                early = fell - residual > self.step_threshold_s
            late = False
        if not (gone_back or early or late):
            self._outliers = 0
            return False
        self._outliers += 1
        return self._outliers >= self.step_confirm

    def _fit(self) -> None:
        n = len(self._blocks)
        if n == 0:  # the first block: its least-late sample so far
            lag, device_stamp = self._block_min
            self._ref, self._offset = device_stamp, lag
            self._drift, self._held = self.prior_drift, True
            return
        while n > 2 and self._blocks[0][0] < self._blocks[-1][0] - self.drift_window_s:
            self._blocks.popleft()  # after a gap (a continued mapping): device seconds count
            n -= 1
        d = np.fromiter((b[0] for b in self._blocks), float, n)
        y = np.fromiter((b[1] for b in self._blocks), float, n)
        ref = float(d[-1])
        # blocks a backlog held beyond the threshold, once the lag has come back down after
        # them, say how far behind the host ran, not where the floor is: left out of the
        # line, which then neither tilts across the backlog's end nor waits for it to leave
        # the window. A rise still going on (the newest blocks) stays in: it may be the host
        # clock stepping forward, which the line follows as the window turns over.
        base = y - self._drift * (d - ref)
        low = base <= np.min(base[d >= ref - self.window_s]) + self.step_threshold_s
        kept = low | (np.arange(n) > np.flatnonzero(low)[-1])
        d, y = d[kept], y[kept]
        self._span = float(d[-1] - d[0])
        if d.size >= self.min_drift_blocks and self._span >= self.min_drift_span_s:
            slope = pairwise_median_slope(d, y, self.min_drift_span_s / 4)
            slope = min(max(slope, -self.max_drift), self.max_drift)
            self._held = False
            recent = d >= ref - self.window_s
        else:
            slope = self.prior_drift
            self._held = True
            recent = d >= ref - self.hold_s
        window = d >= ref - self.window_s
        floor = float(np.min(y[window] - slope * (d[window] - ref)))
        above = y[recent] - slope * (d[recent] - ref)
        # held: a few blocks, the first of a connection waiting longest (a backlog): low ones
        quantile = HELD_QUANTILE if self._held else self.offset_quantile
        offset = float(np.quantile(above, quantile)) if above.size else floor
        self._floor_gap = offset - floor
        self._ref, self._offset, self._drift = ref, offset, slope
        self._residual = float(np.sqrt(np.mean((above - offset) ** 2))) if above.size else 0.0

    def state(self) -> ClockState:
        return ClockState(
            offset_s=0.0 if self._offset is None else self._offset,
            drift_ppm=self._drift * 1e6,
            residual_s=self._residual,
            blocks=min(len(self._blocks), self._recent),
            steps=self.steps,
            held_back=self.held_back,
            drift_held=self._held,
            span_s=self._span,
            continued=self.continued,
        )


# A read whose gap since the previous one exceeds this many times the stream's usual time per
# frame came after a stall (of the host, the network or the sender): its frames were sent
# somewhere in that gap, and where is not known. A sender that stalled and then sends its
# missed frames back to back (each with the joints of its sending) arrives as one read that
# the even spread misplaces by tens of ms (docs/timing.md has the measured case). Jitter of a
# regular sender (MotoROS: a frame every 22-28 ms) stays well within 1.5 times.
RECEIPT_GAP_FACTOR = 1.5
# ... and only a gap beyond the usual by more than this (s) is flagged: receipt times jitter by
# about a millisecond whatever the rate (the host's wake-ups), which a 1 kHz stream's gaps
# would exceed 1.5 times without any stall
RECEIPT_GAP_MIN_S = 0.005
# the usual time per frame: the median over this many recent reads (every read counts, so a
# stream whose rate changes is learned anew), judged once this many have come
RECEIPT_USUAL_READS = 32
RECEIPT_USUAL_MIN_READS = 8


class ReceiptStamps:
    """Host stamps for a device that gives none (MotoROS leaves its time at 0): receipt time.

    Frames that reach the host in one read share a receipt time, yet were sent apart: the
    earlier ones arrived somewhere after the previous read, so they are spread evenly between
    the previous stamp and this receipt (the last frame keeps the receipt time). A stamp never
    repeats or goes back (a host clock stepped back): it is placed just after its
    predecessor, and counted. A read after a gap longer than `RECEIPT_GAP_FACTOR` times the
    usual time per frame (and `RECEIPT_GAP_MIN_S` beyond it) sets `uncertain_s` (else 0): by
    how much its stamps may be off."""

    def __init__(self) -> None:
        self._last = -math.inf
        self.held_back = 0
        self.uncertain_s = 0.0  # the last read's: its gap beyond the usual time per frame (s)
        self.usual_s = math.nan  # the usual time per frame (s), once known
        self._per_frame: collections.deque[float] = collections.deque(maxlen=RECEIPT_USUAL_READS)
        self._reconnected = False  # the next read's gap is a reconnection's, not a stall

    def restart(self) -> None:
        """A new connection: its first read is not judged (the time without a connection is
        no stall of the stream); its stamps still go on after the previous ones."""
        self._reconnected = True

    def place(self, receipt_t: float, count: int) -> list[float]:
        """Stamps for `count` frames received together at `receipt_t`, oldest first."""
        if count <= 0:
            return []
        last = self._last
        self.uncertain_s = 0.0
        if receipt_t <= last:
            self.held_back += 1
            receipt_t = last + MIN_STEP_S * count
        elif math.isfinite(last) and not self._reconnected:
            self._judge(receipt_t - last, count)
        self._reconnected = False
        start = last if math.isfinite(last) else receipt_t - MIN_STEP_S * count
        step = (receipt_t - start) / count
        stamps = [start + step * (i + 1) for i in range(count - 1)] + [receipt_t]
        self._last = receipt_t
        return stamps

    def _judge(self, gap: float, count: int) -> None:
        """The read's gap against the usual time per frame, then the usual one updated (a
        median: a few stalls do not move it)."""
        usual = self.usual_s
        # False while the usual one is not known (nan)
        if gap > RECEIPT_GAP_FACTOR * usual and gap - usual > RECEIPT_GAP_MIN_S:
            self.uncertain_s = gap - usual
        per_frame = self._per_frame
        per_frame.append(gap / count)
        if len(per_frame) >= RECEIPT_USUAL_MIN_READS:
            self.usual_s = sorted(per_frame)[len(per_frame) // 2]


# ---- clock domains: which rule turns a device stamp into a sample's `t` ------------------------
# (the stream's [robot] / [tracker] clock: `Stamper` is the one rule every adapter stamps
# through; docs/timing.md tells the user's side)

__all__ += ["DOMAINS", "DRIFT_PRIOR_MAX_AGE_S", "RESUME_MAX_AGE_S", "Stamp", "Stamper"]

DOMAINS = ("shared", "device", "receipt")
# A "shared" stamp may lead its receipt by this much before it is flagged. On one host the
# stamp is read before the message leaves and the receipt after it arrives, from the same
# clock, so it can never lead; across hosts it leads by at most their synchronisation error
# minus the transport time. PTP keeps hosts within microseconds (hardware) to ~0.1 ms
# (software), NTP/chrony on a LAN within ~0.1-1 ms: 1 ms flags only clocks that disagree by
# more than a working synchronisation allows (a stamp from another clock, a sync that broke).
SHARED_AHEAD_TOLERANCE_S = 1e-3
# What a user whose stamps are not on the cell's clock after all should do.
_NOT_SHARED = 'stamps not on the cell\'s clock: set this input\'s clock to "device" or "receipt"'
# A saved mapping (a restarted adapter's) goes on within this age: its blocks are within the
# drift window (60 s of device time), so they still count; older, a new mapping learns anew,
# from the saved drift within DRIFT_PRIOR_MAX_AGE_S (a crystal's drift moves with its
# temperature by about a ppm per kelvin: a day-old drift is a better prior than zero).
RESUME_MAX_AGE_S = 60.0
DRIFT_PRIOR_MAX_AGE_S = 86400.0
# How many messages a Stamper keeps (the counters count every case).
_KEEP_MESSAGES = 8


@dataclass(frozen=True)
class Stamp:
    stamp: float  # the sample's stream time (host clock, or the shared clock that is the host's)
    flags: tuple[str, ...] = ()
    # a mapped ("device") stamp: the drift of the line it was mapped with, so that a consumer
    # can carry it onto a later line of the same mapping (see ClockMapper.map)
    drift: float | None = None


class Stamper:
    """The one rule for turning a device's stamps into sample times, per clock domain:

    - "shared": the stamps are already on the cell's common clock (ROS time on one host,
      PTP): used as they are. A stamp ahead of its receipt by more than `ahead_tolerance_s`
      or older than `max_age_s` at receipt is counted and flagged ("stamp_ahead",
      "stamp_old"), never remapped. A stamp that goes back (a publisher restarted, a
      simulated clock reset) starts a new epoch and is flagged "stamp_back".
    - "device": the device's free-running clock, mapped onto the host's (ClockMapper). A
      clock step the mapper detects starts a new epoch; samples stamped while the mapping has
      no line yet (its first block) are flagged "clock_relearning".
    - "receipt": no device time: the receipt time (ReceiptStamps spreads frames that arrive
      in one read); the device's time, if any, stays in the sample's device_stamp.

    A sample without a device time in the "shared" or "device" domain is stamped on receipt,
    counted ("no_device_time") and flagged. `epoch` grows whenever the time base starts anew
    (`restart()` on a new connection, a step, a stamp going back); the caller starts it from
    a number of its own (e.g. the process's start time) so that a restarted process does not
    repeat one. Pure: no I/O, no clock reads.
    """

    def __init__(
        self,
        domain: str,
        max_age_s: float = 0.5,
        ahead_tolerance_s: float = SHARED_AHEAD_TOLERANCE_S,
        epoch: int = 0,
    ) -> None:
        if domain not in DOMAINS:
            raise ValueError(f"clock domain {domain!r} is not one of {', '.join(DOMAINS)}")
        self.domain = domain
        self.max_age_s = max_age_s
        self.ahead_tolerance_s = ahead_tolerance_s
        self.epoch = epoch
        self.counters: collections.Counter[str] = collections.Counter()
        self.messages: collections.deque[str] = collections.deque(maxlen=_KEEP_MESSAGES)
        self.last: dict[str, str] = {}  # the newest message per counter
        self.mapper = ClockMapper()
        self.receipt = ReceiptStamps()
        self._last_shared = -math.inf

    def restart(self, fresh: bool = False) -> None:
        """A new connection. A mapped device clock that has a line goes on on it (the same
        oscillator; its first block of new data confirms the line, else a step starts a new
        epoch) and keeps its epoch; otherwise, or when the caller knows that the device's
        time base starts anew (`fresh`: a controller that restarted), a new epoch."""
        self._last_shared = -math.inf
        self.receipt.restart()
        if self.domain == "device" and self.mapper.state().blocks > 0 and not fresh:
            self.mapper.reconnect()
            return
        self.epoch += 1
        old = self.mapper
        prior = old.prior_drift if old.learning else old.state().drift_ppm * 1e-6
        self.mapper = ClockMapper(prior_drift=prior)  # the same oscillator: its drift

    def export(self) -> dict[str, object] | None:
        """The mapping for a later adapter of the same device to continue (`resume`), with
        the epoch it runs under; None when there is nothing to continue (not a mapped clock,
        or no line yet)."""
        if self.domain != "device" or self.mapper.state().blocks == 0:
            return None
        return {"domain": self.domain, "epoch": self.epoch, "mapping": self.mapper.export()}

    def resume(self, saved: object, age_s: float) -> str:
        """Continue the mapping a previous adapter of this device saved `age_s` seconds ago
        (`export`): within `RESUME_MAX_AGE_S` the line and its epoch go on (the next
        `restart` keeps them); within `DRIFT_PRIOR_MAX_AGE_S` only its drift is the prior of
        a new mapping. What was done, in words (for the log)."""
        if self.domain != "device" or not isinstance(saved, dict):
            return "nothing to continue"
        mapping, epoch = saved.get("mapping"), saved.get("epoch")
        if saved.get("domain") != "device" or not isinstance(mapping, dict):
            return "not a device clock's mapping: ignored"
        if not (math.isfinite(age_s) and age_s >= 0.0):
            return "saved at an unknown time: ignored"
        fresh = age_s <= RESUME_MAX_AGE_S and isinstance(epoch, int)
        if fresh and isinstance(epoch, int) and self.mapper.resume(mapping):
            self.epoch = epoch
            st = self.mapper.state()
            return (
                f"the mapping saved {age_s:.1f} s ago goes on (drift {st.drift_ppm:+.2f} "
                f"ppm, epoch {epoch}), if the device's first block agrees"
            )
        drift, held = mapping.get("drift"), mapping.get("held")
        usable = isinstance(drift, float) and held is False and age_s <= DRIFT_PRIOR_MAX_AGE_S
        if usable and isinstance(drift, float) and abs(drift) <= self.mapper.max_drift:
            self.mapper.prior_drift = drift
            return f"drift {drift * 1e6:+.2f} ppm (saved {age_s:.0f} s ago) as the prior"
        return f"saved {age_s:.0f} s ago: too old, or not usable; learning anew"

    def stamp(self, device_stamp: float | None, receipt_t: float) -> Stamp:
        """The stamp of one sample the device stamped `device_stamp` (None: it gives none) and
        the host received at `receipt_t`."""
        if self.domain == "receipt":
            return self._received(receipt_t, 1)[0]
        if device_stamp is None:
            self._note(
                "no_device_time",
                f"a sample without device time in the {self.domain!r} "
                "clock domain: stamped on receipt",
            )
            return self._received(receipt_t, 1, ("no_device_time",))[0]
        if self.domain == "device":
            return self._mapped(device_stamp, receipt_t)
        return self._shared(device_stamp, receipt_t)

    def stamp_received_together(self, count: int, receipt_t: float) -> list[Stamp]:
        """Stamps for `count` samples without device time that arrived in one read (receipt
        domain only): spread between the previous stamp and this receipt."""
        return self._received(receipt_t, count)

    def _received(self, receipt_t: float, count: int, flags: tuple[str, ...] = ()) -> list[Stamp]:
        """Receipt stamps (`ReceiptStamps`) for `count` samples read together; after a stall
        each is flagged "receipt_gap" (a consumer leaves such samples out of what needs their
        exact time: the delay fits), counted, and said, naming the stall rather than the
        motion."""
        receipt = self.receipt
        stamps = receipt.place(receipt_t, count)
        if receipt.uncertain_s > 0.0:
            usual = receipt.usual_s
            self._note(
                "receipt_gap",
                f"{count} sample(s) received {(receipt.uncertain_s + usual) * 1e3:.0f} ms "
                f"after the previous read, against {usual * 1e3:.0f} ms per sample usually: "
                "the host, the network or the sender stalled, and receipt times cannot say "
                f"when they were sent: stamps uncertain by up to "
                f"{receipt.uncertain_s * 1e3:.0f} ms, flagged receipt_gap",
            )
            flags = (*flags, "receipt_gap")
        return [Stamp(t, flags) for t in stamps]

    def _mapped(self, device_stamp: float, receipt_t: float) -> Stamp:
        steps = self.mapper.steps
        t = self.mapper.map(device_stamp, receipt_t)
        flags: tuple[str, ...] = ()
        if self.mapper.steps != steps:
            self.epoch += 1
            self._note(
                "clock_step",
                f"the device clock stepped at device time {device_stamp:.6f}: "
                "the mapping starts anew",
            )
            flags = ("clock_step",)
        # no line yet (an offset from one block), or a continued line not yet confirmed
        if self.mapper.state().blocks < 2 or self.mapper.checking:
            flags = (*flags, "clock_relearning")
        # the line's drift, for a consumer to carry the stamp onto a later line; none for a
        # stamp off the line (held back, or a receipt time kept while a step is confirmed)
        return Stamp(t, flags, self.mapper.drift if self.mapper.on_line else None)

    def _shared(self, device_stamp: float, receipt_t: float) -> Stamp:
        flags: list[str] = []
        tol = self.ahead_tolerance_s
        if device_stamp < self._last_shared - tol:
            self.epoch += 1
            back = self._last_shared - device_stamp
            self._note(
                "stamp_back",
                f"a shared-clock stamp went back by {back:.6f} s (a "
                "publisher restarted or its clock was reset): a new epoch",
            )
            flags.append("stamp_back")
        self._last_shared = device_stamp
        age = receipt_t - device_stamp
        if age < -tol:
            self._note(
                "stamp_ahead",
                f"a shared-clock stamp {-age * 1e3:.3f} ms ahead of its receipt (more than "
                f"{tol * 1e3:g} ms): are the clocks synchronised? ({_NOT_SHARED})",
            )
            flags.append("stamp_ahead")
        elif age > self.max_age_s:
            self._note(
                "stamp_old",
                f"a shared-clock stamp {age:.3f} s old at receipt (more "
                f"than timing.max_stamp_age_s = {self.max_age_s:g} s; {_NOT_SHARED})",
            )
            flags.append("stamp_old")
        return Stamp(device_stamp, tuple(flags))

    def _note(self, counter: str, message: str) -> None:
        self.counters[counter] += 1
        self.messages.append(message)
        self.last[counter] = message

    def state(self) -> dict[str, object]:
        """For an adapter's status: the domain, the epoch, what was counted and, for a
        mapped clock, the mapping (offset, drift, residual...)."""
        out: dict[str, object] = {"domain": self.domain, "epoch": self.epoch}
        if self.domain == "device":
            st = self.mapper.state()
            out.update(
                offset_s=st.offset_s,
                drift_ppm=st.drift_ppm,
                residual_s=st.residual_s,
                blocks=st.blocks,
                steps=st.steps,
                held_back=st.held_back,
                drift_held=st.drift_held,
                continued=st.continued,
            )
        else:
            out["held_back"] = self.receipt.held_back
        out["counters"] = dict(self.counters)
        out["messages"] = list(self.messages)
        return out
