"""The delay followed online, a stretch of samples at a time: which fits are trusted and when
the delay in use may change. The offline fit itself is fit/delay.py."""

from __future__ import annotations

import collections
import dataclasses
import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple, TypeVar

import numpy as np

from keo_service.core.kinematics import Cell
from keo_service.fit.delay import (
    LEVER_M,
    MIN_SPEED,
    DelayFit,
    DelayNotIdentifiableError,
    _mad_sigma,
    fit_delay,
)
from keo_service.fit.delay_trend import LevelAndRate, SteadyOrMoving
from keo_service.fit.stamp_lines import Anchor, moved

_T = TypeVar("_T")


@dataclass(frozen=True)
class DelayMeasurement:
    """One stretch's fitted delay, its standard error, the tool's RMS speed over it and the
    stream time it ends at."""

    delay_s: float
    se_s: float
    speed_rms: float
    t: float
    current_s: float = math.nan  # the delay in use when the stretch was fitted
    t_mid: float = math.nan  # the stream time the fit describes (its stretch's middle; nan: t)
    rms_m: float = 0.0  # the residual scatter at the fitted delay (m, moving samples)
    # how well the stretch's motion alone separates a delay from a constant error in the
    # tool frame and a slow drift (`separable_se`); nan: not measured (no orientation)
    sep_se_s: float = math.nan
    # the fit's own (clustered) standard error, before the error model's share is added to
    # `se_s`; nan: the same as se_s
    own_se_s: float = math.nan
    # how far the tool-frame and base-frame error models' fits of the stretch disagree (s;
    # nan: only one of them gave a fit)
    model_s: float = math.nan
    # the pooled fit: all the samples since the delay was last unknown (the motion's
    # start, up to `pool_s`) in one fit, and its standard error (nan: none, see `_pooled`)
    pooled_s: float = math.nan
    pooled_se_s: float = math.nan
    # the pool came but the fit could not use it (counted by `combine`: `pools_unusable`)
    pool_unusable: bool = False
    # the tool's RMS angular speed over the stretch (rad/s; nan: no orientation measured)
    turn_rms: float = math.nan

    @property
    def described_t(self) -> float:
        return self.t if math.isnan(self.t_mid) else self.t_mid


@dataclass(frozen=True)
class DelayRefused:
    """A stretch without a delay: the counter it counts under and why, in words."""

    counter: str
    reason: str
    t: float = math.nan  # the stream time the stretch ends at (nan: not known)
    # `separable_se` of the stretch when its motion was measured and found unable to
    # separate a delay (nan: refused for another reason)
    sep_se_s: float = math.nan
    pooled_s: float = math.nan  # the pooled fit, as in `DelayMeasurement`
    pooled_se_s: float = math.nan
    pool_unusable: bool = False


@dataclass(frozen=True)
class DelayDecision:
    """What the tracker last decided about the delay in use, its words and its numbers apart:
    the status line, the estimate message and the Rerun view show the words
    (`keo_service.live.status_view.delay_tracking_text`: one delay, the one in use), the log
    line (`OnlineDelayTracker.last_result`) the numbers too.

    Attributes:
        verdict: the kind of decision, one word: waiting, kept, unsettled, settled, changed,
            refined, restarted.
        reason: why, in words, without the delays the fits gave (a count of fits, sigmas,
            the residual scatter in um may be there: they are no second delay).
        fit_s: the newest fit the decision was about, s (nan: none).
        fit_se_s: its standard error with the fits' scatter beyond their own, s.
        speed_m_s: the tool's RMS speed over its stretch, m/s.
        consensus_s: the recent fits' consensus it weighed, s (nan: none).
        consensus_se_s: its standard error, s.
        t: the stream time of the stretch's end, s (nan: no stretch)."""

    verdict: str
    reason: str
    fit_s: float = math.nan
    fit_se_s: float = math.nan
    speed_m_s: float = math.nan
    consensus_s: float = math.nan
    consensus_se_s: float = math.nan
    t: float = math.nan

    def log_text(self) -> str:
        """The log's line: the words with the fit's and the consensus's values."""
        words = f"{self.verdict}: {self.reason}"
        if math.isfinite(self.consensus_s):
            words += (
                f" (consensus {self.consensus_s * 1e6:.1f} +/- {self.consensus_se_s * 1e6:.1f} us)"
            )
        if not math.isfinite(self.fit_s):
            return words
        return (
            f"fit {self.fit_s * 1e6:.1f} +/- {self.fit_se_s * 1e6:.1f} us "
            f"at {self.speed_m_s * 1e3:.0f} mm/s; {words}"
        )


@dataclass(frozen=True)
class DelayTrackerSettings:
    """The online tracker's settings (plain data; the defaults are what the scenario matrix
    of docs/timing-delay.md was run with)."""

    span_s: float = 2.5  # a settled stretch, lengthened up to max_span_s while fits are rough
    max_span_s: float = 10.0
    young_span_s: float = 2.0  # stretches while the clock mappings are young (young_s)
    young_s: float = 10.0
    max_samples: int = 40_000  # bounded buffers, per stream
    max_gap_s: float = 0.05  # no joints interpolated across a wider encoder gap
    max_position_se_m: float = 2.5e-6  # stretches lengthen until fits are known to this at speed
    max_se_s: float = 2e-3  # a fit rougher than this is refused
    outlier_sigmas: float = 4.0  # the running estimate's outlier gate (refinements only)
    settle_s: float = 4.0  # samples left out after a time base starts anew
    min_wander_s: float = 2e-6  # the least scatter of fits beyond their standard errors
    restart_sigma_s: float = 50e-6  # the delay in use's se grows by this at a restart
    max_apply_m: float = 10e-6  # a refinement needs the estimate known to this at speed
    steady_walk: float = 25e-12
    level_walk: float = 4e-12
    rate_walk: float = 1e-12
    rate_relax_s: float = 30.0
    rate_prior: float = 2e-6
    # the gate for a change of the delay in use (issue 45)
    consensus_fits: int = 5  # the consensus is over this many recent fits
    change_sigmas: float = 4.0  # consensus vs delay in use: incompatible at this many sigma
    confirm_sigmas: float = 2.5  # each confirming fit off the delay in use by this many
    first_tau_s: float = 300e-6  # a fit's scatter beyond its se, until 3 fits measure it
    # settled when the consensus is known to this at the tool's speed (or in urad at its
    # turning speed, where that is faster)
    settle_m: float = 20e-6
    # while the delay is not settled, all samples since it was last unknown are fitted at
    # once too (the pooled fit), over at most this long, the tracker's samples thinned to at
    # most pool_rows (its cost bounded: the encoder's are all kept for the interpolation)
    pool_s: float = 30.0
    pool_rows: int = 3000


class _Pose(NamedTuple):
    """One pose as `add_samples` reads a tracker sample (`add_tracker`)."""

    stamp: float
    position: Sequence[float]
    quaternion: Sequence[float] | None
    clock_epoch: int
    seq: int
    flags: bool
    device_stamp: float | None
    clock_drift: float | None


class _Joints(NamedTuple):
    """One joint sample as `add_samples` reads it (`add_encoder`)."""

    stamp: float
    joints: Sequence[float]
    clock_epoch: int
    seq: int
    flags: bool
    device_stamp: float | None
    clock_drift: float | None


@dataclass(frozen=True)
class _Fit:
    value: float
    se: float  # the fit's own standard error
    t: float  # the stream time it describes
    speed: float  # the tool's RMS speed over it (m/s)
    rms: float  # the residual scatter at the fitted delay (m, moving samples)
    young: bool = False  # of a young clock mapping's stamps, which still move
    sep_se: float = math.nan  # `separable_se` of its stretch (nan: not measured)
    own_se: float = math.nan  # its own (clustered) standard error (nan: `se`)
    model: float = math.nan  # its two error models' disagreement (nan: not measured)
    turn: float = math.nan  # the tool's RMS angular speed over it (rad/s; nan: not measured)

    @property
    def weigh(self) -> float:
        """The speed a delay error of this stretch is weighed at: the tool point's, or the
        turn's at `LEVER_M` when that is faster (a micrometre and a microradian alike, as the
        targets weigh them: a wrist turning fast about a slow tool point)."""
        return self.speed if not self.turn * LEVER_M > self.speed else self.turn * LEVER_M


@dataclass(frozen=True)
class _ModelFit:
    """A stretch's (or the pool's) fit of the error model that left less residual, with
    what its se is made of: the two models' disagreement (s; nan: one model only) and the
    motion's separability (`separable_se`), and the tracker stamps it spans."""

    fit: DelayFit
    model_s: float
    sep_se_s: float
    t_first: float
    t_last: float


