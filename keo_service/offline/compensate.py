"""`keo compensate`: the joints (and the nominal-model pose to command) that put the user's
TCP on each target under the identified model, as a library function.

    from keo_service import compensate
    result = compensate("ur10_B/analysis/model.toml", "targets.csv", "compensated.csv")
    print(result.summary["correction_mm"], result.region)

The model is `keo analyze`'s model.toml, in the nominal robot's frames (see
`keo_service.core.compensation`): a correction is the model's kinematic error at the target,
not a rigid motion the tracker registration absorbed. The targets' and the output's columns:
`keo_service.io.targets`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from keo_service.core.compensation import (
    FLAGS,
    CalibratedRegion,
    Compensated,
    ToolModel,
)
from keo_service.core.compensation import (
    compensate as solve_targets,
)
from keo_service.core.model_corrections import approach_directions
from keo_service.core.rotations import quaternion_matrices
from keo_service.fit.accuracy import predicted_position_sigma
from keo_service.io.analysis_report import saved_accuracy
from keo_service.io.cell import tool_model
from keo_service.io.config import Config, load_config
from keo_service.io.targets import Targets, read_targets, write_compensated


@dataclass
class CompensateResult:
    """What `keo compensate` writes and prints.

    Attributes:
        result: the solve per target (`core.compensation.Compensated`): the corrected joints
            (rad), the nominal-model tool pose to command (m, rotation matrix), the
            correction (m, rad) and the solve's residual (m, rad), the flags per target.
        targets: the targets as read (`io.targets.Targets`).
        region: the model's calibrated region; None for a model.toml that does not state it.
        accuracy_mm: (N,) the model's predicted position accuracy (RMS, mm) at each target in
            a session other than the one it was calibrated in (the usual case: compensation
            runs on later days), the between-session term `[model] accuracy_session_mm`
            included; NaN where the model states none or for a tool orientation no
            calibration pose had.
        summary: what the command prints (`--json`): counts of the flags, the corrections'
            RMS and max (mm, mrad), the residuals' max (um, urad), the region, the stated
            accuracy and its between-session term.
        out: the output file written, None when none was asked for.
        accuracy_same_session_mm: (N,) the same without the between-session term: what the
            model states for the session it was calibrated in.
    """

    result: Compensated
    targets: Targets
    region: CalibratedRegion | None
    accuracy_mm: np.ndarray
    summary: dict[str, Any]
    out: Path | None
    accuracy_same_session_mm: np.ndarray | None = None


def compensate_targets(model: ToolModel, targets: Targets) -> Compensated:
    """The goals of the targets and their compensation. Backlash (a direction-dependent
    effect) takes each joint's approach direction from the row order, as a program runs."""
    seeds: np.ndarray | None = targets.q
    if targets.is_program:
        assert seeds is not None
        R_goal, p_goal = model.poses(seeds, identified=False)
        nominal = True
    else:
        assert targets.p is not None
        assert targets.quat is not None
        R_goal = np.ascontiguousarray(quaternion_matrices(targets.quat).transpose(2, 0, 1))
        p_goal, nominal = targets.p, False
    direction = None
    corr = model.corrections
    if corr is not None and np.any(corr.backlash) and seeds is not None:
        direction = approach_directions(seeds)
    return solve_targets(model, R_goal, p_goal, seeds, direction, seeds_are_nominal=nominal)


def predicted_accuracy(config: Config, result: Compensated) -> tuple[np.ndarray, np.ndarray]:
    """The model's predicted position accuracy (RMS, mm) at each target's compensated joints,
    by the rule `keo analyze` states and judges it with (`fit.accuracy`): its held-out RMS
    inside the calibrated joint ranges, rising to the extrapolation bands' figure over the
    maps' fade length outside them. Returns (in another session, in the calibration session):
    the first adds the between-session term `[model] accuracy_session_mm` in quadrature,
    because a program is compensated on days after the calibration, and what differs between
    sessions is in no held-out pose of the session the model was fitted on. Stated outside
    the calibrated region too, where the rule was judged (docs/analyze.md: each UR10 series'
    model on the other's poses, most of them outside its region); NaN where the model states
    none, or for a tool orientation no calibration pose had."""
    n = len(result.flags)
    stated = saved_accuracy(config)
    m = config.model
    if stated is None:  # a model.toml without calibrated ranges: one figure everywhere
        same = np.full(n, m.accuracy_mm if m.accuracy_mm > 0.0 else np.nan)
        later = np.sqrt(same**2 + m.accuracy_session_mm**2)
    else:
        same = predicted_position_sigma(stated, result.q)
        later = predicted_position_sigma(stated, result.q, off_session=True)
    if result.outside_region_m is not None:
        unseen = np.isinf(result.outside_region_m)
        same[unseen] = np.nan
        later[unseen] = np.nan
    return later, same


def _rms(v: np.ndarray) -> float:
    return float(np.sqrt(np.mean(v**2)))


