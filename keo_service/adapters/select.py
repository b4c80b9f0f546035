"""The adapter and the mock of a config's protocols, as the protocol table (io.protocols)
names them: the one place that turns a row's "module:name" into the class or function.

Kept apart from the adapters themselves so that the TCP adapters (`devices`) and the UDP ones
(`udp_devices`, which build on `devices`) do not import each other.
"""

from __future__ import annotations

import importlib
from typing import Any

from keo_service.io.config import Config
from keo_service.io.protocols import Protocol, Section, protocol_for

__all__ = ["encoder_adapter_for", "load", "mock_factory", "protocol_of", "tracker_adapter_for"]


def load(where: str) -> Any:
    """The object a table row names, "module:name" in keo_service.adapters."""
    module, _, name = where.partition(":")
    return getattr(importlib.import_module(f"keo_service.adapters.{module}"), name)


def protocol_of(config: Config, section: Section) -> Protocol:
    """The table's row for the protocol the config gives a section's device."""
    device = config.robot if section == "robot" else config.tracker
    return protocol_for(section, device.protocol)


def encoder_adapter_for(config: Config) -> Any:
    """The encoder adapter class of `robot.protocol` (ros2's `Ros2JointStateAdapter` takes
    the URDF's joint names instead of their number)."""
    return load(protocol_of(config, "robot").adapter)


def tracker_adapter_for(config: Config) -> Any:
    """The tracker adapter class of `tracker.protocol`."""
    return load(protocol_of(config, "tracker").adapter)


def mock_factory(protocol: Protocol) -> Any:
    """The function that builds the protocol's mock device from `MockSettings`."""
    return load(protocol.mock)