class OnlineDelayTracker:
    """The delay found online from the motion, trusted only as far as it is known.

    Samples go into bounded buffers (on the event loop); when a stretch of clean data has
    gathered since the last fit (`span_s`, up to `max_span_s` while its fits are rough),
    the service takes that stretch (`snapshot`) and fits it off the loop (`measure`:
    `fit_delay` over that stretch only, so successive fits see disjoint data), then folds
    the result in on the loop (`combine`). A stretch gives no fit when the tool hardly moved
    or its motion cannot separate a delay (`separable_se`), and a fit is usable only with
    `se <= max_se_s`. Usable fits join the recent fits; the delay in use changes only
    through their robust consensus, under the gate of `_decide` (a configured delay is a
    prior: the consensus must be incompatible with it, confirmed by a later stretch, lower
    the residual scatter, be separable by the motion and be known better than the delay in
    use). Once settled, the running estimate below may refine the delay in use by steps
    too small to matter at the tool's speed.

    The running estimate is a Kalman filter over the delay's level in two views
    (`SteadyOrMoving`): "steady", whose level walks (`steady_walk`), and "moving", whose
    level walks (`level_walk`) with a rate that walks too (`rate_walk`, relaxing to zero over
    `rate_relax_s`); the one that has been predicting the fits better gives the estimate.
    Each accepted fit says the delay at its stretch's middle, with the variance se^2 +
    tau^2, where tau^2 is the scatter of fits beyond their own standard errors (a fit's
    standard error cannot know how its stretch's error model fits the robot), from how far
    each fit lies off the line through its neighbours, at least `min_wander_s`^2. The delay
    the stamps need moves as the mapped clocks' floors move with the load and their drifts
    converge, often steadily for tens of seconds, so an older fit says less about it now,
    and a steady walk is followed, not lagged (a mean of recent fits, however weighted, lags
    it). The estimate is the level at the newest stretch's end, its standard error the
    filter's. It refines the delay in use (slewed, never a jump) only when known to
    `max_apply_m` at the tool's speed; otherwise (fits scattering widely, as when the
    robot's geometry makes an error the stretches' model does not hold) it is not applied.

    Fits of stretches that end within `young_s` of the first samples or of a restart are
    provisional: a young clock mapping's stamps move while its drift converges. So while
    young the stretches are shorter (`young_span_s`) and the newest fit alone is the delay,
    each replacing the one before (its stamps are the most settled), applied only when known
    to `max_apply_m` at the tool's speed; the first fit of a later stretch replaces them too
    (averaged instead, they left the delay short of what the settled stamps needed).

    Mapped samples ("device" clocks) come with their line's drift: each stretch is fitted
    under each stream's newest line, and the delay applied is carried along as the lines
    move (`delay_now`), the running estimate with it (see fit/stamp_lines.py): a line's move
    needs no fit to be followed.

    Samples a source flagged (its clock re-learning, a stamp ahead of its receipt or too
    old) are left out. When either stream's time base starts anew (its `clock_epoch`
    changes, or its `seq` goes back while it gives no epoch: an adapter restarted; one that
    went on on its saved clock mapping keeps its epoch), the data before it is dropped,
    the first `settle_s` seconds after it too (the new mapping learns its drift), and so are
    the fits before it (a new mapping carries a new transport floor): the next accepted fit
    decides the delay; until then the delay in use stays as it was, its standard error grown
    by `restart_sigma_s`.
    """

    def __init__(
        self,
        cell: Cell,
        settings: DelayTrackerSettings | None = None,
        prior_s: float = 0.0,
        prior_se_s: float | None = None,
        **changes: Any,
    ) -> None:
        """`prior_s` and `prior_se_s`: the configured delay and its standard uncertainty
        (None: nothing is known, the delay is found from the motion and estimates are flagged
        until it settles); `changes`: settings by name, over `settings`."""
        st = dataclasses.replace(settings or DelayTrackerSettings(), **changes)
        self.settings = st
        # fits run off the event loop: give them their own scratch data for gravity torques
        self.cell = (
            cell
            if cell.nominal_model is None
            else dataclasses.replace(cell, gravity_data=cell.nominal_model.createData())
        )
        self.span_s = st.span_s
        self.max_span_s = max(st.max_span_s, st.span_s)
        self._stretch_s = st.span_s  # the settled stretch now: lengthened while fits are rough
        self.young_span_s = st.young_span_s
        self.max_gap_s = st.max_gap_s
        self.max_position_se_m = st.max_position_se_m
        self.max_se_s = st.max_se_s
        self.outlier_sigmas = st.outlier_sigmas
        self.settle_s = st.settle_s
        self.min_wander_s = st.min_wander_s
        self.restart_sigma_s = st.restart_sigma_s
        self.max_apply_m = st.max_apply_m
        # each stream's samples as rows of floats (`_Rows`): (stamp, joints..., device stamp)
        # and (stamp, x, y, z, qw, qx, qy, qz, device stamp), nan for what a sample lacks
        self._enc = _Rows(st.max_samples)
        self._trk = _Rows(st.max_samples)
        # each mapped stream's newest sample on its clock mapping's line, as (stamp, device
        # stamp, drift): kept per sample, made an `Anchor` only when one is asked for
        # (`_newest`); the lines the running estimate is expressed under; those of the stretch
        # being fitted
        self._newest_rows: dict[str, tuple[float, float, float]] = {}
        self._newest_made: dict[str, Anchor] | None = None
        self._frame: dict[str, Anchor] = {}
        self._fitting_frame: dict[str, Anchor] | None = None
        self._start = -math.inf  # stream time from which samples count
        self.young_s = st.young_s
        self._young_until = math.nan  # fits of stretches ending before this are provisional
        self._provisional = 0  # how many of the fits kept are provisional
        self._sources: dict[str, tuple[int, int]] = {}  # stream -> (epoch, last seq)
        self._trend = SteadyOrMoving(
            LevelAndRate(st.steady_walk, 0.0, st.rate_relax_s, 0.0),
            LevelAndRate(st.level_walk, st.rate_walk, st.rate_relax_s, st.rate_prior),
        )
        # accepted settled fits (value, se, segment, stream time described): a segment ends
        # when a time base starts anew
        self._history: collections.deque[tuple[float, float, int, float]] = collections.deque(
            maxlen=32
        )
        # every fit of the current segment, whatever became of it: the consensus is theirs
        self._recent: collections.deque[_Fit] = collections.deque(maxlen=16)
        # tau^2 of the recent fits, keyed by their count and the newest (`_tau2`)
        self._tau2_cache: tuple[tuple[int, _Fit | None], float] = ((-1, None), math.nan)
        self._segment = 0
        self._suspect: tuple[float, float, float] | None = None  # an outlier fit, to compare
        self._trend_fits = 0  # fits the running estimate has taken since it started
        self.estimate: float | None = None  # the running estimate of the delay (s)
        self.se: float | None = None  # its standard error (s)
        known = prior_se_s is not None and math.isfinite(prior_se_s) and prior_se_s > 0
        # the delay in use, under `_frame` (s), and its standard error: the configured one
        # is a prior (the user's calibration), not a starting guess
        self.applied: float | None = prior_s if known else None
        self.applied_se: float | None = prior_se_s if known else None
        self.settled = known  # False: every estimate is flagged until the fits agree
        # the delay in use descends from a configured prior (refined or changed since only
        # through the gate): a restart leaves it settled (`restart`)
        self._from_prior = known
        # where the delay in use comes from: configured, confirmed (configured, a precise fit
        # agreed), fit or unknown; and the stream time of the fit behind it (nan: none)
        self.source_kind = "configured" if known else "unknown"
        self.source_t = math.nan
        self.step = False  # the last change is a step (confirmed), not a refinement to slew to
        self._applied_t = math.nan  # the stream time it describes
        self._estimate_t = math.nan  # the stream time `estimate` describes
        self.counters: collections.Counter[str] = collections.Counter()
        self.decision = DelayDecision("waiting", "no stretch fitted yet")
        # the kind of the last decision (its verdict, or the counter of a stretch that gave no
        # fit): the service says a decision when its kind changes
        self.state = "waiting"
        self._start_anew()

    def _start_anew(self) -> None:
        """What a new time base or a delay set by hand makes unknown again."""
        # does the newest stretch's motion separate a delay from a tool error and its slow
        # drift to `settle_m` at its speed (`separable_se`)? None: no stretch measured yet
        self.separable: bool | None = None
        # while not settled: the stretches' rows since the delay was last unknown, encoder and
        # tracker (`take`), for the pooled fit; and the newest pooled fit (value, se)
        self._pool: tuple[list[np.ndarray], list[np.ndarray]] = ([], [])
        self._pool_stretches = 0  # how many stretches the newest pool taken holds
        self.pooled: tuple[float, float] | None = None

    # ---- samples (on the event loop: cheap) ---------------------------------------------

    def add_encoder(
        self,
        t: float,
        q: Sequence[float],
        epoch: int = 0,
        seq: int = 0,
        flagged: bool = False,
        device_stamp: float | None = None,
        clock_drift: float | None = None,
    ) -> None:
        """One joint sample; a mapped one ("device" clock) with its device stamp and its
        line's drift (`JointSample.clock_drift`): `add_samples` of this one sample."""
        self.add_samples((_Joints(t, q, epoch, seq, flagged, device_stamp, clock_drift),), _Pose)

    def add_tracker(
        self,
        t: float,
        p: Sequence[float],
        quat: Sequence[float] | None,
        epoch: int = 0,
        seq: int = 0,
        flagged: bool = False,
        device_stamp: float | None = None,
        clock_drift: float | None = None,
    ) -> None:
        """One pose; a mapped one as in `add_encoder`: `add_samples` of this one sample."""
        pose = _Pose(t, p, quat, epoch, seq, flagged, device_stamp, clock_drift)
        self.add_samples((pose,), _Pose)

    # complexity (C901, PLR0912, PLR0915): one loop over the block with both streams' checks,
    # the restarts and the clock lines inline (a Python call per sample is what it saves)
    def add_samples(  # noqa: C901, PLR0912, PLR0915
        self, samples: Sequence[Any], tracker_type: type
    ) -> None:
        """The tracker's intake: samples in arrival order, poses (those of `tracker_type`; a
        gap, with no position, is skipped) and joint samples (the others), each checked
        (flagged, non-finite, a wrong length, a stamp not after the stream's newest: left
        out, counted where it is wrong), a stream's time base starting anew (`restart`) and
        its clock line (a mapped sample's device stamp and drift) followed as it comes. The
        samples are the wire's messages as decoded (their fields by name: stamp, position,
        quaternion or joints, clock_epoch, seq, flags, device_stamp, clock_drift);
        `add_tracker` and `add_encoder` are this for one sample. Why a block: the service
        hands its samples over a block at a time, so that no Python call per sample is left
        on the data path for this (docs/performance.md)."""
        isfinite, nan = math.isfinite, math.nan
        sources, newest, counters = self._sources, self._newest_rows, self.counters
        enc_rows: list[tuple[float, ...]] = []
        trk_rows: list[tuple[float, ...]] = []
        enc_last, trk_last = self._enc.last, self._trk.last
        enc_width = self._enc.width
        start = self._start
        for m in samples:
            is_trk = type(m) is tracker_type
            if is_trk:
                p = m.position
                if p is None:
                    continue
                stream = "tracker"
            else:
                stream = "encoder"
            t, epoch, seq = m.stamp, m.clock_epoch, m.seq
            # the first samples start the young clock mappings (`young_s`)
            known = sources.get(stream)
            if isfinite(t) and math.isnan(self._young_until):
                self._young_until = t + self.young_s
            sources[stream] = (epoch, seq)
            # a seq going back is a restarted publisher: a new time base unless the publisher
            # says otherwise by its epoch (an adapter that went on on its saved clock mapping
            # keeps it); one that gives no epoch (0) says nothing
            if known is not None and (epoch != known[0] or (seq < known[1] and epoch == 0)):
                self.restart(t, f"the {stream} time base started anew")  # clears the buffers
                enc_rows.clear()
                trk_rows.clear()
                enc_last = trk_last = -math.inf
                start = self._start
            # a mapped stream's newest sample on its line (a stamp off the line comes without a
            # drift); the device stamp kept with the sample only while the stream is mapped
            # by a line (not for a shared clock or receipt times)
            dev = m.device_stamp
            device = nan
            if dev is not None and isfinite(dev):
                drift = m.clock_drift
                if drift is not None and isfinite(drift) and isfinite(t):
                    newest[stream] = (t, dev, drift)
                    self._newest_made = None
                if stream in newest:
                    device = dev
            if m.flags or t < start:
                counters[f"{stream}_left_out"] += 1
                continue
            # finite checks on the floats as they came: numpy's isfinite().all() per row cost
            # several times the rest of a sample's intake (docs/performance.md)
            if is_trk:
                quat = m.quaternion
                finite = all(map(isfinite, p)) and (quat is None or all(map(isfinite, quat)))
                if isfinite(t) and finite and t > trk_last:
                    if len(p) != 3 or (quat is not None and len(quat) != 4):
                        counters["tracker_wrong_length"] += 1
                        continue
                    trk_rows.append((t, *p, *(_NO_QUAT if quat is None else quat), device))
                    trk_last = t
            else:
                q = m.joints
                if isfinite(t) and all(map(isfinite, q)) and t > enc_last:
                    if enc_width and len(q) + 2 != enc_width:
                        counters["encoder_wrong_length"] += 1
                        continue
                    enc_rows.append((t, *q, device))
                    enc_width = enc_width or len(q) + 2
                    enc_last = t
        if enc_rows:
            self._enc.extend(enc_rows)
        if trk_rows:
            self._trk.extend(trk_rows)

    @property
    def _newest(self) -> dict[str, Anchor]:
        """Each mapped stream's newest sample on its line, as anchors (made once per change)."""
        if self._newest_made is None:
            self._newest_made = {k: Anchor(*v) for k, v in self._newest_rows.items()}
        return self._newest_made

    @property
    def last_result(self) -> str:
        """The last decision as the log says it: with the fit's and the consensus's values."""
        return self.decision.log_text()

    @property
    def source(self) -> str:
        """Where the delay in use comes from, in words (stream times as they are)."""
        if self.source_kind == "confirmed":
            return f"configured, confirmed by the fit at {self.source_t:.1f} s"
        if self.source_kind == "fit":
            return f"fit at {self.source_t:.1f} s"
        return self.source_kind

    def _set_source(self, kind: str, t: float = math.nan) -> None:
        self.source_kind, self.source_t = kind, t

    @property
    def _carried(self) -> bool:
        """Whether the delay in use follows the lines' moves. A fitted value describes the
        stamps under its fit's lines; the user's calibration was made under no line keo saw,
        and a young mapping's line moves while its stamps stay right (a held drift), so a
        configured delay moves with them only once a fit precise enough to matter agreed
        with it (`source` then says so). One fact, read off `source`."""
        return self.source_kind != "configured"

    def delay_now(self) -> float | None:
        """The delay to use now: the estimate last applied, carried along as the mapped
        streams' lines moved since the stretch it was fitted under (a tracker stamp that moved
        later needs a longer delay, an encoder stamp a shorter one; the move where the
        estimate describes). A configured delay is carried only once a precise fit agreed with
        it (`_carried`). None before one was applied."""
        if self.applied is None:
            return None
        if not self._carried:
            return self.applied
        # `_moved(self._newest, ...)` on the lines' plain floats: this runs per sample
        at = self._applied_t
        where = None if math.isnan(at) else at
        rows, frame = self._newest_rows, self._frame
        return self.applied + (
            _moved_row(rows.get("tracker"), frame.get("tracker"), where)
            - _moved_row(rows.get("encoder"), frame.get("encoder"), where)
        )

    def _moved(self, lines: dict[str, Anchor], at: float) -> float:
        """How far the delay the stamps need at stream time `at` moved from the running
        estimate's lines to these (0 for a stream not mapped by a line)."""
        frame = self._frame
        where = None if math.isnan(at) else at  # a configured delay describes no instant
        return moved(lines.get("tracker"), frame.get("tracker"), where) - moved(
            lines.get("encoder"), frame.get("encoder"), where
        )

    def _move_to(self, lines: dict[str, Anchor] | None) -> None:
        """Express the running estimate under these lines (None: a measurement that came
        without its snapshot's lines): each value (the filter's level and rate, the fits
        kept, the estimate applied) moved as the lines differ where it describes. By
        construction, no fit is needed to follow a line's move."""
        if lines is None:
            return
        if not self._frame or not self._trend.started:
            self._frame = dict(lines)
            return
        at = self._trend.t
        level = self._moved(lines, at)
        rate = self._moved(lines, at + 1.0) - level  # the lines' drifts differ
        self._trend.shift(level, rate)
        self._history = collections.deque(
            (
                (v + self._moved(lines, t) if seg == self._segment else v, se, seg, t)
                for v, se, seg, t in self._history
            ),
            maxlen=self._history.maxlen,
        )
        self._recent = collections.deque(
            (dataclasses.replace(f, value=f.value + self._moved(lines, f.t)) for f in self._recent),
            maxlen=self._recent.maxlen,
        )
        if self._suspect is not None:
            value, se, t = self._suspect
            self._suspect = (value + self._moved(lines, t), se, t)
        if self.estimate is not None:
            self.estimate += self._moved(lines, self._estimate_t)
        if self.applied is not None and self._carried:
            self.applied += self._moved(lines, self._applied_t)
        self._frame = dict(lines)

    def restart(self, t: float, why: str) -> None:
        """A stream's time base started anew at stream time t: drop what came before."""
        self.applied = self.delay_now()  # as in use now; the new mapping's lines are new
        self._newest_rows.clear()
        self._newest_made = None
        self._frame = {}
        self._fitting_frame = None
        self._enc.clear()
        self._trk.clear()
        self._trend.reset()
        self._provisional = 0
        self._suspect = None
        self._segment += 1
        self._recent.clear()
        # a delay found from nothing is found again under the new mapping (flagged until
        # then); one that descends from the user's calibration stays a prior, changed only
        # through the gate (refined or changed by fits, it is still no fit of nothing)
        if not self._from_prior:
            self.settled = False
        if self.se is not None:  # the delay in use is less sure under the new mapping
            self.se = math.hypot(self.se, self.restart_sigma_s)
        if self.applied_se is not None:
            self.applied_se = math.hypot(self.applied_se, self.restart_sigma_s)
        if math.isfinite(t):
            self._start = t + self.settle_s
            self._young_until = t + self.young_s
        self.counters["restarts"] += 1
        self.decision = DelayDecision(
            "restarted", f"{why}; fitting again after {self.settle_s:g} s", t=t
        )
        self.state = "restarted"
        self._start_anew()

    # ---- fits ---------------------------------------------------------------------------

    def due(self) -> bool:
        trk = self._trk
        return len(trk) > 0 and trk.last - trk.first() >= self._span()

    def _span(self) -> float:
        """The stretch to fit next: shorter while the clock mappings are young."""
        young = (
            bool(self._newest_rows)  # only mapped stamps are young (not receipt or shared ones)
            and len(self._trk) > 0
            and self._trk.first() + self.young_span_s <= self._young_until
        )
        return self.young_span_s if young else self._stretch_s

    def snapshot(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
        """The stretch to fit as arrays (`take`, then `stretch_arrays`, in one call), without
        its pool (the pooled fit: `take` and `pool_arrays`)."""
        return stretch_arrays(self.take(with_pool=False))

    def take(self, with_pool: bool = True) -> Stretch:
        """The stretch to fit, consumed from the buffers (on the loop: slices of their arrays;
        the stamps are mapped by `stretch_arrays`), with each stream's newest line, which the
        next `combine` takes the fit to be under: the next fit sees only newer samples. The
        tracker's samples from the first to `_span()` after it; the encoder's from 1 s before
        the first to 1 s after the last of those; the encoder's kept from 1 s before the last
        on, for the next stretch. `with_pool`: the pool's rows made too (while the delay is
        not settled; the stretch joins the pool either way)."""
        first = self._trk.first()
        trk = self._trk.take_through(first + self._span())
        end = float(trk[-1, 0])
        enc = self._enc.between(first - 1.0, end + 1.0)
        self._enc.drop_before(end - 1.0)
        # the whole stretch under each stream's newest line (see fit/stamp_lines.py)
        self._fitting_frame = dict(self._newest)
        enc_line, trk_line = self._newest.get("encoder"), self._newest.get("tracker")
        pool = self._pooled_rows(enc, trk, with_pool)
        return Stretch(
            enc,
            trk,
            enc_line,
            trk_line,
            None if pool is None else Stretch(pool[0], pool[1], enc_line, trk_line),
        )

    def _pooled_rows(
        self, enc: np.ndarray, trk: np.ndarray, made: bool = True
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """While the delay is not settled: this stretch's rows added to the pool (the
        encoder's without the rows the pool has already, stretches overlap there by 1 s),
        the pool's older stretches dropped once the next one starts more than `pool_s`
        before its newest row (so it spans `pool_s` and one stretch), and the pool's rows (encoder,
        tracker, the tracker's thinned to `pool_rows`) when it holds more than this
        stretch and rows of both streams (an encoder silent while the tracker goes on
        leaves no pool: nothing to join). None once settled (the pool is emptied), or when
        not `made` (its rows not joined: the concatenation is the cost)."""
        enc_pool, trk_pool = self._pool
        if self.settled:
            enc_pool.clear()
            trk_pool.clear()
            return None
        if enc_pool and enc.shape[0]:
            enc = enc[enc[:, 0] > enc_pool[-1][-1, 0]]
        if enc.shape[0]:
            enc_pool.append(enc)
        if trk.shape[0]:
            trk_pool.append(trk)
        if len(trk_pool) < 2 or sum(c.shape[0] for c in enc_pool) < 2:
            return None
        newest = float(trk_pool[-1][-1, 0])
        while len(trk_pool) > 2 and float(trk_pool[1][0, 0]) < newest - self.settings.pool_s:
            trk_pool.pop(0)
        oldest = float(trk_pool[0][0, 0]) - 1.0
        while len(enc_pool) > 1 and float(enc_pool[1][0, 0]) < oldest:
            enc_pool.pop(0)
        self._pool_stretches = len(trk_pool)
        if not made:
            return None
        return np.concatenate(enc_pool), thinned(trk_pool, self.settings.pool_rows)

    def fit(
        self,
        window: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None],
        current: float,
    ) -> float | None:
        """Fit one stretch and fold it in: the running estimate if this fit moved it."""
        return self.combine(self.measure(window, current))

    def guess(self, current: float) -> float:
        """Where a fit starts: the delay in use once settled, else the recent fits' (a
        Gauss-Newton fit from far off, e.g. 0 where tens of milliseconds are right, can stop
        in a wrong minimum)."""
        if not self.settled and self._recent:
            cons = self.consensus()
            return cons[0] if cons is not None else self._recent[-1].value
        return current

    def measure(
        self,
        window: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None],
        current: float,
        guess: float | None = None,
        pool: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]
        | None = None,
    ) -> DelayMeasurement | DelayRefused:
        """The delay over one stretch, or why there is none, and with `pool` (the arrays of
        `Stretch.pool`, while the delay is not settled) the pooled fit too. Runs anywhere (a
        worker thread, or a process given the `guess` its tracker made): with `guess` it
        reads the tracker's settings only and changes nothing."""
        if guess is None:
            guess = self.guess(current)
        found = self._measure_stretch(window, current, guess)
        if pool is None:
            return found
        try:
            pooled = self._pooled(pool, guess)
        except (ValueError, FloatingPointError, np.linalg.LinAlgError):
            # a pool the fit cannot use is no pooled fit: the stretch's result stands, and
            # `combine` counts it (`pools_unusable`: this runs in the worker)
            return dataclasses.replace(found, pool_unusable=True)
        if pooled is None:
            return found
        return dataclasses.replace(found, pooled_s=pooled[0], pooled_se_s=pooled[1])

    def _pooled(
        self,
        pool: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None],
        guess: float,
    ) -> tuple[float, float] | None:
        """The pooled fit: every sample since the delay was last unknown in one fit (the
        same checks and two error models as a stretch, `_fit_models`; refused too when its
        motion is not measured to separate a delay). Short stretches' models, linear in the
        tool position over 2.5-10 s, take up most of a slow motion's delay signature (over a
        short stretch the velocity is nearly a line in time too) and with geometric errors
        are biased alike; over tens of seconds the velocity turns and the same model leaves
        the signature standing (the scenario matrix's figures: docs/timing-delay.md). None:
        no usable pooled fit."""
        fitted = self._fit_models(pool, guess, pooled=True)
        if isinstance(fitted, DelayRefused):
            return None
        se = _reported_se(fitted.fit.delay_se_s, fitted.model_s, fitted.sep_se_s)
        if not (math.isfinite(fitted.fit.delay_s) and math.isfinite(se)) or se > self.max_se_s:
            return None
        return fitted.fit.delay_s, se

    def _fit_models(
        self,
        window: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None],
        guess: float,
        pooled: bool = False,
    ) -> _ModelFit | DelayRefused:
        """What a stretch and the pool share: the rows the encoder covers (`_covered`),
        enough of them, a motion that separates a delay from a tool error and its slow drift
        (`separable_se`; a tool at rest goes on, its fit says so), and the fit of the error
        model of the two that leaves less residual (`_two_models`); or why there is none.
        `pooled`: a motion whose separation is not measured (no orientation) does not
        separate either (a pool is used only when shown better than the stretches)."""
        enc_t, enc_q, trk_t, trk_p, trk_q = _covered(window, guess, self.max_gap_s)
        if enc_t.size < 20 or trk_t.size < 50:
            end = float(window[2][-1]) if window[2].size else math.nan
            return DelayRefused("fits_without_data", "not enough data in the stretch", end)
        sep = separable_se(trk_t, trk_p, trk_q)
        if (sep > self.max_se_s and _point_moves(trk_t, trk_p)) or (
            pooled and not sep <= self.max_se_s
        ):
            # the motion alone cannot tell a delay from a constant tool error and a slow
            # drift of it: whatever the fit says it knows comes from the error model alone
            return DelayRefused(
                "fits_not_identifiable",
                f"the motion cannot separate a delay from a tool error and its slow drift "
                f"(to {sep * 1e3:.1f} ms > {self.max_se_s * 1e3:.0f} ms: the tool's velocity "
                "in the tool frame hardly changes, as for one joint at constant speed); "
                "changes of speed or direction separate it",
                float(trk_t[-1]),
                sep,
            )
        fits = self._two_models(enc_t, enc_q, trk_t, trk_p, trk_q, guess)
        if isinstance(fits, DelayNotIdentifiableError):
            return DelayRefused("fits_not_identifiable", str(fits), float(trk_t[-1]))
        fit = min(fits, key=lambda f: f.residual_rms_moving)
        return _ModelFit(
            fit, _model_disagreement(fit, fits), sep, float(trk_t[0]), float(trk_t[-1])
        )

    def _two_models(
        self,
        enc_t: np.ndarray,
        enc_q: np.ndarray,
        trk_t: np.ndarray,
        trk_p: np.ndarray,
        trk_q: np.ndarray | None,
        guess: float,
    ) -> list[DelayFit] | DelayNotIdentifiableError:
        """The fits of the two error models (those that gave one), or why neither did. Linear
        in the tool position, with the errors in the tool frame (where the tool's own
        calibration error is constant) or in the base frame (closer for a robot's geometric
        errors)."""
        fits: list[DelayFit] = []
        reason = DelayNotIdentifiableError("no fit")
        for features in ("tool", "position"):
            try:
                fits.append(
                    fit_delay(
                        self.cell,
                        enc_t,
                        enc_q,
                        trk_t,
                        trk_p,
                        trk_q,
                        initial=guess,
                        with_drift=False,
                        features=features,
                        # one stretch is one window; and scipy.stats, which the check
                        # imports, would cost the service seconds at its first fit
                        check_windows=False,
                    )
                )
            except DelayNotIdentifiableError as exc:
                reason = exc
        return fits if fits else reason

    def _measure_stretch(
        self,
        window: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None],
        current: float,
        guess: float,
    ) -> DelayMeasurement | DelayRefused:
        """The delay over one stretch (`_fit_models`), or why there is none."""
        fitted = self._fit_models(window, guess)
        if isinstance(fitted, DelayRefused):
            return fitted
        fit = fitted.fit
        return DelayMeasurement(
            fit.delay_s,
            _reported_se(fit.delay_se_s, fitted.model_s, fitted.sep_se_s),
            fit.speed_rms,
            fitted.t_last,
            current,
            0.5 * (fitted.t_first + fitted.t_last),
            fit.residual_rms_moving if math.isfinite(fit.residual_rms_moving) else 0.0,
            fitted.sep_se_s,
            fit.delay_se_s,
            fitted.model_s,
            turn_rms=fit.turn_rms,
        )

    def combine(self, found: DelayMeasurement | DelayRefused) -> float | None:
        """Fold one measurement in (on the loop, between samples): the delay to use now if
        it changed, else None; what was decided and why in `last_result`, and whether the
        change is a confirmed step (`step`) or a refinement to slew to.

        Every finite fit joins the recent fits, whatever the delay in use; the delay in use
        changes only through them (`_decide`): no single fit, taken or refused, stands in
        the way of the fits that follow. Once settled, the running estimate may still refine
        the delay in use by steps too small to matter at the tool's speed (a device clock's
        stamps walk by microseconds), and only when it is itself known that well."""
        lines, self._fitting_frame = self._fitting_frame, None
        self._note_pooled(found, lines)
        if isinstance(found, DelayRefused):
            self._refused(found)
            if not self.settled and self.pooled is not None:
                self._move_to(lines)  # the pooled fit is under the lines of its snapshot
            return self._with_pooled(found.t, self.applied)
        self._move_to(lines)  # the fit is under the lines of its snapshot
        before = self.applied  # as moved under those lines
        value, se, speed = found.delay_s, found.se_s, found.speed_rms
        # young mappings' stamps still move; receipt and shared-clock stamps have no mapping
        provisional = found.t <= self._young_until and bool(lines)
        own = _own_of(found)
        self.separable = not found.sep_se_s * speed > self.settings.settle_m
        if not provisional:  # young stretches have their own length
            self._fit_stretch(own * speed)  # the length for the fits' own precision
        if not (math.isfinite(value) and math.isfinite(se) and se > 0) or se > self.max_se_s:
            self.counters["fits_refused_imprecise"] += 1
            self.decision = DelayDecision("kept", "the fit gave no usable value", t=found.t)
            self.state = "fits_refused_imprecise"
            return self._with_pooled(found.t, before)
        self.counters["fits_accepted"] += 1  # usable: they join the recent fits
        self._recent.append(
            _Fit(
                value,
                se,
                found.described_t,
                speed,
                found.rms_m,
                young=provisional,
                sep_se=found.sep_se_s,
                own_se=found.own_se_s,
                model=found.model_s,
                turn=found.turn_rms,
            )
        )
        if not self.settled and not provisional:
            # the fits' scatter off their neighbours' line (`_wander2`) is measured from
            # the fits before the delay settles too: a refinement needs it known
            self._history.append((value, own, self._segment, found.described_t))
        if not self._carried and self._confirms(self._recent[-1]):
            self._set_source("confirmed", found.t)
        newest = self._recent[-1]
        decision = dataclasses.replace(
            self._decide(found.t),
            fit_s=newest.value,
            fit_se_s=self._honest(newest),
            speed_m_s=newest.speed,
            t=found.t,
        )
        self.decision, self.state = decision, decision.verdict
        changed = self._with_pooled(found.t, before)
        if changed is not None or not self.settled:
            return changed
        refined = self._refine(found, provisional) if self.settled else None
        if refined is None:
            return None
        self.decision = dataclasses.replace(decision, verdict="refined", reason=refined)
        self.state = "refined"
        return self.delay_now()

    def _note_pooled(
        self, found: DelayMeasurement | DelayRefused, lines: dict[str, Anchor] | None
    ) -> None:
        """Keep a measurement's pooled fit (while not settled), its standard error with its
        error model's share beyond what its two models' disagreement shows: the stretches'
        scatter beyond their own se (tau), as if shared by its stretches (a short pool's two
        models can be biased alike by geometric errors, beyond their disagreement:
        docs/timing-delay.md). A young clock mapping's stamps still move: its pooled
        fit is not kept (as its rough stretch fits are not taken alone), nor is one whose
        stretch's time is not known. A measurement without a pooled fit drops the one kept:
        a pooled fit is of the pool it was measured on, not to be taken again later under
        a newer time as if new. A pool the fit could not use is counted (`pools_unusable`)."""
        if found.pool_unusable:
            self.counters["pools_unusable"] += 1
        young = not found.t > self._young_until and bool(lines)
        if self.settled or young or not (math.isfinite(found.pooled_s) and found.pooled_se_s > 0):
            self.pooled = None
            return
        share = self._tau2() / max(self._pool_stretches, 1)
        self.pooled = (found.pooled_s, math.sqrt(found.pooled_se_s**2 + share))

    def _with_pooled(self, t: float, before: float | None) -> float | None:
        """Where every measurement's folding in ends: while the delay is not settled, the
        newest pooled fit in use when it is known better than what the stretches gave
        (their consensus, or the first fit), whatever the stretch's own fit was (taken,
        refused or imprecise); once settled, the pooled fit dropped. The delay to use now
        if the delay in use is no longer `before`, else None. The flag stays: settling is
        still the stretches' agreement (`_decide_unsettled`)."""
        if self.settled:
            self.pooled = None
        else:
            self._use_pooled(t)
        return self.delay_now() if self.applied != before else None

    def _use_pooled(self, t: float) -> None:
        """The newest pooled fit in use if it is known better than the delay in use."""
        if self.pooled is None or not math.isfinite(t):
            return
        value, se = self.pooled
        if self.applied_se is not None and not se < self.applied_se:
            return
        self._take(value, se, t, step=True)
        self.counters["pooled_in_use"] += 1
        words = (
            "the pooled fit (the samples since the delay was last unknown, up to the newest "
            f"{self.settings.pool_s:g} s) in use (known better than the stretches gave), "
            "until the stretches agree"
        )
        refused = self.decision.verdict == "kept" and self.state.startswith("fits_")
        self.decision = dataclasses.replace(
            self.decision,
            verdict="unsettled",
            reason=f"{self.decision.reason}; {words}" if refused else words,
        )
        if not refused:  # a refusal keeps its kind: the service says its advice once
            self.state = "unsettled"

    def honest_se(
        self, own_se: float, model_s: float = math.nan, sep_se_s: float = math.nan
    ) -> float:
        """A fit's standard error with its error model's share. Within a stretch the
        residual cannot show how far the stretch's error model is off; two things can:
        between stretches, the scatter of the fits beyond their own standard errors (tau,
        `_tau2`), and within it, how far its two error models' fits disagree (`model_s`).
        Both evaluate the same error, so the larger counts, added to the fit's own
        (clustered) se; the motion's separability (`sep_se_s`, `separable_se`) is a floor.
        nan for `model_s` or `sep_se_s`: not measured."""
        model2 = model_s * model_s if math.isfinite(model_s) else 0.0
        var = own_se * own_se + max(model2, self._tau2())
        if math.isfinite(sep_se_s):
            var = max(var, sep_se_s * sep_se_s)
        return math.sqrt(var)

    def _honest(self, fit: _Fit) -> float:
        """`honest_se` of a recent fit."""
        return self.honest_se(_own(fit), fit.model, fit.sep_se)

    def _tau2(self) -> float:
        """tau^2 from the recent fits (all the segment keeps, up to 16, of settled mappings
        when there are three): the scatter of their values beyond their own standard errors
        (`excess_variance`); `first_tau_s`^2 until three fits say. All of them, not the five
        of the consensus: neighbouring stretches of a slow motion share much of their error
        model's bias, so the scatter shows only over more than the motion's period, and a
        scale from five values (four degrees of freedom) lets 2.5 of it cover a normal fit
        93 % of the time at best. Beyond their own (clustered) standard errors, not the ones
        reported with the error models' disagreement: tau is that same error, measured
        between stretches, and fits whose models disagreed widely took the scatter of the
        others into their own se, so tau fell to its floor while a precise fit whose two
        models were wrong alike was reported with its own se alone (docs/timing-delay.md)."""
        key = (len(self._recent), self._recent[-1] if self._recent else None)
        if self._tau2_cache[0] == key:
            return self._tau2_cache[1]
        fits = [f for f in self._recent if not f.young]
        if len(fits) < 3:
            fits = list(self._recent)
        if len(fits) < 3:
            tau2 = self.settings.first_tau_s**2
        else:
            values = np.array([f.value for f in fits])
            ses = np.array([_own(f) for f in fits])
            tau2 = excess_variance(values, ses, self.min_wander_s**2)
        self._tau2_cache = (key, tau2)
        return tau2

    def consensus(self) -> tuple[float, float, list[_Fit]] | None:
        """The recent fits' robust consensus: the weighted median, then the weighted mean of
        the fits within 3 sigma of it (at least two), its standard error scaled up by their
        own disagreement. Symmetric: it knows nothing of the delay in use."""
        # a young clock mapping's fits describe stamps that moved since: once two fits of
        # settled mappings are there, theirs only; until then the newest two
        pool = [f for f in self._recent if not f.young]
        if len(pool) < 2:
            pool = list(self._recent)[-2:]
        fits = pool[-self.settings.consensus_fits :]
        if len(fits) < 2:
            return None
        sig = np.array([self._honest(f) for f in fits])
        val = np.array([f.value for f in fits])
        order = np.argsort(val)
        cw = np.cumsum(1.0 / sig[order] ** 2)
        median = float(val[order][np.searchsorted(cw, 0.5 * cw[-1])])
        inside = np.abs(val - median) <= 3.0 * sig
        if inside.sum() < 2:
            return None
        w = 1.0 / sig[inside] ** 2
        mean = float(np.sum(w * val[inside]) / np.sum(w))
        chi2 = float(np.sum(w * (val[inside] - mean) ** 2))
        se = math.sqrt(1.0 / float(np.sum(w)) * max(1.0, chi2 / (inside.sum() - 1)))
        return mean, se, [f for f, k in zip(fits, inside, strict=True) if k]

    def _decide(self, t: float) -> DelayDecision:
        """The gate of a change of the delay in use. Unknown (nothing configured): the
        newest usable fit until two agree, then their consensus (a step: anything measured
        beats nothing), and the delay is settled once three agree to `settle_m` at the tool's
        speed; estimates are flagged until then. Settled (configured, or found): it changes
        only when (a) the consensus is incompatible with the delay in use at
        `change_sigmas`, the delay in use's own uncertainty counted (a configured delay's
        is `timing.delay_se_s`), (b) at least two of the fits behind it, the newest among
        them, are each off the delay in use by `confirm_sigmas` on the same side (a later,
        independent stretch confirms the earlier), and (c) on the newest stretch's samples
        the residual scatter is lower with the consensus than with the delay in use."""
        cons = self.consensus()
        newest = self._recent[-1]
        precise = newest.se * newest.speed <= self.max_apply_m
        if cons is None and self.applied is None and (precise or not newest.young):
            # nothing is known: one usable fit beats nothing (flagged, and the fits that
            # follow revise it by the consensus like any other; with honest standard errors
            # a receipt-stamped encoder's fits are rough, and waiting for a precise one
            # left the delay at 0 for many seconds); but a young clock mapping's rough fit
            # is not taken alone (its stamps still move; docs/timing-delay.md)
            self._take(newest.value, self._honest(newest), t, step=True)
            return DelayDecision("unsettled", "the first fit, in use until fits agree")
        if cons is None:
            self.counters["fits_without_consensus"] += 1
            return DelayDecision("kept", "the recent fits do not agree yet")
        c, se_c, members = cons
        agreed = f"{len(members)} fits agree"

        def decided(verdict: str, reason: str) -> DelayDecision:
            return DelayDecision(verdict, reason, consensus_s=c, consensus_se_s=se_c)

        if not self.settled or self.applied is None:
            return decided(*self._decide_unsettled(t, cons, agreed))
        applied = self.applied
        # the delay in use walks on since it was set (device clocks' stamps move with load)
        since = 0.0 if math.isnan(self._applied_t) else max(0.0, t - self._applied_t)
        applied_se = math.sqrt((self.applied_se or 0.0) ** 2 + self.settings.steady_walk * since)
        z = abs(c - applied) / math.sqrt(se_c**2 + applied_se**2)
        if z < self.settings.change_sigmas:
            self.counters["fits_agree"] += 1
            return decided("kept", f"{agreed}, {z:.1f} sigma from the delay in use")
        if not se_c < applied_se:
            # automation may only improve on the delay in use: a value known less precisely
            # than it (a configured delay's `delay_se_s`) is no improvement, however far off
            self.counters["changes_less_precise"] += 1
            return decided("kept", f"{agreed}, known less precisely than the delay in use")
        side = math.copysign(1.0, c - applied)
        confirming = [
            f
            for f in members
            if side * (f.value - applied)
            > self.settings.confirm_sigmas * math.hypot(self._honest(f), applied_se)
        ]
        if len(confirming) < 2 or confirming[-1] is not newest:
            self.counters["changes_unconfirmed"] += 1
            return decided("kept", f"{agreed}, waiting for a later stretch to confirm")
        if self.settings.change_sigmas * newest.sep_se > abs(c - applied):
            # nan (not measured) passes; the newest stretch's motion must show the change
            # beyond what a constant tool error and a slow drift can take
            self.counters["changes_not_separable"] += 1
            return decided(
                "kept",
                f"{agreed}, but the newest stretch's motion cannot separate a delay from a "
                f"tool error to better than {newest.sep_se * 1e6:.0f} us",
            )
        return decided(*self._change_if_better(t, (c, se_c, agreed), applied, z))

    def _change_if_better(
        self, t: float, consensus: tuple[float, float, str], applied: float, z: float
    ) -> tuple[str, str]:
        """Gate (c) of `_decide`: the change is taken only when, on the newest stretch's
        samples, the residual scatter is lower with the consensus (value, se, how many agree)
        than with the delay in use, `z` sigma from it: the data must show the improvement,
        not only the fits' standard errors."""
        c, se_c, agreed = consensus
        newest = self._recent[-1]
        old = math.hypot(newest.rms, (applied - newest.value) * newest.speed)
        new = math.hypot(newest.rms, (c - newest.value) * newest.speed)
        if not new < old:
            self.counters["changes_not_better"] += 1
            return "kept", f"scatter {new * 1e6:.1f} um with it, {old * 1e6:.1f} um without"
        self._take(c, se_c, t, step=True)
        self._trend.start(c, se_c * se_c, newest.t)
        self._trend_fits = 0
        self.counters["changes"] += 1
        return (
            "changed",
            f"{agreed}, {z:.1f} sigma from the delay before; scatter on the newest stretch "
            f"{old * 1e6:.1f} -> {new * 1e6:.1f} um",
        )

    def _decide_unsettled(
        self, t: float, cons: tuple[float, float, list[_Fit]], agreed: str
    ) -> tuple[str, str]:
        """While the delay is not settled the consensus is taken at once; it settles once three
        fits of settled mappings agree to `settle_m` at the tool's speed and the motion
        separates a delay."""
        c, se_c, members = cons
        newest = self._recent[-1]
        speed = float(np.median([f.weigh for f in members]))
        taken = "in use"
        if newest.young and newest in members:  # its stamps are the most settled
            c, se_c = newest.value, self._honest(newest)
            taken = "the newest fit in use (young clock mappings: its stamps are the newest)"
        self._take(c, se_c, t, step=True)
        grown = len(members) >= 3 and not any(f.young for f in members)
        # and the motion itself separates a delay (not so for one joint at constant
        # speed, whose fits agree on a value the motion cannot tell from a tool error)
        separates = not newest.sep_se * newest.speed > self.settings.settle_m
        # fits of one motion are biased alike (the stamps' errors and the stretches'
        # error model change slowly): their mean is known no better than the best of them;
        # and one precise fit among rough ones is that fit alone, whose own se may miss (a
        # stretch 2.9 se off settled a MotoROS stop-and-go run 243 us off): two stretches
        # must each know the delay that well, a later one confirming an earlier one
        se_settle = max(se_c, sorted(self._honest(f) for f in members)[1])
        if grown and separates and se_settle * speed <= self.settings.settle_m:
            self.settled = True
            self._start_trend(members)
            return "settled", agreed
        to = self.settings.settle_m * 1e6
        if not separates:
            # the fits may agree, but on a value the motion cannot tell from a tool error:
            # the flag stays, and the reason says why (issue 45: "the fit says so")
            return "unsettled", (
                f"{agreed}, {taken}, but the motion cannot separate a delay from a tool error "
                f"to better than {newest.sep_se * 1e6:.0f} us; changes of speed or direction "
                "separate it"
            )
        return "unsettled", (
            f"{agreed}, {taken} until they agree to {to:g} um (or urad) at the tool's speed"
        )

    def _start_trend(self, members: list[_Fit]) -> None:
        """Start the running estimate from the fits that settled the delay, in their order,
        each with its own standard error and the fits' scatter off their neighbours' line
        (as `_refine` feeds it): the walk they showed is followed from the next fit on.
        Started from their consensus alone (one value, their mean), it knew nothing of that
        walk, lagged it by the consensus's span, and refined the delay in use only after
        three more fits; meanwhile the delay the stamps need walked on (docs/timing-delay.md,
        the device-clock run)."""
        tau2 = self._wander2()
        first, *rest = members
        self._trend.start(first.value, _own(first) ** 2 + tau2, first.t)
        for fit in rest:
            self._trend.update(fit.value, _own(fit) ** 2 + tau2, fit.t)
        self._trend_fits = len(members)

    def _confirms(self, fit: _Fit) -> bool:
        """Does this fit confirm the configured delay in use, so that from now on the delay
        follows the clock mappings' lines (`_carried`)? Only a fit precise to `max_apply_m` at
        the fastest the tool moved in the recent fits (a fit of the slow start is precise at
        its own speed and not at the motion's), of a mapping no longer young (a young line
        still learns its drift: carried along it, a right delay walks off with the line's
        learning; docs/timing-delay.md), and within `change_sigmas` of the delay in use. The
        fit is the newest of the recent fits."""
        if self.applied is None or self.applied_se is None or fit.young:
            return False
        se = fit.se
        fastest = max(f.weigh for f in self._recent)
        if not se * fastest <= self.max_apply_m:
            return False
        return abs(fit.value - self.applied) <= self.settings.change_sigmas * math.hypot(
            se, self.applied_se
        )

    def _take(self, value: float, se: float, t: float, step: bool) -> None:
        self.applied, self.applied_se, self._applied_t = value, se, t
        self.estimate, self.se, self._estimate_t = value, se, t
        self._set_source("fit", t)
        self.step = step

    def _refine(self, found: DelayMeasurement, provisional: bool) -> str | None:
        """The running estimate (a Kalman filter over the fits, `delay_trend`), applied as a
        refinement when it is known to `max_apply_m` at the tool's speed and moves the delay
        by at most three times that there (larger changes go through `_decide`). None when
        it did not refine the delay in use; else the reason, in words."""
        value, speed = found.delay_s, found.speed_rms
        # the running estimate follows the delay's walk between stretches: what a fit knows
        # of that is its own standard error; the error models' share and the motion's floor
        # (in `se_s`) are biases that stretches of one motion share, which a walk does not move
        se = found.own_se_s if math.isfinite(found.own_se_s) else found.se_s
        t_fit = found.described_t
        fresh = provisional or self._provisional or not self._trend.started
        moved = None if fresh else self._outlier(value, se, t_fit)
        if moved is False:
            return None
        self._suspect = None
        self._provisional = int(provisional)
        if not provisional:
            self._history.append((value, se, self._segment, t_fit))
        tau2 = self._wander2()
        if fresh and self.applied is not None and self.applied_se is not None:
            # the filter starts from the delay in use with its uncertainty (a configured
            # prior, or the consensus it came from), never from one fit alone
            self._trend.start(self.applied, self.applied_se**2, t_fit)
            self._trend_fits = 0
        elif fresh:
            self._trend.start(value, se * se + tau2, t_fit)
            self._trend_fits = 0
        elif isinstance(moved, tuple):
            self._trend.start(moved[0], moved[1] ** 2 + tau2, moved[2])
            self._trend_fits = 1
        self._trend.update(value, se * se + tau2, t_fit)
        self._trend_fits += 1
        estimate, estimate_var = self._trend.predict(found.t)
        self.estimate, self.se = estimate, math.sqrt(estimate_var)
        self._estimate_t = found.t
        if (
            provisional
            # a refinement is the work of several fits, never one, and only once their
            # scatter beyond their se is measured (fits biased alike by the robot's geometry
            # refined a right delay while that scatter was still assumed)
            or self._trend_fits < 3
            or not self._wander_known()
            or self.applied is None
            or self.se * speed > self.max_apply_m
            or abs(self.estimate - self.applied) * speed > 3.0 * self.max_apply_m
        ):
            return None
        self.applied_se = self.se
        self.applied, self._applied_t = self.estimate, self._estimate_t
        self._set_source("fit", self._estimate_t)
        self.step = False
        self.counters["refinements"] += 1
        return (
            f"by the running estimate ({self._trend.chosen} view, "
            f"{self._trend.rate * 1e6:+.1f} us/s)"
        )

    def _refused(self, found: DelayRefused) -> None:
        """Count a stretch without a delay; one too short to separate a delay at all (a
        settled one) lengthens the stretch, as a rough fit does."""
        if found.counter == "fits_not_identifiable" and not found.t <= self._young_until:
            self._fit_stretch(math.inf)
        if math.isfinite(found.sep_se_s):
            self.separable = False
        self.counters[found.counter] += 1
        self.decision = DelayDecision("kept", found.reason, t=found.t)
        self.state = found.counter

    def _fit_stretch(self, precision_m: float) -> None:
        """The settled stretch as short as gives fits known to `max_position_se_m` at the
        tool's speed: twice as long after a rougher fit, up to `max_span_s`; half as long
        after one precise enough to stay so at half the length (a fit's standard error
        grows about as the length to the power -1.5), down to `span_s`. (Short stretches
        follow the delay's walk; a robot whose geometry the stretches' linear error model
        does not hold needs longer ones for a fit worth taking.)"""
        if not math.isfinite(precision_m) or precision_m > self.max_position_se_m:
            self._stretch_s = min(2.0 * self._stretch_s, self.max_span_s)
        elif precision_m * 2.0**1.5 <= self.max_position_se_m:
            self._stretch_s = max(0.5 * self._stretch_s, self.span_s)

    def _outlier(
        self, value: float, se: float, t_fit: float
    ) -> tuple[float, float, float] | bool | None:
        """Is a fit far off the running estimate (`outlier_sigmas` combined standard
        errors)? None: no. False: yes, and refused (why, in `last_result`). Else the fit
        before it, which was just as far off and agrees with it: the delay moved."""
        tau2 = self._wander2()
        level, level_var = self._trend.predict(t_fit)
        spread = math.sqrt(level_var + se * se + tau2)
        if abs(value - level) <= self.outlier_sigmas * spread:
            return None
        suspect, self._suspect = self._suspect, (value, se, t_fit)
        if suspect is not None:
            # the two agree as far as the delay may have walked between them
            walked = self._trend.views["steady"].level_walk * abs(t_fit - suspect[2])
            together = math.sqrt(se * se + suspect[1] ** 2 + tau2 + walked)
            if abs(value - suspect[0]) <= self.outlier_sigmas * together:
                return suspect
        return False

    def _se_at(self, t: float) -> float | None:
        """The running estimate's standard error at stream time t: grown by the walk since
        its newest fit. Judged against it, a new fit is neither refused as less precise than
        an estimate that has gone stale nor as an outlier from it (against the unaged
        estimate, fits of a walking delay were refused in a row and the delay in use fell
        behind)."""
        if not self._trend.started:
            return self.se
        return math.sqrt(self._trend.predict(t)[1])

    def _wander_known(self) -> bool:
        """Have three triples of the current segment's fits measured their scatter?"""
        hist = [h for h in self._history if h[2] == self._segment]
        return len(hist) >= 5

    def _wander2(self) -> float:
        """tau^2: the scatter of accepted fits beyond their standard errors, within each
        segment (between restarts), from how far each fit lies off the straight line
        through its neighbours (a steady walk of the delay is not scatter): the median over
        0.4549 (a normal variable's squared median), so that one wild fit does not make every
        fit look wild. Until 3 such triples say, from the differences of successive fits
        (which count a walk as scatter too: modest while little is known), and (10
        min_wander_s)^2 until 3 of those say. At least min_wander_s^2."""
        floor = self.min_wander_s**2
        hist = list(self._history)
        off2: list[float] = []
        se2: list[float] = []
        for a, b, c in _triples(hist):
            if a[2] == b[2] == c[2] and a[3] < b[3] < c[3]:
                w = (b[3] - a[3]) / (c[3] - a[3])  # b's place between its neighbours
                factor = 1.0 + (1.0 - w) ** 2 + w * w  # white scatter's variance, times this
                off2.append((b[0] - (1.0 - w) * a[0] - w * c[0]) ** 2 / factor)
                se2.append((b[1] ** 2 + ((1.0 - w) * a[1]) ** 2 + (w * c[1]) ** 2) / factor)
        if len(off2) < 3:
            off2, se2 = [], []
            for a, b in itertools.pairwise(hist):
                if a[2] == b[2]:
                    off2.append((b[0] - a[0]) ** 2 / 2.0)
                    se2.append((a[1] ** 2 + b[1] ** 2) / 2.0)
        if len(off2) < 3:
            return max(floor, (10 * self.min_wander_s) ** 2)  # unknown yet: be modest
        return max(floor, float(np.median(off2)) / 0.4549 - float(np.median(se2)))

    def forget(self, prior_s: float = 0.0, prior_se_s: float | None = None) -> None:
        """The delay was set by hand (a reload): start afresh from it, a prior as at start."""
        self._trend.reset()
        self._provisional = 0
        self._suspect = None
        self._frame = {}
        self._recent.clear()
        self.estimate = self.se = None
        known = prior_se_s is not None and math.isfinite(prior_se_s) and prior_se_s > 0
        self.applied = prior_s if known else None
        self.applied_se = prior_se_s if known else None
        self.settled = self._from_prior = known
        self._set_source("configured" if known else "unknown")
        self.decision = DelayDecision("restarted", "the delay was set anew (a reload)")
        self.state = "restarted"
        # counted as a start anew, as a new time base is: a fit in flight across the reload
        # (the service compares this count) is of samples from before it, and is dropped
        self.counters["restarts"] += 1
        self._start_anew()


