"""The estimator over whole recordings at once: the same output as feeding `Estimator` one
sample at a time in time-stamp order (`run_offline`), computed with array operations.

The decisions (rejects, held steps, the step cap, directions, range flags) are the array
forms of `rules`, which the streaming estimator applies one sample at a time. What this
module adds is the bookkeeping of *when* the streaming estimator decides, for arrays:

* Input order is the two-pointer merge of the streams (encoder first on ties). Each sample
  gets its position in that merged order ("event"); rejects are decided per sample from the
  running maximum of earlier good stamps.
* A tracker sample waits in a FIFO until the encoder stream reaches its delayed time or it
  has waited `stale_after_s` of tracker time; it is resolved at the first event where either
  holds, and never before its predecessor (a running maximum of those events).
* At that event the encoder buffer holds the accepted encoder samples seen so far (at most
  its capacity), so interpolation and its verdicts (gap, stale, too old) follow from the
  number of encoder samples accepted by then.
* The observer recursion x_k = (1 - a_k) x_{k-1} + a_k m_k with a_k = 1 - exp(-L dt_k) is a
  linear recurrence: solved in blocks (a loop over the position inside a block for all
  blocks at once, then a loop over blocks), which keeps each value within a few roundings
  of the sequential loop.

What it does not cover raises `BatchUnsupportedError` and the caller runs the streaming path:
"latest" alignment, more than MAX_PENDING samples waiting at once, non-finite kinematics.
No I/O.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass

import numpy as np

from keo_service.core.chain import Chain
from keo_service.core.errors import KeoError
from keo_service.core.estimator import Estimate
from keo_service.core.kinematics import Cell, channels_for
from keo_service.core.rotations import log3_many, quaternion_matrices, transposed_times
from keo_service.core.rules import (
    HELD_REASONS,
    MAX_MESSAGES,
    MAX_PENDING,
    NON_FINITE_VALUE,
    OUTSIDE_CALIBRATED_RANGE,
    CalibratedRanges,
    directions,
    encoder_non_finite,
    encoder_stamp_problem,
    encoder_verdicts,
    first_beyond,
    held_reasons,
    not_unit_quaternion,
    step_caps,
    tracker_stamp_problem,
    tracker_value_problem,
    tracker_verdicts,
)
from keo_service.core.settings import EstimatorSettings

__all__ = ["BatchResult", "BatchUnsupportedError", "estimate_batch", "measured_errors"]

CHUNK = 8192  # rows per pass of the kinematics
OBSERVER_ROWS = 8 * CHUNK  # rows per step of the observer's recursion


class BatchUnsupportedError(KeoError):
    """This input needs the streaming estimator (the message says why)."""


@dataclass(frozen=True)
class BatchResult:
    """One row per estimate, in output order: `Estimate`'s fields as columns (the same
    names; `to_estimates` and `from_estimates` convert). No `device_stamp` column: recordings
    hold no device stamps."""

    stamp: np.ndarray  # (n,)
    measured: np.ndarray  # (n, C); NaN where held
    estimate: np.ndarray  # (n, C)
    flags: list[str]  # "" or the flags joined by "|"
    encoder_stamp: np.ndarray  # (n,) the encoder time evaluated
    joints: np.ndarray | None  # (n, nq); NaN where held; None when not asked for
    channels: tuple[str, ...]
    counters: dict[str, int]
    messages: list[str]

    @property
    def held(self) -> np.ndarray:
        held: np.ndarray = (
            np.isnan(self.measured).any(axis=1)
            if self.measured.size
            else (np.zeros(self.stamp.size, dtype=bool))
        )
        return held

    @classmethod
    def from_estimates(
        cls,
        estimates: list[Estimate],
        channels: tuple[str, ...],
        nq: int,
        counters: dict[str, int],
        messages: list[str],
    ) -> BatchResult:
        """The same rows from `Estimate` objects (what `run_offline` returns)."""
        nan_c, nan_q = np.full(len(channels), np.nan), np.full(nq, np.nan)
        return cls(
            np.array([e.stamp for e in estimates], dtype=float),
            np.array([nan_c if e.measured is None else e.measured for e in estimates]).reshape(
                -1, len(channels)
            ),
            np.array([e.estimate for e in estimates]).reshape(-1, len(channels)),
            ["|".join(e.flags) for e in estimates],
            np.array([np.nan if e.encoder_stamp is None else e.encoder_stamp for e in estimates]),
            np.array([nan_q if e.joints is None else e.joints for e in estimates]).reshape(-1, nq),
            channels,
            counters,
            messages,
        )

    def to_estimates(self) -> list[Estimate]:
        """The same rows as `Estimate` objects (what `run_offline` returns)."""
        out = []
        held = self.held
        for k in range(self.stamp.size):
            flags = tuple(self.flags[k].split("|")) if self.flags[k] else ()
            if held[k]:
                out.append(
                    Estimate(
                        float(self.stamp[k]),
                        None,
                        self.estimate[k].copy(),
                        flags,
                        float(self.encoder_stamp[k]),
                        self.channels,
                    )
                )
            else:
                out.append(
                    Estimate(
                        float(self.stamp[k]),
                        self.measured[k].copy(),
                        self.estimate[k].copy(),
                        flags,
                        float(self.encoder_stamp[k]),
                        self.channels,
                        None if self.joints is None else self.joints[k].copy(),
                    )
                )
        return out


# ---- kinematics over arrays ------------------------------------------------------------------


def measured_errors(
    cell: Cell,
    chain: Chain,
    q: np.ndarray,
    p_ks: np.ndarray,
    quat_ks: np.ndarray | None,
    direction: np.ndarray | None = None,
) -> np.ndarray:
    """`kinematics.measured_error` for N samples at once: (N, 6), or (N, 3) without
    orientation. `quat_ks` (N, 4) unit quaternions, scalar first."""
    q = corrected_joint_arrays(cell, q, direction)
    # everything in the tracker frame k: T_kt = T_bk^-1 T_bt(q), then T_ts = T_kt^-1 T_ks
    R_kt, p_kt = chain.flange_frames(
        q, head=cell.T_bk.inverse().homogeneous, tail=cell.T_nt.homogeneous
    )  # (3, 3, N), (3, N)
    d = np.asarray(p_ks, dtype=float).T - p_kt
    p_ts = R_kt[0] * d[0] + R_kt[1] * d[1] + R_kt[2] * d[2]  # R_kt^T (p_ks - p_kt)
    out = np.empty((q.shape[0], 3 if quat_ks is None else 6))
    out[:, :3] = p_ts.T
    if quat_ks is None:
        return out
    R_ks = quaternion_matrices(np.asarray(quat_ks, dtype=float))
    out[:, 3:] = log3_many(transposed_times(R_kt, R_ks))
    return out


def corrected_joint_arrays(
    cell: Cell, q: np.ndarray, direction: np.ndarray | None = None
) -> np.ndarray:
    """`kinematics.corrected_joints` for N samples (N, nq); q itself without corrections."""
    q = np.atleast_2d(np.asarray(q, dtype=float))
    corr = cell.corrections
    if corr is None:
        return q
    tau = None
    if np.any(corr.compliance) and cell.nominal_model is not None:
        from pinocchio import computeGeneralizedGravity

        tau = np.array(
            [computeGeneralizedGravity(cell.nominal_model, cell.gravity_data, qi) for qi in q]
        )
    return np.asarray(corr.joint_angles(q, tau, direction))


def tool_frames(cell: Cell, chain: Chain, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`kinematics.tool_pose` for N samples: T_bt as rotations (3, 3, N) and positions
    (3, N), on the identified model when the cell has one (in chunks that stay in cache)."""
    q = corrected_joint_arrays(cell, q)
    n = q.shape[0]
    R, p = np.empty((3, 3, n)), np.empty((3, n))
    tail = cell.T_nt.homogeneous
    for lo in range(0, n, CHUNK):
        rows = slice(lo, lo + CHUNK)
        R[:, :, rows], p[:, rows] = chain.flange_frames(q[rows], tail=tail)
    return R, p


