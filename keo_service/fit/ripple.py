"""Periodic joint errors read off the residual: per joint, the periodogram of the residual
against that joint's angle, and the few significant sine/cosine terms. No I/O.

To first order the residual moves with a small angle error d_j(q_j) of joint j as
dr/dq_j * d_j(q_j), so a term a sin(w q_j) + b cos(w q_j) adds two columns,
(dr/dq_j) sin(w q_j) and (dr/dq_j) cos(w q_j). The periodogram of joint j at angular
frequency w (per rad of the joint's angle; the period is 2 pi / w) is how much of the
residual those two columns explain beyond what the model's own parameters (registration and
kept effects) already can, in units of the residual's variance: the least-squares
(Lomb-Scargle) periodogram, with the model's Jacobian projected out. Terms are taken greedily,
strongest first, while each explains more than SIGNIFICANCE residual variances (a 1 %
false-alarm level for the largest of the scanned frequencies of noise alone), at most
MAX_TERMS_PER_JOINT per joint. A period is scanned only if the joint's calibrated range holds
MIN_CYCLES of it: a longer one is a polynomial over the range, not a period the data show,
and would be extrapolated on nothing. Whether the terms are kept is the analysis's held-out
judgement (blocks and extrapolation bands), not this module's.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from keo_service.fit.model import Data, Model, numeric_jacobian

MIN_PERIOD_RAD = 0.12  # shortest period scanned
MAX_PERIOD_RAD = 1.6  # longest: the cyclic effect carries 1 and 2 per revolution
MIN_CYCLES = 2.0  # a period must fit this often into the joint's range
OVERSAMPLE = 5  # frequency steps per resolution element (2 pi / range)
MAX_TERMS_PER_JOINT = 3
MAX_TERMS = 9
MAX_POSES = 3000  # poses the periodogram reads at most (an even subset of larger data)
SIGNIFICANCE = 25.0  # explained / residual variance for a term to count (see module doc)


def _orth(A: np.ndarray) -> np.ndarray:
    Q, R = np.linalg.qr(A)
    keep = np.abs(np.diag(R)) > 1e-10 * max(1e-300, float(np.max(np.abs(np.diag(R)))))
    out: np.ndarray = Q[:, keep]
    return out


def find_terms(
    model: Model, x: np.ndarray, data: Data, tau: np.ndarray, noise: float
) -> tuple[list[tuple[int, float]], dict[str, Any]]:
    """The (joint, period) terms the residual's spectra show, and per joint its periodogram
    (periods, amplitude in rad, explained variance ratio) and the terms taken."""
    if data.n > MAX_POSES:  # the spectrum from an even subset: its cost grows with the rows
        rows = np.linspace(0, data.n - 1, MAX_POSES).round().astype(int)
        data, tau = data.subset(rows), tau[rows]
    r0 = model.residuals(x, data, tau)
    width = r0.size // data.n
    row_w = data.row_weights(width)
    w = np.ones(r0.size) if row_w is None else row_w
    # gross outliers must not make peaks: Huber weights at 3 noise sigmas
    w = w * np.sqrt(np.minimum(1.0, 3 * noise / np.maximum(np.abs(r0), 1e-300)))
    J = numeric_jacobian(lambda z: model.residuals(z, data, tau), x, r0) * w[:, None]
    Q = _orth(J)
    r = r0 * w
    r = r - Q @ (Q.T @ r)
    dof = max(1, r.size - Q.shape[1])
    grads = _joint_gradients(model, x, data, tau, r0, w)
    grids = _frequency_grids(data.q)
    terms: list[tuple[int, float]] = []
    spectra: dict[str, Any] = {}
    names = model.chain.robot.joint_names
    while len(terms) < MAX_TERMS:
        s2 = float(r @ r) / dof
        best: tuple[float, int, float] | None = None
        for j, omegas in grids.items():
            if sum(1 for t in terms if t[0] == j) >= MAX_TERMS_PER_JOINT:
                continue
            power, amp = _periodogram(r, Q, grads[j], data.q[:, j], omegas)
            ratio = power / s2
            name = names[j] if j < len(names) else f"joint_{j + 1}"
            entry = spectra.setdefault(
                name,
                {
                    "periods_rad": (2 * np.pi / omegas).tolist(),
                    "amplitude_mrad": (amp * 1e3).tolist(),
                    "explained_variance_ratio": ratio.tolist(),
                    "terms": [],
                },
            )
            del entry  # the first scan of each joint is its spectrum; later ones only choose
            k = int(np.argmax(ratio))
            if ratio[k] > SIGNIFICANCE and (best is None or ratio[k] > best[0]):
                best = (float(ratio[k]), j, float(omegas[k]))
        if best is None:
            break
        ratio_best, j, omega = best
        period = 2 * np.pi / omega
        terms.append((j, period))
        name = names[j] if j < len(names) else f"joint_{j + 1}"
        spectra[name]["terms"].append(
            {"period_rad": period, "per_revolution": omega, "explained_variance_ratio": ratio_best}
        )
        cols = _columns(grads[j], data.q[:, j], omega)
        cols = cols - Q @ (Q.T @ cols)
        Q = np.column_stack([Q, _orth(cols)])
        r = r - Q[:, -2:] @ (Q[:, -2:].T @ r)
    return terms, spectra


def _joint_gradients(
    model: Model, x: np.ndarray, data: Data, tau: np.ndarray, r0: np.ndarray, w: np.ndarray
) -> list[np.ndarray]:
    """Per joint (poses, width): the weighted residual's derivative by that joint's angle
    (one evaluation per joint: each pose depends on its own joints only)."""
    width = r0.size // data.n
    out = []
    h = 1e-6
    for j in range(model.chain.nq):
        q = data.q.copy()
        q[:, j] += h
        shifted = dataclasses.replace(data, q=q)
        g = (model.residuals(x, shifted, tau) - r0) / h
        out.append((g * w).reshape(data.n, width))
    return out


def _frequency_grids(q: np.ndarray) -> dict[int, np.ndarray]:
    """Per joint whose range holds MIN_CYCLES of a period in the scanned band: its angular
    frequencies (per rad), OVERSAMPLE steps per resolution element."""
    grids = {}
    for j in range(q.shape[1]):
        span = float(np.ptp(q[:, j]))
        longest = min(MAX_PERIOD_RAD, span / MIN_CYCLES)
        if longest <= MIN_PERIOD_RAD:
            continue
        step = 2 * np.pi / span / OVERSAMPLE
        grids[j] = np.arange(2 * np.pi / longest, 2 * np.pi / MIN_PERIOD_RAD + step, step)
    return grids


def _columns(grad: np.ndarray, qj: np.ndarray, omega: float) -> np.ndarray:
    """(rows, 2): the residual's change with a unit sine and cosine angle error of the joint."""
    out: np.ndarray = np.column_stack(
        [(grad * np.sin(omega * qj)[:, None]).ravel(), (grad * np.cos(omega * qj)[:, None]).ravel()]
    )
    return out


def _periodogram(
    r: np.ndarray, Q: np.ndarray, grad: np.ndarray, qj: np.ndarray, omegas: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per frequency the residual's sum of squares the two columns explain beyond Q's span,
    and the amplitude sqrt(a^2 + b^2) (rad) of the fitted term."""
    power = np.zeros(omegas.size)
    amp = np.zeros(omegas.size)
    for i, omega in enumerate(omegas):
        C = _columns(grad, qj, omega)
        C = C - Q @ (Q.T @ C)
        M = C.T @ C
        g = C.T @ r
        try:
            ab = -np.linalg.solve(M, g)
        except np.linalg.LinAlgError:
            continue
        power[i] = float(-g @ ab)
        amp[i] = float(np.hypot(*ab))
    return power, amp
