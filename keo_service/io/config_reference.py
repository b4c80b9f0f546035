"""The config reference: one description per key, kept here and nowhere else.

`keo init` writes a commented config from it and docs/config.md is generated from it; both
walk the config's msgspec Structs (`io.config`) for the keys, types, bounds and defaults, so
a key added to the Structs without a line here fails the tests (and a line here without its
key too). Regenerate the page with `python -m keo_service.io.config_reference docs/config.md`.
"""

from __future__ import annotations

import sys
import textwrap
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec
import tomli_w

from keo_service.io.config import (
    DEFAULT_ROBOT_CLOCKS,
    DEFAULT_ROBOT_PORTS,
    DEFAULT_TRACKER_CLOCKS,
    Config,
)

# section -> what it is (None: the top level)
SECTIONS: dict[str, str] = {
    "": "the cell",
    "robot": "the robot: its model and the controller's joint stream",
    "tool": "the nominal tool frame seen from the flange (T_nt)",
    "tracker": "the tracker: its frame seen from the robot base (T_bk) and its stream",
    "observer": "the observer (docs/design.md §2)",
    "timing": "aligning the two streams (docs/design.md §3)",
    "bus": "Zenoh: where `keo run` listens and the other processes connect",
    "bus.roles": "mTLS certificate common name -> role (needs bus.tls_mtls and "
    "bus.access_control); roles: encoder, tracker, service, client, operator, router (a hub: "
    "`keo router`'s certificate)",
    "model": "effects `keo analyze` identified (it writes them into model.toml); applied live: "
    "joint offsets, placement, compliance, cyclic, joint-angle maps",
    "ros2": "ROS 2 (rmw_zenoh's wire format on keo's own Zenoh sessions)",
    "compensation": "limits on live corrections (keo/<cell>/correction): larger or faster ones "
    "are clamped and counted",
}