# ---- the linear recurrence -------------------------------------------------------------------


def first_order_recursion(
    x0: np.ndarray, b: np.ndarray, c: np.ndarray, out: np.ndarray | None = None
) -> np.ndarray:
    """x_k = b_k x_{k-1} + c_k for k = 0..n-1 (rows), from x0: c (n, C); b (n, C), or (n, 1)
    for one factor shared by every channel. Written into `out` (n, C) when given (a view
    too, e.g. rows of a column-major table), which is returned.

    Blocks of about sqrt(n): within each block from zero for all blocks at once, then the
    block ends carried through in order, then every row gets its carry times the block's
    running product. No product is divided by, so nothing overflows (an underflowed product
    is a carry that really has decayed to nothing)."""
    n = c.shape[0]
    size, blocks = recursion_blocks(n)
    return blocked_recursion(
        x0, blocked(b, size, blocks, 1.0), blocked(c, size, blocks, 0.0), n, out
    )


def recursion_blocks(n: int) -> tuple[int, int]:
    """(rows per block, blocks) for `first_order_recursion` over n rows."""
    size = max(16, math.isqrt(n))
    return size, -(-n // size)


def blocked(rows: np.ndarray, size: int, blocks: int, pad: float) -> np.ndarray:
    """rows (n, F) as (position in block, F, block), contiguous, the last block padded with
    `pad`: each step of the recursion then reads and writes every block's row at that
    position in contiguous runs, a factor shared by the channels too."""
    n, width = rows.shape
    out = np.empty((size, width, blocks))
    by_block = out.transpose(2, 0, 1)  # (block, position, F): a view of `out`
    full = n // size
    by_block[:full] = rows[: full * size].reshape(full, size, width)
    if n > full * size:
        by_block[full, : n - full * size] = rows[full * size :]
        by_block[full, n - full * size :] = pad
    return out


def blocked_recursion(
    x0: np.ndarray, factors: np.ndarray, local: np.ndarray, n: int, out: np.ndarray | None
) -> np.ndarray:
    """`first_order_recursion` over `blocked` inputs: `factors` (b; 1 or C of them) and
    `local` (c), which becomes the solution from zero inside each block."""
    size, channels, blocks = local.shape
    scratch = np.empty((channels, blocks))
    for k in range(1, size):
        np.multiply(factors[k], local[k - 1], out=scratch)
        local[k] += scratch
    product = np.multiply.accumulate(factors, axis=0)  # the running product inside each block
    carry = _block_carries(x0, product[-1], local[-1])  # the state entering each block
    local += product * carry[None, :, :]
    if out is None:
        out = np.empty((n, channels))
    full = n // size
    # copy=False: a view of `out` or an error, never a copy that would be written in vain
    by_block = out[: full * size].reshape(full, size, channels, copy=False)
    by_block[...] = local[:, :, :full].transpose(2, 0, 1)
    if n > full * size:
        out[full * size :] = local[: n - full * size, :, full]
    return out


def _block_carries(x0: np.ndarray, ends: np.ndarray, solved: np.ndarray) -> np.ndarray:
    """The state entering each block: x0, then state = (block's product) * state + (its
    solution from zero at its end), block after block. On Python floats, channel by channel
    (the same roundings as numpy's, a tenth of the cost on a few hundred short rows)."""
    channels, blocks = solved.shape
    carry = np.empty((channels, blocks))
    shared = ends.shape[0] == 1
    for ch in range(channels):
        state = float(x0[ch])
        column = []
        for factor, end in zip(
            ends[0 if shared else ch].tolist(), solved[ch].tolist(), strict=True
        ):
            column.append(state)
            state = factor * state + end
        carry[ch] = column
    return carry


# ---- the estimator's bookkeeping -------------------------------------------------------


def _merge_counts(enc_t: np.ndarray, trk_t: np.ndarray) -> np.ndarray:
    """For each tracker sample, how many encoder samples the time-stamp merge (encoder first
    on ties, as `run_offline`) puts before it."""
    if enc_t.size == 0:
        return np.zeros(trk_t.size, dtype=np.int64)
    if np.all(np.isfinite(enc_t)) and np.all(np.diff(enc_t) >= 0):
        # the merge takes encoders while e <= t; NaN tracker stamps take all that are left
        counts: np.ndarray = np.searchsorted(enc_t, trk_t, side="right")
        return np.maximum.accumulate(counts) if counts.size else counts
    out = np.empty(trk_t.size, dtype=np.int64)
    e = enc_t.tolist()
    i = 0
    for j, tj in enumerate(trk_t.tolist()):
        while i < len(e) and not e[i] > tj:
            i += 1
        out[j] = i
    return out


def _merged_order(enc_t: np.ndarray, trk_t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each encoder and each tracker sample's position in the time-stamp merge."""
    m, n = enc_t.size, trk_t.size
    if m and n and _finite_and_sorted(trk_t) and _finite_and_sorted(enc_t):
        # both sorted: the few encoder stamps searched among the many tracker stamps, and
        # the other way round counted from that (fewer binary searches: docs/performance.md)
        ahead = np.searchsorted(trk_t, enc_t, side="left")  # trackers before each encoder
        before = _sorted_counts(ahead, n)  # encoders before each tracker (e <= t)
        return np.arange(m) + ahead, before + np.arange(n)
    before = _merge_counts(enc_t, trk_t)
    trk_pos = before + np.arange(n)
    enc_pos = np.arange(m) + np.searchsorted(before, np.arange(m), "right")
    return enc_pos, trk_pos


def _finite_and_sorted(t: np.ndarray) -> bool:
    return bool(np.all(t[1:] >= t[:-1])) and bool(np.isfinite(t[0]) and np.isfinite(t[-1]))


def _sorted_counts(positions: np.ndarray, n: int) -> np.ndarray:
    """For j in [0, n): how many of `positions` (integers in [0, n]) are <= j. With
    positions[i] = searchsorted(a, b[i], side) for sorted a (n,) and b, this is
    searchsorted(b, a, the other side) without its binary searches."""
    return _counts_up_to(positions, n)[1:]


@dataclass(frozen=True)
class _Accepted:
    """The samples the estimator accepts, in stamp order, and what it said about the rest."""

    E: np.ndarray  # encoder stamps (m,)
    Q: np.ndarray  # encoder joints (m, nq)
    E_pos: np.ndarray  # each one's position in the merged order (m,)
    T: np.ndarray  # tracker stamps (n,)
    P: np.ndarray  # positions (n, 3)
    quat: np.ndarray | None  # quaternions (n, 4), scalar first; None for a single reflector
    arrival: np.ndarray  # each tracker sample's position in the merged order (n,)
    counters: dict[str, int]
    messages: list[str]


def _count(counters: dict[str, int], name: str, n: int) -> None:
    if n:
        counters[name] = counters.get(name, 0) + int(n)


def _accept(
    enc_t: np.ndarray,
    enc_q: np.ndarray,
    trk_t: np.ndarray,
    trk_p: np.ndarray,
    trk_quat: np.ndarray | None,
) -> _Accepted:
    """Phase 1: the merged order of the two streams, which samples the estimator accepts
    (`rules`), and its counters and messages for the others (the newest MAX_MESSAGES, in
    arrival order)."""
    counters: dict[str, int] = {}
    # ---- merged order
    enc_pos, trk_pos = _merged_order(enc_t, trk_t)
    enc = encoder_verdicts(enc_t, enc_q)
    trk = tracker_verdicts(trk_t, trk_p, trk_quat)

    # ---- rejects: every one counted, the newest MAX_MESSAGES (in arrival order) in words
    for name, mask in (
        ("encoder_non_finite", ~enc.finite),
        ("encoder_duplicate", enc.duplicate),
        ("encoder_out_of_order", enc.out_of_order),
        ("tracker_non_finite", trk.non_finite),
        ("tracker_duplicate", trk.duplicate),
        ("tracker_out_of_order", trk.out_of_order),
        ("tracker_not_unit_quaternion", trk.not_unit),
    ):
        _count(counters, name, mask.sum())
        _count(counters, "rejected", mask.sum())
    enc_ok, accepted = enc.ok, trk.accepted
    enc_bad, trk_bad = np.flatnonzero(~enc_ok), np.flatnonzero(~accepted)
    bad_pos = np.concatenate([enc_pos[enc_bad], trk_pos[trk_bad]])
    newest_kept = np.sort(bad_pos)[-MAX_MESSAGES] if bad_pos.size > MAX_MESSAGES else -1
    rejects: list[tuple[int, str]] = []  # (event position, message)
    for i in enc_bad[enc_pos[enc_bad] >= newest_kept]:
        t = float(enc_t[i])
        if enc.finite[i]:
            _name, msg = encoder_stamp_problem(t, float(enc.newest[i]))
        else:
            _name, msg = encoder_non_finite(t)
        rejects.append((int(enc_pos[i]), msg))
    for j in trk_bad[trk_pos[trk_bad] >= newest_kept]:
        t = float(trk_t[j])
        if not trk.timely[j]:
            _name, msg = tracker_stamp_problem(t, float(trk.last[j]))
        else:
            what = NON_FINITE_VALUE if trk.non_finite_value[j] else not_unit_quaternion(trk.norm[j])
            _name, msg = tracker_value_problem(t, what)
        rejects.append((int(trk_pos[j]), msg))
    rejects.sort(key=lambda item: item[0])
    messages = [m for _p, m in rejects[-MAX_MESSAGES:]]

    if enc_ok.all():
        E, Q, E_pos = enc_t, enc_q, enc_pos
    else:
        E, Q, E_pos = enc_t[enc_ok], enc_q[enc_ok], enc_pos[enc_ok]
    _count(counters, "encoder_samples", E.size)
    every = bool(accepted.all())
    T = trk_t if every else trk_t[accepted]
    _count(counters, "tracker_samples", T.size)
    return _Accepted(
        E=E,
        Q=Q,
        E_pos=E_pos,
        T=T,
        P=trk_p if every else trk_p[accepted],
        # normalised once, where the measured error is formed (the estimator normalises
        # twice; the difference is a rounding)
        quat=trk_quat if trk_quat is None or every else trk_quat[accepted],
        arrival=trk_pos if every else trk_pos[accepted],
        counters=counters,
        messages=messages,
    )


@dataclass(frozen=True)
class _Bracket:
    """Phase 2: where each accepted tracker sample's encoder time falls among the accepted
    encoder samples (whatever the verdict on it later)."""

    target: np.ndarray  # the encoder time of each tracker sample (n,)
    first_cover: np.ndarray  # the first encoder sample at or after it (may be m)
    g0: np.ndarray  # the encoder samples to interpolate between (clipped to the stream)
    g: np.ndarray
    t0: np.ndarray  # their stamps
    t1: np.ndarray
    on_sample: np.ndarray  # the target is an encoder stamp


def _bracket(settings: EstimatorSettings, streams: _Accepted) -> _Bracket:
    E, n = streams.E, streams.T.size
    target = settings.delay.encoder_times(streams.T)
    if E.size and n and _finite_and_sorted(target):
        # E_i < target_j exactly when j >= the count of targets <= E_i (both sorted)
        first_cover = _sorted_counts(np.searchsorted(target, E, side="right"), n)
    else:
        first_cover = np.searchsorted(E, target, side="left")
    g = np.minimum(first_cover, max(E.size - 1, 0))
    g0 = np.maximum(g - 1, 0)
    t0, t1 = (E[g0], E[g]) if E.size else (np.zeros(n), np.zeros(n))
    on_sample = E[g] == target if E.size else np.zeros(n, dtype=bool)
    return _Bracket(target, first_cover, g0, g, t0, t1, on_sample)


def _resolution(
    settings: EstimatorSettings, streams: _Accepted, first_cover: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """When each tracker sample is resolved (its encoder data came, or it went stale), as
    what the estimator had seen by then: (encoder samples buffered, tracker intervals)."""
    n = streams.T.size
    never = np.iinfo(np.int64).max
    covered_at = np.full(n, never)
    if streams.E.size:
        covers = first_cover < streams.E.size
        covered_at[covers] = streams.E_pos[first_cover[covers]]
    stale_index = first_beyond(streams.T, settings.stale_after_s)
    stale_at = np.where(stale_index < n, streams.arrival[np.minimum(stale_index, n - 1)], never)
    ready = np.minimum(np.maximum(streams.arrival, covered_at), stale_at)
    resolved = np.maximum.accumulate(ready)
    # positions in the merged order are small integers: counting them gives searchsorted's
    # answers without its binary searches (a third of the batch path's own time on 600k rows)
    events = int(max(streams.arrival[-1], streams.E_pos[-1] if streams.E.size else 0)) + 1
    resolved_before = _counts_up_to(resolved, events)[streams.arrival]  # resolved < arrival
    waiting = np.arange(n) - np.minimum(np.arange(n), resolved_before)
    if waiting.max() >= MAX_PENDING:
        raise BatchUnsupportedError(f"more than {MAX_PENDING} tracker samples wait at once")
    at = np.minimum(resolved, events - 1) + 1  # "never": after every event
    have = _counts_up_to(streams.E_pos, events)[at]  # encoder samples buffered then
    seen = _counts_up_to(streams.arrival, events)[at] - 1  # tracker intervals by then
    return have, seen


def _counts_up_to(positions: np.ndarray, events: int) -> np.ndarray:
    """c[x + 1]: how many of `positions` (integers >= 0; from `events` on, "never") are <= x,
    for x in [-1, events): np.searchsorted(sorted positions, x, "right") by counting."""
    counts = np.zeros(events + 1, dtype=np.int64)
    counts[1:] = np.bincount(np.minimum(positions, events), minlength=events + 1)[:events]
    return np.cumsum(counts, out=counts)


@dataclass(frozen=True)
class _Verdicts:
    """Phase 4: which steps are held and why, and what each update saw."""

    reason: np.ndarray  # index into HELD_REASONS per tracker sample (0: not held)
    ok: np.ndarray  # not held: an update of the observer
    have: np.ndarray  # encoder samples buffered when each was resolved
    seen: np.ndarray  # tracker intervals seen by then
    flags: np.ndarray  # each row's flag (object array of str)


def _verdicts(settings: EstimatorSettings, streams: _Accepted, where: _Bracket) -> _Verdicts:
    have, seen = _resolution(settings, streams, where.first_cover)
    reason = held_reasons(
        settings, streams.E, have, where.target, (where.t0, where.t1, where.on_sample)
    )
    flags = np.array(HELD_REASONS, dtype=object)[reason]
    for code, name in enumerate(HELD_REASONS):
        if code:
            _count(streams.counters, f"held_{name}", int(np.sum(reason == code)))
    return _Verdicts(reason, reason == 0, have, seen, flags)


class _Rows:
    """The output rows, each written once, in its chunk (fresh pages cost). Column-major: an
    estimate file's columns are contiguous, so the writer's columns are views of these."""

    def __init__(self, n: int, nq: int, channels: int, keep_joints: bool) -> None:
        self.joints = np.empty((n, nq)) if keep_joints else None
        self.measured = np.empty((n, channels), order="F")
        self.estimate = np.empty((n, channels), order="F")


class _Kinematics:
    """Phase 3: each row's joints and measured error, chunk by chunk. They do not depend on
    whether the row ends up held, so they run on worker threads (numpy lets go of the GIL in
    its loops) while the caller works out which rows are held; in row chunks that stay in
    cache (whole-recording temporaries cost more in page faults than in arithmetic). Held
    rows' results are discarded."""

    def __init__(
        self, cell: Cell, streams: _Accepted, where: _Bracket, rows: _Rows, ranges: bool
    ) -> None:
        self.cell, self.streams, self.where, self.rows = cell, streams, where, rows
        self.chain = Chain(cell.robot)
        self.ranges = ranges  # hand back each chunk's joints for the range flags
        self.direction: np.ndarray | None = None  # backlash: the joints' directions

    def __call__(self, lo: int) -> np.ndarray | None:
        rows = slice(lo, lo + CHUNK)
        w_, s, out = self.where, self.streams, self.rows
        q0, q1 = s.Q[w_.g0[rows]], s.Q[w_.g[rows]]
        with np.errstate(invalid="ignore", divide="ignore"):
            w = (w_.target[rows] - w_.t0[rows]) / (w_.t1[rows] - w_.t0[rows])
            chunk = np.where(w_.on_sample[rows, None], q1, q0 + w[:, None] * (q1 - q0))
        chunk[~np.isfinite(chunk).all(axis=1)] = 0.0  # outside the encoder data: held
        out.measured[rows] = measured_errors(
            self.cell,
            self.chain,
            chunk,
            s.P[rows],
            None if s.quat is None else s.quat[rows],
            None if self.direction is None else self.direction[rows],
        )
        if out.joints is not None:
            out.joints[rows] = chunk
        return chunk if self.ranges else None


class _Observer:
    """Phase 6: the observer over the updates in order, in steps of at least OBSERVER_ROWS
    rows (the recursion's cost per call falls with its length); the state carries over."""

    def __init__(
        self,
        settings: EstimatorSettings,
        streams: _Accepted,
        verdicts: _Verdicts,
        channels: int,
    ) -> None:
        self.settings = settings
        self.ok = ok = verdicts.ok
        seen = verdicts.seen
        self.gains = np.asarray(settings.gains[:channels], dtype=float)
        # the recursion's factors per channel, or once for all when the gains are equal
        equal = bool(np.all(self.gains == self.gains[0]))
        self.factor_gains = self.gains[:1] if equal else self.gains
        self.upd = np.flatnonzero(ok)
        self.every_row = self.upd.size == ok.size
        self.dt = np.empty(0)
        if self.upd.size:
            caps = step_caps(settings, np.diff(streams.T), seen[self.upd[1:]])
            self.dt = np.minimum(np.diff(streams.T[self.upd]), caps)  # dt[k - 1]: to update k
        _count(streams.counters, "estimates", self.upd.size)
        self.state = np.zeros(channels)  # what rows before the first update carry
        self.done_updates = 0  # updates before the rows observed next
        self.observed = 0  # rows observed so far

    def run_to(self, hi: int, measured: np.ndarray, estimate: np.ndarray) -> None:
        """The rows from those observed so far up to `hi`."""
        upd, settings = self.upd, self.settings
        lo, self.observed = self.observed, hi
        first = self.done_updates
        last = hi if self.every_row else int(np.searchsorted(upd, hi))
        if first == 0 and last > 0:
            m0 = measured[upd[0]]
            gains = self.gains
            if settings.start == "first":
                self.state = m0.copy()
            else:
                first_dt = 1.0 / settings.sample_rate_hz  # as if one period had passed
                self.state = -np.expm1(-gains * first_dt) * m0
            estimate[upd[0]] = self.state
            first = 1
        if last > first:
            self._updates(first, last, measured, estimate)
        if not self.every_row and upd.size:
            # a held row carries the state of the newest update before it (these rows' or
            # an earlier one's), zeros before the first update
            held_rows = lo + np.flatnonzero(~self.ok[lo:hi])
            newest_update = np.searchsorted(upd, held_rows) - 1
            estimate[held_rows] = estimate[upd[np.maximum(newest_update, 0)]]
            estimate[held_rows[newest_update < 0]] = 0.0
        self.done_updates = last

    def _updates(self, first: int, last: int, measured: np.ndarray, estimate: np.ndarray) -> None:
        """Updates first..last-1 (indices into `upd`) of the recursion, in place."""
        rows: slice | np.ndarray = slice(first, last)
        if not self.every_row:
            rows = self.upd[first:last]
            if rows[-1] - rows[0] == last - first - 1:  # no held row among them
                rows = slice(int(rows[0]), int(rows[-1]) + 1)
        n = last - first
        size, blocks = recursion_blocks(n)
        # a_k = 1 - exp(-L dt_k) once per distinct gain (usually one for every channel)
        dt = blocked(self.dt[first - 1 : last - 1, None], size, blocks, 0.0)
        alpha = -np.expm1(-self.factor_gains[:, None] * dt)
        local = blocked(measured[rows], size, blocks, 0.0)
        np.multiply(alpha, local, out=local)
        if isinstance(rows, slice):
            self.state = blocked_recursion(self.state, 1.0 - alpha, local, n, estimate[rows])[-1]
        else:
            block = blocked_recursion(self.state, 1.0 - alpha, local, n, None)
            estimate[rows] = block
            self.state = block[-1]
        self.state = np.array(self.state)  # not a view of `estimate`


def _finish_chunk(
    rows: slice,
    verdicts: _Verdicts,
    out: _Rows,
    chunk_joints: np.ndarray | None,
    ranges: CalibratedRanges,
    counters: dict[str, int],
) -> None:
    """Phase 5, per chunk once its kinematics are done: held rows emptied, range flags."""
    held = ~verdicts.ok[rows]  # every row when there is no encoder data (nothing computed)
    if held.any():
        out.measured[rows][held] = np.nan
        if out.joints is not None:
            out.joints[rows][held] = np.nan
    if not np.isfinite(out.measured[rows][~held]).all():
        raise BatchUnsupportedError("the kinematics gave a non-finite error")
    if chunk_joints is not None:
        outside = ~held & ranges.outside_rows(chunk_joints)
        verdicts.flags[rows][outside] = OUTSIDE_CALIBRATED_RANGE
        _count(counters, OUTSIDE_CALIBRATED_RANGE, int(outside.sum()))


def _check_supported(settings: EstimatorSettings) -> None:
    if settings.alignment != "interpolate":
        raise BatchUnsupportedError(f"alignment {settings.alignment!r} runs sample by sample")
    if settings.start not in ("zero", "first"):
        raise BatchUnsupportedError(f"observer start {settings.start!r}")


def _as_streams(
    nq: int,
    encoder_t: np.ndarray,
    encoder_q: np.ndarray,
    tracker_t: np.ndarray,
    tracker_p: np.ndarray,
    tracker_quat: np.ndarray | None,
) -> _Accepted:
    """Phase 1: the inputs as float arrays of their shapes, with the rejects taken out."""
    enc_t = np.asarray(encoder_t, dtype=float).reshape(-1)
    trk_t = np.asarray(tracker_t, dtype=float).reshape(-1)
    return _accept(
        enc_t,
        np.asarray(encoder_q, dtype=float).reshape(enc_t.size, nq),
        trk_t,
        np.asarray(tracker_p, dtype=float).reshape(trk_t.size, 3),
        None if tracker_quat is None else np.asarray(tracker_quat, dtype=float).reshape(-1, 4),
    )


def _empty_result(streams: _Accepted, nq: int) -> BatchResult:
    """No tracker sample was accepted: no rows, the rejects' counters and messages."""
    return BatchResult(
        np.empty(0),
        np.empty((0, 0)),
        np.empty((0, 0)),
        [],
        np.empty(0),
        np.empty((0, nq)),
        (),
        streams.counters,
        streams.messages,
    )


class _SharedChunks:
    """The kinematics chunks in row order, each computed once: by a worker thread from the
    first on while the calling thread decides the verdicts, and by the calling thread too
    whenever it waits for one (`result`). The calling thread's own work is about as long as
    the kinematics, so two threads share them at the end, and never three share two cores
    (docs/performance.md)."""

    def __init__(
        self,
        kinematics: Callable[[int], np.ndarray | None],
        starts: range,
        caller_helps: bool,
    ) -> None:
        self._kinematics = kinematics
        self._starts = starts
        self._caller_helps = caller_helps
        self._futures: list[Future[np.ndarray | None]] = [Future() for _ in starts]
        self._claimed = 0  # chunks before this one have a thread
        self._lock = threading.Lock()
        self._worker = threading.Thread(target=self._work, name="keo-batch", daemon=True)
        self._worker.start()

    def _claim(self) -> int | None:
        with self._lock:
            if self._claimed >= len(self._futures):
                return None
            self._claimed += 1
            return self._claimed - 1

    def _compute(self, index: int) -> None:
        future = self._futures[index]
        try:
            future.set_result(self._kinematics(self._starts[index]))
        except BaseException as exc:  # raised where the chunk is taken; never left pending
            future.set_exception(exc)

    def _work(self) -> None:
        while (index := self._claim()) is not None:
            self._compute(index)

    def result(self, index: int) -> np.ndarray | None:
        """Chunk `index`'s joints for the range flags (or None), once computed; the calling
        thread computes the next unclaimed chunks meanwhile."""
        future = self._futures[index]
        while self._caller_helps and not future.done():
            ahead = self._claim()
            if ahead is None:
                break
            self._compute(ahead)
        return future.result()

    def stop(self) -> None:
        """No chunk started after this; returns once the worker's chunk is done."""
        with self._lock:
            self._claimed = len(self._futures)
        self._worker.join()


def _run_chunks(
    cell: Cell,
    settings: EstimatorSettings,
    streams: _Accepted,
    where: _Bracket,
    out: _Rows,
    n_channels: int,
) -> _Verdicts:
    """Phases 3-5: the kinematics on a worker thread while the verdicts are decided, then
    chunk by chunk in order as they are done: held rows and range flags, and the observer.
    Fills `out`; returns the verdicts (the flags)."""
    n = streams.T.size
    corr = cell.corrections
    ranges = CalibratedRanges(corr)
    kinematics = _Kinematics(cell, streams, where, out, bool(ranges))
    starts = range(0, n, CHUNK)
    backlash = corr is not None and bool(np.any(corr.backlash))
    # compliance: Pinocchio's gravity per row on the cell's one data object, in Python; the
    # worker alone keeps that data to one thread
    compliance = corr is not None and bool(np.any(corr.compliance))
    chunks: _SharedChunks | None = None
    try:
        if streams.E.size and not backlash:
            chunks = _SharedChunks(kinematics, starts, caller_helps=not compliance)
        verdicts = _verdicts(settings, streams, where)
        if streams.E.size and backlash:  # the directions need the verdicts' timing
            kinematics.direction = directions(streams.E, streams.Q)[
                np.maximum(verdicts.have - 1, 0)
            ]
            chunks = _SharedChunks(kinematics, starts, caller_helps=not compliance)
        observer = _Observer(settings, streams, verdicts, n_channels)
        if not observer.upd.size:
            out.estimate.fill(0.0)
        for index, start in enumerate(starts):
            chunk_joints = None if chunks is None else chunks.result(index)
            hi = min(start + CHUNK, n)
            _finish_chunk(slice(start, hi), verdicts, out, chunk_joints, ranges, streams.counters)
            if hi - observer.observed >= OBSERVER_ROWS or hi == n:
                observer.run_to(hi, out.measured, out.estimate)
    finally:
        if chunks is not None:
            chunks.stop()
    return verdicts


def estimate_batch(
    cell: Cell,
    settings: EstimatorSettings,
    encoder_t: np.ndarray,
    encoder_q: np.ndarray,
    tracker_t: np.ndarray,
    tracker_p: np.ndarray,
    tracker_quat: np.ndarray | None,
    keep_joints: bool = True,
) -> BatchResult:
    """What `run_offline(Estimator(cell, settings), ...)` returns, as arrays (without the
    joints of each row unless `keep_joints`: an estimate file does not hold them).

    Phases: accept (rejects), bracket (where each encoder time falls), kinematics (worker
    threads), verdicts (when each sample is resolved and whether it is held), then chunk by
    chunk as the workers finish: held rows and range flags, and the observer in order."""
    _check_supported(settings)
    nq = cell.robot.nq
    streams = _as_streams(nq, encoder_t, encoder_q, tracker_t, tracker_p, tracker_quat)
    n = streams.T.size
    if n == 0:
        return _empty_result(streams, nq)
    channels = channels_for(tracker_quat is None)
    streams.counters["channels"] = len(channels)
    where = _bracket(settings, streams)
    out = _Rows(n, nq, len(channels), keep_joints)
    verdicts = _run_chunks(cell, settings, streams, where, out, len(channels))
    return BatchResult(
        stamp=streams.T,
        measured=out.measured,
        estimate=out.estimate,
        flags=verdicts.flags.tolist(),
        encoder_stamp=where.target,
        joints=out.joints,
        channels=channels,
        counters=streams.counters,
        messages=streams.messages,
    )
