"""Accuracy: the estimate against the simulator's injected truth."""

from __future__ import annotations

import dataclasses
from typing import Any

from keo_service.core.timing import DelayModel
from keo_service.fit.evaluate import estimate_error_rms, estimate_run
from keo_service.io.cell import cell_from_config, estimator_settings
from keo_service.io.config import Config
from keo_service.sim.simulate import make_scenario, simulate


def accuracy(config: Config, seed: int = 1) -> dict[str, Any]:
    cell = cell_from_config(config)
    run = simulate(
        cell, make_scenario("paper-vertical", {"error_drift_m_per_s": "2e-5"}), seed=seed
    )
    base = dataclasses.replace(estimator_settings(config), delay=DelayModel(run.scenario.delay_s))

    def rms_for(**changes: Any) -> tuple[float, float]:
        settings = dataclasses.replace(base, **changes)
        series = estimate_run(cell, settings, run)
        mask = series.stamp > series.stamp[0] + 5.0
        return estimate_error_rms(series, run.truth_t, run.truth, mask)

    configured = base.gains[0]
    gains = [0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0]
    sweep = {g: rms_for(gains=(g,) * 6)[0] for g in gains}
    best = min(sweep, key=lambda g: sweep[g])
    interp = rms_for()
    latest = rms_for(alignment="latest")
    ref_best = rms_for(alignment="latest", gains=(best,) * 6)
    return {
        "scenario": "paper-vertical with 20 um/s drift of the true error",
        "configured_gain": configured,
        "best_gain": best,
        "interpolate_pos_mm": interp[0] * 1e3,
        "interpolate_rot_mrad": interp[1] * 1e3,
        "latest_pos_mm": latest[0] * 1e3,
        "latest_rot_mrad": latest[1] * 1e3,
        "best_gain_interpolate_pos_mm": sweep[best] * 1e3,
        "best_gain_latest_pos_mm": ref_best[0] * 1e3,
        "reference_over_keo": latest[0] / sweep[best],
        "gain_sweep_pos_mm": {str(g): v * 1e3 for g, v in sweep.items()},
    }
