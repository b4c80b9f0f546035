"""The estimator over whole recordings at once: the same output as feeding `Estimator` one
sample at a time in time-stamp order (`run_offline`), computed with array operations.

Streaming semantics, restated for arrays (see `estimator.py` for the one-sample version):

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
import os
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from keo_service.core.chain import Chain
from keo_service.core.errors import KeoError
from keo_service.core.estimator import (
    DIRECTION_DEADBAND,
    MAX_MESSAGES,
    MAX_PENDING,
    NON_FINITE_VALUE,
    OUTSIDE_CALIBRATED_RANGE,
    UNIT_QUATERNION_TOLERANCE,
    Estimate,
    encoder_non_finite,
    encoder_stamp_problem,
    not_unit_quaternion,
    tracker_stamp_problem,
)
from keo_service.core.kinematics import Cell, channels_for
from keo_service.core.rotations import log3_many, quaternion_matrices, transposed_times
from keo_service.core.settings import EstimatorSettings, encoder_capacity

__all__ = ["BatchResult", "BatchUnsupportedError", "estimate_batch", "measured_errors"]

RECENT_INTERVALS = 64  # the estimator's window of tracker intervals for the step cap
CAP_REFRESH = 16  # ... refreshed every this many intervals
CAP_MIN_INTERVALS = 8
CHUNK = 8192  # rows per pass of the kinematics
KINEMATICS_THREADS = min(2, os.cpu_count() or 1)
OBSERVER_ROWS = 8 * CHUNK  # rows per step of the observer's recursion
MEDIAN_WINDOWS = 1024  # step-cap windows sorted at once
# held reasons in the estimator's words; code 0 is "not held"
HELD_REASONS = ("", "encoder_stale", "encoder_too_old", "encoder_gap")


class BatchUnsupportedError(KeoError):
    """This input needs the streaming estimator (the message says why)."""


@dataclass(frozen=True)
class BatchResult:
    """One row per estimate, in output order."""

    t: np.ndarray  # (n,)
    measured: np.ndarray  # (n, C); NaN where held
    estimate: np.ndarray  # (n, C)
    flags: list[str]  # "" or the flags joined by "|"
    encoder_t: np.ndarray  # (n,) the encoder time evaluated
    joints: np.ndarray | None  # (n, nq); NaN where held; None when not asked for
    channels: tuple[str, ...]
    counters: dict[str, int]
    messages: list[str]

    @property
    def held(self) -> np.ndarray:
        held: np.ndarray = (
            np.isnan(self.measured).any(axis=1)
            if self.measured.size
            else (np.zeros(self.t.size, dtype=bool))
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
            np.array([e.t for e in estimates], dtype=float),
            np.array([nan_c if e.measured is None else e.measured for e in estimates]).reshape(
                -1, len(channels)
            ),
            np.array([e.estimate for e in estimates]).reshape(-1, len(channels)),
            ["|".join(e.flags) for e in estimates],
            np.array([np.nan if e.encoder_t is None else e.encoder_t for e in estimates]),
            np.array([nan_q if e.joints is None else e.joints for e in estimates]).reshape(-1, nq),
            channels,
            counters,
            messages,
        )

    def to_estimates(self) -> list[Estimate]:
        """The same rows as `Estimate` objects (what `run_offline` returns)."""
        out = []
        held = self.held
        for k in range(self.t.size):
            flags = tuple(self.flags[k].split("|")) if self.flags[k] else ()
            if held[k]:
                out.append(
                    Estimate(
                        float(self.t[k]),
                        None,
                        self.estimate[k].copy(),
                        flags,
                        float(self.encoder_t[k]),
                        self.channels,
                    )
                )
            else:
                out.append(
                    Estimate(
                        float(self.t[k]),
                        self.measured[k].copy(),
                        self.estimate[k].copy(),
                        flags,
                        float(self.encoder_t[k]),
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


def first_order_recursion(x0: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """x_k = b_k x_{k-1} + c_k for k = 0..n-1 (rows), from x0; returns (n, C).

    Blocks of about sqrt(n): within each block from zero for all blocks at once, then the
    block ends carried through in order, then every row gets its carry times the block's
    running product. No product is divided by, so nothing overflows (an underflowed product
    is a carry that really has decayed to nothing)."""
    n, channels = c.shape
    if n == 0:
        return np.empty((0, channels))
    size = max(16, math.isqrt(n))
    blocks = -(-n // size)
    pad = blocks * size - n
    # (position in block, block, channel): each step below reads and writes contiguous rows
    bb = np.concatenate([b, np.ones((pad, channels))]).reshape(blocks, size, channels)
    cc = np.concatenate([c, np.zeros((pad, channels))]).reshape(blocks, size, channels)
    bb = np.ascontiguousarray(bb.transpose(1, 0, 2))
    local = np.ascontiguousarray(cc.transpose(1, 0, 2))  # becomes the from-zero solution
    product = bb  # becomes the running product of b inside each block
    scratch = np.empty((blocks, channels))
    for k in range(1, size):
        np.multiply(bb[k], local[k - 1], out=scratch)
        local[k] += scratch
        product[k] *= product[k - 1]
    carry = np.empty((blocks, channels))  # the state entering each block
    state = np.asarray(x0, dtype=float)
    for i in range(blocks):
        carry[i] = state
        state = product[-1, i] * state + local[-1, i]
    local += product * carry[None, :, :]
    out: np.ndarray = local.transpose(1, 0, 2).reshape(blocks * size, channels)[:n]
    return out


# ---- the estimator -------------------------------------------------------------------------


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


def _prior_max(t: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """For each sample, the largest stamp among earlier samples for which `counts` is True
    (-inf when none)."""
    masked = np.where(counts, t, -np.inf)
    prior = np.empty_like(masked)
    if masked.size:
        prior[0] = -np.inf
        prior[1:] = np.maximum.accumulate(masked)[:-1]
    return prior


def _first_beyond(t_acc: np.ndarray, limit: float) -> np.ndarray:
    """For each accepted tracker sample a, the first later b with t_b - t_a > limit (the
    estimator's own subtraction), or t_acc.size."""
    n = t_acc.size
    b = np.searchsorted(t_acc, t_acc + limit, side="right")
    np.maximum(b, np.arange(1, n + 1), out=b)
    # t_a + limit and t_b - t_a may round apart at the boundary: settle those few one by one
    unsettled = t_acc[b - 1] - t_acc > limit
    unsettled |= (b < n) & ~(t_acc[np.minimum(b, n - 1)] - t_acc > limit)
    for a in np.flatnonzero(unsettled).tolist():
        k = int(b[a])
        while k > a + 1 and t_acc[k - 1] - t_acc[a] > limit:
            k -= 1
        while k < n and not t_acc[k] - t_acc[a] > limit:
            k += 1
        b[a] = k
    return b


def _step_caps(settings: EstimatorSettings, intervals: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """The estimator's cap on each update's dt (`Estimator._max_step`), for updates that saw
    `seen` tracker intervals: max_dt_s until 8 were seen, then 3 x the median of the last 64,
    recomputed at the first such update and whenever the count is a multiple of 16."""
    caps = np.full(seen.size, settings.max_dt_s)
    valid = seen >= CAP_MIN_INTERVALS
    if not valid.any():
        return caps
    first = int(np.argmax(valid))
    recompute = valid & (seen % CAP_REFRESH == 0)
    recompute[first] = True
    where = np.flatnonzero(recompute)
    counts = seen[where]
    values = np.empty(where.size)
    full = counts >= RECENT_INTERVALS
    if full.any():
        starts = counts[full] - RECENT_INTERVALS
        every_window = sliding_window_view(intervals, RECENT_INTERVALS)
        if starts.size > 1 and (np.diff(starts) == CAP_REFRESH).all():  # the usual: a view
            windows = every_window[starts[0] :: CAP_REFRESH][: starts.size]
        else:
            windows = every_window[starts]
        medians = np.empty(windows.shape[0])
        for lo in range(0, windows.shape[0], MEDIAN_WINDOWS):  # sorted copies stay in cache
            rows = slice(lo, lo + MEDIAN_WINDOWS)
            medians[rows] = _sorted_median(np.sort(windows[rows]))
        values[full] = medians
    for k in np.flatnonzero(~full):
        values[k] = _sorted_median(np.sort(intervals[: counts[k]])[None, :])[0]
    values = np.minimum(settings.max_dt_s, 3.0 * values)
    last = np.maximum.accumulate(np.where(recompute, np.arange(seen.size), -1))
    rank = np.cumsum(recompute) - 1  # a recomputing update's index in `where`
    caps[valid] = values[rank[last[valid]]]
    return caps


def _sorted_median(rows: np.ndarray) -> np.ndarray:
    """np.median of each sorted row: the middle value, or (a + b) / 2 of the two middle values
    as median computes it (for an odd count that is (a + a) / 2 = a, exactly). A sort is 10x
    faster than median's partition on rows of 64."""
    k = rows.shape[1]
    out: np.ndarray = (rows[:, (k - 1) // 2] + rows[:, k // 2]) / 2.0
    return out


def _directions(t: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Each joint's direction of its last move after each accepted encoder sample."""
    out = np.zeros_like(q)
    if q.shape[0] < 2:
        return out
    step = np.diff(q, axis=0)
    dt = np.maximum(np.diff(t), 1e-6)
    moved = np.abs(step) > DIRECTION_DEADBAND * dt[:, None]
    rows = np.arange(1, q.shape[0])[:, None]
    last = np.maximum.accumulate(np.where(moved, rows, 0), axis=0)
    signs = np.zeros_like(q)
    signs[1:] = np.sign(step)
    out[1:] = np.take_along_axis(signs, last, axis=0)
    return out


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
    """The merged order of the two streams, which samples the estimator accepts, and its
    counters and messages for the others (the newest MAX_MESSAGES, in arrival order)."""
    counters: dict[str, int] = {}
    # ---- merged order
    before = _merge_counts(enc_t, trk_t)  # encoders ahead of each tracker sample
    trk_pos = before + np.arange(trk_t.size)
    enc_pos = np.arange(enc_t.size) + np.searchsorted(before, np.arange(enc_t.size), "right")

    # ---- encoder acceptance
    enc_finite = np.isfinite(enc_t) & np.isfinite(enc_q).all(axis=1)
    enc_newest = _prior_max(enc_t, enc_finite)
    enc_ok = enc_finite & (enc_t > enc_newest)
    enc_dup = enc_finite & (enc_t == enc_newest)
    enc_old = enc_finite & (enc_t < enc_newest)

    # ---- tracker acceptance (time first, then values)
    t_finite = np.isfinite(trk_t)
    values_finite = np.isfinite(trk_p).all(axis=1)
    norm = np.ones(trk_t.size)
    if trk_quat is not None:
        values_finite &= np.isfinite(trk_quat).all(axis=1)
        with np.errstate(invalid="ignore"):
            norm = np.sqrt(np.einsum("ij,ij->i", trk_quat, trk_quat))
    unit = ~(np.abs(norm - 1.0) > UNIT_QUATERNION_TOLERANCE)
    passing = t_finite & values_finite & unit
    last_t = _prior_max(trk_t, passing)
    dup = t_finite & (trk_t == last_t)
    old = t_finite & (trk_t < last_t)
    timely = t_finite & ~dup & ~old
    non_finite_value = timely & ~values_finite
    not_unit = timely & values_finite & ~unit
    accepted = timely & values_finite & unit

    # ---- rejects: every one counted, the newest MAX_MESSAGES (in arrival order) in words
    for name, mask in (
        ("encoder_non_finite", ~enc_finite),
        ("encoder_duplicate", enc_dup),
        ("encoder_out_of_order", enc_old),
        ("tracker_non_finite", ~t_finite | non_finite_value),
        ("tracker_duplicate", dup),
        ("tracker_out_of_order", old),
        ("tracker_not_unit_quaternion", not_unit),
    ):
        _count(counters, name, mask.sum())
        _count(counters, "rejected", mask.sum())
    enc_bad, trk_bad = np.flatnonzero(~enc_ok), np.flatnonzero(~accepted)
    bad_pos = np.concatenate([enc_pos[enc_bad], trk_pos[trk_bad]])
    newest_kept = np.sort(bad_pos)[-MAX_MESSAGES] if bad_pos.size > MAX_MESSAGES else -1
    rejects: list[tuple[int, str]] = []  # (event position, message)
    for i in enc_bad[enc_pos[enc_bad] >= newest_kept]:
        t = float(enc_t[i])
        if enc_finite[i]:
            _name, msg = encoder_stamp_problem(t, float(enc_newest[i]))
        else:
            _name, msg = encoder_non_finite(t)
        rejects.append((int(enc_pos[i]), msg))
    for j in trk_bad[trk_pos[trk_bad] >= newest_kept]:
        t = float(trk_t[j])
        if not timely[j]:
            _name, msg = tracker_stamp_problem(t, float(last_t[j]))
        else:
            what = NON_FINITE_VALUE if non_finite_value[j] else not_unit_quaternion(norm[j])
            msg = f"tracker sample at t={t!r}: {what[1]}"
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
    stale_index = _first_beyond(streams.T, settings.stale_after_s)
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


def _held_reasons(
    settings: EstimatorSettings,
    E: np.ndarray,
    have: np.ndarray,
    target: np.ndarray,
    bracket: tuple[np.ndarray, np.ndarray, np.ndarray],
) -> np.ndarray:
    """Interpolation's verdict per tracker sample, as an index into HELD_REASONS (0: none),
    from the encoder samples buffered when it was resolved; `bracket` is (t0, t1, on_sample)."""
    t0, t1, on_sample = bracket
    capacity = encoder_capacity(settings)
    reason = np.zeros(target.size, dtype=np.int8)
    newest = np.where(have > 0, E[np.maximum(have - 1, 0)] if E.size else 0.0, -np.inf)
    oldest = np.where(have > 0, E[np.maximum(have - capacity, 0)] if E.size else 0.0, np.inf)
    reason[(have == 0) | (target > newest)] = 1
    reason[(reason == 0) & (target < oldest)] = 2
    reason[(reason == 0) & ~on_sample & (t1 - t0 > settings.max_gap_s)] = 3
    reason[(reason == 0) & (target < newest - settings.buffer_s)] = 2
    return reason


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
    joints of each row unless `keep_joints`: an estimate file does not hold them)."""
    if settings.alignment != "interpolate":
        raise BatchUnsupportedError(f"alignment {settings.alignment!r} runs sample by sample")
    if settings.start not in ("zero", "first"):
        raise BatchUnsupportedError(f"observer start {settings.start!r}")
    nq = cell.robot.nq
    enc_t = np.asarray(encoder_t, dtype=float).reshape(-1)
    trk_t = np.asarray(tracker_t, dtype=float).reshape(-1)
    streams = _accept(
        enc_t,
        np.asarray(encoder_q, dtype=float).reshape(enc_t.size, nq),
        trk_t,
        np.asarray(tracker_p, dtype=float).reshape(trk_t.size, 3),
        None if tracker_quat is None else np.asarray(tracker_quat, dtype=float).reshape(-1, 4),
    )
    E, Q, T, P, quat = streams.E, streams.Q, streams.T, streams.P, streams.quat
    counters = streams.counters
    n = T.size
    if n == 0:
        return BatchResult(
            np.empty(0),
            np.empty((0, 0)),
            np.empty((0, 0)),
            [],
            np.empty(0),
            np.empty((0, nq)),
            (),
            counters,
            streams.messages,
        )
    channels = channels_for(tracker_quat is None)
    counters["channels"] = len(channels)

    # ---- where each sample's encoder time falls, and the kinematics there: they do not depend
    # on whether the sample ends up held, so they run on worker threads (numpy lets go of the
    # GIL in its loops) while this thread works out which samples are held; in row chunks
    # that stay in cache (whole-recording temporaries cost more in page faults than in
    # arithmetic). Held rows' results are discarded.
    target = settings.delay.encoder_times(T)
    first_cover = np.searchsorted(E, target, side="left")
    g = np.minimum(first_cover, max(E.size - 1, 0))
    g0 = np.maximum(g - 1, 0)
    t0, t1 = (E[g0], E[g]) if E.size else (np.zeros(n), np.zeros(n))
    on_sample = E[g] == target if E.size else np.zeros(n, dtype=bool)
    channel_count = len(channels)
    # each row written once, in its chunk: fresh pages cost
    joints = np.empty((n, nq)) if keep_joints else None
    # column-major: an estimate file's columns are contiguous, so the writer's columns are
    # views of these (no copies of the whole recording)
    measured = np.empty((n, channel_count), order="F")
    estimate = np.empty((n, channel_count), order="F")
    corr = cell.corrections
    chain = Chain(cell.robot)
    direction: np.ndarray | None = None  # backlash: the joints' directions, known below
    ranges = corr.map_ranges() if corr is not None else []
    spans = [(j, r) for j, r in enumerate(ranges) if r is not None]
    range_cols = [j for j, _r in spans]
    range_low = np.array([r[0] for _j, r in spans])
    range_high = np.array([r[1] for _j, r in spans])

    def kinematics(lo: int) -> np.ndarray | None:
        """The chunk's joints and measured errors; its joints back when the range flags
        need them."""
        rows = slice(lo, lo + CHUNK)
        q0, q1 = Q[g0[rows]], Q[g[rows]]
        with np.errstate(invalid="ignore", divide="ignore"):
            w = (target[rows] - t0[rows]) / (t1[rows] - t0[rows])
            chunk = np.where(on_sample[rows, None], q1, q0 + w[:, None] * (q1 - q0))
        chunk[~np.isfinite(chunk).all(axis=1)] = 0.0  # outside the encoder data: held
        measured[rows] = measured_errors(
            cell,
            chain,
            chunk,
            P[rows],
            None if quat is None else quat[rows],
            None if direction is None else direction[rows],
        )
        if joints is not None:
            joints[rows] = chunk
        return chunk if spans else None

    starts = range(0, n, CHUNK)
    backlash = corr is not None and bool(np.any(corr.backlash))
    # compliance: Pinocchio's gravity per row on the cell's one data object, in Python; one
    # worker keeps that data to one thread
    compliance = corr is not None and bool(np.any(corr.compliance))
    workers = 1 if compliance else KINEMATICS_THREADS
    pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="keo-batch")
    try:
        chunks_done: Iterator[np.ndarray | None] = iter([None] * len(starts))
        if E.size and not backlash:
            chunks_done = pool.map(kinematics, starts)

        # ---- when each sample is resolved, and interpolation's verdicts then
        have, seen = _resolution(settings, streams, first_cover)
        reason = _held_reasons(settings, E, have, target, (t0, t1, on_sample))
        ok = reason == 0
        if E.size and backlash:
            direction = _directions(E, Q)[np.maximum(have - 1, 0)]
            chunks_done = pool.map(kinematics, starts)
        flags = np.array(HELD_REASONS, dtype=object)[reason]
        for code, name in enumerate(HELD_REASONS):
            if code:
                _count(counters, f"held_{name}", int(np.sum(reason == code)))

        # ---- the observer's inputs over all updates
        gains = np.asarray(settings.gains[: len(channels)], dtype=float)
        upd = np.flatnonzero(ok)
        every_row = upd.size == n
        dt = np.empty(0)
        if upd.size:
            caps = _step_caps(settings, np.diff(T), seen[upd[1:]])
            dt = np.minimum(np.diff(T[upd]), caps)  # dt[k - 1] leads to update k
        else:
            estimate.fill(0.0)
        _count(counters, "estimates", upd.size)

        # ---- chunk by chunk as the workers finish: held rows emptied, range flags, and the
        # observer in order (in steps of OBSERVER_ROWS: the recursion's cost per call falls
        # with its length)
        state = np.zeros(channel_count)  # what rows before the first update carry
        done_updates = 0  # updates before the rows observed next
        observed = 0  # rows observed so far
        for start, chunk_joints in zip(starts, chunks_done, strict=True):
            hi = min(start + CHUNK, n)
            rows = slice(start, hi)
            held = ~ok[rows]  # every row when there is no encoder data (nothing computed)
            if held.any():
                measured[rows][held] = np.nan
                if joints is not None:
                    joints[rows][held] = np.nan
            if not np.isfinite(measured[rows][~held]).all():
                raise BatchUnsupportedError("the kinematics gave a non-finite error")
            if chunk_joints is not None:
                outside = ~held & np.any(
                    (chunk_joints[:, range_cols] < range_low)
                    | (chunk_joints[:, range_cols] > range_high),
                    axis=1,
                )
                flags[rows][outside] = OUTSIDE_CALIBRATED_RANGE
                _count(counters, OUTSIDE_CALIBRATED_RANGE, int(outside.sum()))
            if hi - observed < OBSERVER_ROWS and hi < n:
                continue
            lo, observed = observed, hi
            # the observer over these rows' updates; the state carries over
            first = done_updates
            last = hi if every_row else int(np.searchsorted(upd, hi))
            if first == 0 and last > 0:
                m0 = measured[upd[0]]
                if settings.start == "first":
                    state = m0.copy()
                else:
                    first_dt = 1.0 / settings.sample_rate_hz  # as if one period had passed
                    state = -np.expm1(-gains * first_dt) * m0
                estimate[upd[0]] = state
                first = 1
            if last > first:
                update_rows: slice | np.ndarray = (
                    slice(first, last) if every_row else upd[first:last]
                )
                alpha = -np.expm1(-gains[None, :] * dt[first - 1 : last - 1, None])
                block = first_order_recursion(state, 1.0 - alpha, alpha * measured[update_rows])
                estimate[update_rows] = block
                state = block[-1]
            if not every_row and upd.size:
                # a held row carries the state of the newest update before it (these rows'
                # or an earlier one's), zeros before the first update
                held_rows = lo + np.flatnonzero(~ok[lo:hi])
                newest_update = np.searchsorted(upd, held_rows) - 1
                estimate[held_rows] = estimate[upd[np.maximum(newest_update, 0)]]
                estimate[held_rows[newest_update < 0]] = 0.0
            done_updates = last
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
    return BatchResult(
        t=T,
        measured=measured,
        estimate=estimate,
        flags=flags.tolist(),
        encoder_t=target,
        joints=joints,
        channels=channels,
        counters=counters,
        messages=streams.messages,
    )
