"""`keo estimate`: the service's own alignment and observer over recorded files.

Recordings go through the batch path (`core.batch`: the streaming estimator's output computed
with array operations); what it does not cover (the "latest" alignment, more tracker samples
waiting at once than the live queue holds) runs sample by sample through `Estimator`."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from keo_service.core.batch import BatchResult, BatchUnsupportedError, estimate_batch
from keo_service.core.estimator import Estimator, EstimatorSettings, run_offline
from keo_service.io.cell import cell_from_config, estimator_settings
from keo_service.io.config import Config
from keo_service.io.interchange import read_encoder, read_tracker, write_estimate_table
from keo_service.io.mcap_files import is_mcap, read_mcap


@dataclass
class OfflineResult:
    table: BatchResult  # one row per estimate
    path: str  # "batch", or "streaming (<why>)"


def estimate_files(
    config: Config,
    encoder_path: str | Path,
    tracker_path: str | Path,
    settings: EstimatorSettings | None = None,
    streaming: bool = False,
) -> OfflineResult:
    cell = cell_from_config(config)
    names = cell.robot.joint_names
    # a ROS 2 MCAP recording may stand for either file (or both)
    encoder = (
        read_mcap(encoder_path, names)[0]
        if is_mcap(encoder_path)
        else read_encoder(encoder_path, nq=cell.robot.nq)
    )
    tracker = (
        read_mcap(tracker_path, names)[1] if is_mcap(tracker_path) else read_tracker(tracker_path)
    )
    settings = settings or estimator_settings(config)
    streams = (encoder.t, encoder.q, tracker.t, tracker.p, tracker.quat)
    why = "asked for"
    if not streaming:
        try:
            return OfflineResult(estimate_batch(cell, settings, *streams), "batch")
        except BatchUnsupportedError as exc:
            why = str(exc)
    estimator = Estimator(cell, settings)
    estimates = run_offline(estimator, *streams)
    table = BatchResult.from_estimates(
        estimates,
        estimator.channels or (),
        cell.robot.nq,
        dict(estimator.counters),
        list(estimator.messages),
    )
    return OfflineResult(table, f"streaming ({why})")


def write_estimates(path: str | Path, result: OfflineResult) -> None:
    t = result.table
    write_estimate_table(path, t.t, t.measured, t.estimate, t.flags, t.channels)
