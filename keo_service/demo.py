"""`keo demo`: the embedded default."""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from keo_service.config import load_config
from keo_service.evaluate import as_series, truth_at
from keo_service.kinematics import cell_from_config
from keo_service.pipeline import Estimator, EstimatorSettings, run_offline
from keo_service.simulate import make_scenario, simulate


def run_demo(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    cell = cell_from_config(config)
    run = simulate(
        cell, make_scenario("paper-vertical", {"duration_s": repr(args.duration)}), seed=args.seed
    )
    est = Estimator(cell, EstimatorSettings.from_config(config))
    series = as_series(
        run_offline(
            est, run.encoder.t, run.encoder.q, run.tracker.t, run.tracker.p, run.tracker.quat
        )
    )
    truth = truth_at(series.t[-1:], run.truth_t, run.truth)[0]
    final = series.estimate[-1]
    summary = {
        "mode": "offline",
        "estimates": int(series.t.size),
        "final_estimate": final.tolist(),
        "truth": truth.tolist(),
        "final_error_mm": float(np.linalg.norm(final[:3] - truth[:3]) * 1e3),
    }
    if args.json:
        sys.stdout.write(json.dumps(summary) + "\n")
    else:
        print(summary)
    return 0