# key -> (unit, what it means); "" unit: none
KEYS: dict[str, tuple[str, str]] = {
    "cell": ("", "the cell's name: every key expression is keo/<cell>/..."),
    "robot.urdf": ("", "the robot's URDF (required); a relative path is relative to this file"),
    "robot.base_frame": (
        "",
        "the URDF frame the robot base is (the tracker's placement is given in it)",
    ),
    "robot.flange_frame": ("", "the URDF frame of the flange (the tool is given in it)"),
    "robot.protocol": (
        "",
        "the controller's joint stream: motoros (ROS-Industrial simple "
        "message), rtde (Universal Robots), ros2 (sensor_msgs/msg/JointState "
        "over rmw_zenoh), kuka_rsi (KUKA RSI, keo is the UDP server), abb_egm "
        "(ABB EGM)",
    ),
    "robot.clock": (
        "",
        "what the joint stamps are: shared (already on the cell's common "
        "clock), device (the controller's own clock, mapped onto the host's), "
        "receipt (none: stamped on arrival); not given: the protocol's default ("
        + ", ".join(f"{k} {v}" for k, v in DEFAULT_ROBOT_CLOCKS.items())
        + ")",
    ),
    "robot.correction": (
        "",
        "where live corrections go: none, rtde_registers (six RTDE input "
        "double registers), kuka_rsi (RKorr in the RSI reply), abb_egm",
    ),
    "robot.correction_register": (
        "",
        "rtde_registers: the first of the six input double registers",
    ),
    "robot.host": ("", "the controller's address (kuka_rsi, abb_egm: the address keo listens on)"),
    "robot.port": (
        "",
        "the controller's port; 0: the protocol's default ("
        + ", ".join(f"{k} {v}" for k, v in DEFAULT_ROBOT_PORTS.items() if v)
        + ")",
    ),
    "robot.byte_order": ("", "motoros: the controller's byte order (big on FS100)"),
    "robot.frequency_hz": (
        "Hz",
        "rtde: the output rate asked of the controller (500 on e-Series, 125 on CB3)",
    ),
    "robot.joint_states_topic": (
        "",
        "ros2: the JointState topic; joints are picked by name into the URDF's order",
    ),
    "robot.silent_after_s": (
        "s",
        "a connected controller that sends nothing for this long is "
        "reported silent (adapter log and status)",
    ),
    "tool.xyz": ("m", "flange -> nominal tool frame: translation"),
    "tool.rpy": (
        "rad",
        "flange -> nominal tool frame: rotation, URDF convention R = Rz(yaw) Ry(pitch) Rx(roll)",
    ),
    "tracker.xyz": ("m", "robot base -> tracker frame: translation"),
    "tracker.rpy": ("rad", "robot base -> tracker frame: rotation (roll, pitch, yaw as tool.rpy)"),
    "tracker.probe_xyz": (
        "m",
        "the tracker's probe in the flange frame, a measurement frame (keo analyze identifies "
        "it; [tool] stays the TCP); not given: the probe is at [tool]",
    ),
    "tracker.probe_rpy": ("rad", "the probe's rotation in the flange frame (as tool.rpy)"),
    "tracker.host": ("", "line: the tracker's line-protocol server"),
    "tracker.port": ("", "line: its TCP port"),
    "tracker.protocol": (
        "",
        "line (keo's line protocol over TCP, docs/line-protocol.md) or "
        "ros2 (geometry_msgs/msg/PoseStamped, or PointStamped for a single "
        "reflector, in metres)",
    ),
    "tracker.pose_topic": ("", "ros2: the pose topic"),
    "tracker.clock": (
        "",
        "what the pose stamps are (as robot.clock); not given: the "
        "protocol's default ("
        + ", ".join(f"{k} {v}" for k, v in DEFAULT_TRACKER_CLOCKS.items())
        + ")",
    ),
    "tracker.uncertainty_um": ("um", "standard uncertainty per coordinate: the constant part"),
    "tracker.uncertainty_um_per_m": (
        "um/m",
        "and the part proportional to the distance from the tracker (a datasheet's 15 um + 6 um/m)",
    ),
    "tracker.silent_after_s": (
        "s",
        "a connected tracker that sends nothing for this long is "
        "reported silent (adapter log and status)",
    ),
    "observer.gain": (
        "1/s",
        "the observer's gain per channel px, py, pz, rx, ry, rz; one "
        "number: the same gain on every channel. Higher follows faster and "
        "passes more noise (`keo gain` prints the trade-off)",
    ),
    "observer.max_dt_s": (
        "s",
        "a sample after a longer gap updates as if it came this long "
        "after the previous one (one pose after a beam break cannot pull "
        "the estimate all the way)",
    ),
    "timing.delay_s": (
        "s",
        "the tracker stream lags the encoder stream by this much "
        "(`keo calibrate-delay` measures it)",
    ),
    "timing.delay_se_s": (
        "s",
        "the standard uncertainty of timing.delay_s (`keo calibrate-delay` writes it): the "
        "online fit takes delay_s as a prior with it and changes it only when the fits are "
        "incompatible with it at high confidence; with delay_s = 0 the delay is not known, "
        "whatever this says (found from the motion, estimates flagged until it settles)",
    ),
    "timing.drift_ppm": (
        "ppm",
        "the tracker's clock runs fast by this much relative to the encoder's",
    ),
    "timing.drift_ref_s": (
        "s",
        "stream time at which timing.delay_s holds when drift_ppm is not zero",
    ),
    "timing.alignment": (
        "",
        "interpolate (the joints at each pose's time) or latest (the "
        "reference method: the newest joints at a fixed rate)",
    ),
    "timing.sample_rate_hz": ("Hz", "latest: the fixed rate"),
    "timing.track_delay": (
        "",
        "follow the delay online while the tool moves, from delay_s (docs/timing-delay.md)",
    ),
    "timing.buffer_s": ("s", "encoder samples kept for alignment (stream time)"),
    "timing.max_gap_s": ("s", "two encoder samples further apart are not interpolated between"),
    "timing.stale_after_s": (
        "s",
        "a pose waits at most this long (stream time) for encoder data to cover it",
    ),
    "timing.max_stamp_age_s": (
        "s",
        "a shared-clock stamp older than this at receipt (or ahead of it) is counted and flagged",
    ),
    "timing.clock_state_dir": (
        "",
        "where adapters keep their device-clock mappings (offset, drift), so that a "
        "restarted adapter goes on on the same line instead of learning the drift anew; "
        '"" = not kept (docs/timing.md)',
    ),
    "bus.mode": ("", "peer (keo run listens itself) or client (through a router)"),
    "bus.listen": ("", "Zenoh endpoints `keo run` listens on"),
    "bus.connect": (
        "",
        "Zenoh endpoints the adapters, clients, keo echo/record/replay "
        "connect to; empty: bus.listen",
    ),
    "bus.multicast_scouting": (
        "",
        "find peers by multicast (off: two runs on one machine never meet by accident)",
    ),
    "bus.tls_root_ca": (
        "",
        "tls/ endpoints: the CA that signed the other side's certificate (relative to this file)",
    ),
    "bus.tls_certificate": ("", "this node's certificate (relative to this file)"),
    "bus.tls_private_key": ("", "this node's private key (relative to this file)"),
    "bus.tls_mtls": ("", "both sides prove who they are (mutual TLS)"),
    "bus.access_control": (
        "",
        "keo's sessions and `keo router` enforce per-key rights by role (needs tls_mtls)",
    ),
    "bus.roles": (
        "",
        'certificate common name -> role, e.g. "encoder.cell1" = "encoder"; a router\'s '
        'certificate gets "router" (leaves take what it relays)',
    ),
    "model.effects": ("", "the effects identified, by name"),
    "model.joint_offsets": ("rad", "per joint: zero offset"),
    "model.compliance": ("rad/(N m)", "per joint: deflection per torque of gravity"),
    "model.backlash": ("rad", "per joint (reported, not applied live)"),
    "model.cyclic": ("rad", "per joint: a1, b1, a2, b2 of the 1st and 2nd harmonic"),
    "model.placement": ("m, rad", "per joint: a 6-vector correcting the joint's placement"),
    "model.map_knots": (
        "rad",
        "per joint: the joint-angle map's knots (increasing); empty: no map",
    ),
    "model.map_values": ("rad", "per joint: the angle error at each knot"),
    "model.map_taper_rad": (
        "rad",
        "outside its knots each map fades linearly to zero over this distance (keo analyze "
        "chooses it on held-out bands at the ends of the joint ranges); absent: 0.1",
    ),
    "model.temperature_m_per_c": ("m/degC", "sensor drift with temperature (reported)"),
    "model.temperature_ref_c": ("degC", "the temperature where that drift is zero"),
    "model.time_drift_m_per_s": ("m/s", "sensor drift with time (reported)"),
    "model.time_ref_s": ("s", "the time where that drift is zero"),
    "model.coupling_joints": (
        "",
        "per coupling [j, k] (0-based): joint j's angle error moves with joint k's angle",
    ),
    "model.coupling_slopes": ("rad/rad", "per coupling: the linear term in joint k's angle"),
    "model.coupling_knots": ("rad", "per coupling: knots of the map of joint k's angle"),
    "model.coupling_values": ("rad", "per coupling: joint j's angle error at each knot"),
    "model.base_xyz": (
        "m",
        "the model in the nominal robot's frames: its base before the joint chain, the rigid "
        "motion the tracker registration cannot tell from the arm (keo analyze)",
    ),
    "model.base_rpy": ("rad", "and its rotation (as tool.rpy)"),
    "model.flange_xyz": (
        "m",
        "its flange after the joint chain, the rigid motion the probe mount cannot tell from "
        "the arm (keo analyze)",
    ),
    "model.flange_rpy": ("rad", "and its rotation (as tool.rpy)"),
    "model.flange_by": (
        "",
        'what pinned the flange: "probe" (the stated probe mount, taken as true) or "arm" (the '
        "arm closest to the nominal robot)",
    ),
    "model.calibrated_q_min": ("rad", "per joint: the smallest angle the calibration poses had"),
    "model.calibrated_q_max": ("rad", "per joint: the largest"),
    "model.calibrated_region": (
        "m",
        "per orientation band of the TCP (down, side, up): the box its positions swept in the "
        "base frame over the calibration poses: [[model.calibrated_region]] tables with band, "
        "poses, lower, upper",
    ),
    "model.accuracy_mm": (
        "mm",
        "the model's held-out position RMS within its own session (keo compensate adds "
        "accuracy_session_mm in quadrature for a later session)",
    ),
    "model.accuracy_mrad": ("mrad", "and its orientation RMS"),
    "model.accuracy_outside_mm": ("mm", "held-out position RMS on extrapolation bands"),
    "model.accuracy_session_mm": (
        "mm",
        "what another session adds to the stated accuracy in quadrature (from "
        "leave-one-session-out, else the bands' default; 0: that default)",
    ),
    "model.accuracy_session_source": ("", "how accuracy_session_mm was found"),
    "model.ripple_joints": ("", "per periodic joint error term: the joint (0-based)"),
    "model.ripple_periods_rad": ("rad", "per term: the period in that joint's angle"),
    "model.ripple_sin": ("rad", "per term: amplitude of sin(2 pi q / period)"),
    "model.ripple_cos": ("rad", "per term: amplitude of cos(2 pi q / period)"),
    "ros2.enabled": (
        "",
        "keo run also publishes each estimate as "
        "/keo/<cell>/kinematic_error (PoseWithCovarianceStamped)",
    ),
    "ros2.domain_id": ("", "the ROS 2 domain"),
    "ros2.distro": ("", "the ROS 2 distribution of the other side (type hashes)"),
    "ros2.publish_tf": ("", "also publish the error as a TF frame"),
    "compensation.max_mm": ("mm", "a live correction larger than this is clamped (and counted)"),
    "compensation.max_mrad": ("mrad", "and one turning more than this"),
    "compensation.max_rate_mm_s": ("mm/s", "and one changing faster than this"),
    "compensation.max_age_s": (
        "s",
        "a received correction older than this is not applied by any controller output (RTDE "
        "registers, KUKA RSI, ABB EGM): they send zero",
    ),
    "compensation.rate_hz": (
        "Hz",
        "the correction's own cycle: validity checked and the correction renewed or "
        "invalidated at least this often; 0: the observer's period, at least 2 ms",
    ),
    "compensation.stale_after_s": (
        "s",
        "a correction is valid only while the newest encoder sample, tracker pose and "
        "estimate arrived within this (host time); else it goes to zero within one cycle",
    ),
}


