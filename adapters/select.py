"""Which adapter class serves a config's `robot.protocol` and `tracker.protocol`.

Kept apart from the adapters themselves so that the TCP adapters (`devices`) and the UDP ones
(`udp_devices`, which build on `devices`) do not import each other.
"""

from __future__ import annotations

from keo_service.adapters.devices import (
    EncoderAdapter,
    Ros2PoseAdapter,
    RtdeEncoderAdapter,
    TrackerAdapter,
)
from keo_service.adapters.udp_devices import UDP_ADAPTERS
from keo_service.io.config import Config

__all__ = ["encoder_adapter_for", "tracker_adapter_for"]


def encoder_adapter_for(config: Config) -> type[EncoderAdapter]:
    """The encoder adapter of `robot.protocol` (ros2: `Ros2JointStateAdapter`, which needs
    the URDF's joint names, is built by the caller)."""
    protocol = config.robot.protocol
    if protocol in UDP_ADAPTERS:  # kuka_rsi, abb_egm: UDP servers the controller sends to
        return UDP_ADAPTERS[protocol]
    return RtdeEncoderAdapter if protocol == "rtde" else EncoderAdapter


def tracker_adapter_for(config: Config) -> type[TrackerAdapter | Ros2PoseAdapter]:
    """The tracker adapter of `tracker.protocol`."""
    return Ros2PoseAdapter if config.tracker.protocol == "ros2" else TrackerAdapter
