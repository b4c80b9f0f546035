"""`keo estimate`: the service's own alignment and observer over recorded files.

Recordings go through the batch path (`core.batch`: the streaming estimator's output computed
with array operations); what it does not cover (the "latest" alignment, more tracker samples
waiting at once than the live queue holds) runs sample by sample through `Estimator`."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from keo_service.io.interchange import read_encoder, read_tracker, write_estimate_table

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
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="keo-read") as pool:
        # a tracker CSV is read while the cell is built and the encoder file read (polars
        # parses without the GIL); an error in the encoder file still comes first
        tracker_csv = None if _maybe_mcap(tracker_path) else pool.submit(read_tracker, tracker_path)
        # the kinematics libraries load while it parses (Pinocchio alone takes ~0.1 s)
        from keo_service.core.batch import BatchResult, BatchUnsupportedError, estimate_batch
        from keo_service.core.estimator import Estimator, run_offline
        from keo_service.io.cell import cell_from_config, estimator_settings

        cell = cell_from_config(config)
        names = cell.robot.joint_names
        # a ROS 2 MCAP recording may stand for either file (or both)
        if _maybe_mcap(encoder_path):
            from keo_service.io.mcap_files import read_mcap

            encoder = read_mcap(encoder_path, names)[0]
        else:
            encoder = read_encoder(encoder_path, nq=cell.robot.nq)
        if tracker_csv is None:
            from keo_service.io.mcap_files import read_mcap

            tracker = read_mcap(tracker_path, names)[1]
        else:
            tracker = tracker_csv.result()
    settings = settings or estimator_settings(config)
    streams = (encoder.t, encoder.q, tracker.t, tracker.p, tracker.quat)
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


def _maybe_mcap(path: str | Path) -> bool:
    """An MCAP recording (rosbags, ~40 ms to import, is loaded only for one)."""
    if not (Path(path).suffix == ".mcap" or Path(path).is_dir()):
        return False
    from keo_service.io.mcap_files import is_mcap

    return is_mcap(path)


def write_estimates(path: str | Path, result: OfflineResult) -> None:
    t = result.table
    write_estimate_table(path, t.t, t.measured, t.estimate, t.flags, t.channels)
