"""The transfer table of docs/analyze.md: a model fitted on one UR10 session, carried to the
other with only the tracker registration and the probe mount re-identified
(`keo analyze --registration-only`), judged on that session's held-out poses.

    python docs/transfer_table.py [--data data/ur10_lasertracker] [--work DIR] [--json]

Imports both series (as `keo import ur10-lasertracker` does), analyzes each, then carries each
model to the other series. Prints one row per direction: held-out position RMS (and max) of
the carried model, the nominal robot's held-out RMS there, and the other session's own model.
Rerun it after every change to the fit: this table is what the change is judged on.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "ur10_lasertracker.toml"
SERIES = {
    "A": "Series_A/measurements_grid.csv",
    "B": "Series_B/measurements_joint_configurations.csv",
}


def _quiet(fn: Any, *args: Any, **kw: Any) -> Any:
    """Run `fn` with its progress lines (stderr) kept, so the table stays readable."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        return fn(*args, **kw)


def run(data_dir: Path, work: Path) -> dict[str, Any]:
    from keo_service.io.config import load_config
    from keo_service.io.importers import import_dataset
    from keo_service.offline.analyze import run_analysis

    config = load_config(CONFIG)
    own: dict[str, dict[str, Any]] = {}
    timings: dict[str, float] = {}
    for name, rel in SERIES.items():
        out = work / name
        if not (out / "tracker.csv").exists():
            import_dataset("ur10-lasertracker", data_dir / rel, out)
        start = time.perf_counter()
        own[name] = _quiet(
            run_analysis, config, out / "encoder.csv", out / "tracker.csv", out / "an", False
        )
        timings[f"fit {name}"] = time.perf_counter() - start
    rows = []
    for src, dst in (("A", "B"), ("B", "A")):
        model = load_config(work / src / "an" / "model.toml")
        start = time.perf_counter()
        rep = _quiet(
            run_analysis,
            model,
            work / dst / "encoder.csv",
            work / dst / "tracker.csv",
            work / f"{src}_on_{dst}",
            True,
        )
        timings[f"{src} on {dst}"] = time.perf_counter() - start
        rows.append(
            {
                "model_from": src,
                "applied_to": dst,
                "held_out_pos_rms_mm": rep["final"]["validation"]["pos_rms_mm"],
                "held_out_pos_max_mm": rep["final"]["validation"]["pos_max_mm"],
                "nominal_pos_rms_mm": rep["baseline"]["validation"]["pos_rms_mm"],
                "own_model_pos_rms_mm": own[dst]["final"]["validation"]["pos_rms_mm"],
                "carried_maps": rep.get("carried_maps"),
                "stated_accuracy": rep.get("predicted_vs_measured"),
            }
        )
    within = {k: v["final"]["validation"]["pos_rms_mm"] for k, v in own.items()}
    return {"transfer": rows, "within_session": within, "seconds": timings}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=ROOT / "data" / "ur10_lasertracker")
    ap.add_argument("--work", type=Path, default=None, help="keep the files here")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    with contextlib.ExitStack() as stack:
        work = args.work or Path(stack.enter_context(tempfile.TemporaryDirectory()))
        result = run(args.data, work)
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    print("| model from | applied to | held out, mm RMS (max) | nominal there | own model |")
    print("|---|---|---|---|---|")
    for r in result["transfer"]:
        print(
            f"| {r['model_from']} | {r['applied_to']} | {r['held_out_pos_rms_mm']:.3f} "
            f"({r['held_out_pos_max_mm']:.2f}) | {r['nominal_pos_rms_mm']:.3f} | "
            f"{r['own_model_pos_rms_mm']:.3f} |"
        )
    print()
    print(
        "| model from | applied to | within the 95 % band: own session's band | with the "
        "between-session term | predicted / measured RMS, mm |"
    )
    print("|---|---|---|---|---|")
    for r in result["transfer"]:
        cov = r["stated_accuracy"] or {}
        if "within_session_band" not in cov:
            continue
        print(
            f"| {r['model_from']} | {r['applied_to']} | "
            f"{cov['within_session_band']['within_95_pct']:.1f} % | {cov['within_95_pct']:.1f} % "
            f"(+{cov['session_mm']:.3f} mm) | {cov['predicted_rms_mm']:.3f} / "
            f"{cov['measured_rms_mm']:.3f} |"
        )
    within = {k: round(v, 4) for k, v in result["within_session"].items()}
    print("within session, held out:", within)
    print("seconds:", {k: round(v, 1) for k, v in result["seconds"].items()}, file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
