"""The delay between the streams as a candidate of `keo analyze`: fitted from the motion
(`fit.delay`), judged like every other effect on held-out poses. No I/O.

Apart from `fit.delay` so that the live service's delay tracker does not load the analysis'
model and fit."""

from __future__ import annotations

from typing import Any

import numpy as np

from keo_service.core.chain import Chain
from keo_service.core.kinematics import Cell
from keo_service.fit.analysis import KEEP_MARGIN, split
from keo_service.fit.delay import DelayFit, fit_delay
from keo_service.fit.model import Data, Model, fit, initial_registration, stats

DELAY_SAMPLES = 60_000  # tracker samples the delay fit uses at most (evenly thinned)


def fit_recording_delay(
    cell: Cell,
    enc_t: np.ndarray,
    enc_q: np.ndarray,
    trk_t: np.ndarray,
    trk_p: np.ndarray,
    trk_quat: np.ndarray | None,
    initial: float,
) -> DelayFit:
    """The delay (and drift) of a recording from its motion; a long recording is thinned to
    every k-th tracker sample (plenty for one delay and one drift). Raises
    `DelayNotIdentifiableError` when the motion cannot determine it."""
    k = max(1, trk_t.size // DELAY_SAMPLES)
    quat = None if trk_quat is None else trk_quat[::k]
    return fit_delay(cell, enc_t, enc_q, trk_t[::k], trk_p[::k], quat, initial=initial)


def judge_delay(
    chain: Chain, found: DelayFit, before: Data, after: Data, position_only: bool
) -> dict[str, Any]:
    """The delay's report entry: the registered nominal model fitted to the streams paired
    with the config's delay (`before`) and with the found one (`after`), compared held out;
    `kept` if pairing with it lowers the held-out position RMS by KEEP_MARGIN."""

    def held_out(d: Data) -> tuple[dict[str, Any], dict[str, Any]]:
        tr, va = split(d.n)
        train, val = d.subset(tr), d.subset(va)
        tau_tr, tau_va = chain.gravity_torques(train.q), chain.gravity_torques(val.q)
        model = Model(
            chain, position_only, [], initial_registration(chain, train, None, position_only)
        )
        x = fit(model, train, tau_tr, model.x, 50e-6).x
        return stats(model, x, train, tau_tr).as_dict(), stats(model, x, val, tau_va).as_dict()

    old_train, old_val = held_out(before)
    new_train, new_val = held_out(after)
    gain = 1 - new_val["pos_rms_mm"] / old_val["pos_rms_mm"]
    return {
        "name": "time_delay",
        "description": "delay (and clock drift) between the streams",
        "parameters": {
            "delay_s": found.delay_s,
            "se_s": found.delay_se_s,
            "drift_ppm": found.drift * 1e6,
            "drift_se_ppm": found.drift_se * 1e6,
            "t_ref_s": found.t_ref,
            "explained": found.explained,
        },
        "train": new_train,
        "validation": new_val,
        "held_out_improvement_pct": 100 * gain,
        "kept": gain >= KEEP_MARGIN,
        "baseline": {"train": old_train, "validation": old_val},
    }