@dataclass(frozen=True)
class Entry:
    section: str  # "" for the top level, "robot", "bus.roles", ...
    key: str  # the full dotted key
    name: str  # the last part
    kind: str  # the TOML type with its bounds, in words
    default: Any  # msgspec.NODEFAULT when required
    unit: str
    text: str


# what the config's string patterns mean, in words
_PATTERNS = {
    r"^[A-Za-z0-9_\-]+$": "letters, digits, _ and -",
    r"^/[A-Za-z][A-Za-z0-9_]*(/[A-Za-z][A-Za-z0-9_]*)*$": "a ROS 2 topic name, e.g. /a/b",
}


def _kind(t: Any) -> str:
    info = msgspec.inspect
    if isinstance(t, info.UnionType):
        parts = [_kind(x) for x in t.types if not isinstance(x, info.NoneType)]
        return " or ".join(parts)
    if isinstance(t, info.LiteralType):
        return " | ".join(f'"{v}"' for v in sorted(map(str, t.values)))
    if isinstance(t, info.BoolType):
        return "true | false"
    if isinstance(t, info.IntType | info.FloatType):
        name = "integer" if isinstance(t, info.IntType) else "number"
        lo = f">= {t.ge:g}" if t.ge is not None else (f"> {t.gt:g}" if t.gt is not None else "")
        hi = f"<= {t.le:g}" if t.le is not None else (f"< {t.lt:g}" if t.lt is not None else "")
        bounds = ", ".join(b for b in (lo, hi) if b)
        return f"{name} ({bounds})" if bounds else name
    if isinstance(t, info.StrType):
        if t.pattern is None:
            return "string"
        return "string (" + _PATTERNS.get(t.pattern, f"matching {t.pattern}") + ")"
    if isinstance(t, info.ListType):
        n = ""
        if t.min_length is not None and t.min_length == t.max_length:
            n = f"{t.min_length} "
        inner = _kind(t.item_type).split(" (")[0]
        return f"list of {n}{inner}" + ("" if inner.endswith("s") else "s")
    if isinstance(t, info.DictType):
        return "table"
    return type(t).__name__


