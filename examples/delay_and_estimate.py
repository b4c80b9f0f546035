"""Find the delay between the streams of a recording, then estimate with it: two library calls.

    keo simulate --config configs/demo.toml --scenario paper-vertical --out rec
    python examples/delay_and_estimate.py --config configs/demo.toml rec

`calibrate_delay` is `keo calibrate-delay` and `estimate` is `keo estimate`; both take paths
(as here) or arrays, and return typed results in SI units (s, m, rad). The config's own delay
is ignored here on purpose: the one found from the motion replaces it.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import msgspec

from keo_service import calibrate_delay, estimate, load_config


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", required=True, help="keo config (TOML)")
    parser.add_argument("recording", type=Path, help="folder with encoder.csv and tracker.csv")
    args = parser.parse_args(argv)
    encoder, tracker = args.recording / "encoder.csv", args.recording / "tracker.csv"

    config = load_config(args.config)
    found = calibrate_delay(config, encoder, tracker)
    print(f"delay: {found.delay_s * 1e3:.2f} +/- {found.delay_se_s * 1e3:.2f} ms")
    if not found.explained:
        print("the fit does not explain the data: " + "; ".join(found.notes))
        return 1
    timing = msgspec.structs.replace(config.timing, delay_s=found.delay_s)
    result = estimate(msgspec.structs.replace(config, timing=timing), encoder, tracker)
    last = result.estimate[-1]
    values = ", ".join(f"{n} {v * 1e3:+.3f}" for n, v in zip(result.channels, last, strict=True))
    print(f"{result.stamp.size} estimates, {result.held} held ({result.path})")
    print(f"final estimate at t={result.stamp[-1]:.3f} s (mm, mrad): {values}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
