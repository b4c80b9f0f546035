"""The fits' z-scores per scenario of the online delay matrix (docs/timing-delay.md, issue 45):
every encoder x tracker x motion x geometry case run through the online tracker with the
right delay configured, until 200 fits (or an hour of stream time), z = |fit - injected| /
the se each fit reports. Runs in parallel processes; writes JSON rows and prints the table.

    python docs/delay_coverage.py [--fits 200] [--jobs 2] [--out coverage.json] [filter]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any


def _finite(v: Any) -> Any:
    """JSON has no NaN: a scenario without fits has no z."""
    return None if isinstance(v, float) and math.isnan(v) else v


def _one(args: tuple[int, int, float]) -> dict[str, Any]:
    from keo_service.io.cell import cell_from_config
    from keo_service.io.config import load_config
    from keo_service.resources import demo_config_path
    from keo_service.sim.delay_study import coverage, matrix_cases

    index, fits, max_seconds = args
    cell = cell_from_config(load_config(demo_config_path()))
    case = matrix_cases()[index]
    return coverage(cell, case, min_fits=fits, max_seconds=max_seconds).row()


def main() -> int:
    from keo_service.sim.delay_study import coverage_markdown, matrix_cases

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fits", type=int, default=200)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--max-seconds", type=float, default=3600.0)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("filter", nargs="?", default="", help="only scenarios containing this")
    args = ap.parse_args()
    cases = matrix_cases()
    chosen = [i for i, c in enumerate(cases) if args.filter in c.label]
    rows: list[dict[str, Any]] = []
    with ProcessPoolExecutor(args.jobs) as pool:
        for row in pool.map(_one, [(i, args.fits, args.max_seconds) for i in chosen]):
            rows.append(row)
            print(json.dumps(row), file=sys.stderr, flush=True)
            if args.out is not None:
                clean = [{k: _finite(v) for k, v in r.items()} for r in rows]
                args.out.write_text(json.dumps(clean, indent=1), encoding="utf-8")
    sys.stdout.write(coverage_markdown(rows))
    worst = min((r["within_2_5"] for r in rows if r["fits"]), default=math.nan)
    print(f"\nworst scenario: {100 * worst:.1f} % of fits within 2.5 se", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
