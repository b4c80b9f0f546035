"""model.toml, the file `keo analyze` writes and `keo run` and `keo compensate` read: the
input config with the identified model, stated so that a user can check it and carry it.

- Frames: the model in the nominal robot's frames (`core.compensation.pinning`): the rigid
  motions the tracker registration and the probe mount absorbed are moved out of the arm
  into `[tracker] xyz/rpy` and `[tracker] probe_xyz/rpy`; `[model] base_*/flange_*` say what
  was left. `[tool]` stays the user's TCP.
- Validity: the calibrated region (each joint's range, the tool's box per orientation band)
  and the model's held-out accuracy.
- Travel: only the keys the input config gave and the identified ones; paths relative to the
  file itself; a comment naming the config it came from.
"""

from __future__ import annotations

import os
import shutil
import tomllib
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import pinocchio as pin
import tomli_w

from keo_service.core.compensation import calibrated_region, pinning
from keo_service.io.cell import (
    corrections_from_config,
    probe_frame,
    robot_from_config,
    tool_model,
)
from keo_service.io.config import Config, RegionBandConfig

# keys whose value is a path, relative to the config file that holds it
PATH_KEYS = (
    ("robot", "urdf"),
    ("timing", "clock_state_dir"),
    ("bus", "tls_root_ca"),
    ("bus", "tls_certificate"),
    ("bus", "tls_private_key"),
)
# what keo analyze identifies (written whatever the input said)
IDENTIFIED = {
    "tracker": ("xyz", "rpy", "probe_xyz", "probe_rpy"),
    "timing": ("delay_s", "drift_ppm", "drift_ref_s"),
}


def _xyz_rpy(T: np.ndarray) -> tuple[list[float], list[float]]:
    return T[:3, 3].tolist(), pin.rpy.matrixToRpy(T[:3, :3]).tolist()


def pinned_config(
    config: Config,
    q: np.ndarray,
    position_only: bool,
    accuracy_mm: float = 0.0,
    accuracy_mrad: float = 0.0,
    calibrated_q: np.ndarray | None = None,
) -> Config:
    """`config` (with the fit's registration in [tracker] xyz/rpy, its probe in probe_xyz/rpy
    and its effects in [model], all for the raw chain) restated in the nominal robot's frames
    over the calibration joints q, with the calibrated region and the accuracy. The region
    (joint ranges, tool boxes) is that of `calibrated_q` (None: q): `keo analyze` gives the
    training rows, the poses the model was fitted on, so a held-out pose beyond them counts
    as outside, as it does for the maps' knots and the stated accuracy."""
    robot = robot_from_config(config)
    corrections = corrections_from_config(config.model, robot.nq, config.source)
    T_bk = pin.SE3(
        pin.rpy.rpyToMatrix(np.asarray(config.tracker.rpy, dtype=float)),
        np.asarray(config.tracker.xyz, dtype=float),
    ).homogeneous
    T_np = probe_frame(config).homogeneous
    pinned = pinning(robot, corrections, q, T_bk, T_np, position_only, stated_mount(config))
    base_xyz, base_rpy = _xyz_rpy(pinned.base)
    flange_xyz, flange_rpy = _xyz_rpy(pinned.flange)
    trk_xyz, trk_rpy = _xyz_rpy(pinned.T_bk)
    probe_xyz, probe_rpy = _xyz_rpy(pinned.T_np)
    tracker = msgspec.structs.replace(
        config.tracker, xyz=trk_xyz, rpy=trk_rpy, probe_xyz=probe_xyz, probe_rpy=probe_rpy
    )
    model = msgspec.structs.replace(
        config.model,
        base_xyz=base_xyz,
        base_rpy=base_rpy,
        flange_xyz=flange_xyz,
        flange_rpy=flange_rpy,
        flange_by=pinned.flange_by,
        accuracy_mm=float(accuracy_mm),
        accuracy_mrad=float(accuracy_mrad or 0.0),
    )
    out = msgspec.structs.replace(config, tracker=tracker, model=model)
    region = calibrated_region(tool_model(out), q if calibrated_q is None else calibrated_q)
    model = msgspec.structs.replace(
        model,
        calibrated_q_min=region.q_min.tolist(),
        calibrated_q_max=region.q_max.tolist(),
        calibrated_region=[
            msgspec.convert(
                {
                    "band": b.band,
                    "poses": b.poses,
                    "lower": b.lower.tolist(),
                    "upper": b.upper.tolist(),
                },
                RegionBandConfig,
            )
            for b in region.bands
        ],
    )
    return msgspec.structs.replace(out, model=model)


