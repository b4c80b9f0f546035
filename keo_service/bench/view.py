"""`keo view DIR --out FILE.rrd`: a recording as a Rerun file, estimates included.

A recording made by `keo record` (interchange CSV or a ROS 2 MCAP folder) holds the raw
streams only; this runs the service's own alignment and observer over it (the array path of
`keo estimate`, with the joints kept so that the robot can be drawn) and logs the result
through the same `RerunSink` as `keo run --rrd`: the same layout, entities and timeline, so a
viewed recording and a live one look alike. No bus, no processes, no replay in real time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from keo_service.core.errors import KeoError

if TYPE_CHECKING:
    from keo_service.core.estimator import Estimate
    from keo_service.core.settings import EstimatorSettings
    from keo_service.io.config import Config
    from keo_service.offline.recording import Recording

STATUS_EVERY_S = 1.0  # stream seconds between the delay rows (as the live status sends them)


@dataclass(frozen=True)
class ViewResult:
    out: Path
    estimates: int
    held: int
    duration_s: float
    path: str  # "batch" or "streaming (<why>)"
    warnings: list[str]


def recording_files(directory: Path) -> tuple[Path, Path]:
    """The encoder and tracker sources of a recording folder (an MCAP folder is both)."""
    from keo_service.io.mcap_files import is_mcap

    if is_mcap(directory):
        return directory, directory
    encoder, tracker = directory / "encoder.csv", directory / "tracker.csv"
    missing = [p.name for p in (encoder, tracker) if not p.is_file()]
    if missing:
        raise KeoError(
            f"{directory}: no {' and no '.join(missing)} and no MCAP recording (a folder "
            "written by keo record, or keo simulate's output)"
        )
    return encoder, tracker


def view_recording(config: Config, directory: Path, out: Path) -> ViewResult:
    """Estimate over the recording and write every estimate, the robot and the measured error
    to `out` (one Rerun file, not rolled)."""
    from keo_service.io.cell import estimator_settings
    from keo_service.live.rerun_logger import RerunLogger
    from keo_service.offline.library import delay_warning
    from keo_service.offline.recording import read_recording

    encoder, tracker = recording_files(directory)
    recording = read_recording(config, encoder, tracker)
    warning = delay_warning(config, recording, encoder_name=str(encoder), tracker_name=str(tracker))
    estimates, path = _estimates(recording, estimator_settings(config))
    if not estimates:
        raise KeoError(f"{directory}: the recording gives no estimate (no tracker samples?)")
    channels = next((e.channels for e in estimates if e.channels), ("px", "py", "pz"))
    sink = RerunLogger(
        recording.cell, rrd=out, channels=channels, roll_after_s=math.inf, urdf=config.robot.urdf
    )
    next_status = -math.inf
    try:
        for est in estimates:
            sink.add(est)
            if est.stamp >= next_status:
                sink.add_status({"delay_s": config.timing.delay_s})
                next_status = est.stamp + STATUS_EVERY_S
    finally:
        sink.close()
    held = sum(1 for e in estimates if e.held)
    span = estimates[-1].stamp - estimates[0].stamp
    return ViewResult(out, len(estimates), held, span, path, [warning] if warning else [])


def _estimates(recording: Recording, settings: EstimatorSettings) -> tuple[list[Estimate], str]:
    """Every estimate with the joints it was evaluated at (the array path when it can)."""
    from keo_service.core.batch import BatchUnsupportedError, estimate_batch
    from keo_service.core.estimator import Estimator, run_offline

    streams = recording.streams()
    try:
        table = estimate_batch(recording.cell, settings, *streams, keep_joints=True)
        return table.to_estimates(), "batch"
    except BatchUnsupportedError as exc:
        estimator = Estimator(recording.cell, settings)
        return run_offline(estimator, *streams), f"streaming ({exc})"
