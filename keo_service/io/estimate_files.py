"""`keo estimate`: the service's own alignment and observer over recorded files."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from keo_service.core.estimator import Estimate, Estimator, EstimatorSettings, run_offline
from keo_service.io.cell import cell_from_config, estimator_settings
from keo_service.io.config import Config
from keo_service.io.interchange import EstimateWriter, read_encoder, read_tracker
from keo_service.io.mcap_files import is_mcap, read_mcap


@dataclass
class OfflineResult:
    estimates: list[Estimate]
    counters: dict[str, int]
    messages: list[str]
    channels: tuple[str, ...]


def estimate_files(
    config: Config,
    encoder_path: str | Path,
    tracker_path: str | Path,
    settings: EstimatorSettings | None = None,
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
    estimator = Estimator(cell, settings or estimator_settings(config))
    estimates = run_offline(estimator, encoder.t, encoder.q, tracker.t, tracker.p, tracker.quat)
    return OfflineResult(
        estimates, dict(estimator.counters), list(estimator.messages), estimator.channels or ()
    )


def write_estimates(path: str | Path, result: OfflineResult) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", encoding="utf-8", newline="") as f:
        writer = EstimateWriter(f, result.channels)
        for e in result.estimates:
            writer.write(e.t, e.measured, e.estimate, e.flags)