# the other error model's residual this many times the chosen one's: rejected by the data
# (docs/timing-delay.md: at 1.5 the disagreement of receipt-stamped fits was dropped too
# often and their coverage fell; at 3 the test subset is as without the rule)
MODEL_REJECT_RATIO = 3.0


def _own_of(found: DelayMeasurement) -> float:
    """A measurement's own (clustered) standard error, without its error model's share."""
    return found.own_se_s if math.isfinite(found.own_se_s) else found.se_s


def _own(fit: _Fit) -> float:
    """A recent fit's own (clustered) standard error, without its error model's share."""
    return fit.own_se if math.isfinite(fit.own_se) else fit.se


def _point_moves(t: np.ndarray, p: np.ndarray) -> bool:
    """Does the tracked point move (its mean speed over the stretch, from samples 0.1 s
    apart so that the tracker's noise is no speed, above twice `MIN_SPEED`)?"""
    span = float(t[-1] - t[0])
    if span <= 0.2:
        return False
    k = np.unique(np.searchsorted(t, np.arange(t[0], t[-1], 0.1)))
    path = float(np.sum(np.linalg.norm(np.diff(p[k], axis=0), axis=1)))
    return path / span > 2 * MIN_SPEED


def _model_disagreement(fit: DelayFit, fits: list[DelayFit]) -> float:
    """How far the tool-frame and the base-frame error models' delays disagree. The other
    model counts only while the data do not reject it (its residual within
    MODEL_REJECT_RATIO of the chosen fit's): with a tool error alone and noise-free poses the
    tool-frame fit leaves almost nothing, and the other model's disagreement says nothing
    about it. nan: only one model gave a fit, or the other is rejected."""
    others = [f for f in fits if f is not fit]
    if not others or others[0].residual_rms_moving > MODEL_REJECT_RATIO * fit.residual_rms_moving:
        return math.nan
    return abs(fit.delay_s - others[0].delay_s)


