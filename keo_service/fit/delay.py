"""The delay between the encoder and tracker streams, found from whatever motion was recorded.
No I/O.

While the tool moves at velocity v, reading the joints at t - d instead of the true t - d*
shifts the measured error by v (d - d*) (angular velocity for orientation). The error itself
changes only with the configuration, so we model it with smooth features of the joints
(1, sin q_j, cos q_j per channel) and fit, by linear least squares around the current guess,

    e(t; d) = F(q) a + v(t) delta + v(t) (t - t_ref) rho

then move the guess by -delta (Gauss-Newton, a few rounds). The standard errors come from
the residual, clustered in short blocks of time (see `_block_covariance`). If the motion
cannot separate delta from the configuration features (too little motion, a single
constant-velocity direction), the standard error is large and we refuse to give a number.
The online tracker, which fits short stretches of this, is fit/delay_online.py.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np

from keo_service.core.batch import CHUNK, tool_frames
from keo_service.core.chain import shared_chain
from keo_service.core.errors import KeoError
from keo_service.core.kinematics import Cell
from keo_service.core.rotations import log3_many, quaternion_matrices

VELOCITY_STEP_S = 0.005  # central differences for the tool's velocity, at least
VELOCITY_INTERVALS = 2.0  # ... and at least this many of the encoder's sample intervals
STATE_ROWS = 4 * CHUNK  # samples whose tool states are computed at once
MIN_SPEED = 0.005  # m/s: slower than this is "at rest"
LEVER_M = 1.0  # m per rad: how a turn counts in the tool's speed
MAX_SE_S = 0.002  # refuse when the delay's standard error is larger than this


class DelayNotIdentifiableError(KeoError):
    """The recorded motion cannot determine the delay; the message says why."""


@dataclass
class DelayFit:
    delay_s: float
    delay_se_s: float
    drift: float  # s/s; delay(t) = delay_s + drift (t - t_ref)
    drift_se: float
    t_ref: float
    drift_significant: bool
    residual_rms_moving: float
    residual_rms_rest: float
    samples: int
    moving_fraction: float
    explained: bool
    iterations: int
    window_delays_s: list[float] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    speed_rms: float = math.nan  # the tool's RMS speed over the fitted samples (m/s)
    turn_rms: float = math.nan  # its RMS angular speed (rad/s; nan: no orientation measured)


def _mad_sigma(x: np.ndarray) -> float:
    """The median absolute deviation scaled to a normal's sigma (what scipy.stats'
    median_abs_deviation(scale="normal") gives; scipy.stats costs the service seconds of
    start-up to import, and online delay tracking is on by default)."""
    return float(np.median(np.abs(x - np.median(x)))) * 1.482602218505602


def _interp_joints(enc_t: np.ndarray, enc_q: np.ndarray, t: np.ndarray) -> np.ndarray:
    return np.column_stack([np.interp(t, enc_t, enc_q[:, j]) for j in range(enc_q.shape[1])])


def _tool_states(
    cell: Cell, enc_t: np.ndarray, enc_q: np.ndarray, t: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Tool pose, linear and angular velocity (base frame) at encoder times t (central
    differences over VELOCITY_STEP_S), STATE_ROWS samples at a time: the three passes of
    kinematics and their temporaries for a whole recording would cost more in fresh pages
    than in arithmetic (every row is computed on its own, so the chunks change nothing).
    Within a chunk the three times (t, t - h, t + h) go through the interpolation and the
    kinematics as one stack of rows: one pass of calls instead of three, for the short
    stretches of the online fits."""
    chain = shared_chain(cell.robot)
    h = max(VELOCITY_STEP_S, VELOCITY_INTERVALS * _sample_interval(enc_t))
    n = t.size
    q0 = np.empty((n, enc_q.shape[1]))
    R, p = np.empty((3, 3, n)), np.empty((n, 3))
    v, w = np.empty((n, 3)), np.empty((n, 3))
    for lo in range(0, n, STATE_ROWS):
        rows = slice(lo, lo + STATE_ROWS)
        t_rows = t[rows]
        m = t_rows.size
        q3 = _interp_joints(enc_t, enc_q, np.concatenate([t_rows, t_rows - h, t_rows + h]))
        R3, p3 = tool_frames(cell, chain, q3)
        q0[rows] = q3[:m]
        R[:, :, rows] = R3[:, :, :m]
        p[rows] = p3[:, :m].T
        R_m, p_m = R3[:, :, m : 2 * m], p3[:, m : 2 * m]
        R_p, p_p = R3[:, :, 2 * m :], p3[:, 2 * m :]
        v[rows] = ((p_p - p_m) / (2 * h)).T
        w[rows] = log3_many(np.einsum("ian,kan->ikn", R_p, R_m)) / (2 * h)  # log3(R_p R_m^T)
    return q0, p, np.moveaxis(R, 2, 0), v, w


