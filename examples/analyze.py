"""What the robot model still gets wrong: analyze a recording with the library and summarise
its report (the fields of report.json that docs/design.md §6 fixes).

    keo simulate --config configs/demo.toml --scenario static-poses --out rec
    python examples/analyze.py --config configs/demo.toml rec out

`analyze` is what `keo analyze` runs: it writes report.json, report.md, plots and model.toml
(the config with every kept effect, usable by `keo run` and `keo compensate`) into the output
folder, and returns the report as a dict.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from keo_service import KeoError, analyze


def stats(s: dict[str, float]) -> str:
    return f"{s['pos_rms_mm']:.3f} mm RMS over {s['n']} poses"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", required=True, help="keo config (TOML)")
    parser.add_argument("recording", type=Path, help="folder with encoder.csv and tracker.csv")
    parser.add_argument("out", type=Path, help="where the report goes")
    args = parser.parse_args(argv)

    try:
        result = analyze(
            args.config,
            args.recording / "encoder.csv",
            args.recording / "tracker.csv",
            args.out,
            quiet=True,  # no progress lines; warnings stay in result.warnings
        )
    except KeoError as exc:
        print(f"cannot analyze: {exc}")
        return 1
    for warning in result.warnings:
        print(f"warning: {warning}")
    print(f"nominal model, held out: {stats(result.baseline['validation'])}")
    for effect in result.effects:
        print(f"  + {effect['name']}: {stats(effect['validation'])}")
    print(f"final model, held out: {stats(result.final['validation'])}")
    print(f"not explained: {result.report['unexplained']}")
    print(f"the model with these effects: {result.model_path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