def _reported_se(own_se: float, model: float, sep: float) -> float:
    """The standard error a stretch's fit reports. Its own (clustered) one cannot see how
    far the stretch's error model is off; two things measured on the stretch can: how far
    the tool-frame and the base-frame error models' fits disagree (`model`, added,
    `_model_disagreement`), and how well the motion alone separates a delay from a constant
    tool error and its slow drift (`separable_se`, a floor: one joint at constant speed is
    fitted precisely and wrongly). docs/timing-delay.md has the coverage each brought."""
    se = own_se if not math.isfinite(model) else math.hypot(own_se, model)
    return max(se, sep) if math.isfinite(sep) else se


def excess_variance(values: np.ndarray, se: np.ndarray, floor: float) -> float:
    """tau^2, the variance the values scatter by beyond their own standard errors.

    Paule and Mandel's estimator of the "dark uncertainty" between laboratories that measured
    one quantity (a random effect, as in key comparisons; stretches of one motion are such
    laboratories, each with its own error model's bias): the tau^2 at which the values'
    weighted scatter about their weighted mean, each weighted by 1 / (se^2 + tau^2), is what
    n values of those variances show (chi^2 = n - 1). Fits of unequal precision need it: the
    median of the fits' variances taken off a common scatter (the estimator before) let fits
    whose se counts a large error-model disagreement hide the scatter of precise fits ten
    times their se apart. Taken over the values within `SCATTER_SIGMAS` of their weighted
    median, starting from the robust scatter (their median absolute deviation less their
    median variance) and growing with what the members show, so that one wild value (a first
    fit 6.5 se off in the issue's cell) does not set the scatter of the others. At least
    `floor`."""
    tau2 = max(floor, _mad_sigma(values) ** 2 - float(np.median(se * se)))
    for _ in range(20):
        sig = np.sqrt(se * se + tau2)
        order = np.argsort(values)
        cw = np.cumsum(1.0 / sig[order] ** 2)
        centre = float(values[order][np.searchsorted(cw, 0.5 * cw[-1])])
        members = np.abs(values - centre) <= SCATTER_SIGMAS * sig
        if members.sum() < 2:
            return tau2
        grown = max(tau2, _paule_mandel(values[members], se[members], floor))
        if grown <= tau2 * 1.001:
            return grown
        tau2 = grown
    return tau2