def _outside_region(d: np.ndarray) -> dict[str, Any]:
    """How many targets lie outside the calibrated region, and the farthest (mm; None when
    one had an orientation no calibration pose had)."""
    out = d[d > 0.0]
    return {
        "targets": int(out.size),
        "max_mm": None if np.isinf(out).any() else (float(out.max() * 1e3) if out.size else 0.0),
        "unseen_orientation": int(np.isinf(out).sum()),
    }


def _region_summary(region: CalibratedRegion | None, names: list[str]) -> dict[str, Any] | None:
    if region is None:
        return None
    return {
        "joints_rad": {
            n: [float(lo), float(hi)]
            for n, lo, hi in zip(names, region.q_min, region.q_max, strict=True)
        },
        "tool_boxes_m": [
            {
                "band": b.band,
                "poses": b.poses,
                "lower": b.lower.tolist(),
                "upper": b.upper.tolist(),
            }
            for b in region.bands
        ],
    }


def compensate(
    config: Config | str | Path,
    targets: str | Path,
    out: str | Path | None = None,
    accuracy_columns: bool = False,
) -> CompensateResult:
    """The joints (and the nominal-model pose to command) that put the user's TCP on each
    target under the identified model (`keo compensate`).

    Args:
        config: `keo analyze`'s model.toml (its path, or loaded as a `Config`): the model
            with its identified effects.
        targets: the targets CSV (`keo_service.io.targets`): a joint program `q1..qN` (rad)
            or tool poses `x,y,z,qw,qx,qy,qz` (m, scalar-first quaternion).
        out: where to write the output CSV; None: write nothing.
        accuracy_columns: also write predicted_mm, predicted_mrad, accuracy_mm (in a later
            session), accuracy_same_session_mm (in the calibration session) and
            outside_region_mm.

    Returns:
        The solve, the targets, the region, the predicted accuracy and the summary.

    Raises:
        ConfigError: the config cannot be read or has no identified model (naming the key).
        DataFormatError: the targets file is missing or malformed (naming line and column).
    """
    if not isinstance(config, Config):
        config = load_config(config)
    model = tool_model(config, require_effects=True)
    read = read_targets(targets, model.nq)
    result = compensate_targets(model, read)
    accuracy, same_session = predicted_accuracy(config, result)
    out_path = None if out is None else Path(out)
    if out_path is not None:
        write_compensated(
            out_path,
            read,
            result,
            accuracy if accuracy_columns else None,
            same_session if accuracy_columns else None,
        )
    counts = dict.fromkeys(FLAGS, 0)
    for row in result.flags:
        for f in row:
            counts[f] += 1
    ok = np.array([not ({"unreachable", "not_converged"} & set(f)) for f in result.flags])
    saved = saved_accuracy(config)
    session_mm = saved.session_mm if saved is not None else config.model.accuracy_session_mm
    session_source = (
        saved.session_source if saved is not None else config.model.accuracy_session_source
    )
    stated = np.isfinite(accuracy)
    pred_m = result.predicted_m if result.predicted_m is not None else np.zeros(0)
    pred_r = result.predicted_rad if result.predicted_rad is not None else np.zeros(0)
    summary: dict[str, Any] = {
        "out": None if out_path is None else str(out_path),
        "targets": int(result.q.shape[0]),
        "form": "joint program" if read.is_program else "tool poses",
        "tool_frame": {"xyz": list(config.tool.xyz), "rpy": list(config.tool.rpy)},
        "flags": counts,
        "correction_mm": {
            "rms": _rms(result.correction_m * 1e3),
            "max": float(np.max(result.correction_m) * 1e3),
        },
        "correction_mrad": {
            "rms": _rms(result.correction_rad * 1e3),
            "max": float(np.max(result.correction_rad) * 1e3),
        },
        "predicted_mm_rms": _rms(pred_m * 1e3) if pred_m.size else None,
        "predicted_mrad_rms": _rms(pred_r * 1e3) if pred_r.size else None,
        "model_accuracy_mm": config.model.accuracy_mm or None,
        "accuracy_session_mm": session_mm,
        "accuracy_session_source": session_source,
        "accuracy_mm_rms": _rms(accuracy[stated]) if stated.any() else None,
        "accuracy_stated_targets": int(stated.sum()),
        "model_accuracy_mrad": config.model.accuracy_mrad or None,
        "residual_um_max": float(np.max(result.residual_m[ok]) * 1e6) if ok.any() else None,
        "residual_urad_max": float(np.max(result.residual_rad[ok]) * 1e6) if ok.any() else None,
        "calibrated_region": _region_summary(model.region, list(model.robot.joint_names)),
        "outside_region": None
        if result.outside_region_m is None
        else _outside_region(result.outside_region_m),
    }
    return CompensateResult(result, read, model.region, accuracy, summary, out_path, same_session)
