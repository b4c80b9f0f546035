"""What the robot model still gets wrong: run `keo analyze` on a recording and summarise its
report (the fields of report.json that docs/design.md §6 fixes).

    keo simulate --config configs/demo.toml --scenario static-poses --out rec
    python examples/analyze.py --config configs/demo.toml rec out

The analysis is a command, not a library call: it writes report.json, report.md, plots and
model.toml (the config with every kept effect, usable by `keo run`) into the output folder.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path


def stats(s: dict[str, float]) -> str:
    return f"{s['pos_rms_mm']:.3f} mm RMS over {s['n']} poses"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", required=True, help="keo config (TOML)")
    parser.add_argument("recording", type=Path, help="folder with encoder.csv and tracker.csv")
    parser.add_argument("out", type=Path, help="where the report goes")
    args = parser.parse_args(argv)

    keo = shutil.which("keo") or ""
    command = [keo] if keo else [sys.executable, "-m", "keo_service.cli"]
    done = subprocess.run(
        [
            *command,
            "analyze",
            "--config",
            args.config,
            "--encoder",
            str(args.recording / "encoder.csv"),
            "--tracker",
            str(args.recording / "tracker.csv"),
            "--out",
            str(args.out),
            "--json",
        ],
        capture_output=True,
        text=True,
        check=False,
    )
    if done.returncode != 0:
        print(done.stderr, file=sys.stderr)
        return done.returncode
    report = json.loads((args.out / "report.json").read_text())
    print(f"nominal model, held out: {stats(report['baseline']['validation'])}")
    for effect in report["effects"]:
        print(f"  + {effect['name']}: {stats(effect['validation'])}")
    print(f"final model, held out: {stats(report['final']['validation'])}")
    print(f"not explained: {report['unexplained']}")
    print(f"the model with these effects: {args.out / 'model.toml'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
