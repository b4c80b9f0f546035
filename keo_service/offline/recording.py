"""A recording read once: both streams and the cell that interprets them."""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from keo_service.io.interchange import EncoderData, TrackerData, read_encoder, read_tracker

if TYPE_CHECKING:
    import numpy as np

    from keo_service.core.kinematics import Cell
    from keo_service.io.config import Config


@dataclass(frozen=True)
class Recording:
    """Both streams as recorded (nothing dropped or reordered: the estimator decides what it
    refuses) and the cell built from the config they were read with."""

    cell: Cell
    encoder: EncoderData
    tracker: TrackerData

    def streams(
        self,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
        """(encoder t, q, tracker t, p, quat): the estimator's and the delay fit's inputs."""
        e, k = self.encoder, self.tracker
        return e.t, e.q, k.t, k.p, k.quat


def read_recording(
    config: Config,
    encoder_path: str | Path,
    tracker_path: str | Path,
    mcap: bool = True,
    while_parsing: Callable[[], object] | None = None,
) -> Recording:
    """Each file read once. With `mcap`, a ROS 2 MCAP recording may stand for either file (or
    both). The tracker CSV is parsed on a worker thread (polars parses without the GIL) while
    `while_parsing` runs (e.g. the caller's imports), the kinematics libraries load, the cell
    is built and the encoder file is read; an error in the encoder file still comes first."""
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="keo-read") as pool:
        tracker_mcap = mcap and _maybe_mcap(tracker_path)
        tracker_csv = None if tracker_mcap else pool.submit(read_tracker, tracker_path)
        if while_parsing is not None:
            while_parsing()
        # the kinematics libraries load while it parses: Pinocchio's import is a good part of
        # a short command (docs/performance.md)
        from keo_service.io.cell import cell_from_config

        cell = cell_from_config(config)
        names = cell.robot.joint_names
        if mcap and _maybe_mcap(encoder_path):
            from keo_service.io.mcap_files import read_mcap

            encoder = read_mcap(encoder_path, names)[0]
        else:
            encoder = read_encoder(encoder_path, nq=cell.robot.nq)
        if tracker_csv is None:
            from keo_service.io.mcap_files import read_mcap

            tracker = read_mcap(tracker_path, names)[1]
        else:
            tracker = tracker_csv.result()
    return Recording(cell, encoder, tracker)


def _maybe_mcap(path: str | Path) -> bool:
    """Whether the path is an MCAP recording. rosbags is imported only for one: its import
    is a noticeable part of a short command over CSV files (docs/performance.md)."""
    if not (Path(path).suffix == ".mcap" or Path(path).is_dir()):
        return False
    from keo_service.io.mcap_files import is_mcap

    return is_mcap(path)
