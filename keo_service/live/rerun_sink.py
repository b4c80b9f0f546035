"""Rerun logging, kept at the edge: `blueprint()` sets up the layout, `RerunSink` batches
estimates and sends them at display rate (`rerun_process` runs it in a process of its own,
so that logging never sits in the estimator's path, on the event loop or on its GIL).

Entities (values in mm and mrad, on the `stream_time` timeline of the samples):
    keo/error/<px|py|pz|rx|ry|rz>     time series of [measured, estimate]
    world/robot/links (line strip of joint origins), world/tool, world/sensor, world/tracker
    keo/status/delay_ms (the delay in use), keo/status/delay_ms_upper and _lower (it +/- its
    standard error, when known), keo/status/rate_hz/<stream>, keo/status/counters/<name>

A recording file is rolled every `ROLL_AFTER_S`: the Rerun SDK keeps a few hundred bytes per
chunk of an open file until it closes it (its index), which at 1 kHz grew the Rerun process
by about 7 MB a minute without end; closing the file frees them. `PATH` first, then
`<stem>-0001<suffix>`, ...: one recording id across them (open them together and Rerun shows
one recording), each file whole on its own (static frames and series styles in each).
"""

from __future__ import annotations

import time
import uuid
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import pinocchio as pin
import rerun as rr
import rerun.blueprint as rrb

from keo_service.core.estimator import Estimate
from keo_service.core.kinematics import Cell, sensor_pose_from_error, tool_pose

TIMELINE = "stream_time"
MAX_BATCH = 20_000  # rows kept between flushes at most; a flush is forced beyond
COLORS = {"measured": [150, 150, 150], "estimate": [230, 80, 30]}
ROLL_AFTER_S = 600.0  # a new recording file every 10 minutes (wall time)


def rolled_path(rrd: Path, index: int) -> Path:
    """The file of the index-th roll: `rrd` itself first, then `<stem>-0001<suffix>`, ..."""
    return rrd if index == 0 else rrd.with_name(f"{rrd.stem}-{index:04d}{rrd.suffix}")


def error_entity(channel: str) -> str:
    return f"keo/error/{channel}"


def display_scale(channel: str) -> float:
    return 1e3  # m -> mm, rad -> mrad


def blueprint(channels: Sequence[str]) -> rrb.Blueprint:
    unit = {"p": "mm", "r": "mrad"}
    plots = [
        rrb.TimeSeriesView(origin=f"/{error_entity(c)}", name=f"{c} [{unit[c[0]]}]")
        for c in channels
    ]
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Grid(*plots, grid_columns=3 if len(plots) > 3 else len(plots)),
            rrb.Vertical(
                rrb.Spatial3DView(origin="/world", name="cell"),
                rrb.TimeSeriesView(origin="/keo/status", name="delay, rates, counters"),
                row_shares=[2, 1],
            ),
            column_shares=[3, 2],
        ),
        rrb.TimePanel(state="collapsed"),
    )


