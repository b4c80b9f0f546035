"""Config: every key checked, and the error names the key and what was expected."""

from __future__ import annotations

import argparse
import gc

import pytest

from keo_service.cli import common
from keo_service.core.errors import ConfigError
from keo_service.io.config import load_config
from tests.conftest import CONFIGS, DEMO, keo, write_config

GOOD = """
cell = "c1"
[robot]
urdf = "@ROBOTS@/mh180.urdf"
"""


def test_demo_config_loads_with_defaults(demo_config):
    assert demo_config.cell == "demo"
    assert demo_config.robot.port == 50241
    assert demo_config.timing.alignment == "interpolate"
    assert demo_config.bus.listen == ["tcp/127.0.0.1:7447"]


def test_minimal_config_gets_design_defaults(tmp_path):
    c = load_config(write_config(tmp_path, GOOD))
    assert c.observer.gain == [1.0] * 6
    assert c.timing.delay_s == 0.0
    assert c.timing.sample_rate_hz == 40.0
    assert c.robot.byte_order == "little"
    assert c.bus.mode == "peer"


@pytest.mark.parametrize(
    ("body", "key", "words"),
    [
        ("colour = 3\n" + GOOD, "colour", "unknown key"),
        (GOOD + "typo_key = 1\n", "robot.typo_key", "unknown key"),
        (GOOD + "port = 'fifty'\n", "robot.port", "Expected `int`"),
        (GOOD + "byte_order = 'middle'\n", "robot.byte_order", "Invalid enum value"),
        (GOOD + "[tool]\nxyz = [0.0, 0.1]\n", "tool.xyz", "length"),
        (GOOD + "[tracker]\nrpy = [0.0, 0.1, 0.2, 0.3]\n", "tracker.rpy", "length"),
        (GOOD + "[observer]\ngain = [1.0, 1.0, 0.0, 1.0, 1.0, 1.0]\n", "observer.gain[2]", "> 0.0"),
        (GOOD + "[observer]\ngain = [1.0, 1.0, 1.0]\n", "observer.gain", "length"),
        (GOOD + "[timing]\nalignment = 'nearest'\n", "timing.alignment", "Invalid enum value"),
        ("cell = 'c'\n[robot]\n", "robot.urdf", "required key is missing"),
        ("[robot]\nurdf = 'nope.urdf'\n", "robot.urdf", "file not found"),
        (GOOD + "flange_frame = 'flange99'\n", "robot.flange_frame", "not in the URDF"),
        ("cell = 'a b'\n[robot]\nurdf = '@ROBOTS@/mh180.urdf'\n", "cell", "matching regex"),
    ],
)
def test_bad_config_names_the_key(tmp_path, body, key, words):
    path = write_config(tmp_path, body)
    with pytest.raises(ConfigError) as info:
        config = load_config(path)
        from keo_service.io.cell import cell_from_config

        cell_from_config(config)  # frames are checked against the URDF
    assert info.value.key == key
    assert words in str(info.value)


def test_toml_syntax_error_is_reported(tmp_path):
    path = write_config(tmp_path, "cell = \n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(path)


def test_cli_exits_2_and_names_the_key(tmp_path):
    path = write_config(tmp_path, GOOD + "[observer]\ngain = [1.0, -1.0, 1.0, 1.0, 1.0, 1.0]\n")
    result = keo(
        "simulate", "--config", str(path), "--scenario", "paper-step", "--out", str(tmp_path / "o")
    )
    assert result.returncode == 2
    assert "observer.gain[1]" in result.stderr


def test_cli_bad_usage_exits_2():
    result = keo("gain", "--rate", "40")
    assert result.returncode == 2
    assert "--gain" in result.stderr
    result = keo("simulate", "--config", str(DEMO), "--scenario", "nowhere", "--out", "/tmp/x")
    assert result.returncode == 2
    assert "unknown scenario" in result.stderr


def test_an_empty_config_gives_the_estimators_defaults():
    from keo_service.core.settings import EstimatorSettings
    from keo_service.io.cell import estimator_settings
    from keo_service.io.config import parse_config

    config = parse_config({"robot": {"urdf": str(CONFIGS / "robots" / "ur10.urdf")}}, source="t")
    assert estimator_settings(config) == EstimatorSettings()


def test_a_batch_command_runs_with_the_collector_paused_and_gets_it_back():
    seen = []

    def command(args: argparse.Namespace) -> int:
        seen.append(gc.isenabled())
        return 3

    def failing(args: argparse.Namespace) -> int:
        seen.append(gc.isenabled())
        raise ConfigError("keo.toml", "model.urdf", "missing")

    assert gc.isenabled()
    assert common.collector_paused(command)(argparse.Namespace()) == 3
    assert gc.isenabled()
    with pytest.raises(ConfigError):
        common.collector_paused(failing)(argparse.Namespace())
    assert gc.isenabled()
    assert seen == [False, False]