def _default(field: Any) -> Any:
    if field.default is not msgspec.NODEFAULT:
        return field.default
    if field.default_factory is not msgspec.NODEFAULT:
        return field.default_factory()
    return msgspec.NODEFAULT


def entries() -> Iterator[Entry]:
    """Every key of the config in the Structs' order, top-level keys first (TOML puts them
    before any table)."""
    top = msgspec.inspect.type_info(Config)
    assert isinstance(top, msgspec.inspect.StructType)
    sections = []
    for f in top.fields:
        if f.name == "source":
            continue
        if isinstance(f.type, msgspec.inspect.StructType):
            sections.append(f)
            continue
        yield _entry("", f)
    for sec in sections:
        assert isinstance(sec.type, msgspec.inspect.StructType)
        for f in sec.type.fields:
            yield _entry(sec.name, f)


def _entry(section: str, f: Any) -> Entry:
    key = f"{section}.{f.name}" if section else f.name
    unit, text = KEYS.get(key, ("", ""))
    kind = _kind(f.type)
    if key == "observer.gain":
        kind = "number, or " + kind
    return Entry(section, key, f.name, kind, _default(f), unit, text)


def missing_descriptions() -> list[str]:
    """Keys of the Structs without a description here, and descriptions without a key."""
    keys = {e.key for e in entries()}
    return sorted((keys - set(KEYS)) | (set(KEYS) - keys))


