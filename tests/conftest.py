from __future__ import annotations

import subprocess
import sys
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


def wait_for_status(config, timeout: float = 20.0) -> None:
    """Until the service answers a status query, through the client API."""
    with SyncClient.from_config(config, connect_timeout_s=timeout) as keo:
        keo.status(timeout=timeout)
