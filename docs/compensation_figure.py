"""The README's compensation figure: for a model `keo analyze` identified, what a compensated
program is predicted to achieve on the poses it held out (the same split as `keo analyze`),
beside the uncompensated error.

    python docs/compensation_figure.py CONFIG ENCODER TRACKER MODEL_TOML

For every held-out pose i (joints q_i, the probe measured at T_bk T_ks_i through the model's
registration, carried rigidly to the TCP: M_i = T_bk T_ks_i T_np^-1 T_nt with the model's
probe T_np and the user's [tool] T_nt): the program's target is the nominal tool pose
N(q_i). Uncompensated, the robot puts the tool at M_i: the error is N(q_i)^-1 M_i.
Compensated, `keo compensate` (the same code) gives joints q_c with Model(q_c) = N(q_i); the
real tool there is predicted from what the model still misses at q_i, carried to the nearby
q_c:
true(q_c) = Model(q_c) Model(q_i)^-1 M_i, so the error is Model(q_i)^-1 M_i. The Newton solve
runs on every held-out pose and its flags and residuals are reported.

Which registration the "uncompensated" column uses: model.toml's ([tracker] xyz/rpy and
probe_xyz/rpy), which keo analyze states in the nominal robot's frames (the rigid motion that
best carries the nominal robot onto the identified one over the calibration poses,
`keo_service.core.compensation.pinning`). It is therefore close to, not the same as,
report.json's `baseline.validation` (the nominal model with its own registration fitted, what
the README's uncompensated column quotes); both are printed.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pinocchio as pin

from keo_service.core.compensation import compensate
from keo_service.core.kinematics import se3_from_xyz_rpy
from keo_service.fit.analysis import split
from keo_service.io.cell import probe_frame, tool_model
from keo_service.io.config import load_config
from keo_service.offline.analyze import load_data


def errors(
    R_a: np.ndarray, p_a: np.ndarray, R_b: np.ndarray, p_b: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Position (mm) and rotation (mrad) of frames b seen from frames a."""
    pos = np.linalg.norm(np.einsum("nji,nj->ni", R_a, p_b - p_a), axis=1) * 1e3
    rot = np.array([np.linalg.norm(pin.log3(a.T @ b)) for a, b in zip(R_a, R_b, strict=True)])
    return pos, rot * 1e3


def main(config_path: str, encoder: str, tracker: str, model_path: str) -> dict[str, object]:
    config = load_config(config_path)
    data, position_only = load_data(config, Path(encoder), Path(tracker))
    assert not position_only
    _train, val = split(data.n)
    model_config = load_config(model_path)
    model = tool_model(model_config, require_effects=True)
    T_bk = se3_from_xyz_rpy(model_config.tracker.xyz, model_config.tracker.rpy)
    # probe -> TCP, rigid on the flange: the measurement carried to the user's tool
    T_pt = probe_frame(model_config).actInv(
        se3_from_xyz_rpy(model_config.tool.xyz, model_config.tool.rpy)
    )
    q = data.q[val]
    assert data.R_ks is not None
    R_s = np.einsum("ij,njk->nik", T_bk.rotation, data.R_ks[val])
    p_s = data.p_ks[val] @ T_bk.rotation.T + T_bk.translation
    R_m = np.einsum("nij,jk->nik", R_s, T_pt.rotation)
    p_m = p_s + np.einsum("nij,j->ni", R_s, T_pt.translation)
    R_n, p_n = model.poses(q, identified=False)
    R_i, p_i = model.poses(q, identified=True)
    result = compensate(model, R_n, p_n, q, seeds_are_nominal=True)
    un_pos, un_rot = errors(R_n, p_n, R_m, p_m)
    co_pos, co_rot = errors(R_i, p_i, R_m, p_m)
    flags: dict[str, int] = {}
    for row in result.flags:
        for f in row:
            flags[f] = flags.get(f, 0) + 1

    def rms(v: np.ndarray) -> float:
        return float(np.sqrt(np.mean(v * v)))

    baseline = None
    report = Path(model_path).parent / "report.json"
    if report.is_file():
        baseline = json.loads(report.read_text())["baseline"]["validation"]
    return {
        "held_out_poses": int(q.shape[0]),
        "nominal_own_registration": baseline,
        "uncompensated": {
            "pos_rms_mm": rms(un_pos),
            "pos_max_mm": float(un_pos.max()),
            "rot_rms_mrad": rms(un_rot),
        },
        "compensated_predicted": {
            "pos_rms_mm": rms(co_pos),
            "pos_max_mm": float(co_pos.max()),
            "rot_rms_mrad": rms(co_rot),
        },
        "correction_mm_rms": rms(result.correction_m * 1e3),
        "correction_mrad_rms": rms(result.correction_rad * 1e3),
        "solve_residual_max_m": float(result.residual_m.max()),
        "solve_residual_max_rad": float(result.residual_rad.max()),
        "flags": flags,
    }


if __name__ == "__main__":
    print(json.dumps(main(*sys.argv[1:5]), indent=2))
