"""Estimate a recording with the estimator of the live service, one sample at a time.

    keo simulate --config configs/demo.toml --scenario path --out rec
    python examples/estimate_recording.py --config configs/demo.toml rec

Reads the interchange files (encoder.csv: t,q1..qN; tracker.csv: t,x,y,z,qw,qx,qy,qz) with
the standard library, feeds both streams to `Estimator` in time order as a live service
would see them, and prints the final estimate and the estimator's counters. `keo estimate`
does the same over whole files, faster, and writes every estimate.
"""

from __future__ import annotations

import argparse
import csv
import heapq
from pathlib import Path

from keo_service import Estimator, cell_from_config, estimator_settings, load_config


def rows(path: Path) -> list[list[float]]:
    with path.open(newline="") as f:
        reader = csv.reader(f)
        next(reader)  # the header
        return [[float(v) for v in row] for row in reader]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", required=True, help="keo config (TOML)")
    parser.add_argument("recording", type=Path, help="folder with encoder.csv and tracker.csv")
    args = parser.parse_args(argv)

    config = load_config(args.config)
    estimator = Estimator(cell_from_config(config), estimator_settings(config))
    encoder = ((r[0], 0, r[1:]) for r in rows(args.recording / "encoder.csv"))
    tracker = ((r[0], 1, r[1:]) for r in rows(args.recording / "tracker.csv"))
    last = None
    for t, stream, values in heapq.merge(encoder, tracker, key=lambda s: (s[0], s[1])):
        if stream == 0:
            out = estimator.on_encoder(t, values)
        else:  # x, y, z and the quaternion scalar first (absent for a single reflector)
            out = estimator.on_tracker(t, values[:3], values[3:7] or None)
        last = out[-1] if out else last
    last = (estimator.flush() or [last])[-1]
    if last is None:
        print("no estimate")
        return 1
    channels = ", ".join(
        f"{name} {value * 1e3:+.3f}"
        for name, value in zip(last.channels, last.estimate_values(), strict=True)
    )
    print(f"final estimate at t={last.stamp:.3f} s (mm, mrad): {channels}")
    counters = dict(estimator.counters)
    print("counters: " + ", ".join(f"{k}={v}" for k, v in sorted(counters.items())))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
