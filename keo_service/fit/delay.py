"""The delay between the encoder and tracker streams, found from whatever motion was recorded.
No I/O.

While the tool moves at velocity v, reading the joints at t - d instead of the true t - d*
shifts the measured error by v (d - d*) (angular velocity for orientation). The error itself
changes only with the configuration, so we model it with smooth features of the joints
(1, sin q_j, cos q_j per channel) and fit, by linear least squares around the current guess,

    e(t; d) = F(q) a + v(t) delta + v(t) (t - t_ref) rho

then move the guess by -delta (Gauss-Newton, a few rounds). The standard errors come from the
residual, inflated for its autocorrelation. If the motion cannot separate delta from the
configuration features (too little motion, a single constant-velocity direction), the
standard error is large and we refuse to give a number.
"""

from __future__ import annotations

import collections
import dataclasses
import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TypeVar

import numpy as np

from keo_service.core.batch import CHUNK, tool_frames
from keo_service.core.chain import Chain
from keo_service.core.errors import KeoError
from keo_service.core.kinematics import Cell
from keo_service.core.rotations import log3_many, quaternion_matrices
from keo_service.fit.delay_trend import LevelAndRate, SteadyOrMoving
from keo_service.fit.stamp_lines import Anchor, moved

_T = TypeVar("_T")

VELOCITY_STEP_S = 0.005  # central differences for the tool's velocity
STATE_ROWS = 4 * CHUNK  # samples whose tool states are computed at once
MIN_SPEED = 0.005  # m/s: slower than this is "at rest"
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