def stated_mount(config: Config) -> np.ndarray:
    """The probe mount the input config (`config.source`) stated: `[tracker] probe_xyz/rpy`,
    else its [tool] (a config whose tool is the probe); for a config built in code, its
    [tool]."""
    raw = _raw(config)
    tracker, tool = raw.get("tracker", {}), raw.get("tool", {})
    if "probe_xyz" in tracker or "probe_rpy" in tracker:
        xyz, rpy = tracker.get("probe_xyz", [0.0] * 3), tracker.get("probe_rpy", [0.0] * 3)
    elif raw:
        xyz, rpy = tool.get("xyz", [0.0] * 3), tool.get("rpy", [0.0] * 3)
    else:
        xyz, rpy = config.tool.xyz, config.tool.rpy
    T = np.eye(4)
    T[:3, :3] = pin.rpy.rpyToMatrix(np.asarray(rpy, dtype=float))
    T[:3, 3] = np.asarray(xyz, dtype=float)
    return T


def region_markdown(config: Config) -> list[str]:
    """The calibrated region as report lines."""
    m = config.model
    if not m.calibrated_q_min:
        return []
    robot = robot_from_config(config)
    lines = [
        "## Where the model is valid",
        "",
        "The calibration poses took the joints and the TCP ([tool]) here; `keo compensate` flags "
        "targets outside (naming the joint, or the orientation band, and how far).",
        "",
        "| joint | calibrated range (rad) |",
        "|---|---|",
    ]
    for name, lo, hi in zip(robot.joint_names, m.calibrated_q_min, m.calibrated_q_max, strict=True):
        lines.append(f"| {name} | {lo:+.3f} .. {hi:+.3f} |")
    lines += [
        "",
        "| tool z axis | poses | x (m) | y (m) | z (m) |",
        "|---|---|---|---|---|",
    ]
    for b in m.calibrated_region:
        lines.append(
            f"| {b.band} | {b.poses} | {b.lower[0]:+.3f} .. {b.upper[0]:+.3f} | "
            f"{b.lower[1]:+.3f} .. {b.upper[1]:+.3f} | {b.lower[2]:+.3f} .. {b.upper[2]:+.3f} |"
        )
    lines += [
        "",
        "(bands: the tool's z axis within 45 degrees of pointing down, of horizontal, or of "
        "pointing up; boxes in the robot base frame)",
        "",
    ]
    return lines


def region_report(config: Config) -> dict[str, Any] | None:
    """The calibrated region for report.json."""
    m = config.model
    if not m.calibrated_q_min:
        return None
    return {
        "q_min_rad": list(m.calibrated_q_min),
        "q_max_rad": list(m.calibrated_q_max),
        "tool_boxes_m": [msgspec.to_builtins(b) for b in m.calibrated_region],
    }


def _raw(config: Config) -> dict[str, Any]:
    source = Path(config.source) if config.source else None
    if source is None or not source.is_file():
        return {}
    try:
        return tomllib.loads(source.read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError):
        return {}


def write_model_toml(config: Config, out_dir: Path) -> Path:
    """model.toml in `out_dir`, with a copy of the robot's URDF beside it (so that the folder
    can be moved to another machine as it is). Returns the file's path."""
    out_dir.mkdir(parents=True, exist_ok=True)
    urdf = Path(config.robot.urdf)
    copy = out_dir / urdf.name
    if urdf.resolve() != copy.resolve():
        shutil.copyfile(urdf, copy)
    robot = msgspec.structs.replace(config.robot, urdf=str(copy))
    path = out_dir / "model.toml"
    path.write_text(model_toml(msgspec.structs.replace(config, robot=robot), out_dir))
    return path


def model_toml(config: Config, out_dir: Path) -> str:
    """The text of model.toml in `out_dir`: the keys the input config (`config.source`) gave,
    with their new values, the identified ones and the whole [model] section; paths relative
    to `out_dir`; a first comment naming the input config."""
    raw = _raw(config)
    full = msgspec.to_builtins(config)
    doc: dict[str, Any] = {"cell": config.cell}
    for name, section in full.items():
        if not isinstance(section, dict):
            continue
        given = raw.get(name, {}) if raw else section
        keep = set(given) | set(IDENTIFIED.get(name, ()))
        if name == "model":
            keep = set(section)
        entry = {k: v for k, v in section.items() if k in keep and v is not None}
        if name == "model":  # empty lists say nothing: leave them out
            entry = {
                k: v
                for k, v in entry.items()
                if v not in ([], 0.0) or k in ("effects", "map_taper_rad")
            }
            if not entry.get("map_knots"):  # a fade length without maps says nothing
                entry.pop("map_taper_rad", None)
        if entry:
            doc[name] = entry
    for section, key in PATH_KEYS:
        value = doc.get(section, {}).get(key)
        if value:
            doc[section][key] = Path(
                os.path.relpath(Path(value).resolve(), out_dir.resolve())
            ).as_posix()
    head = (
        f"# written by keo analyze from {config.source or 'a config built in code'}: that "
        "config's keys, the identified registration\n# ([tracker] xyz/rpy, probe_xyz/rpy) and "
        "model ([model]); [tool] is the TCP compensation targets refer to.\n"
        "# Paths are relative to this file.\n"
    )
    return head + tomli_w.dumps(doc)
