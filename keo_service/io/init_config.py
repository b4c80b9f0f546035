"""`keo init`: a complete, commented config for a cell (docs/design.md §6).

The values are the config's defaults except what the cell needs: the robot model (copied next
to the config, so the pair moves together), the protocols and their ports, and a plausible
placement of the tracker and the probe for the mocks (measure yours, or let `keo analyze
--registration-only` identify them). The file is checked by loading it back before it is
written.
"""

from __future__ import annotations

import math
import shutil
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import msgspec

from keo_service.core.errors import ConfigError
from keo_service.io.config import Config, load_config, parse_config
from keo_service.io.config_reference import commented_toml
from keo_service.io.protocols import names as protocol_names
from keo_service.io.protocols import protocol_for
from keo_service.resources import configs_dir

ROBOTS = ("ur10", "mh180")
ROBOT_PROTOCOLS = protocol_names("robot")  # the protocol table's (io.protocols)
TRACKER_PROTOCOLS = protocol_names("tracker")


@dataclass(frozen=True)
class InitOptions:
    robot: str  # "ur10", "mh180" or a URDF path
    robot_protocol: str
    tracker_protocol: str
    out: Path
    cell: str = "cell1"
    robot_host: str = "127.0.0.1"
    robot_port: int = 0  # 0: the protocol's default
    tracker_host: str = "127.0.0.1"
    tracker_port: int = 5005
    listen: str = "tcp/127.0.0.1:7447"
    force: bool = False


CLOCK_STATE_DIR = "clock-state"  # beside the config


def _urdf_source(robot: str) -> Path:
    if robot in ROBOTS:
        return configs_dir() / "robots" / f"{robot}.urdf"
    path = Path(robot)
    if path.suffix.lower() != ".urdf" or not path.is_file():
        raise ConfigError(
            "--robot", "robot", f"'{robot}' is neither {' nor '.join(ROBOTS)} nor a URDF file"
        )
    return path


def _frames(urdf: Path) -> tuple[str, str, int]:
    """The base and flange frames to use (base_link and tool0 when the URDF has them, else its
    root link and the end of its chain) and the number of moving joints."""
    try:
        root = ET.parse(urdf).getroot()
    except ET.ParseError as exc:
        raise ConfigError("--robot", "robot", f"{urdf}: not valid XML: {exc}") from None
    links = [e.get("name", "") for e in root.iter("link")]
    joints = list(root.iter("joint"))
    children = {j.find("child").get("link", "") for j in joints if j.find("child") is not None}  # type: ignore[union-attr]
    parents = {j.find("parent").get("link", "") for j in joints if j.find("parent") is not None}  # type: ignore[union-attr]
    moving = sum(1 for j in joints if j.get("type") in ("revolute", "continuous", "prismatic"))
    base = (
        "base_link" if "base_link" in links else next((x for x in links if x not in children), "")
    )
    leaves = [x for x in links if x not in parents]
    flange = "tool0" if "tool0" in links else (leaves[-1] if leaves else "")
    if not base or not flange or moving == 0:
        raise ConfigError("--robot", "robot", f"{urdf}: no kinematic chain found")
    return base, flange, moving


def _cell_values(opts: InitOptions, urdf_name: str, base: str, flange: str) -> dict[str, object]:
    """The config's values for this cell: defaults plus what differs."""
    ur = opts.robot == "ur10"
    robot: dict[str, object] = {
        "urdf": urdf_name,
        "base_frame": base,
        "flange_frame": flange,
        "protocol": opts.robot_protocol,
        "host": opts.robot_host,
        "port": opts.robot_port,
    }
    if opts.robot_protocol == "rtde":
        robot["correction"] = "none"
    return {
        "cell": opts.cell,
        "robot": robot,
        # a probe 100 mm (UR10) or 150 mm (MH180) out of the flange
        "tool": {"xyz": [0.0, 0.0, 0.1 if ur else 0.15], "rpy": [0.0, 0.0, 0.0]},
        # the tracker 3 m (4 m) in front of the robot, turned to face it
        "tracker": {
            "xyz": [3.0, 0.0, 0.0] if ur else [4.0, 0.5, 0.0],
            "rpy": [0.0, 0.0, math.pi],
            "protocol": opts.tracker_protocol,
            "host": opts.tracker_host,
            "port": opts.tracker_port,
        },
        "bus": {"mode": "peer", "listen": [opts.listen], "connect": []},
        # a restarted adapter goes on with its device clock's mapping (docs/timing.md)
        "timing": {"clock_state_dir": CLOCK_STATE_DIR},
    }


def _header(opts: InitOptions, urdf_name: str) -> str:
    robot = opts.robot if opts.robot in ROBOTS else Path(opts.robot).name
    name = opts.out.name
    # ros2: the mocks are ROS 2 drivers publishing on this config's bus (rmw_zenoh)
    robot_mock = f"keo mock robot --config {name} --loop"
    tracker_mock = f"keo mock tracker --config {name} --loop"
    return f"""keo config: {robot} over {opts.robot_protocol}, a {opts.tracker_protocol} tracker
(written by `keo init`; every key with its meaning [unit], allowed values and default).

Relative paths are relative to this file: the robot model is {urdf_name} beside it.
[tool] and [tracker] hold a plausible probe and tracker placement for the mocks: measure
yours, or let `keo analyze --registration-only` identify them from a recording.

Try it with mock devices, each command in its own terminal (the mocks agree on their time
base by themselves; --loop plays the scenario again and again):
  keo run --config {name}
  {robot_mock}
  {tracker_mock}
  keo adapter encoder --config {name}
  keo adapter tracker --config {name}
  keo status --config {name}
Reference: docs/config.md; the tracker line protocol: docs/line-protocol.md."""


def write_init_config(opts: InitOptions) -> Config:
    """Write the config (and the URDF beside it); returns the config as loaded back."""
    if opts.robot_protocol not in ROBOT_PROTOCOLS:
        raise ConfigError("--robot-protocol", "robot.protocol", f"one of {ROBOT_PROTOCOLS}")
    if opts.tracker_protocol not in TRACKER_PROTOCOLS:
        raise ConfigError("--tracker-protocol", "tracker.protocol", f"one of {TRACKER_PROTOCOLS}")
    out = opts.out
    if out.exists() and not opts.force:
        raise ConfigError("--out", "out", f"{out} exists; choose another file or pass --force")
    source = _urdf_source(opts.robot)
    base, flange, nq = _frames(source)
    fixed = protocol_for("robot", opts.robot_protocol).joints
    if fixed and nq != fixed:
        raise ConfigError(
            "--robot", "robot.urdf", f"{nq} joints; {opts.robot_protocol} reports {fixed}"
        )
    out.parent.mkdir(parents=True, exist_ok=True)
    target = out.parent / source.name
    if target.resolve() != source.resolve():
        if target.exists() and target.read_bytes() != source.read_bytes():
            raise ConfigError("--robot", "robot.urdf", f"{target} exists and differs from {source}")
        shutil.copyfile(source, target)
    values = _cell_values(opts, source.name, base, flange)
    config = parse_config(values, source=str(out), base_dir=out.parent)
    config = msgspec.structs.replace(  # written relative to the config, as given
        config,
        robot=msgspec.structs.replace(config.robot, urdf=source.name),
        timing=msgspec.structs.replace(config.timing, clock_state_dir=CLOCK_STATE_DIR),
    )
    text = commented_toml(config, _header(opts, source.name))
    out.write_text(text, encoding="utf-8")
    return load_config(out)