def _mad_sigma(x: np.ndarray) -> float:
    """The median absolute deviation scaled to a normal's sigma (what scipy.stats'
    median_abs_deviation(scale="normal") gives; scipy.stats costs the service 1.7 s of
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
    than in arithmetic (every row is computed on its own, so the chunks change nothing)."""
    chain = Chain(cell.robot)
    h = VELOCITY_STEP_S
    n = t.size
    q0 = np.empty((n, enc_q.shape[1]))
    R, p = np.empty((3, 3, n)), np.empty((n, 3))
    v, w = np.empty((n, 3)), np.empty((n, 3))
    for lo in range(0, n, STATE_ROWS):
        rows = slice(lo, lo + STATE_ROWS)
        q0[rows] = _interp_joints(enc_t, enc_q, t[rows])
        R[:, :, rows], p_rows = tool_frames(cell, chain, q0[rows])
        p[rows] = p_rows.T
        R_m, p_m = tool_frames(cell, chain, _interp_joints(enc_t, enc_q, t[rows] - h))
        R_p, p_p = tool_frames(cell, chain, _interp_joints(enc_t, enc_q, t[rows] + h))
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
    motion; measured 50-100 us of bias on 5 s stretches of a UR10 turning its tool)."""
    ones = np.ones((q.shape[0], 1))
    if kind in ("position", "tool"):
        return np.hstack([ones, p - p.mean(axis=0)])
    return np.hstack([ones, np.sin(q), np.cos(q)])


def _effective_factor(residual: np.ndarray) -> float:
    """Variance inflation (1 + rho)/(1 - rho) for lag-1 autocorrelated residuals."""
    r = residual - residual.mean()
    denom = float(r @ r)
    if denom <= 0:
        return 1.0
    rho = float(r[1:] @ r[:-1]) / denom
    rho = min(max(rho, 0.0), 0.98)
    return (1 + rho) / (1 - rho)


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
    speed = np.linalg.norm(v, axis=1)
    moving = speed > MIN_SPEED
    if moving.mean() < 0.05 or np.sqrt(np.mean(speed**2)) < 2 * MIN_SPEED:
        raise DelayNotIdentifiableError(
            f"the tool hardly moves (RMS speed {np.sqrt(np.mean(speed**2)) * 1e3:.1f} mm/s, "
            f"moving {100 * moving.mean():.0f} % of the time): a delay only shows while it "
            "moves; record motion with changes of speed or direction"
        )
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
    del Qf, q, p_bt, R_bt, v, w, vel, err
    beta, *_ = np.linalg.lstsq(X_p, y_p, rcond=None)
    resid = y_p - X_p @ beta
    inflate = float(np.mean([_effective_factor(resid[c * n : (c + 1) * n]) for c in range(nch)]))
    # heteroscedasticity-robust (timing noise grows with speed), inflated for correlation
    try:
        bread = np.linalg.inv(X_p.T @ X_p)
        meat = (X_p * (resid**2)[:, None]).T @ X_p
        cov = bread @ meat @ bread * inflate
    except np.linalg.LinAlgError:
        cov = np.full((X_p.shape[1], X_p.shape[1]), np.inf)
    speed_rms = float(np.sqrt(np.mean(speed**2)))
    return _Round(beta, cov, resid, scale, moving, X_p, y_p, nch, inflate, speed_rms)


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
    keep = np.all(np.isfinite(trk_p), axis=1) & np.isfinite(trk_t)
    if trk_quat is not None:
        keep &= np.all(np.isfinite(trk_quat), axis=1)
    trk_t, trk_p = trk_t[keep], trk_p[keep]
    trk_quat = None if trk_quat is None else trk_quat[keep]
    order = np.argsort(enc_t)
    enc_t, enc_q = enc_t[order], enc_q[order]
    margin = 0.2
    inside = (trk_t - initial > enc_t[0] + margin) & (trk_t - initial < enc_t[-1] - margin)
    trk_t, trk_p = trk_t[inside], trk_p[inside]
    trk_quat = None if trk_quat is None else trk_quat[inside]
    if trk_t.size < 50:
        raise DelayNotIdentifiableError(
            f"only {trk_t.size} tracker samples overlap the encoder stream"
        )
    T_bk = cell.T_bk
    p_bs = trk_p @ T_bk.rotation.T + T_bk.translation
    # the tracker's rotations in the base frame (N, 3, 3)
    R_bs = (
        None
        if trk_quat is None
        else np.einsum("ij,jkn->nik", T_bk.rotation, quaternion_matrices(trk_quat))
    )
    t_ref = float(np.mean(trk_t))
    delay = initial
    drift = 0.0
    iterations = 0
    last: _Round | None = None
    for _ in range(max_iterations):
        iterations += 1
        last = None  # the previous round's arrays go before this round's are made
        last = _linearised_round(
            cell,
            (enc_t, enc_q),
            (trk_t, p_bs, R_bs),
            trk_t - (delay + drift * (trk_t - t_ref)),
            t_ref,
            with_drift,
            features,
        )
        # e(t; d) = e_true + v (d - d_true): the fitted coefficient is how far off we are
        step = float(last.beta[0])
        delay -= step
        if with_drift:
            drift -= float(last.beta[1])
        if abs(step) < 1e-7:
            break
    assert last is not None  # max_iterations >= 1
    beta, cov, resid, scale, moving = last.beta, last.cov, last.resid, last.scale, last.moving
    nch, X_p, y_p, inflate = last.nch, last.X_p, last.y_p, last.inflate
    se = float(math.sqrt(cov[0, 0])) if np.isfinite(cov[0, 0]) else math.inf
    drift_se = float(math.sqrt(cov[1, 1])) if with_drift and np.isfinite(cov[1, 1]) else math.inf
    res = resid.reshape(nch, -1).T * scale  # back to metres / radians
    res_pos = np.linalg.norm(res[:, :3], axis=1)
    rms_moving = float(np.sqrt(np.mean(res_pos[moving] ** 2))) if moving.any() else math.nan
    rms_rest = float(np.sqrt(np.mean(res_pos[~moving] ** 2))) if (~moving).any() else math.nan
    notes: list[str] = []
    if not se < MAX_SE_S:
        raise DelayNotIdentifiableError(
            f"the motion cannot separate a delay from a configuration-dependent error "
            f"(standard error {se * 1e3:.1f} ms > {MAX_SE_S * 1e3:.0f} ms); a move at constant "
            "velocity along one direction is not enough: include rests, changes of speed or of "
            "direction"
        )
    significant = with_drift and abs(drift) > 3 * drift_se
    if with_drift and not significant:
        notes.append(f"no significant clock drift ({drift * 1e6:.1f} +/- {drift_se * 1e6:.1f} ppm)")
    # a constant delay (and drift) explains the data if separate stretches of time agree on it
    windows: list[tuple[float, float]] = []
    explained = True
    if check_windows:
        windows = _window_delays(
            X_p[:, 0],
            y_p - (X_p[:, 1:] @ beta[1:] if with_drift else 0.0),
            trk_t,
            nch,
            float(inflate),
        )
        explained, spread_note = _consistent(windows)
        if not explained:
            notes.append(spread_note)
    return DelayFit(
        window_delays_s=[delay - w[0] for w in windows],
        delay_s=delay,
        delay_se_s=se,
        drift=drift if significant else 0.0,
        drift_se=drift_se,
        t_ref=t_ref,
        drift_significant=significant,
        residual_rms_moving=rms_moving,
        residual_rms_rest=rms_rest,
        samples=int(trk_t.size),
        moving_fraction=float(moving.mean()),
        explained=explained,
        iterations=iterations,
        notes=notes,
        speed_rms=last.speed_rms,
    )


WINDOWS = 6
PRACTICAL_SPREAD_S = 0.001


def _window_delays(
    x: np.ndarray, y: np.ndarray, t: np.ndarray, nch: int, inflate: float
) -> list[tuple[float, float]]:
    """The delay correction fitted on each of WINDOWS stretches of time: (value, se)."""
    n = t.size
    bounds = np.linspace(t[0], t[-1] + 1e-9, WINDOWS + 1)
    out = []
    for a, b in itertools.pairwise(bounds):
        rows = np.tile((t >= a) & (t < b), nch)[: x.size]
        xx = float(x[rows] @ x[rows])
        if xx <= 0 or rows.sum() < 20 * nch:
            continue
        est = float(x[rows] @ y[rows]) / xx
        r = y[rows] - est * x[rows]
        robust = float((x[rows] ** 2) @ (r**2)) / (xx * xx)
        out.append((est, math.sqrt(robust * inflate)))
    del n
    return out


def _consistent(windows: list[tuple[float, float]]) -> tuple[bool, str]:
    from scipy.stats import chi2

    if len(windows) < 3:
        return True, ""
    est = np.array([w[0] for w in windows])
    se = np.array([w[1] for w in windows])
    ok = np.isfinite(se) & (se > 0) & (se < 0.05)
    est, se = est[ok], se[ok]
    if est.size < 3:
        return True, ""
    w = 1 / se**2
    mean = float(np.sum(w * est) / np.sum(w))
    stat = float(np.sum(((est - mean) / se) ** 2))
    p = float(chi2.sf(stat, est.size - 1))
    # statistically and practically different: within 1 ms a constant delay serves
    if p >= 1e-3 or np.ptp(est) < PRACTICAL_SPREAD_S:
        return True, ""
    return False, (
        f"no constant delay (and drift) explains these streams: stretches of the "
        f"recording disagree by up to {np.ptp(est) * 1e3:.2f} ms (chi2 {stat:.0f} on "
        f"{est.size - 1} dof); the delay varies, or samples are stamped unevenly"
    )


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

    @property
    def described_t(self) -> float:
        return self.t if math.isnan(self.t_mid) else self.t_mid


@dataclass(frozen=True)
class DelayRefused:
    """A stretch without a delay: the counter it counts under and why, in words."""

    counter: str
    reason: str
    t: float = math.nan  # the stream time the stretch ends at (nan: not known)


class OnlineDelayTracker:
    """The delay found online from the motion, trusted only as far as it is known.

    Samples go into bounded buffers (on the event loop); when a stretch of clean data has
    gathered since the last fit (`span_s`, up to `max_span_s` while its fits are rough),
    the service takes that stretch (`snapshot`) and fits it off the loop (`measure`:
    `fit_delay` over that stretch only, so successive fits see disjoint data), then folds
    the result in on the loop (`combine`). A fit is accepted only when

    - the tool moved (`fit_delay` refuses otherwise: at rest nothing changes),
    - its standard error is small against what it changes at the tool's speed there:
      `se * v_rms <= max_position_se_m` (a delay only matters through `v * delay`), or the
      delay in use is not known that well yet (then a rougher fit still helps: it is
      weighted by its variance); and always `se <= max_se_s`,
    - it agrees with the running estimate (within `outlier_sigmas` combined standard
      errors), unless the next fit agrees with it too (then the delay really moved).

    The running estimate is a Kalman filter over the delay's level in two views
    (`SteadyOrMoving`): "steady", whose level walks (`steady_walk`), and "moving", whose
    level walks (`level_walk`) with a rate that walks too (`rate_walk`, relaxing to zero over
    `rate_relax_s`); the one that has been predicting the fits better gives the estimate.
    Each accepted fit says the delay at its stretch's middle, with the variance se^2 +
    tau^2, where tau^2 is the scatter of fits beyond their own standard errors (a fit's
    standard error cannot know how its stretch's error model fits the robot), from how far
    each fit lies off the line through its neighbours, at least `min_wander_s`^2. The delay
    the stamps need moves as the mapped clocks' floors move with the load and their drifts
    converge, often steadily (3-5 us/s for 10-20 s in the device-clock test), so an older
    fit says less about it now, and a steady walk is followed, not lagged. (An equal-weight
    mean of the last 8 fits lagged the walk by 20 s: 40-60 us behind; a mean weighted by
    age, 15-20 us at the end of a run.) The estimate is the level at the newest stretch's
    end, its standard error the filter's. The service
    slews the estimator's delay to it, never jumps, when it is known to `max_apply_m` at the
    tool's speed or is more than three standard errors away from the delay in use; otherwise
    (fits scattering widely, as when the robot's geometry makes an error the stretches'
    model does not hold) it is shown but not applied.

    Fits of stretches that end within `young_s` of the first samples or of a restart are
    provisional: a young clock mapping's stamps move while its drift converges (in the
    device-clock test the first 5 s fit lay 60-160 us below the delay the stamps needed from
    10 s on). So while young the stretches are shorter (`young_span_s`) and the newest fit
    alone is the delay, each replacing the one before (its stamps are the most settled),
    applied only when known to `max_apply_m` at the tool's speed; the first fit of a later
    stretch replaces them too. (With 5 s stretches averaged, the delay in use at 10 s after
    the start was 50 us short of what the settled stamps needed: 28 urad at that tool's
    turning speed.)

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
        span_s: float = 2.5,
        max_span_s: float = 10.0,
        young_span_s: float = 2.0,
        max_samples: int = 40_000,
        max_gap_s: float = 0.05,
        max_position_se_m: float = 2.5e-6,
        max_se_s: float = 2e-3,
        outlier_sigmas: float = 4.0,
        settle_s: float = 4.0,
        min_wander_s: float = 2e-6,
        restart_sigma_s: float = 50e-6,
        max_apply_m: float = 10e-6,
        steady_walk: float = 25e-12,
        level_walk: float = 4e-12,
        rate_walk: float = 1e-12,
        rate_relax_s: float = 30.0,
        rate_prior: float = 2e-6,
        young_s: float = 10.0,
    ) -> None:
        # fits run off the event loop: give them their own scratch data for gravity torques
        self.cell = (
            cell
            if cell.nominal_model is None
            else dataclasses.replace(cell, gravity_data=cell.nominal_model.createData())
        )
        self.span_s = span_s
        self.max_span_s = max(max_span_s, span_s)
        self._stretch_s = span_s  # the settled stretch now: lengthened while fits are rough
        self.young_span_s = young_span_s
        self.max_gap_s = max_gap_s
        self.max_position_se_m = max_position_se_m
        self.max_se_s = max_se_s
        self.outlier_sigmas = outlier_sigmas
        self.settle_s = settle_s
        self.min_wander_s = min_wander_s
        self.restart_sigma_s = restart_sigma_s
        self.max_apply_m = max_apply_m
        # (stamp, joints, device stamp or None)
        self._enc: collections.deque[tuple[float, np.ndarray, float | None]] = collections.deque(
            maxlen=max_samples
        )
        # (stamp, position, quaternion or None, device stamp or None)
        self._trk: collections.deque[tuple[float, np.ndarray, np.ndarray | None, float | None]] = (
            collections.deque(maxlen=max_samples)
        )
        # each mapped stream's newest sample on its clock mapping's line; the lines the
        # running estimate is expressed under; those of the stretch being fitted
        self._newest: dict[str, Anchor] = {}
        self._frame: dict[str, Anchor] = {}
        self._fitting_frame: dict[str, Anchor] | None = None
        self._start = -math.inf  # stream time from which samples count
        self.young_s = young_s
        self._young_until = math.nan  # fits of stretches ending before this are provisional
        self._provisional = 0  # how many of the fits kept are provisional
        self._sources: dict[str, tuple[int, int]] = {}  # stream -> (epoch, last seq)
        self._trend = SteadyOrMoving(
            LevelAndRate(steady_walk, 0.0, rate_relax_s, 0.0),
            LevelAndRate(level_walk, rate_walk, rate_relax_s, rate_prior),
        )
        # accepted settled fits (value, se, segment, stream time described): a segment ends
        # when a time base starts anew
        self._history: collections.deque[tuple[float, float, int, float]] = collections.deque(
            maxlen=32
        )
        self._segment = 0
        self._suspect: tuple[float, float, float] | None = None  # an outlier fit, to compare
        self.estimate: float | None = None  # the running estimate of the delay (s)
        self.se: float | None = None  # its standard error (s)
        self.applied_se: float | None = None  # that of the estimate last applied (s)
        self.applied: float | None = None  # the estimate last applied, under `_frame` (s)
        self._applied_t = math.nan  # the stream time it describes
        self._estimate_t = math.nan  # the stream time `estimate` describes
        self.counters: collections.Counter[str] = collections.Counter()
        self.last_result: str = "waiting for motion"

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
        line's drift (`JointSample.clock_drift`)."""
        self._source("encoder", t, epoch, seq)
        device = self._line("encoder", t, device_stamp, clock_drift)
        if flagged or t < self._start:
            self.counters["encoder_left_out"] += 1
            return
        q_arr = np.asarray(q, dtype=float)
        newer = not self._enc or t > self._enc[-1][0]
        if math.isfinite(t) and np.isfinite(q_arr).all() and newer:
            self._enc.append((t, q_arr, device))

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
        """One pose; a mapped one as in `add_encoder`."""
        self._source("tracker", t, epoch, seq)
        device = self._line("tracker", t, device_stamp, clock_drift)
        if flagged or t < self._start:
            self.counters["tracker_left_out"] += 1
            return
        p_arr = np.asarray(p, dtype=float)
        q_arr = None if quat is None else np.asarray(quat, dtype=float)
        finite = np.isfinite(p_arr).all() and (q_arr is None or np.isfinite(q_arr).all())
        if math.isfinite(t) and finite and (not self._trk or t > self._trk[-1][0]):
            self._trk.append((t, p_arr, q_arr, device))

    def _line(
        self, stream: str, t: float, device_stamp: float | None, drift: float | None
    ) -> float | None:
        """Keep a mapped stream's newest sample on its line (a stamp off the line comes
        without a drift); the device stamp to keep with the sample, None when the stream's
        stamps are not mapped by a line (a shared clock, receipt times)."""
        if device_stamp is None or not math.isfinite(device_stamp):
            return None
        if drift is not None and math.isfinite(drift) and math.isfinite(t):
            self._newest[stream] = Anchor(t, device_stamp, drift)
        return device_stamp if stream in self._newest else None

    def delay_now(self) -> float | None:
        """The delay to use now: the estimate last applied, carried along as the mapped
        streams' lines moved since the stretch it was fitted under (a tracker stamp that moved
        later needs a longer delay, an encoder stamp a shorter one; the move where the
        estimate describes). None before one was applied."""
        if self.applied is None:
            return None
        return self.applied + self._moved(self._newest, self._applied_t)

    def _moved(self, lines: dict[str, Anchor], at: float) -> float:
        """How far the delay the stamps need at stream time `at` moved from the running
        estimate's lines to these (0 for a stream not mapped by a line)."""
        frame = self._frame
        return moved(lines.get("tracker"), frame.get("tracker"), at) - moved(
            lines.get("encoder"), frame.get("encoder"), at
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
        if self._suspect is not None:
            value, se, t = self._suspect
            self._suspect = (value + self._moved(lines, t), se, t)
        if self.estimate is not None:
            self.estimate += self._moved(lines, self._estimate_t)
        if self.applied is not None:
            self.applied += self._moved(lines, self._applied_t)
        self._frame = dict(lines)

    def _source(self, stream: str, t: float, epoch: int, seq: int) -> None:
        known = self._sources.get(stream)
        if math.isnan(self._young_until) and math.isfinite(t):
            self._young_until = t + self.young_s  # the first samples: young clock mappings
        self._sources[stream] = (epoch, seq)
        # a seq going back is a restarted publisher: a new time base unless the publisher
        # says otherwise by its epoch (an adapter that went on on its saved clock mapping
        # keeps it); one that gives no epoch (0) says nothing
        if known is not None and (epoch != known[0] or (seq < known[1] and epoch == 0)):
            self.restart(t, f"the {stream} time base started anew")

    def restart(self, t: float, why: str) -> None:
        """A stream's time base started anew at stream time t: drop what came before."""
        self.applied = self.delay_now()  # as in use now; the new mapping's lines are new
        self._newest.clear()
        self._frame = {}
        self._fitting_frame = None
        self._enc.clear()
        self._trk.clear()
        self._trend.reset()
        self._provisional = 0
        self._suspect = None
        self._segment += 1
        if self.se is not None:  # the delay in use is less sure under the new mapping
            self.se = math.hypot(self.se, self.restart_sigma_s)
        if self.applied_se is not None:
            self.applied_se = math.hypot(self.applied_se, self.restart_sigma_s)
        if math.isfinite(t):
            self._start = t + self.settle_s
            self._young_until = t + self.young_s
        self.counters["restarts"] += 1
        self.last_result = f"restarted: {why}; fitting again after {self.settle_s:g} s"

    # ---- fits ---------------------------------------------------------------------------

    def due(self) -> bool:
        return bool(self._trk) and self._trk[-1][0] - self._trk[0][0] >= self._span()

    def _span(self) -> float:
        """The stretch to fit next: shorter while the clock mappings are young."""
        young = bool(self._trk) and self._trk[0][0] + self.young_span_s <= self._young_until
        return self.young_span_s if young else self._stretch_s

    def snapshot(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
        """Copies of the stretch to fit (call on the loop, then fit anywhere), its stamps
        under each stream's newest line, which the next `combine` takes the fit to be under;
        the stretch is consumed: the next fit sees only newer samples."""
        first = self._trk[0][0]
        trk = [s for s in self._trk if s[0] <= first + self._span()]
        end = trk[-1][0]
        enc = [s for s in self._enc if first - 1.0 <= s[0] <= end + 1.0]
        while self._trk and self._trk[0][0] <= end:
            self._trk.popleft()
        while self._enc and self._enc[0][0] < end - 1.0:
            self._enc.popleft()
        # the whole stretch under each stream's newest line (see fit/stamp_lines.py)
        self._fitting_frame = dict(self._newest)
        enc_t = self._on_line("encoder", [(s[0], s[2]) for s in enc])
        enc_q = np.array([s[1] for s in enc]) if enc else np.empty((0, 0))
        trk_t = self._on_line("tracker", [(s[0], s[3]) for s in trk])
        trk_p = np.array([s[1] for s in trk])
        quats = [s[2] for s in trk]
        trk_q = None if any(q is None for q in quats) else np.array(quats)
        return enc_t, enc_q, trk_t, trk_p, trk_q

    def _on_line(self, stream: str, stamps: list[tuple[float, float | None]]) -> np.ndarray:
        """The stamps (stamp, device stamp) of a stream under its newest line: a sample's
        device stamp carried by the line, its own stamp when it has none."""
        t = np.array([s for s, _ in stamps], dtype=float)
        anchor = self._newest.get(stream)
        if anchor is not None and t.size:
            device = np.array([math.nan if d is None else d for _, d in stamps])
            mapped = ~np.isnan(device)
            t[mapped] = anchor.at(device[mapped])
        return t

    def fit(
        self,
        window: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None],
        current: float,
    ) -> float | None:
        """Fit one stretch and fold it in: the running estimate if this fit moved it."""
        return self.combine(self.measure(window, current))

    def measure(
        self,
        window: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None],
        current: float,
    ) -> DelayMeasurement | DelayRefused:
        """The delay over one stretch, or why there is none. Runs anywhere (a worker
        thread): it reads the tracker's settings only and changes nothing."""
        enc_t, enc_q, trk_t, trk_p, trk_q = _covered(window, current, self.max_gap_s)
        if enc_t.size < 20 or trk_t.size < 50:
            return DelayRefused("fits_without_data", "not enough data in the stretch")
        # the error model of a short stretch: linear in the tool position, with the errors in
        # the tool frame (where the tool's own calibration error is constant) or in the base
        # frame (closer for a robot's geometric errors); the one that leaves less residual
        fits: list[DelayFit] = []
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
                        initial=current,
                        with_drift=False,
                        features=features,
                        # one stretch is one window; and scipy.stats, which the check
                        # imports, would cost the service seconds at its first fit
                        check_windows=False,
                    )
                )
            except DelayNotIdentifiableError as exc:
                reason = exc
        if not fits:
            return DelayRefused("fits_not_identifiable", str(reason), float(trk_t[-1]))
        fit = min(fits, key=lambda f: f.residual_rms_moving)
        middle = 0.5 * float(trk_t[0] + trk_t[-1])
        return DelayMeasurement(
            fit.delay_s, fit.delay_se_s, fit.speed_rms, float(trk_t[-1]), current, middle
        )

    def combine(self, found: DelayMeasurement | DelayRefused) -> float | None:
        """Accept or refuse one measurement (on the loop) and fold it into the running
        estimate: the estimate to apply, else None (and why, in `last_result`)."""
        lines, self._fitting_frame = self._fitting_frame, None
        if isinstance(found, DelayRefused):
            self._refused(found)
            return None
        self._move_to(lines)  # the fit is under the lines of its snapshot
        value, se, speed = found.delay_s, found.se_s, found.speed_rms
        provisional = found.t <= self._young_until
        if not provisional:  # young stretches have their own length
            self._fit_stretch(se * speed)
        said = f"{value * 1e6:.1f} +/- {se * 1e6:.1f} us at {speed * 1e3:.0f} mm/s"
        if not (math.isfinite(value) and math.isfinite(se) and se > 0):
            self.counters["fits_refused_imprecise"] += 1
            self.last_result = "kept: the fit gave no finite value"
            return None
        # welcome while the delay in use is provisional or not known to max_position_se_m at
        # this speed (as sure as it is now: the delay walks on since its newest fit); once it
        # is, only fits that are themselves that precise count
        se_now = self._se_at(found.t)
        known = not provisional and se_now is not None and se_now * speed <= self.max_position_se_m
        if se > self.max_se_s or (known and se * speed > self.max_position_se_m):
            self.counters["fits_refused_imprecise"] += 1
            self.last_result = (
                f"kept: fit {said} not precise enough ({se * speed * 1e6:.1f} um at that "
                f"speed; trusted below {self.max_position_se_m * 1e6:g} um)"
            )
            return None
        t_fit = found.described_t
        # provisional fits described stamps that have moved since: the newest replaces them,
        # a later stretch's first fit too (it is not held against them); after a restart the
        # first fit starts the filter
        fresh = provisional or self._provisional or not self._trend.started
        moved = None if fresh else self._outlier(value, se, t_fit)
        if moved is False:
            self.counters["fits_refused_outlier"] += 1
            self.last_result = f"kept: fit {said} {self.last_result}"
            return None
        self._suspect = None
        self._provisional = int(provisional)
        if not provisional:  # the scatter of fits is judged from settled mappings' only
            self._history.append((value, se, self._segment, t_fit))
        tau2 = self._wander2()  # with this fit: its own scatter counts against it too
        if fresh:
            self._trend.start(value, se * se + tau2, t_fit)
        else:
            if isinstance(moved, tuple):  # two in a row: the delay moved
                self._trend.start(moved[0], moved[1] ** 2 + tau2, moved[2])
            self._trend.update(value, se * se + tau2, t_fit)
        estimate, estimate_var = self._trend.predict(found.t)
        self.estimate, self.se = estimate, math.sqrt(estimate_var)
        self._estimate_t = found.t
        self.counters["fits_accepted"] += 1
        self.last_result = (
            f"fit {said}; delay {self.estimate * 1e6:.1f} +/- {self.se * 1e6:.1f} us "
            f"({self._trend.chosen}, {self._trend.rate * 1e6:+.1f} us/s; "
            f"scatter {math.sqrt(tau2) * 1e6:.1f} us"
            f"{', provisional' if provisional else ''})"
        )
        # applied when known well enough at this speed, or clearly better than the delay in
        # use; otherwise the fits scatter too much (an error the short stretches' model does
        # not hold, e.g. a robot's geometry) and the delay in use is left alone
        # a provisional fit is the delay alone, judged by its own standard error (the scatter
        # of fits is not known yet), and never as merely "better": replaced within seconds, a
        # rough one could only step the delay far the wrong way (a 2 s stretch of a robot with
        # geometry errors fitted 29.08 +/- 0.34 ms where 28.40 was right)
        current = found.current_s
        better = (
            not provisional
            and math.isfinite(current)
            and abs(self.estimate - current) > 3 * self.se
        )
        judged_se = se if provisional else self.se
        if judged_se * speed > self.max_apply_m and not better:
            self.counters["estimates_not_applied"] += 1
            self.last_result += f"; not applied ({judged_se * speed * 1e6:.0f} um at that speed)"
            return None
        self.applied_se = self.se
        self.applied, self._applied_t = self.estimate, self._estimate_t
        return self.delay_now()

    def _refused(self, found: DelayRefused) -> None:
        """Count a stretch without a delay; one too short to separate a delay at all (a
        settled one) lengthens the stretch, as a rough fit does."""
        if found.counter == "fits_not_identifiable" and not found.t <= self._young_until:
            self._fit_stretch(math.inf)
        self.counters[found.counter] += 1
        self.last_result = f"kept: {found.reason}"

    def _fit_stretch(self, precision_m: float) -> None:
        """The settled stretch as short as gives fits known to `max_position_se_m` at the
        tool's speed: twice as long after a rougher fit, up to `max_span_s`; half as long
        after one precise enough to stay so at half the length (a fit's standard error
        grows about as the length to the power -1.5), down to `span_s`. (2.5 s stretches
        follow the delay's walk, measured at 3-5 us/s; a robot whose geometry the
        stretches' linear error model does not hold needs 5-10 s for a fit worth taking.)"""
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
        self.last_result = (
            f"disagrees with {level * 1e6:.1f} +/- {spread * 1e6:.1f} us "
            "(one more like it and it is taken)"
        )
        return False

    def _se_at(self, t: float) -> float | None:
        """The running estimate's standard error at stream time t: grown by the walk since
        its newest fit. Judged against it, a new fit is neither refused as less precise than
        an estimate that has gone stale nor as an outlier from it (the delay the device-clock
        test needed walked 50 us in 30 s; fits against the unaged estimate were refused four
        times in a row, the delay in use 30 us behind)."""
        if not self._trend.started:
            return self.se
        return math.sqrt(self._trend.predict(t)[1])

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

    def forget(self) -> None:
        """The delay was set by hand (a reload): start the running estimate afresh."""
        self._trend.reset()
        self._provisional = 0
        self._suspect = None
        self._frame = {}
        self.estimate = self.se = self.applied_se = self.applied = None


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
    keep = inside & (enc_t[k] - enc_t[k - 1] <= max_gap_s)
    return enc_t, enc_q, trk_t[keep], trk_p[keep], None if trk_q is None else trk_q[keep]
