"""The hot path: the estimator fed a 1 kHz recording in process, beside the naive floor
(the same work without the estimator's bookkeeping)."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

from keo_service.core.errors import KeoError
from keo_service.core.estimator import Estimator
from keo_service.core.settings import EstimatorSettings
from keo_service.io.cell import cell_from_config, estimator_settings
from keo_service.io.config import Config
from keo_service.sim.simulate import SimulatedRun, make_scenario, simulate


def khz_run(config: Config, seconds: float) -> SimulatedRun:
    scen = make_scenario(
        "path",
        {
            "duration_s": repr(seconds),
            "tracker_rate_hz": "1000",
            "tracker_rate_std_hz": "50",
            "encoder_rate_hz": "250",
            "encoder_rate_std_hz": "10",
        },
    )
    return simulate(cell_from_config(config), scen, seed=1)


def _hot_path_pass(
    cell: Any, settings: EstimatorSettings, run: SimulatedRun, with_rerun: bool
) -> tuple[int, float]:
    """One pass over the run with a fresh estimator: (aligned samples, CPU seconds of this
    process). `with_rerun`: every estimate goes to a `RerunWorker` as in `keo run --rrd`
    (encoded and piped to a process of its own); its buffer holds the whole pass, so nothing
    is dropped (a drop costs less than a frame), and the Rerun process finishes its file after
    the pass."""
    est = Estimator(cell, settings)
    worker = None
    tmp = None
    if with_rerun:
        from keo_service.live.rerun_process import RerunWorker

        tmp = tempfile.TemporaryDirectory()
        worker = RerunWorker(cell, rrd=Path(tmp.name) / "bench.rrd", max_buffer=1 << 30)
        worker.start()
    # the samples as the service gets them from decoded messages: floats and lists of floats
    quat = run.tracker.quat
    assert quat is not None  # the benchmark scenario is a 6-DoF probe
    enc_t, enc_q = run.encoder.t.tolist(), run.encoder.q.tolist()
    trk_t, trk_p, trk_q = run.tracker.t.tolist(), run.tracker.p.tolist(), quat.tolist()
    n_enc = len(enc_t)
    cpu0 = time.process_time()
    n = 0
    i = 0
    for j, t in enumerate(trk_t):
        while i < n_enc and enc_t[i] <= t:
            est.on_encoder(enc_t[i], enc_q[i])
            i += 1
        for e in est.on_tracker(t, trk_p[j], trk_q[j]):
            n += 1
            if worker is not None:
                worker.submit(e)
    cpu = time.process_time() - cpu0
    if worker is not None:
        worker.close(timeout=120.0)  # the Rerun process finishes the recording
        if worker.failure is not None or worker.dropped:
            raise KeoError(
                f"the Rerun process did not log every estimate ({worker.dropped} dropped): "
                f"{worker.failure}"
            )
    if tmp is not None:
        tmp.cleanup()
    return n, cpu


def _rate_summary(rates: list[float], n: int) -> dict[str, float]:
    rate = float(np.median(rates))
    return {
        "samples": n,
        "repeats": len(rates),
        "samples_per_s": rate,
        "samples_per_s_best": max(rates),
        "samples_per_s_worst": min(rates),
        "us_per_sample": 1e6 / rate,
        "core_share_at_1kHz_pct": 100.0 * 1000.0 / rate,
    }


def hot_path(config: Config, seconds: float, with_rerun: bool, repeats: int = 5) -> dict[str, Any]:
    """Aligned samples per CPU second, `repeats` passes over the same run; the median is the
    figure (a shared machine's noise only ever slows a pass down), best and worst beside it.
    `with_rerun`: what `keo run --rrd` adds in the service's process (the Rerun process's own
    CPU is in the end-to-end `--rrd` run, where it works at the tracker's pace)."""
    run = khz_run(config, seconds)
    cell = cell_from_config(config)
    settings = estimator_settings(config)
    rates = []
    n = 0
    for _ in range(repeats):
        n, cpu = _hot_path_pass(cell, settings, run, with_rerun)
        rates.append(n / cpu)
    summary: dict[str, Any] = _rate_summary(rates, n)
    if with_rerun:
        summary["rerun"] = "process"  # what the pass measured (earlier runs: "same thread")
    return summary


def floor_pass(cell: Any, run: SimulatedRun) -> tuple[int, float, float]:
    """The per-sample floor of Python over Pinocchio: for each tracker sample only what the
    math needs (forward kinematics on preallocated data, the tool and sensor poses, the
    error transform and its log3), joints from the newest encoder sample, no validation, no
    interpolation, no observer: (samples, CPU seconds, wall seconds)."""
    model, data = cell.robot.model, cell.robot.create_data()
    flange, T_nt, T_bk = cell.robot.flange_frame_id, cell.T_nt, cell.T_bk
    quat = run.tracker.quat
    assert quat is not None
    xyzquat = np.hstack([run.tracker.p, quat[:, 1:], quat[:, :1]])  # pin's x y z qx qy qz qw
    enc_index = np.searchsorted(run.encoder.t, run.tracker.t, side="right") - 1
    cpu0, wall0 = time.process_time(), time.perf_counter()
    n = 0
    for j in range(run.tracker.t.size):
        i = enc_index[j]
        if i < 0:
            continue
        pin.framesForwardKinematics(model, data, run.encoder.q[i])
        T_bt = data.oMf[flange] * T_nt
        T_bs = T_bk * pin.XYZQUATToSE3(xyzquat[j])
        err = T_bt.actInv(T_bs)
        pin.log3(err.rotation)
        n += 1
    return n, time.process_time() - cpu0, time.perf_counter() - wall0


def hot_path_and_floor(
    config: Config, seconds: float, repeats: int = 7
) -> tuple[dict[str, float], dict[str, float]]:
    """keo's hot path and the naive floor in alternating passes over the same run, so that a
    noisy neighbour slows both alike; the ratio is the median of the per-pair ratios."""
    run = khz_run(config, seconds)
    cell = cell_from_config(config)
    settings = estimator_settings(config)
    hot, floor, ratios = [], [], []
    n_hot = n_floor = 0
    for _ in range(repeats):
        n_floor, cpu_floor, _wall = floor_pass(cell, run)
        n_hot, cpu_hot = _hot_path_pass(cell, settings, run, False)
        floor.append(n_floor / cpu_floor)
        hot.append(n_hot / cpu_hot)
        ratios.append(hot[-1] / floor[-1])
    hot_summary = _rate_summary(hot, n_hot)
    hot_summary["over_floor"] = float(np.median(ratios))
    hot_summary["over_floor_best"] = max(ratios)
    hot_summary["over_floor_worst"] = min(ratios)
    return hot_summary, _rate_summary(floor, n_floor)