SCATTER_SIGMAS = 4.0  # a fit this far off the others' weighted median does not set their scatter


def _paule_mandel(values: np.ndarray, se: np.ndarray, floor: float) -> float:
    """The tau^2 at which sum w (x - mean_w)^2 = n - 1, w = 1 / (se^2 + tau^2) (at least
    `floor`), by bisection in log tau^2: the weighted scatter falls as tau^2 grows."""
    n = values.size

    def excess(tau2: float) -> float:
        w = 1.0 / (se * se + tau2)
        mean = float(np.sum(w * values) / np.sum(w))
        return float(np.sum(w * (values - mean) ** 2)) - (n - 1)

    if n < 2 or excess(floor) <= 0.0:
        return floor
    lo, hi = math.log(floor), math.log(max(floor, float(np.ptp(values)) ** 2) * 4.0)
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if excess(math.exp(mid)) > 0.0 else (lo, mid)
    return math.exp(hi)


def _triples(items: list[_T]) -> list[tuple[_T, _T, _T]]:
    """Each item with its two neighbours: (a, b, c) for every b between them."""
    return list(zip(items, items[1:], items[2:], strict=False))


def _covered(
    window: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None],
    delay: float,
    max_gap_s: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """The window without tracker samples whose encoder time (under `delay`) falls outside
    the encoder samples or between two further apart than `max_gap_s` (a stalled or restarted
    adapter): interpolating the joints across such a gap would read a made-up motion."""
    enc_t, enc_q, trk_t, trk_p, trk_q = window
    if enc_t.size < 2 or trk_t.size == 0:
        return window
    at = trk_t - delay
    k = np.searchsorted(enc_t, at)
    inside = (k > 0) & (k < enc_t.size)
    k = np.clip(k, 1, enc_t.size - 1)
    sound = (np.diff(enc_t) <= max_gap_s) & ~resent_joint_intervals(enc_q)
    keep = inside & sound[k - 1]
    return enc_t, enc_q, trk_t[keep], trk_p[keep], None if trk_q is None else trk_q[keep]


