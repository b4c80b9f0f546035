"""`keo estimate`: the service's own alignment and observer over a recording.

Recordings go through the batch path (`core.batch`: the streaming estimator's output computed
with array operations); what it does not cover (the "latest" alignment, more tracker samples
waiting at once than the live queue holds) runs sample by sample through `Estimator`."""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from keo_service.io.interchange import write_estimate_table
from keo_service.offline.recording import Recording, read_recording

if TYPE_CHECKING:
    from keo_service.core.batch import BatchResult
    from keo_service.core.settings import EstimatorSettings
    from keo_service.io.config import Config


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
    """Read the recording once and estimate over it (the config's estimator settings unless
    given)."""
    recording = read_recording(config, encoder_path, tracker_path, while_parsing=load_estimators)
    if settings is None:
        from keo_service.io.cell import estimator_settings

        settings = estimator_settings(config)
    return estimate_recording(recording, settings, streaming)


def estimate_recording(
    recording: Recording, settings: EstimatorSettings, streaming: bool = False
) -> OfflineResult:
    """The batch path, or the streaming estimator when asked for or when the batch path
    cannot reproduce it sample-exactly."""
    from keo_service.core.batch import BatchResult, BatchUnsupportedError, estimate_batch
    from keo_service.core.estimator import Estimator, run_offline

    cell = recording.cell
    streams = recording.streams()
    why = "asked for"
    if not streaming:
        try:
            table = estimate_batch(cell, settings, *streams, keep_joints=False)
            return OfflineResult(table, "batch")
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


def load_estimators() -> None:
    """Import both estimators while the tracker file parses: their imports then add no wall
    time to a short command."""
    for module in ("keo_service.core.batch", "keo_service.core.estimator"):
        importlib.import_module(module)


def write_estimates(path: str | Path, result: OfflineResult) -> None:
    t = result.table
    write_estimate_table(path, t.stamp, t.measured, t.estimate, t.flags, t.channels)
