"""The programs in examples/ run as a user would run them (their own processes, the public
API only), and print what the simulator's truth says they should."""

from __future__ import annotations

import re
import subprocess
import sys
import time

import numpy as np
import pytest

from keo_service.bench.demo import loopback_config
from keo_service.bench.procs import process_group
from keo_service.io.config import config_to_toml
from tests.conftest import DEMO, REPO, keo

EXAMPLES = REPO / "examples"


def run_example(name: str, *args: str, timeout: float = 180.0) -> str:
    done = subprocess.run(
        [sys.executable, str(EXAMPLES / name), *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    return done.stdout


def test_every_example_is_run_by_a_test():
    here = (REPO / "tests" / "test_examples.py").read_text()
    for path in EXAMPLES.glob("*.py"):
        assert f'"{path.name}"' in here, path.name


def test_examples_use_only_the_public_api():
    import keo_service

    for path in EXAMPLES.glob("*.py"):
        for line in path.read_text().splitlines():
            if line.startswith(("import keo_service", "from keo_service")):
                names = re.sub(r".* import ", "", line).replace("(", "").split(",")
                assert line.startswith("from keo_service import "), (path.name, line)
                assert {n.strip() for n in names if n.strip()} <= set(keo_service.__all__)


def test_estimate_a_recording(tmp_path):
    rec = tmp_path / "rec"
    done = keo("simulate", "--config", str(DEMO), "--scenario", "path", "--out", str(rec),
               "--set", "duration_s=20", "--seed", "3")  # fmt: skip
    assert done.returncode == 0, done.stderr
    out = run_example("estimate_recording.py", "--config", str(DEMO), str(rec))
    final = re.search(r"final estimate at t=([\d.]+) s \(mm, mrad\): (.*)", out)
    assert final, out
    values = [float(v.split()[1]) for v in final.group(2).split(", ")]
    truth = np.loadtxt(rec / "truth.csv", delimiter=",", skiprows=1)
    true_mm = 1e3 * truth[-1, 1:]
    # the injected error is millimetres (and drifts; the observer, L = 1/s, follows it with a
    # lag): the estimate is within a tenth of the error's size, which a zero estimate is not
    size = np.max(np.abs(true_mm[:3]))
    assert size > 1.0
    assert np.max(np.abs(np.array(values[:3]) - true_mm[:3])) < 0.1 * size, (values, true_mm)
    assert "tracker_samples=" in out


def test_delay_then_estimate_with_the_library(tmp_path):
    """`calibrate_delay` finds the simulator's 28 ms; `estimate` with it follows the injected
    error (truth.csv)."""
    rec = tmp_path / "rec"
    done = keo("simulate", "--config", str(DEMO), "--scenario", "paper-vertical", "--out",
               str(rec), "--set", "duration_s=20", "--seed", "4")  # fmt: skip
    assert done.returncode == 0, done.stderr
    out = run_example("delay_and_estimate.py", "--config", str(DEMO), str(rec))
    delay = float(re.search(r"delay: ([\d.]+) \+/- [\d.]+ ms", out).group(1))
    assert abs(delay - 28.0) < 2.0
    final = re.search(r"final estimate at t=([\d.]+) s \(mm, mrad\): (.*)", out)
    assert final, out
    values = np.array([float(v.split()[1]) for v in final.group(2).split(", ")])
    truth = np.loadtxt(rec / "truth.csv", delimiter=",", skiprows=1)
    true_mm = 1e3 * truth[-1, 1:]
    size = np.max(np.abs(true_mm[:3]))
    assert size > 1.0
    assert np.max(np.abs(values[:3] - true_mm[:3])) < 0.15 * size, (values, true_mm)


@pytest.mark.slow
@pytest.mark.e2e
def test_analyze_a_recording(tmp_path):
    """`keo analyze` on stop-and-measure poses of a robot whose geometry differs from the
    nominal: the held-out error falls from millimetres to the simulated noise."""
    rec = tmp_path / "rec"
    done = keo("simulate", "--config", str(DEMO), "--scenario", "static-poses", "--out",
               str(rec), "--set", "poses=120", "--seed", "1")  # fmt: skip
    assert done.returncode == 0, done.stderr
    out = run_example("analyze.py", "--config", str(DEMO), str(rec), str(tmp_path / "out"))
    nominal = float(re.search(r"nominal model, held out: ([\d.]+) mm", out).group(1))
    final = float(re.search(r"final model, held out: ([\d.]+) mm", out).group(1))
    assert nominal > 0.5
    assert final < 0.1
    assert (tmp_path / "out" / "model.toml").exists()


@pytest.mark.e2e
def test_subscribe_to_a_running_service(demo_config, tmp_path):
    config = loopback_config(demo_config)
    cfg = tmp_path / "live.toml"
    cfg.write_text(config_to_toml(config))
    t0 = time.time() + 3.0
    play = ["--scenario", "paper-step", "--seed", "2", "--t0", repr(t0), "--duration", "20"]
    with process_group(tmp_path) as procs:
        procs.start_cell(cfg, play)
        out = run_example("subscribe.py", "--config", str(cfg), "--count", "5", timeout=60.0)
    lines = out.splitlines()
    assert lines[0].startswith(f"cell {config.cell}: ")
    assert "delay 28.0 ms" in lines[0]  # the demo config's delay
    estimates = [line for line in lines[1:] if line.startswith("t=")]
    assert len(estimates) == 5


@pytest.mark.slow
@pytest.mark.e2e
def test_compensate_a_program(tmp_path):
    """`compensate` as a library call on the model of a simulated analysis: the corrections
    it reports are the model's predicted deviation from the nominal robot, and the region it
    prints is the calibration's."""
    rec = tmp_path / "rec"
    done = keo("simulate", "--config", str(DEMO), "--scenario", "static-poses", "--out",
               str(rec), "--set", "poses=120", "--seed", "2")  # fmt: skip
    assert done.returncode == 0, done.stderr
    done = keo("analyze", "--config", str(DEMO), "--encoder", str(rec / "encoder.csv"),
               "--tracker", str(rec / "tracker.csv"), "--out", str(tmp_path / "an"),
               timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr
    program = np.loadtxt(rec / "encoder.csv", delimiter=",", skiprows=1)[::10, 1:7]
    targets = tmp_path / "targets.csv"
    np.savetxt(targets, program, delimiter=",", header="q1,q2,q3,q4,q5,q6", comments="")
    out = run_example(
        "compensate.py", str(tmp_path / "an" / "model.toml"), str(targets), str(tmp_path / "o.csv")
    )
    found = re.search(
        r"corrections ([\d.]+) mm .*deviation from the nominal robot: ([\d.]+) mm", out
    )
    assert found, out
    assert float(found.group(1)) == pytest.approx(float(found.group(2)), rel=0.05)
    assert "calibrated: tool" in out
