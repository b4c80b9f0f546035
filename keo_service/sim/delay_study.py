"""`keo delay-study`: true vs found delay on simulated scenarios, and what the found delay
does to the estimate's error against the truth (README table)."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from keo_service.core.timing import DelayModel
from keo_service.fit.delay import DelayNotIdentifiableError, fit_delay
from keo_service.fit.evaluate import estimate_error_rms, estimate_run
from keo_service.io.cell import cell_from_config, estimator_settings
from keo_service.io.config import Config
from keo_service.sim.simulate import make_scenario, simulate

CASES: list[tuple[str, dict[str, str]]] = [
    ("paper-vertical", {}),
    ("workspace", {}),
    ("path", {}),
    ("path", {"delay_jitter_s": "0.008"}),
    ("path", {"drift_ppm": "50"}),
    ("path", {"drift_ppm": "500"}),
    ("path", {"position_only": "true"}),
    ("path", {"delay_change_s": "0.015"}),
    ("paper-step", {}),
]


def delay_study(config: Config, seed: int = 1) -> list[dict[str, Any]]:
    cell = cell_from_config(config)
    rows = []
    for name, sets in CASES:
        run = simulate(cell, make_scenario(name, sets), seed=seed)
        sc = run.scenario
        row: dict[str, Any] = {
            "scenario": name,
            "settings": sets,
            "true_delay_ms": sc.delay_s * 1e3,
            "true_drift_ppm": sc.drift_ppm,
        }
        try:
            fit = fit_delay(
                cell,
                run.encoder.t,
                run.encoder.q,
                run.tracker.t,
                run.tracker.p,
                run.tracker.quat,
                initial=config.timing.delay_s,
            )
        except DelayNotIdentifiableError as exc:
            row["refused"] = str(exc)
            rows.append(row)
            continue
        # the true delay at the fit's reference time: stamps = tau (1 + drift) + delay
        true_at_ref = sc.delay_s + sc.drift_ppm * 1e-6 * (fit.t_ref - sc.delay_s)
        row.update(
            {
                "found_delay_ms": fit.delay_s * 1e3,
                "se_ms": fit.delay_se_s * 1e3,
                "error_ms": (fit.delay_s - true_at_ref) * 1e3,
                "found_drift_ppm": fit.drift * 1e6 if fit.drift_significant else 0.0,
                "drift_se_ppm": fit.drift_se * 1e6,
                "explained": fit.explained,
                "notes": fit.notes,
            }
        )
        base = dataclasses.replace(estimator_settings(config))
        for label, delay in (
            ("none", DelayModel()),
            ("found", DelayModel(fit.delay_s, fit.drift, fit.t_ref)),
        ):
            settings = dataclasses.replace(base, delay=delay)
            series = estimate_run(cell, settings, run)
            mask = series.stamp > series.stamp[0] + 5.0
            pos, _rot = estimate_error_rms(series, run.truth_t, run.truth, mask)
            row[f"estimate_error_{label}_mm"] = pos * 1e3
        rows.append(row)
    return rows


def delay_markdown(rows: list[dict[str, Any]]) -> str:
    lines = [
        "| scenario | true delay (ms) | found (ms) | error (ms) | true drift (ppm) | "
        "found drift (ppm) | estimate error, no delay (mm) | with found delay (mm) | verdict |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        label = r["scenario"] + ("".join(f", {k}={v}" for k, v in r["settings"].items()))
        if "refused" in r:
            lines.append(
                f"| {label} | {r['true_delay_ms']:.1f} | refused | | | | | | "
                f"{r['refused'].split(':')[0]} |"
            )
            continue
        verdict = "ok" if r["explained"] else "no constant delay explains it"
        lines.append(
            f"| {label} | {r['true_delay_ms']:.1f} | "
            f"{r['found_delay_ms']:.3f} ± {r['se_ms']:.3f} | "
            f"{r['error_ms']:+.3f} | {r['true_drift_ppm']:.0f} | {r['found_drift_ppm']:.1f} ± "
            f"{r['drift_se_ppm']:.1f} | {r['estimate_error_none_mm']:.4f} | "
            f"{r['estimate_error_found_mm']:.4f} | {verdict} |"
        )
    return "\n".join(lines) + "\n"


def as_jsonable(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [
        {k: (float(v) if isinstance(v, np.floating) else v) for k, v in r.items()} for r in rows
    ]