def _toml_value(value: Any) -> str:
    """One value as inline TOML (tomli-w escapes strings and writes floats exactly)."""
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return (
            "{" + ", ".join(f"{_toml_value(k)} = {_toml_value(v)}" for k, v in value.items()) + "}"
        )
    line = tomli_w.dumps({"v": value})
    return line.split("=", 1)[1].strip()


def _default_text(e: Entry) -> str:
    if e.default is msgspec.NODEFAULT:
        return "required"
    if e.default is None and e.key.startswith("tracker.probe_"):
        return "[tool]'s"
    if e.default is None:
        return "the protocol's"
    if e.key == "robot.port":
        return "0 (the protocol's)"
    if isinstance(e.default, dict):
        return "{}"
    return _toml_value(e.default)


def commented_toml(values: Config, header: str) -> str:
    """`values` as TOML, every key with its meaning, unit, allowed values and default above
    it. Keys of tables (bus.roles) are written as an empty table with an example."""
    doc = msgspec.to_builtins(values)
    lines = [f"# {line}" if line else "#" for line in header.splitlines()]
    lines.append("")
    section = None
    for e in entries():
        if e.section != section:
            section = e.section
            if section:
                lines += ["", f"# ---- [{section}]: {SECTIONS[section]}", f"[{section}]"]
        if e.key == "bus.roles":
            lines += [
                "",
                f"[{e.key}]",
                f"# {SECTIONS['bus.roles']}",
                '# "encoder.cell1" = "encoder"',
            ]
            continue
        value = doc[e.section][e.name] if e.section else doc[e.name]
        if value is None and e.key.startswith("tracker.probe_"):  # not given: at [tool]
            value = doc["tool"][e.name.removeprefix("probe_")]
        unit = f" [{e.unit}]" if e.unit else ""
        lines += textwrap.wrap(f"{e.text}{unit}", 96, initial_indent="# ", subsequent_indent="# ")
        default = _default_text(e)
        lines.append(
            f"#   {e.kind}; " + ("required" if default == "required" else f"default {default}")
        )
        lines.append(f"{e.name} = {_toml_value(value)}")
    return "\n".join(lines) + "\n"


def markdown() -> str:
    """docs/config.md."""
    out = [
        "# Config reference",
        "",
        "<!-- generated by `python -m keo_service.io.config_reference docs/config.md` from the",
        "     config types (keo_service/io/config.py) and their descriptions",
        "     (keo_service/io/config_reference.py); do not edit by hand -->",
        "",
        "A keo config is one TOML file. Every key is optional with the default shown except",
        "`robot.urdf`; unknown keys are errors (with a suggestion when a known key is close);",
        "relative paths are relative to the config file. `keo init` writes a complete config",
        "for a cell with every key below, commented. Units are SI on the wire and in files;",
        "the config's own units are in the Unit column.",
        "",
        "An error names the key, e.g. `c.toml: key 'observer.gain[2]': Expected `float` > 0.0`,",
        "and every command exits 2 on a bad config.",
    ]
    section = None
    for e in entries():
        if e.section != section:
            section = e.section
            title = f"`[{section}]`" if section else "Top level"
            out += [
                "",
                f"## {title}",
                "",
                SECTIONS[section][0].upper() + SECTIONS[section][1:] + ".",
                "",
                "| key | type | default | unit | meaning |",
                "|---|---|---|---|---|",
            ]
        cells = [f"`{e.name}`", e.kind, f"`{_default_text(e)}`", e.unit, e.text]
        out.append("| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |")
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    text = markdown()
    if args:
        Path(args[0]).write_text(text, encoding="utf-8")
    else:
        sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