def _measured_base_errors(
    p_bt: np.ndarray, R_bt: np.ndarray, p_bs: np.ndarray, R_bs: np.ndarray | None
) -> np.ndarray:
    """Errors in the base frame: position p_bs - p_bt, orientation log3(R_bs R_bt^T)."""
    pos: np.ndarray = p_bs - p_bt
    if R_bs is None:
        return pos
    return np.hstack([pos, log3_many(np.einsum("nij,nkj->ikn", R_bs, R_bt))])


def _features(q: np.ndarray, p: np.ndarray, kind: str) -> np.ndarray:
    """Smooth models of the configuration-dependent error: of the joints (whole recordings)
    or, fewer parameters for short windows, linear in the tool position ("position" in the
    base frame, "tool" with the errors and velocities taken in the tool frame, where the
    tool's own calibration error is a constant: in the base frame it turns with the tool,
    which a model linear in the position leaves in the residual, correlated with the
    motion)."""
    ones = np.ones((q.shape[0], 1))
    if kind in ("position", "tool"):
        return np.hstack([ones, p - p.mean(axis=0)])
    return np.hstack([ones, np.sin(q), np.cos(q)])


BLOCK_S = 0.25  # residuals are taken as independent between blocks this long, not within


def _block_covariance(
    X: np.ndarray,
    resid: np.ndarray,
    t: np.ndarray,
    nch: int,
    bread: np.ndarray,
    jackknife: bool = True,
) -> tuple[np.ndarray, float]:
    """The coefficients' covariance with the samples clustered in blocks of BLOCK_S of time,
    all channels of a block together, and the block scores' own lag-1 autocorrelation
    inflating it; and how much larger that is than the per-row (heteroscedasticity-robust)
    covariance. Why blocks: every channel of a sample sees the same timing error (the
    tracker's stamp, the encoder stamps it is interpolated between), and a receipt-stamped
    encoder's jitter reaches all tracker samples between two of its stamps, so rows are
    correlated across channels and over tens of milliseconds; a per-row estimate that treats
    them as independent gave standard errors several times too small. Blocks of a quarter
    second hold that correlation; what is left between blocks (a slowly wrong error model)
    is measured by the scores' autocorrelation. The small-sample factor G/(G-1) keeps a
    stretch of few blocks from claiming too much."""
    n = t.size
    k = X.shape[1]
    if not np.all(np.isfinite(bread)):
        return np.full((k, k), np.inf), 1.0
    rows = (X * resid[:, None]).reshape(nch, n, k).sum(axis=0)  # per-sample scores
    hc = (X * (resid**2)[:, None]).T @ X
    block = np.floor((t - t[0]) / BLOCK_S).astype(np.int64)
    starts = np.flatnonzero(np.r_[True, np.diff(block) != 0])
    scores = np.add.reduceat(rows, starts, axis=0)
    g = scores.shape[0]
    meat = scores.T @ scores * (g / (g - 1) if g > 1 else math.inf)
    s0 = scores[:, 0] - scores[:, 0].mean()
    denom = float(s0 @ s0)
    rho = float(s0[1:] @ s0[:-1]) / denom if denom > 0 and g > 2 else 0.0
    rho = min(max(rho, 0.0), 0.9)
    cov = bread @ meat @ bread * ((1 + rho) / (1 - rho))
    if jackknife and k == 1 and g > 2:
        # the delete-one-block jackknife: a stretch whose information sits in a few blocks
        # (the motion ramping up from rest) has few effective clusters, where the sandwich
        # above claims too much; the jackknife carries each block's leverage
        x = X[:, 0]
        sxx_b = np.add.reduceat((x * x).reshape(nch, n).sum(axis=0), starts)
        sxy_b = np.add.reduceat((x * resid).reshape(nch, n).sum(axis=0), starts)
        sxx = float(sxx_b.sum())
        left = sxx - sxx_b
        if np.all(left > 0):
            # each block left out: the coefficient's change (the residual's own score)
            drop = -sxy_b / left
            jack = (g - 1) / g * float(np.sum((drop - drop.mean()) ** 2))
            cov[0, 0] = max(float(cov[0, 0]), jack * ((1 + rho) / (1 - rho)))
    per_row = float((bread @ hc @ bread)[0, 0])
    inflate = max(1.0, float(cov[0, 0]) / per_row) if per_row > 0 else 1.0
    return cov, inflate


