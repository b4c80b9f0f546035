"""`keo estimate`: the service's own alignment and observer over recorded files.

Recordings go through the batch path (`core.batch`: the streaming estimator's output computed
with array operations); what it does not cover (the "latest" alignment, more tracker samples
waiting at once than the live queue holds) runs sample by sample through `Estimator`."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from keo_service.core.batch import BatchUnsupportedError, estimate_batch
from keo_service.core.estimator import Estimator, EstimatorSettings, run_offline
from keo_service.io.cell import cell_from_config, estimator_settings
from keo_service.io.config import Config
from keo_service.io.interchange import read_encoder, read_tracker, write_estimate_table
from keo_service.io.mcap_files import is_mcap, read_mcap


@dataclass
class OfflineResult:
    t: np.ndarray
    measured: np.ndarray  # NaN where held
    estimate: np.ndarray
    flags: list[str]  # "" or flags joined by "|"
    counters: dict[str, int]
    messages: list[str]
    channels: tuple[str, ...]
    path: str  # "batch", or "streaming (<why>)"

    @property
    def held(self) -> int:
        return int(np.isnan(self.measured).any(axis=1).sum()) if self.measured.size else 0


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
    if streaming:
        return _streaming(Estimator(cell, settings), streams, "streaming (asked for)")
    try:
        batch = estimate_batch(cell, settings, *streams)
    except BatchUnsupportedError as why:
        return _streaming(Estimator(cell, settings), streams, f"streaming ({why})")
    return OfflineResult(
        batch.t,
        batch.measured,
        batch.estimate,
        batch.flags,
        batch.counters,
        batch.messages,
        batch.channels,
        "batch",
    )


def _streaming(estimator: Estimator, streams: tuple[Any, ...], path: str) -> OfflineResult:
    estimates = run_offline(estimator, *streams)
    channels = estimator.channels or ()
    nan = np.full(len(channels), np.nan)
    return OfflineResult(
        np.array([e.t for e in estimates]),
        np.array([nan if e.measured is None else e.measured for e in estimates]).reshape(
            -1, len(channels)
        ),
        np.array([e.estimate for e in estimates]).reshape(-1, len(channels)),
        ["|".join(e.flags) for e in estimates],
        dict(estimator.counters),
        list(estimator.messages),
        channels,
        path,
    )


def write_estimates(path: str | Path, result: OfflineResult) -> None:
    write_estimate_table(
        path, result.t, result.measured, result.estimate, result.flags, result.channels
    )