def resent_joint_intervals(
    enc_q: np.ndarray, ratio: float = 4.0, floor: float = 1e-3
) -> np.ndarray:
    """Per encoder interval, True where its joints were resent: a run of repeated rows that
    ends in a jump (a step `ratio` times larger than the step after it and over `floor`
    rad). That is what an encoder stream looks like after its sender stalled and resent its
    newest row: the stamps go on while the joints stand still, then catch up at once. The
    tool moved all along, so fitting those samples would read a delay into a made-up
    motion (and blame the motion for the fit's failure)."""
    if enc_q.ndim != 2 or enc_q.shape[0] < 3:
        return np.zeros(max(enc_q.shape[0] - 1, 0), dtype=bool)
    step = np.max(np.abs(np.diff(enc_q, axis=0)), axis=1)
    resent = np.zeros(step.size, dtype=bool)
    after = np.append(step[1:], np.inf)
    for jump in np.flatnonzero((step > floor) & (step > ratio * after)):
        start = jump
        while start > 0 and step[start - 1] == 0.0:
            start -= 1
        if start < jump:  # repeated rows before the jump: resent, the jump with them
            resent[start : jump + 1] = True
    return resent


@dataclass(frozen=True)
class Stretch:
    """A stretch taken from the buffers: the encoder's rows (stamp, joints..., device stamp)
    and the tracker's (stamp, x, y, z, qw, qx, qy, qz, device stamp), nan where a sample had
    no device stamp or no quaternion, and each stream's line then (None: not mapped)."""

    enc: np.ndarray
    trk: np.ndarray
    enc_line: Anchor | None
    trk_line: Anchor | None
    # while the delay is not settled: the rows since it was last unknown, for the pooled
    # fit (`OnlineDelayTracker.measure`'s `pool`: `pool_arrays`); None: none
    pool: Stretch | None = None


