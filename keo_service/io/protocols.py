"""The device protocols keo speaks: one row per protocol, read by the config (default port and
clock domain), `keo init`, the adapters' selection and messages, and `keo mock`.

A row names its codec, its adapter and its mock by where they live in `keo_service.adapters`
(strings, resolved there when an adapter or a mock is made): this table sits below the
adapters' layer so that reading a config needs none of them, and so that adding a protocol is
one module (codec, adapter and mock) and one row here.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

__all__ = ["PROTOCOLS", "Protocol", "names", "protocol_for"]

Section = Literal["robot", "tracker"]


@dataclass(frozen=True)
class Protocol:
    """One device protocol as keo speaks it.

    Attributes:
        name: the config's `protocol` value.
        section: the config section of its device, "robot" (an encoder adapter) or "tracker".
        codec: its codec module under `keo_service` (bytes in, typed frames out).
        adapter: its adapter class, "module:Class" in `keo_service.adapters`.
        mock: the function that builds its mock device from `MockSettings`, "module:function"
            in `keo_service.adapters`.
        clock: the clock domain of its stamps when the config gives none ("shared": the
            cell's common clock, "device": the device's own, mapped; "receipt": none).
        correction: the `robot.correction` value that sends live corrections over it ("":
            it carries none).
        port: the device's port when the config gives none (0: none, it comes over the bus).
        words: what the device is, in words, for messages that name what was expected.
        joints: the number of joints it always reports (0: as many as the URDF has).
    """

    name: str
    section: Section
    codec: str
    adapter: str
    mock: str
    clock: Literal["shared", "device", "receipt"]
    correction: str
    port: int
    words: str
    joints: int = 0


PROTOCOLS: tuple[Protocol, ...] = (
    Protocol(
        "motoros",
        "robot",
        codec="adapters.simple_message",
        adapter="devices:EncoderAdapter",
        mock="mock_devices:motoros_mock",
        clock="receipt",  # MotoROS leaves the frame's time at 0
        correction="",
        port=50241,
        words="a MotoROS state server (ROS-Industrial simple message, port 50241 by default)",
    ),
    Protocol(
        "rtde",
        "robot",
        codec="adapters.rtde",
        adapter="devices:RtdeEncoderAdapter",
        mock="mock_devices:rtde_mock",
        clock="device",
        correction="rtde_registers",
        port=30004,
        words="a Universal Robots controller's RTDE server (port 30004 by default)",
        joints=6,
    ),
    Protocol(
        "ros2",
        "robot",
        codec="live.ros2",  # rmw_zenoh's keys and attachments; CDR through rosbags
        adapter="devices:Ros2JointStateAdapter",
        mock="mock_ros2:joint_state_mock",
        clock="shared",  # ROS time
        correction="",
        port=0,
        words="a ROS 2 node publishing the topic",
    ),
    Protocol(
        "kuka_rsi",
        "robot",
        codec="adapters.kuka_rsi",
        adapter="udp_devices:KukaRsiAdapter",
        mock="mock_udp:rsi_mock",
        clock="device",
        correction="kuka_rsi",
        port=49152,
        words="a KUKA controller running RSI (UDP, port 49152 by default)",
        joints=6,
    ),
    Protocol(
        "abb_egm",
        "robot",
        codec="adapters.abb_egm",
        adapter="udp_devices:AbbEgmAdapter",
        mock="mock_udp:egm_mock",
        clock="device",
        correction="abb_egm",
        port=6510,
        words="an ABB controller running EGM (UDP, port 6510 by default)",
    ),
    Protocol(
        "line",
        "tracker",
        codec="adapters.line_protocol",
        adapter="devices:TrackerAdapter",
        mock="mock_devices:line_mock",
        clock="device",
        correction="",
        port=5005,
        words="a tracker speaking keo's line protocol (a hello line, then pose lines)",
    ),
    Protocol(
        "ros2",
        "tracker",
        codec="live.ros2",
        adapter="devices:Ros2PoseAdapter",
        mock="mock_ros2:pose_mock",
        clock="shared",
        correction="",
        port=0,
        words="a ROS 2 node publishing the topic",
    ),
)


def names(section: Section) -> tuple[str, ...]:
    """The protocols a section's device may speak, in the table's order."""
    return tuple(p.name for p in PROTOCOLS if p.section == section)


def protocol_for(section: Section, name: str) -> Protocol:
    """The row of `name` for a section's device; KeyError naming the choices otherwise."""
    for p in PROTOCOLS:
        if p.section == section and p.name == name:
            return p
    raise KeyError(f"{section}.protocol {name!r}: one of {', '.join(names(section))}")