def _refuse_stop_and_measure(enc_t: np.ndarray, trk_t: np.ndarray) -> None:
    """Static stop-and-measure data has no delay to see: refuse it in words rather than read
    the jumps between poses as motion."""
    if enc_t.size == trk_t.size and np.allclose(np.sort(enc_t), np.sort(trk_t), rtol=0, atol=1e-9):
        raise DelayNotIdentifiableError(
            "static stop-and-measure data (one encoder row per tracker row, at the same times): "
            "the robot stands still at every measurement, so there is no delay to see; record "
            "the streams while the robot moves"
        )


@dataclass
class _Round:
    """One Gauss-Newton round's linear fit over the stacked, partialled-out channels."""

    beta: np.ndarray  # delay correction (and drift correction)
    cov: np.ndarray
    resid: np.ndarray  # (nch * N,) channel after channel, in noise units
    scale: np.ndarray  # (nch,) each channel's noise
    moving: np.ndarray  # (N,) the tool faster than MIN_SPEED
    X_p: np.ndarray  # (nch * N, 1 or 2) the velocity columns, features partialled out
    y_p: np.ndarray  # (nch * N,) the errors, features partialled out
    nch: int
    inflate: float  # variance inflation for the residual's autocorrelation
    speed_rms: float  # m/s
    turn_rms: float  # the tool's RMS angular speed (rad/s; nan: a position-only tracker)
    spread_deg: float = 0.0  # the tool velocity's directions, 95 % within this of one, deg
    speed_change: float = 0.0  # the moving tool's speed: its 5-95 % range over its median
    rest: float = 0.0  # the share of the time the tool is at rest


