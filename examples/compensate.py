"""Compensate a joint program (or a list of tool poses) with the model `keo analyze` wrote, as
a library call, and say how big the corrections are against the model's own figures.

    keo import ur10-lasertracker \
        data/ur10_lasertracker/Series_B/measurements_joint_configurations.csv --out ur10_B
    keo analyze --config configs/ur10_lasertracker.toml --encoder ur10_B/encoder.csv \
        --tracker ur10_B/tracker.csv --out ur10_B/analysis
    python examples/compensate.py ur10_B/analysis/model.toml targets.csv compensated.csv

targets.csv: `q1..q6` (a joint program) or `x,y,z,qw,qx,qy,qz` (the TCP, [tool], in the robot
base frame: m, scalar-first quaternion), optionally after an `id` or `t` column.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from keo_service import compensate


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model", type=Path, help="model.toml from keo analyze")
    parser.add_argument("targets", type=Path, help="targets CSV")
    parser.add_argument("out", type=Path, help="where the compensated targets go")
    args = parser.parse_args(argv)

    run = compensate(args.model, args.targets, args.out)
    s = run.summary
    print(f"{s['targets']} targets ({s['form']}) -> {args.out}")
    print(
        f"corrections {s['correction_mm']['rms']:.3f} mm / {s['correction_mrad']['rms']:.3f} mrad "
        f"RMS (the model's predicted deviation from the nominal robot: "
        f"{s['predicted_mm_rms']:.3f} mm / {s['predicted_mrad_rms']:.3f} mrad)"
    )
    if s["model_accuracy_mm"]:
        print(f"the model itself is good to {s['model_accuracy_mm']:.3f} mm RMS (held out)")
    if run.region is not None:
        for band in run.region.bands:
            lo, hi = np.round(band.lower, 3), np.round(band.upper, 3)
            print(f"calibrated: tool {band.band}, {band.poses} poses, box {lo} .. {hi} m")
    flagged = [(i, f) for i, f in enumerate(run.result.details) if f]
    for i, flags in flagged[:10]:
        print(f"  target {i}: {' | '.join(flags)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
