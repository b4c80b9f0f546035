"""`keo estimate` as a process: what it loads, and in which order, before it computes
(docs/performance.md: on two cores the command's wall time rests on its start)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from keo_service.cli.offline import USER_BLAS_THREADS
from keo_service.io.interchange import write_encoder, write_tracker
from keo_service.sim.simulate import make_scenario, simulate
from tests.conftest import CONFIGS, REPO, keo

DEMO = CONFIGS / "demo.toml"


@pytest.fixture(scope="module")
def recording(demo_cell, tmp_path_factory) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("recording")
    run = simulate(demo_cell, make_scenario("path", {"duration_s": "2"}), seed=3)
    write_encoder(folder / "encoder.csv", run.encoder)
    write_tracker(folder / "tracker.csv", run.tracker)
    return folder / "encoder.csv", folder / "tracker.csv"


def _python(code: str, env: dict[str, str] | None = None) -> list[str]:
    """The lines `code` prints, run in a fresh interpreter from the repository."""
    environment = {k: v for k, v in os.environ.items() if k not in USER_BLAS_THREADS}
    environment.update(env or {})
    done = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        check=True,
        cwd=REPO,
        env=environment,
    )
    return done.stdout.split()


def test_the_command_line_is_parsed_without_numpy():
    # a command chooses how numpy loads (BLAS threads) only if parsing did not load it
    code = (
        "import sys\n"
        "from keo_service.cli import build_parser\n"
        "build_parser().parse_args(['estimate', '--config', 'c', '--encoder', 'e', "
        "'--tracker', 't', '--out', 'o'])\n"
        "print('numpy' in sys.modules)\n"
    )
    assert _python(code) == ["False"]


@pytest.mark.parametrize(
    ("chosen", "expected"),
    [
        (None, "1"),
        ({"OPENBLAS_NUM_THREADS": "3"}, "3"),
        # OpenBLAS falls back to these when its own variable is unset: the user's choice too
        ({"OMP_NUM_THREADS": "3"}, None),
        ({"GOTO_NUM_THREADS": "3"}, None),
    ],
)
def test_keo_estimate_runs_blas_on_one_thread_unless_the_user_chose(
    recording, tmp_path, chosen, expected
):
    encoder, tracker = recording
    out = tmp_path / "estimates.csv"
    args = ["estimate", "--config", str(DEMO), "--encoder", str(encoder)]
    args += ["--tracker", str(tracker), "--out", str(out)]
    code = (
        "import os, sys\n"
        "from keo_service.cli import main\n"
        f"code = main({args!r})\n"
        "print(code, 'numpy' in sys.modules, os.environ.get('OPENBLAS_NUM_THREADS'))\n"
    )
    env = {} if chosen is None else chosen
    assert _python(code, env)[-3:] == ["0", "True", str(expected)]  # after the command's line
    assert out.stat().st_size > 0


def test_estimate_starts_reading_before_the_kinematics_library_loads(recording):
    # Pinocchio's import then runs while the tracker file parses on a worker thread
    encoder, tracker = recording
    code = (
        "import sys\n"
        "from keo_service.offline import library\n"
        "read = library.read_recording\n"
        "def reading(*args, **kwargs):\n"
        "    print('pinocchio' in sys.modules)\n"
        "    return read(*args, **kwargs)\n"
        "library.read_recording = reading\n"
        f"result = library.estimate({str(DEMO)!r}, {str(encoder)!r}, {str(tracker)!r})\n"
        "print(result.path, 'pinocchio' in sys.modules)\n"
    )
    assert _python(code) == ["False", "batch", "True"]


@pytest.mark.parametrize("where", ["a directory", "under a file"])
def test_an_estimate_file_that_cannot_be_written_is_named_not_a_traceback(
    recording, tmp_path, where
):
    encoder, tracker = recording
    if where == "a directory":
        out = tmp_path / "estimates"
        out.mkdir()
    else:
        (tmp_path / "plain").write_text("a file, not a folder\n")
        out = tmp_path / "plain" / "estimates.csv"
    done = keo(
        "estimate", "--config", str(DEMO), "--encoder", str(encoder),
        "--tracker", str(tracker), "--out", str(out),
    )  # fmt: skip
    assert done.returncode == 1
    assert "Traceback" not in done.stderr
    assert f"keo estimate: error: cannot write the estimate file '{out}'" in done.stderr


def test_the_estimators_load_while_the_tracker_file_parses(recording):
    # the library's estimate hands the estimators' imports to the reading, which runs them
    # while its worker thread parses the tracker file (before: they loaded after the reading)
    encoder, tracker = recording
    code = (
        "import sys\n"
        "from keo_service.offline import library\n"
        "read = library.read_recording\n"
        "def reading(*args, while_parsing=None, **kwargs):\n"
        "    def parsing():\n"
        "        print('keo_service.core.batch' in sys.modules)\n"
        "        while_parsing()\n"
        "        print('keo_service.core.batch' in sys.modules)\n"
        "    given = None if while_parsing is None else parsing\n"
        "    return read(*args, while_parsing=given, **kwargs)\n"
        "library.read_recording = reading\n"
        f"result = library.estimate({str(DEMO)!r}, {str(encoder)!r}, {str(tracker)!r})\n"
        "print(result.path)\n"
    )
    assert _python(code) == ["False", "True", "batch"]