def _linearised_round(
    cell: Cell,
    encoder: tuple[np.ndarray, np.ndarray],
    tracker: tuple[np.ndarray, np.ndarray, np.ndarray | None],
    enc_times: np.ndarray,
    t_ref: float,
    with_drift: bool,
    features: str,
) -> _Round:
    """The error's linear model around the current delay guess, fitted (encoder: times and
    joints; tracker: times, positions and rotations in the base frame)."""
    enc_t, enc_q = encoder
    trk_t, p_bs, R_bs = tracker
    q, p_bt, R_bt, v, w = _tool_states(cell, enc_t, enc_q, enc_times)
    err = _measured_base_errors(p_bt, R_bt, p_bs, R_bs)
    # a turn shows a delay too (in the orientation): one radian counts as one metre, as the
    # targets weigh a micrometre and a microradian alike (a wrist turning about a still tool
    # point was refused as "hardly moving")
    v_point = v
    motion = v if R_bs is None else np.hstack([v, w * LEVER_M])
    speed = np.linalg.norm(motion, axis=1)
    moving = speed > MIN_SPEED
    if moving.mean() < 0.05 or np.sqrt(np.mean(speed**2)) < 2 * MIN_SPEED:
        raise DelayNotIdentifiableError(
            f"the tool hardly moves (RMS speed {np.sqrt(np.mean(speed**2)) * 1e3:.1f} mm/s, "
            f"moving {100 * moving.mean():.0f} % of the time): a delay only shows while it "
            "moves; record motion with changes of speed or direction"
        )
    spread_deg, speed_change = _motion_variety(motion[moving])
    turn_rms = math.nan if R_bs is None else float(np.sqrt(np.mean(np.sum(w**2, axis=1))))
    vel = np.hstack([v, w]) if R_bs is not None else v
    if features == "tool":  # errors and velocities in the tool frame: R_bt^T x
        for part in (slice(0, 3), slice(3, 6))[: err.shape[1] // 3]:
            err[:, part] = np.einsum("nji,nj->ni", R_bt, err[:, part])
            vel[:, part] = np.einsum("nji,nj->ni", R_bt, vel[:, part])
    n, nch = err.shape
    # weight each channel group by its noise (median absolute first difference)
    scale = np.empty(nch)
    for c in range(nch):
        d1 = np.diff(err[:, c])
        scale[c] = max(_mad_sigma(d1) / math.sqrt(2), 1e-9)
    groups = [slice(0, 3)] + ([slice(3, 6)] if nch == 6 else [])
    for g in groups:
        scale[g] = np.median(scale[g])
    # partial out the configuration features (Frisch-Waugh-Lovell): each channel has its
    # own coefficients on the same features, so the projection is one per channel onto
    # span(F) (a block-diagonal design would hold nch^2 copies of F); the channels are
    # stacked in place, channel after channel
    Qf, _ = np.linalg.qr(_features(q, p_bt, features), mode="reduced")
    y_p = np.empty(nch * n)
    X_p = np.empty((nch * n, 2 if with_drift else 1))
    for c in range(nch):
        cols = [vel[:, c] / scale[c]]
        if with_drift:
            cols.append(vel[:, c] * (trk_t - t_ref) / scale[c])
        rows = slice(c * n, (c + 1) * n)
        for out, a in ((y_p, err[:, c] / scale[c]), (X_p, np.column_stack(cols))):
            out[rows] = a - Qf @ (Qf.T @ a)
    del Qf, q, p_bt, R_bt, w, vel, err
    beta, *_ = np.linalg.lstsq(X_p, y_p, rcond=None)
    resid = y_p - X_p @ beta
    try:
        bread = np.linalg.inv(X_p.T @ X_p)
    except np.linalg.LinAlgError:
        bread = np.full((X_p.shape[1], X_p.shape[1]), np.inf)
    cov, inflate = _block_covariance(X_p, resid, trk_t, nch, bread)
    # the speed a delay error is weighed at: the tool point's, unless only the tool turns
    point_rms = float(np.sqrt(np.mean(np.sum(v_point**2, axis=1))))
    speed_rms = point_rms if point_rms >= 2 * MIN_SPEED else float(np.sqrt(np.mean(speed**2)))
    return _Round(
        beta,
        cov,
        resid,
        scale,
        moving,
        X_p,
        y_p,
        nch,
        inflate,
        speed_rms,
        turn_rms,
        spread_deg,
        speed_change,
        1.0 - float(moving.mean()),
    )


def _motion_variety(motion: np.ndarray) -> tuple[float, float]:
    """What a delay is told apart by, measured on the moving samples' tool velocities (a turn
    scaled to metres as in the fit): how far their directions spread about the principal one
    (the 95th percentile of the angle, deg; a reversal along one line is no spread) and how
    much the speed changes (its 5-95 % range over its median)."""
    speed = np.linalg.norm(motion, axis=1)
    if speed.size < 2 or not np.all(speed > 0):
        return 0.0, 0.0
    unit = motion / speed[:, None]
    axis = np.linalg.svd(unit, full_matrices=False)[2][0]
    angle = np.degrees(np.arccos(np.clip(np.abs(unit @ axis), 0.0, 1.0)))
    lo, mid, hi = np.percentile(speed, [5.0, 50.0, 95.0])
    return float(np.percentile(angle, 95.0)), float((hi - lo) / mid)


def _judge_drift(
    last: _Round,
    trk_t: np.ndarray,
    drift: float,
    drift_se: float,
    with_drift: bool,
    check_windows: bool,
    notes: list[str],
) -> tuple[bool, float]:
    """Is the drift shown, and its standard error. A drift is claimed only when stretches of
    the recording show it beyond their own scatter (`_drift_from_windows`): the samples'
    standard error alone takes a delay that wanders with the load, or jumps, for a drift (a
    short recording of undrifted clocks "showed" hundreds of ppm; docs/timing-delay.md)."""
    if not with_drift:
        return False, drift_se
    claimed = abs(drift) > 3 * drift_se
    if not check_windows:
        if not claimed:
            notes.append(
                f"no significant clock drift ({drift * 1e6:.1f} +/- {drift_se * 1e6:.1f} ppm)"
            )
        return claimed, drift_se
    windows = _windows(last.X_p[:, 0], last.y_p, trk_t, last.nch)
    drift_se, note = _drift_from_windows(windows, trk_t, drift, drift_se, claimed)
    if note:
        notes.append(note)
    return not note, drift_se


def fit_delay(
    cell: Cell,
    enc_t: np.ndarray,
    enc_q: np.ndarray,
    trk_t: np.ndarray,
    trk_p: np.ndarray,
    trk_quat: np.ndarray | None,
    initial: float = 0.0,
    with_drift: bool = True,
    max_iterations: int = 6,
    features: str = "joints",
    check_windows: bool = True,
) -> DelayFit:
    """Least-squares delay (and drift) from recorded streams in the tracker frame."""
    _refuse_stop_and_measure(enc_t, trk_t)
    order = np.argsort(enc_t)
    enc_t, enc_q = enc_t[order], enc_q[order]
    trk_t, p_bs, R_bs = _tracker_in_base(cell, enc_t, trk_t, trk_p, trk_quat, initial)
    t_ref = float(np.mean(trk_t))
    delay, drift, iterations, last = _gauss_newton(
        cell,
        (enc_t, enc_q),
        (trk_t, p_bs, R_bs),
        initial,
        t_ref,
        with_drift,
        max_iterations,
        features,
    )
    se = float(math.sqrt(last.cov[0, 0])) if np.isfinite(last.cov[0, 0]) else math.inf
    drift_se = (
        float(math.sqrt(last.cov[1, 1])) if with_drift and np.isfinite(last.cov[1, 1]) else math.inf
    )
    if not se < MAX_SE_S:
        raise _not_separable(last, se, float(trk_t[-1] - trk_t[0]))
    notes: list[str] = []
    significant, drift_se = _judge_drift(
        last, trk_t, drift, drift_se, with_drift, check_windows, notes
    )
    # a constant delay (and drift) explains the data if separate stretches of time agree on it
    windows: list[tuple[float, float, float]] = []
    explained = True
    if check_windows:
        y = last.y_p - (last.X_p[:, 1:] @ last.beta[1:] if with_drift else 0.0)
        windows = _windows(last.X_p[:, 0], y, trk_t, last.nch)
        explained, spread_note = _consistent(windows, _sample_interval(enc_t))
        if not explained:
            notes.append(spread_note)
    rms_moving, rms_rest = _residual_rms(last)
    return DelayFit(
        window_delays_s=[delay - w[1] for w in windows],
        delay_s=delay,
        delay_se_s=se,
        drift=drift if significant else 0.0,
        drift_se=drift_se,
        t_ref=t_ref,
        drift_significant=significant,
        residual_rms_moving=rms_moving,
        residual_rms_rest=rms_rest,
        samples=int(trk_t.size),
        moving_fraction=float(last.moving.mean()),
        explained=explained,
        iterations=iterations,
        notes=notes,
        speed_rms=last.speed_rms,
        turn_rms=last.turn_rms,
    )


GUESS_MARGIN_S = 0.2  # tracker samples this close to the encoder stream's ends are left out


def _tracker_in_base(
    cell: Cell,
    enc_t: np.ndarray,
    trk_t: np.ndarray,
    trk_p: np.ndarray,
    trk_quat: np.ndarray | None,
    initial: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """The tracker samples the fit can use (finite, their joints inside the encoder stream at
    the initial guess, with a margin for the guess's steps), in the robot's base frame: times,
    positions (N, 3) and rotations (N, 3, 3; None for a position-only tracker)."""
    keep = np.all(np.isfinite(trk_p), axis=1) & np.isfinite(trk_t)
    if trk_quat is not None:
        keep &= np.all(np.isfinite(trk_quat), axis=1)
    margin = GUESS_MARGIN_S
    keep &= (trk_t - initial > enc_t[0] + margin) & (trk_t - initial < enc_t[-1] - margin)
    trk_t, trk_p = trk_t[keep], trk_p[keep]
    trk_quat = None if trk_quat is None else trk_quat[keep]
    if trk_t.size < 50:
        raise DelayNotIdentifiableError(
            f"only {trk_t.size} tracker samples overlap the encoder stream"
        )
    T_bk = cell.T_bk
    p_bs = trk_p @ T_bk.rotation.T + T_bk.translation
    R_bs = (
        None
        if trk_quat is None
        else np.einsum("ij,jkn->nik", T_bk.rotation, quaternion_matrices(trk_quat))
    )
    return trk_t, p_bs, R_bs


def _gauss_newton(
    cell: Cell,
    encoder: tuple[np.ndarray, np.ndarray],
    tracker: tuple[np.ndarray, np.ndarray, np.ndarray | None],
    initial: float,
    t_ref: float,
    with_drift: bool,
    max_iterations: int,
    features: str,
) -> tuple[float, float, int, _Round]:
    """Rounds of the linearised fit from the initial guess: the delay, the drift, how many
    rounds, and the last round (whose covariance and residual describe the result)."""
    trk_t = tracker[0]
    delay, drift = initial, 0.0
    iterations = 0
    last: _Round | None = None
    for _ in range(max_iterations):
        iterations += 1
        last = None  # the previous round's arrays go before this round's are made
        last = _linearised_round(
            cell,
            encoder,
            tracker,
            trk_t - (delay + drift * (trk_t - t_ref)),
            t_ref,
            with_drift,
            features,
        )
        # e(t; d) = e_true + v (d - d_true): the fitted coefficient is how far off we are
        step = float(last.beta[0])
        if not abs(step) <= GUESS_MARGIN_S:
            # a step beyond the margin would read joints outside the recording (a constant-
            # velocity stroke's round jumped seconds and was then refused as "hardly
            # moving"): the round's own standard error says why there is no delay
            break
        delay -= step
        if with_drift:
            drift -= float(last.beta[1])
        if abs(step) < 1e-7:
            break
    assert last is not None
    return delay, drift, iterations, last


ONE_DIRECTION_DEG = 5.0  # velocity directions within this of one: "along one direction"
STEADY_SPEED = 0.1  # a speed range within this share of the speed: "at constant speed"
NEVER_AT_REST = 0.05  # at rest less than this share of the time: "without rests"


def _not_separable(last: _Round, se: float, span_s: float) -> DelayNotIdentifiableError:
    """Why the motion gives no delay, with what was measured of it: a motion is told that it
    moves at constant velocity along one direction only when its velocity directions, its
    speed and its rests show so (a motion that turns and changes speed is not helped by that
    advice); otherwise what it had, and that the stretch is too short for the error model."""
    measured = (
        f"the tool's velocity within {last.spread_deg:.0f} deg of one direction, its speed "
        f"changing by {100 * last.speed_change:.0f} %, at rest {100 * last.rest:.0f} % of the "
        f"time over {span_s:.1f} s"
    )
    steady = (
        last.spread_deg < ONE_DIRECTION_DEG
        and last.speed_change < STEADY_SPEED
        and last.rest < NEVER_AT_REST
    )
    advice = (
        f"{measured}: a move at constant velocity along one direction cannot show a delay; "
        "include rests, changes of speed or of direction"
        if steady
        else f"{measured}: too little for this error model, a longer stretch (or recording) "
        "or larger changes of direction help"
    )
    return DelayNotIdentifiableError(
        f"the motion cannot separate a delay from a configuration-dependent error "
        f"(standard error {se * 1e3:.1f} ms > {MAX_SE_S * 1e3:.0f} ms, "
        f"{se * last.speed_rms * 1e3:.2f} mm at the tool's speed); {advice}"
    )


def _residual_rms(last: _Round) -> tuple[float, float]:
    """The position residual's RMS while moving and at rest (m; NaN where there is none)."""
    res = last.resid.reshape(last.nch, -1).T * last.scale  # back to metres / radians
    res_pos = np.linalg.norm(res[:, :3], axis=1)
    moving = last.moving
    rms_moving = float(np.sqrt(np.mean(res_pos[moving] ** 2))) if moving.any() else math.nan
    rms_rest = float(np.sqrt(np.mean(res_pos[~moving] ** 2))) if (~moving).any() else math.nan
    return rms_moving, rms_rest


WINDOWS = 6
PRACTICAL_SPREAD_S = 0.001
DRIFT_WINDOW_S = 5.0  # a drift is judged on windows this long (6 to 30 of them)
SHOWN_PPM = 100.0  # the drift the minimum span is stated for


def _windows(
    x: np.ndarray, y: np.ndarray, t: np.ndarray, nch: int
) -> list[tuple[float, float, float]]:
    """The delay correction fitted on each stretch of DRIFT_WINDOW_S (WINDOWS to 30 of them):
    (middle, value, se). The se is clustered in blocks of time within the window as the whole
    fit's, and at least the delete-one-block jackknife's (`_block_covariance`), as the online
    fits' are: a window whose information sits in a few blocks (a stroke's acceleration, the
    tool reversing) has few effective clusters, and the sandwich alone claimed too much there
    (constant delays were called "no constant delay"). The whole fit's inflation is not carried
    over: a delay that changes half-way inflates the whole fit's residual, not each window's."""
    n = t.size
    count = int(min(30, max(WINDOWS, (t[-1] - t[0]) // DRIFT_WINDOW_S)))
    bounds = np.linspace(t[0], t[-1] + 1e-9, count + 1)
    out = []
    for a, b in itertools.pairwise(bounds):
        inside = (t >= a) & (t < b)
        if inside.sum() < 20:
            continue
        xw, yw = x.reshape(nch, n)[:, inside], y.reshape(nch, n)[:, inside]
        xx = float(np.sum(xw * xw))
        if not xx > 0:
            continue
        est = float(np.sum(xw * yw)) / xx
        xf = np.zeros((nch, n))
        rf = np.zeros((nch, n))
        xf[:, inside], rf[:, inside] = xw, yw - est * xw
        cov, _ = _block_covariance(xf.reshape(-1, 1), rf.reshape(-1), t, nch, np.array([[1 / xx]]))
        if not np.isfinite(cov[0, 0]) or cov[0, 0] <= 0:
            continue
        out.append((0.5 * (a + b), est, math.sqrt(float(cov[0, 0]))))
    return out


def _shown_factor(windows: int) -> float:
    """How many standard errors show a drift judged on this many windows: 3 (99.73 %), as
    Student's t with windows - 2 degrees of freedom, since the slope's se is scaled by the
    windows' own scatter (with the few windows of a short recording a normal's 3 se claimed
    drifts of undrifted clocks; docs/timing-delay.md)."""
    from scipy.stats import t as student

    if windows < 4:
        return math.inf
    return float(student.ppf(SHOWN_PROBABILITY, windows - 2))


SHOWN_PROBABILITY = 0.99865  # one-sided: a drift beyond 3 sigma of a normal, either sign


def _drift_from_windows(
    windows: list[tuple[float, float, float]],
    t: np.ndarray,
    drift: float,
    drift_se: float,
    claimed: bool,
) -> tuple[float, str]:
    """The drift's standard error: the larger of the samples' (`drift_se`) and the recording's
    windows' (`_windows`: a weighted line through the windows' delays, its slope's se scaled by
    the windows' scatter about the line beyond their own se, chi^2 per degree of freedom when
    above one). And, for a drift not
    shown, a note with the smallest drift this recording can show (`_shown_factor` se) and the
    span that would show SHOWN_PPM (the slope's se falls as the span to the power 1.5 at a
    fixed window count and sample rate)."""
    span = float(t[-1] - t[0])
    if len(windows) < 4:
        return math.inf, (
            f"too short to show a clock drift ({span:.0f} s; a drift is judged on at least 4 "
            f"stretches of {DRIFT_WINDOW_S:g} s)"
        )
    m = np.array([w[0] for w in windows])
    v = -np.array([w[1] for w in windows])  # the window's delay against the fitted line (s)
    w = 1.0 / np.array([w[2] for w in windows]) ** 2
    A = np.column_stack([np.ones_like(m), m - m.mean()])
    cov_line = np.linalg.inv((A * w[:, None]).T @ A)
    coef = cov_line @ (A * w[:, None]).T @ v
    chi2 = float(np.sum(w * (v - A @ coef) ** 2))
    slope_se = math.sqrt(float(cov_line[1, 1]) * max(1.0, chi2 / (len(v) - 2)))
    # the drift is judged at the larger of the samples' and the windows' standard errors:
    # the note states that one, so the drift it prints is always within the floor it names
    se = max(drift_se, slope_se)
    k = _shown_factor(len(v))
    if claimed and abs(drift) > k * se:
        return se, ""
    note = (
        f"no clock drift shown: this {span:.0f} s recording is too short to show one below "
        f"{k * se * 1e6:.3g} ppm (the fit gives {drift * 1e6:.1f} +/- {se * 1e6:.1f} ppm, "
        f"the scatter of {len(v)} stretches counted)"
    )
    if k * se > SHOWN_PPM * 1e-6:
        needed = span * (k * se / (SHOWN_PPM * 1e-6)) ** (2 / 3)
        note += f"; about {needed:.0f} s of such motion would show {SHOWN_PPM:g} ppm"
    return se, note


def _sample_interval(t: np.ndarray) -> float:
    """The stream's median sample interval (s; 0 when it has fewer than two samples)."""
    return float(np.median(np.diff(t))) if t.size > 1 else 0.0


def _consistent(
    windows: list[tuple[float, float, float]], enc_interval_s: float
) -> tuple[bool, str]:
    """Whether the windows ((middle, value, se), about the fitted delay and drift) agree on one
    delay: statistically, at 0.1 %, against their scatter about the fit and against a step at
    any one instant (the two ways a delay changes during a recording: it wanders, or a path or
    an adapter changed; a step fitted as a drift leaves windows that fall before it and rise
    after it, which their scatter alone missed at the jackknife's se), and practically (by
    more than 1 ms, and by more than a tenth of the encoder's sample interval: a stream
    stamped on receipt moves each window's delay by a fraction of its interval)."""
    from scipy.stats import chi2

    mid = np.array([w[0] for w in windows])
    est = np.array([w[1] for w in windows])
    se = np.array([w[2] for w in windows])
    ok = np.isfinite(se) & (se > 0) & (se < 0.05)
    mid, est, se = mid[ok], est[ok], se[ok]
    if est.size < 3:
        return True, ""
    w = 1 / se**2
    mean = float(np.sum(w * est) / np.sum(w))
    stat = float(np.sum(((est - mean) / se) ** 2))
    p = float(chi2.sf(stat, est.size - 1))
    p_step, at = _step_test(mid, est, w)
    # within 1 ms a constant delay serves
    if min(p, p_step) >= 0.001 or np.ptp(est) < max(PRACTICAL_SPREAD_S, 0.1 * enc_interval_s):
        return True, ""
    why = (
        f"chi2 {stat:.0f} on {est.size - 1} dof"
        if p < 0.001
        else f"they step at {at:.1f} s (p = {p_step:.1g})"
    )
    return False, (
        f"no constant delay (and drift) explains these streams: stretches of the "
        f"recording disagree by up to {np.ptp(est) * 1e3:.2f} ms ({why}); the delay varies, or "
        "samples are stamped unevenly"
    )


def _step_test(mid: np.ndarray, est: np.ndarray, w: np.ndarray) -> tuple[float, float]:
    """Do the windows step? The weighted least squares of a line through them against a line
    and a step between any two windows (at least two on either side): the chi^2 the best step
    removes, its p value (1 degree of freedom) times the number of places tried (Bonferroni),
    and where (s). (1, nan) with fewer than 6 windows."""
    from scipy.stats import chi2

    if est.size < 6:
        return 1.0, math.nan

    def misfit(A: np.ndarray) -> float:
        Aw = A * w[:, None]
        coef = np.linalg.lstsq(Aw.T @ A, Aw.T @ est, rcond=None)[0]
        r = est - A @ coef
        return float(np.sum(w * r * r))

    line = np.column_stack([np.ones_like(mid), mid - mid.mean()])
    base = misfit(line)
    places = range(2, est.size - 1)
    gains = [base - misfit(np.column_stack([line, np.arange(est.size) >= k])) for k in places]
    best = int(np.argmax(gains))
    p = min(1.0, float(chi2.sf(max(gains[best], 0.0), 1)) * len(gains))
    k = list(places)[best]
    return p, 0.5 * float(mid[k - 1] + mid[k])


@dataclass
class ReferenceSegment:
    start: float
    end: float
    speed: float
    offset: float
    delay_s: float


def reference_method(
    cell: Cell,
    enc_t: np.ndarray,
    enc_q: np.ndarray,
    trk_t: np.ndarray,
    trk_p: np.ndarray,
    min_duration: float = 1.0,
) -> list[ReferenceSegment]:
    """The paper's t_o = e / v on each constant-velocity stretch (offset against the rest
    before it), with the joints read at the tracker stamps (no alignment)."""
    ok = np.all(np.isfinite(trk_p), axis=1)
    trk_t, trk_p = trk_t[ok], trk_p[ok]
    inside = (trk_t > enc_t[0] + 0.1) & (trk_t < enc_t[-1] - 0.1)
    trk_t, trk_p = trk_t[inside], trk_p[inside]
    if trk_t.size < 10:
        return []
    _q, p_bt, _R, v, _w = _tool_states(cell, enc_t, enc_q, trk_t)
    p_bs = trk_p @ cell.T_bk.rotation.T + cell.T_bk.translation
    err = p_bs - p_bt
    speed = np.linalg.norm(v, axis=1)
    fast = speed > 10 * MIN_SPEED
    may_start = speed >= 10 * MIN_SPEED
    segments: list[ReferenceSegment] = []
    i = 0
    n = trk_t.size
    while i < n:
        if not may_start[i]:
            nxt = np.flatnonzero(may_start[i:])
            if nxt.size == 0:
                break
            i += int(nxt[0])
        j = _stroke_end(v, fast, i, 0.05 * speed[i])
        if trk_t[j] - trk_t[i] >= min_duration:
            # the error changes along the stroke: compare with the rests on both sides
            before = (trk_t < trk_t[i] - 0.5) & (trk_t > trk_t[i] - 3.5) & (speed < MIN_SPEED)
            after = (trk_t > trk_t[j] + 0.5) & (trk_t < trk_t[j] + 3.5) & (speed < MIN_SPEED)
            rest_parts = [m for m in (before, after) if m.sum() > 10]
            if rest_parts:
                direction = np.mean(v[i : j + 1], axis=0)
                mean_speed = float(np.linalg.norm(direction))
                direction /= mean_speed
                rest_error = np.mean([np.mean(err[m], axis=0) for m in rest_parts], axis=0)
                offset = float((np.mean(err[i : j + 1], axis=0) - rest_error) @ direction)
                # tracker lagging (positive delay) makes the offset negative along the motion
                segments.append(
                    ReferenceSegment(
                        float(trk_t[i]), float(trk_t[j]), mean_speed, offset, -offset / mean_speed
                    )
                )
        i = j + 1
    return segments


def _stroke_end(v: np.ndarray, fast: np.ndarray, i: int, tolerance: float) -> int:
    """The last sample j >= i such that every sample in (i, j] moves fast with a velocity
    within `tolerance` of v[i]; searched a block at a time (strokes are thousands long)."""
    n = int(v.shape[0])
    lo = i + 1
    block = 256
    while lo < n:
        hi = min(n, lo + block)
        same = fast[lo:hi] & (np.linalg.norm(v[lo:hi] - v[i], axis=1) < tolerance)
        if not same.all():
            return lo + int(np.argmin(same)) - 1
        lo, block = hi, block * 2
    return n - 1
