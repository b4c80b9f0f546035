"""Where the shipped configs live, in a checkout and in an installed wheel."""

from __future__ import annotations

from pathlib import Path


def configs_dir() -> Path:
    packaged = Path(__file__).parent / "_configs"
    if packaged.is_dir():
        return packaged
    return Path(__file__).resolve().parent.parent / "configs"


def demo_config_path() -> Path:
    return configs_dir() / "demo.toml"
