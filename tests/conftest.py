from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from keo_service.core.kinematics import Cell
from keo_service.io.cell import cell_from_config
from keo_service.io.config import Config, load_config
from keo_service.live.client import SyncClient

REPO = Path(__file__).resolve().parent.parent
CONFIGS = REPO / "configs"
DEMO = CONFIGS / "demo.toml"
# the UR10 + laser tracker data: shipped in data/ (MIT, its LICENSE.md beside it); the shared
# copy beside the checkout when an older clone lacks it
UR10_DATA = next(
    (
        d
        for d in (
            REPO / "data" / "ur10_lasertracker",
            REPO.parent / "shared" / "data" / "ur10_lasertracker",
        )
        if d.is_dir()
    ),
    REPO / "data" / "ur10_lasertracker",
)


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt(f"signal {signum}")


@pytest.fixture(autouse=True)
def _sigterm_unwinds_the_test() -> Iterator[None]:
    """SIGTERM to pytest alone (`kill`, a cancelled CI job) ends the run as Ctrl-C does: the
    running test unwinds, so its `finally` blocks stop the processes it started instead of
    orphaning them."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


@pytest.fixture(scope="session")
def demo_config() -> Config:
    return load_config(DEMO)


@pytest.fixture(scope="session")
def demo_cell(demo_config: Config) -> Cell:
    return cell_from_config(demo_config)


def write_config(tmp_path: Path, body: str, name: str = "c.toml") -> Path:
    path = tmp_path / name
    path.write_text(body.replace("@ROBOTS@", str(CONFIGS / "robots")), encoding="utf-8")
    return path


def keo(*args: str, timeout: float = 120.0) -> subprocess.CompletedProcess[str]:
    """Run the installed CLI as a real process."""
    return subprocess.run(
        [sys.executable, "-m", "keo_service.cli", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )


def run_script(script: Path, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    """Run a Python script from the repository's root as a process of its own, with `env`
    and the repository first on its path (so it can import the tests' helpers); raises on a
    non-zero exit."""
    repo = Path(__file__).resolve().parent.parent
    return subprocess.run(
        [sys.executable, str(script)],
        capture_output=True,
        text=True,
        cwd=repo,
        env={**env, "PYTHONPATH": str(repo)},
        timeout=120,
        check=True,
    )


def wait_for_status(config, timeout: float = 20.0) -> None:
    """Until the service answers a status query, through the client API."""
    with SyncClient.from_config(config, connect_timeout_s=timeout) as keo:
        keo.status(timeout=timeout)


def wait_until(condition: Callable[[], object], timeout: float, what: str) -> None:
    """Poll `condition` until it is true; AssertionError naming `what` after `timeout` s."""
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {timeout:g} s: {what}")
        time.sleep(0.05)


def wait_for_adapters(
    config, names: tuple[str, ...], states: tuple[str, ...], timeout: float = 30.0
) -> None:
    """Until every adapter in `names` says (its own status query) that it is in one of
    `states` ("connected": it has its device; "receiving": data flows)."""
    with SyncClient.from_config(config, connect_timeout_s=timeout) as keo:

        def ready() -> bool:
            now = keo.adapters(timeout=1.0)
            return all(name in now and now[name].state in states for name in names)

        wait_until(ready, timeout, f"adapters {', '.join(names)} {' or '.join(states)}")