class RerunSink:
    """Collects estimates; `flush()` (called at display rate) sends them as columns."""

    def __init__(
        self,
        cell: Cell,
        rrd: Path | None = None,
        viewer: str | None = None,
        channels: Sequence[str] = ("px", "py", "pz", "rx", "ry", "rz"),
        recording_id: str | None = None,
        roll_after_s: float = ROLL_AFTER_S,
    ) -> None:
        self.cell = cell
        self._data = cell.robot.create_data()
        self._rrd = None if rrd is None else Path(rrd)
        self._viewer = viewer
        self._recording_id = recording_id or str(uuid.uuid4())
        self._roll_after_s = roll_after_s
        self.files_opened = 0
        self._blueprint_channels = tuple(channels)
        self._static_done: set[str] = set()
        self._open()
        self._t: list[float] = []
        self._meas: list[np.ndarray] = []
        self._est: list[np.ndarray] = []
        self._channels: tuple[str, ...] = ()
        self._latest: Estimate | None = None
        self.rows_logged = 0

    def _open(self) -> None:
        """A recording stream on the next file (and the viewer, if any), static parts first."""
        self._rec = rr.RecordingStream("keo", recording_id=self._recording_id)
        sinks: list[rr.FileSink | rr.GrpcSink] = []
        if self._rrd is not None:
            path = rolled_path(self._rrd, self.files_opened)
            path.parent.mkdir(parents=True, exist_ok=True)
            sinks.append(rr.FileSink(str(path)))
        if self._viewer is not None:
            sinks.append(rr.GrpcSink(self._viewer))
        self._rec.set_sinks(*sinks, default_blueprint=blueprint(self._blueprint_channels))
        self._opened_at = time.monotonic()
        self._rows_in_file = 0
        self.files_opened += 1
        self._static_done.clear()
        self._log_static_frames()

    def _roll_if_due(self) -> None:
        """Before a batch: a new file when this one is old enough and holds data."""
        if (
            self._rrd is None
            or self._rows_in_file == 0
            or time.monotonic() - self._opened_at < self._roll_after_s
        ):
            return
        self._end_stream()
        self._open()

    def _end_stream(self) -> None:
        """Everything logged so far to its sinks, then the file closed (and its index freed)."""
        self._rec.flush(timeout_sec=5.0)
        self._rec.disconnect()

    def _log_static_frames(self) -> None:
        T = self.cell.T_bk
        self._rec.log(
            "world/tracker",
            rr.Transform3D(
                translation=T.translation, quaternion=pin.Quaternion(T.rotation).coeffs()
            ),
            rr.TransformAxes3D(0.3),
            static=True,
        )

    def add(self, estimate: Estimate) -> None:
        if not estimate.channels:
            return
        if estimate.channels != self._channels:
            self.flush()
            self._channels = estimate.channels
            # the layout follows the measurement: 3 plots for a single reflector, 6 for a probe
            if tuple(estimate.channels) != self._blueprint_channels:
                self._rec.send_blueprint(blueprint(estimate.channels))
                self._blueprint_channels = tuple(estimate.channels)
        n = len(estimate.channels)
        self._t.append(estimate.t)
        self._meas.append(
            estimate.measured if estimate.measured is not None else np.full(n, np.nan)
        )
        self._est.append(estimate.estimate)
        if not estimate.held:
            self._latest = estimate
        if len(self._t) >= MAX_BATCH:
            self.flush()

    def flush(self, status: Mapping[str, object] | None = None) -> None:
        if self._t:
            self._roll_if_due()
            times = [rr.TimeColumn(TIMELINE, timestamp=np.asarray(self._t))]
            meas = np.asarray(self._meas)
            est = np.asarray(self._est)
            for i, c in enumerate(self._channels):
                entity = error_entity(c)
                if entity not in self._static_done:
                    self._rec.log(
                        entity,
                        rr.SeriesLines(
                            names=[f"{c} measured", f"{c} estimate"],
                            colors=[COLORS["measured"], COLORS["estimate"]],
                            widths=[1.0, 2.0],
                        ),
                        static=True,
                    )
                    self._static_done.add(entity)
                k = display_scale(c)
                both = np.column_stack([meas[:, i], est[:, i]]) * k
                self._rec.send_columns(
                    entity, indexes=times, columns=rr.Scalars.columns(scalars=both)
                )
            self.rows_logged += len(self._t)
            self._rows_in_file += len(self._t)
            last_t = self._t[-1]
            self._t, self._meas, self._est = [], [], []
            self._log_scene(last_t)
            if status is not None:
                self._log_status(last_t, status)

    def _log_scene(self, t: float) -> None:
        latest = self._latest
        if latest is None or latest.joints is None or latest.measured is None:
            return
        self._rec.set_time(TIMELINE, timestamp=t)
        model = self.cell.robot.model
        pin.forwardKinematics(model, self._data, latest.joints)
        points = [self._data.oMi[j].translation.copy() for j in range(model.njoints)]
        T_bt = tool_pose(self.cell, self._data, latest.joints)
        points.append(T_bt.translation.copy())
        self._rec.log("world/robot/links", rr.LineStrips3D([np.asarray(points)], radii=0.02))
        self._rec.log(
            "world/tool",
            rr.Transform3D(
                translation=T_bt.translation, quaternion=pin.Quaternion(T_bt.rotation).coeffs()
            ),
            rr.TransformAxes3D(0.15),
        )
        if len(latest.measured) == 6:
            T_bs = sensor_pose_from_error(T_bt, latest.measured)
        else:
            T_bs = pin.SE3(T_bt.rotation, T_bt.act(latest.measured))
        self._rec.log(
            "world/sensor",
            rr.Transform3D(
                translation=T_bs.translation, quaternion=pin.Quaternion(T_bs.rotation).coeffs()
            ),
            rr.TransformAxes3D(0.1),
        )

    def _log_status(self, t: float, status: Mapping[str, object]) -> None:
        self._rec.set_time(TIMELINE, timestamp=t)
        delay = status.get("delay_s")
        if isinstance(delay, float):
            self._rec.log("keo/status/delay_ms", rr.Scalars([delay * 1e3]))
            se = status.get("delay_se_s")  # the band: the delay in use +/- its standard error
            if isinstance(se, float):
                self._rec.log("keo/status/delay_ms_upper", rr.Scalars([(delay + se) * 1e3]))
                self._rec.log("keo/status/delay_ms_lower", rr.Scalars([(delay - se) * 1e3]))
        for group in ("rates_hz", "counters"):
            values = status.get(group)
            if isinstance(values, Mapping):
                for name, value in values.items():
                    self._rec.log(f"keo/status/{group}/{name}", rr.Scalars([float(value)]))

    def close(self) -> None:
        self.flush()
        self._end_stream()
