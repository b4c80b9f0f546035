"""Build the API reference (docs/api/) from the docstrings of `keo_service.__all__`.

    python docs/build_api.py                 # writes docs/api/
    python docs/build_api.py --check         # builds into a temporary folder, warnings as
                                             # errors; says (without failing) when docs/api/
                                             # differs, since another pdoc release may render
                                             # the same docstrings differently

pdoc imports the package and documents what `keo_service.__all__` names (the lazily loaded
names included), with Google-style sections (Args, Returns, Raises). Source views and the
search index are left out: the page is for reading what a name takes and gives, and stays
small enough to keep in the repository.
"""

from __future__ import annotations

import argparse
import filecmp
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
OUT = HERE / "api"
COMMAND = ["-m", "pdoc", "-d", "google", "--no-search", "--no-show-source", "keo_service"]


def build(out: Path) -> None:
    """pdoc in a child interpreter with every warning an error (a docstring pdoc cannot
    read, an annotation it cannot resolve)."""
    subprocess.run([sys.executable, "-W", "error", *COMMAND, "-o", str(out)], check=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--check",
        action="store_true",
        help="build with warnings as errors; say when docs/api/ is stale",
    )
    args = parser.parse_args(argv)
    if not args.check:
        build(OUT)
        print(f"wrote {OUT}")
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        fresh = Path(tmp)
        build(fresh)
        names = sorted(p.name for p in fresh.iterdir())
        same, differ, missing = filecmp.cmpfiles(fresh, OUT, names, shallow=False)
        extra = sorted({p.name for p in OUT.iterdir()} - set(names)) if OUT.is_dir() else []
    if differ or missing or extra:
        print(
            f"docs/api/ differs from this build ({', '.join(differ + missing + extra)}): run "
            "python docs/build_api.py and commit docs/api/ if the docstrings changed",
            file=sys.stderr,
        )
        return 0
    print(f"docs/api/ is current ({', '.join(same)})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
