"""The protocol table (io.protocols) is the one place a protocol is named: every row resolves
to its codec, adapter and mock, every mock is a MockDevice, and what the config, `keo init`,
`keo mock` and the adapters' messages offer is what the table has."""

from __future__ import annotations

import importlib

import pytest

from keo_service.adapters.mock import MockDevice, MockSettings, build_mock
from keo_service.adapters.select import load, protocol_of
from keo_service.bench.fuzz import TARGETS
from keo_service.io import config as config_module
from keo_service.io.init_config import ROBOT_PROTOCOLS, TRACKER_PROTOCOLS
from keo_service.io.protocols import PROTOCOLS, names, protocol_for
from keo_service.sim.simulate import make_scenario, simulate

ROWS = [pytest.param(p, id=f"{p.section}-{p.name}") for p in PROTOCOLS]


def test_the_table_has_each_protocol_of_each_section_once():
    keys = [(p.section, p.name) for p in PROTOCOLS]
    assert len(keys) == len(set(keys))
    # the protocols of docs/design.md §6
    assert set(names("robot")) == {"motoros", "rtde", "ros2", "kuka_rsi", "abb_egm"}
    assert set(names("tracker")) == {"line", "ros2"}
    assert names("robot") == ROBOT_PROTOCOLS
    assert names("tracker") == TRACKER_PROTOCOLS
    with pytest.raises(KeyError, match="one of motoros"):
        protocol_for("robot", "line")


@pytest.mark.parametrize("row", ROWS)
def test_each_row_resolves_to_its_codec_adapter_and_mock(row):
    importlib.import_module(f"keo_service.{row.codec}")
    adapter = load(row.adapter)
    assert adapter.name == ("encoder" if row.section == "robot" else "tracker")
    assert callable(load(row.mock))
    assert row.clock in ("shared", "device", "receipt")
    assert row.words


@pytest.mark.parametrize("row", ROWS)
def test_the_config_takes_the_tables_defaults(demo_config, row):
    doc = {"robot": {"urdf": demo_config.robot.urdf}, row.section: {"protocol": row.name}}
    if row.section == "robot":
        doc["robot"]["urdf"] = demo_config.robot.urdf
    config = config_module.parse_config(doc, source="t.toml")
    device = getattr(config, row.section)
    assert device.clock == row.clock
    if row.section == "robot":
        assert device.port == row.port
    assert protocol_of(config, row.section) == row


def test_a_protocol_the_table_lacks_is_a_config_error_naming_the_key(demo_config):
    from keo_service.core.errors import ConfigError

    doc = {"robot": {"urdf": demo_config.robot.urdf, "protocol": "fanuc"}}
    with pytest.raises(ConfigError, match=r"robot\.protocol"):
        config_module.parse_config(doc, source="t.toml")


@pytest.mark.parametrize("row", ROWS)
def test_every_mock_is_a_mock_device_with_the_settings_it_was_given(demo_config, row):
    run = simulate(_cell(demo_config), make_scenario("path", {"duration_s": "2"}))
    settings = MockSettings(
        device=row.section, protocol=row.name, host="", port=0, t0=1.0, play_until=5.0
    )
    mock = build_mock(settings, demo_config, run)
    assert isinstance(mock, MockDevice)
    assert mock.play_until == 5.0
    if row.port and getattr(demo_config, row.section).protocol != row.name:
        assert mock.port == row.port  # type: ignore[attr-defined]


def test_every_codec_that_reads_outside_bytes_is_fuzzed():
    fuzzed = " ".join(t.name for t in TARGETS)
    for row in PROTOCOLS:
        assert row.name.split("_")[0] in fuzzed or row.name == "line", row.name


def _cell(config):
    from keo_service.io.cell import cell_from_config

    return cell_from_config(config)