def stretch_arrays(
    stretch: Stretch,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """A stretch's arrays, its mapped stamps under the stream's line: (encoder stamps,
    joints, tracker stamps, positions, quaternions or None when a sample had none)."""
    enc, trk = stretch.enc, stretch.trk
    enc_t = _on_line(stretch.enc_line, enc[:, 0], enc[:, -1])
    enc_q = np.ascontiguousarray(enc[:, 1:-1]) if enc.shape[0] else np.empty((0, 0))
    trk_t = _on_line(stretch.trk_line, trk[:, 0], trk[:, -1])
    if not trk.shape[0]:
        return enc_t, enc_q, trk_t, np.array([]), np.array([])
    trk_p = np.ascontiguousarray(trk[:, 1:4])
    quats = trk[:, 4:8]
    trk_q = None if np.isnan(quats[:, 0]).any() else np.ascontiguousarray(quats)
    return enc_t, enc_q, trk_t, trk_p, trk_q


def pool_arrays(
    stretch: Stretch,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None] | None:
    """The arrays of a stretch's pool (`stretch_arrays` of `Stretch.pool`), None: no pool."""
    return None if stretch.pool is None else stretch_arrays(stretch.pool)


def thinned(parts: Sequence[np.ndarray], most: int) -> np.ndarray:
    """The rows of `parts` joined, every k-th kept (k the least that keeps at most `most`):
    `np.concatenate(parts)[::k]`, without joining every row first (a 30 s pool of a 1 kHz
    tracker is 30,000 rows, of which 3,000 are kept; the join is on the event loop)."""
    step = -(-sum(part.shape[0] for part in parts) // most)  # ceil
    kept, offset = [], 0
    for part in parts:
        kept.append(part[(-offset) % step :: step])
        offset += part.shape[0]
    return np.concatenate(kept)


def _on_line(anchor: Anchor | None, stamps: np.ndarray, device: np.ndarray) -> np.ndarray:
    """The stamps of a stream under its line: a sample's device stamp (nan: none) carried by
    the line, its own stamp when it has none."""
    t = np.array(stamps, dtype=float)
    if anchor is not None and t.size:
        mapped = ~np.isnan(device)
        t[mapped] = anchor.at(device[mapped])
    return t


_NO_QUAT = (math.nan,) * 4  # a tracker row's quaternion for a single reflector's sample


def _moved_row(
    newer: tuple[float, float, float] | None, older: Anchor | None, at: float | None
) -> float:
    """`moved(Anchor(*newer), older, at)`: the same operations on plain floats (no anchor
    made per sample)."""
    if newer is None or older is None:
        return 0.0
    stamp, device, drift = newer
    d = device if at is None else device + (at - stamp) / (1.0 + drift)
    return (stamp - older.stamp) + (
        (d - device) * (1.0 + drift) - (d - older.device) * (1.0 + older.drift)
    )


class _Rows:
    """One stream's samples, oldest first, at most `maxlen` of them (the oldest dropped, as
    from a bounded deque), each a row of floats of one width, stamps rising in column 0.

    Per sample a tuple joins a list (`extend`, a block at a time); every `block` rows the list
    becomes rows of an array allocated ahead (grown by doubling, compacted when its end is
    reached), so that a stretch is a slice of it: no array per sample, no walk over a deque.
    `last` is the newest stamp (-inf when empty: any finite stamp is newer)."""

    def __init__(self, maxlen: int, block: int = 256) -> None:
        self.maxlen = max(int(maxlen), 1)
        self.block = block
        self.width = 0  # the rows' width, from the first row (0: none yet)
        self.last = -math.inf
        self._pending: list[tuple[float, ...]] = []
        self._rows: np.ndarray | None = None  # allocated at the first block (a copy sent
        self._head = 0  # to the fit worker at start carries none); rows [_head, _end) of
        self._end = 0  # it are held, then `_pending`

    def __len__(self) -> int:
        return self._end - self._head + len(self._pending)

    def extend(self, rows: list[tuple[float, ...]]) -> None:
        """The rows appended in turn, the oldest dropped once `maxlen` are held."""
        if not self.width:
            self.width = len(rows[0])
        self._pending.extend(rows)
        self.last = rows[-1][0]
        over = len(self) - self.maxlen
        if over > 0:  # full: the oldest dropped
            held = self._end - self._head
            self._head += min(over, held)
            if over > held:
                del self._pending[: over - held]
        if len(self._pending) >= self.block:
            self._flush()

    def first(self) -> float:
        """The oldest stamp (the buffer is not empty)."""
        if self._end > self._head:
            assert self._rows is not None
            return float(self._rows[self._head, 0])
        return self._pending[0][0]

    def clear(self) -> None:
        self._pending = []
        self._head = self._end = 0
        self.last = -math.inf

    def _flush(self) -> None:
        if not self._pending:
            return
        new = np.array(self._pending, dtype=float)
        self._pending = []
        n, held = new.shape[0], self._end - self._head
        rows = self._rows
        if rows is None or self._end + n > rows.shape[0]:
            size = 4 * self.block if rows is None else rows.shape[0]
            while size < 2 * (held + n):  # room for as many again before the next move
                size *= 2
            moved = np.empty((size, self.width)) if rows is None or size > rows.shape[0] else rows
            if rows is not None and held:
                moved[:held] = rows[self._head : self._end]
            self._rows, rows, self._head, self._end = moved, moved, 0, held
        rows[self._end : self._end + n] = new
        self._end += n

    def _held(self) -> np.ndarray:
        self._flush()
        if self._rows is None:
            return np.empty((0, max(self.width, 1)))
        return self._rows[self._head : self._end]

    def take_through(self, stamp: float) -> np.ndarray:
        """The rows with stamps up to `stamp` (a copy), dropped from the buffer."""
        held = self._held()
        k = int(np.searchsorted(held[:, 0], stamp, side="right"))
        out = held[:k].copy()
        self._head += k
        if self._head == self._end:
            self.last = -math.inf
        return out

    def between(self, lo: float, hi: float) -> np.ndarray:
        """The rows with stamps from `lo` to `hi` (a copy)."""
        held = self._held()
        a = int(np.searchsorted(held[:, 0], lo, side="left"))
        b = int(np.searchsorted(held[:, 0], hi, side="right"))
        return held[a : max(a, b)].copy()

    def drop_before(self, stamp: float) -> None:
        """Drop the rows with stamps before `stamp`."""
        held = self._held()
        self._head += int(np.searchsorted(held[:, 0], stamp, side="left"))
        if self._head == self._end:
            self.last = -math.inf


def _quat_matrices(q: np.ndarray) -> np.ndarray:
    """Rotation matrices of unit quaternions (w, x, y, z), one per row."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        1,
    )


def _unexplained(t: np.ndarray, r: np.ndarray, degree: int = 6) -> float:
    """Sum of squares of the smooth part of r(t) (a polynomial of `degree` in time, which
    leaves the samples' noise out) beyond a constant and a straight line in time."""
    x = (t - t.mean()) / max(float(np.ptp(t)), 1e-9) * 2.0
    smooth = np.polynomial.polynomial.polyval(x, np.polynomial.polynomial.polyfit(x, r, degree)).T
    line = np.polynomial.polynomial.polyval(x, np.polynomial.polynomial.polyfit(x, r, 1)).T
    return float(np.sum((smooth - line) ** 2))


def separable_se(trk_t: np.ndarray, trk_p: np.ndarray, trk_q: np.ndarray | None) -> float:
    """The standard error a delay could have from this stretch's motion alone, once a
    constant error in the tool frame and a slow (linear in time) drift of it are allowed:
    a delay changes the measured error by the tool's velocity times the delay, in the tool
    frame R^T v (and R^T w for the orientation), so only the part of that signature which
    is neither constant nor a straight line in time tells a delay from a tool calibration
    error or from a geometric error varying smoothly along the path. For one joint turning
    at constant speed the signature is constant: no stretch of it separates a delay, however
    small the fit's own standard error. The noise is the tracker's own, from its samples'
    second differences. inf: nothing separates; nan: no orientation to say (not measured)."""
    if trk_q is None or trk_t.size < 20:
        return math.nan
    dt = np.diff(trk_t)
    if not (dt > 0).all():
        return math.nan
    R = _quat_matrices(np.asarray(trk_q, dtype=float))
    # the position's and the orientation's increments, in the tool (sensor) frame
    dp = np.einsum("nji,nj->ni", R[:-1], np.diff(trk_p, axis=0))
    rel = np.einsum("nji,njk->nik", R[:-1], R[1:])  # R_i^T R_(i+1)
    dw = 0.5 * np.stack(
        [rel[:, 2, 1] - rel[:, 1, 2], rel[:, 0, 2] - rel[:, 2, 0], rel[:, 1, 0] - rel[:, 0, 1]],
        -1,
    )
    t_mid = 0.5 * (trk_t[1:] + trk_t[:-1])
    info = 0.0
    for inc in (dp, dw):
        # the noise of one sample: increments' differences carry it 6 times (1, -2, 1)
        sigma = max(
            float(np.mean([_mad_sigma(np.diff(inc[:, c])) for c in range(3)])) / math.sqrt(6),
            1e-12,
        )
        info += _unexplained(t_mid, inc / dt[:, None]) / sigma**2
    return math.inf if info <= 0 else 1.0 / math.sqrt(info)
