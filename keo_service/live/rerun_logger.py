"""Rerun logging, kept at the edge: `blueprint()` sets up the layout (the one function that
does, for live, recorded and replayed data alike), `RerunLogger` batches estimates and status
and sends them at display rate (`rerun_process` runs it in a process of its own, so that
logging never sits in the estimator's path, on the event loop or on its GIL).

Entities (on the `stream_time` timeline of the samples):
    keo/error/<px|py|pz|rx|ry|rz>      [measured, estimate, residual] in mm or mrad (the
                                        residual, measured - estimate, hidden until shown)
    keo/tool_speed                      nominal tool speed, mm/s (at most 100 Hz)
    keo/status/delay/in_use             delay in use, ms
    keo/status/delay/band               its band, +-2 standard errors (when it is known)
    keo/status/rate_hz/<stream>         stream rates, Hz
    keo/status/rejects_per_s/<reason>   rejects and drops per second (counter differences)
    keo/status/held_per_s/<reason>      held steps per second
    keo/log                             health changes, held runs, flags, adapter
                                        (re)connections, clock resets, reject messages
    world/robot (capsules or the URDF's meshes), world/tool, world/sensor, world/tracker,
    world/error (the measured error as an arrow, magnified by `arrow_factor`: its label says
    by how much and how long the error is in mm)

Status is sent in columns once a second, errors at every flush: one chunk per entity and
batch instead of a row per call (see docs/viewer.md for the sizes measured).

A recording file is rolled every `ROLL_AFTER_S`: the Rerun SDK keeps a few hundred bytes per
chunk of an open file until it closes it (its index), so the Rerun process grows for as long
as one file stays open (docs/viewer.md has the rate measured); closing the file frees them.
`PATH` first, then `<stem>-0001<suffix>`, ...: one recording id across them (open them
together and Rerun shows one recording), each file whole on its own (static frames and series
styles in each).
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

from keo_service.core.display import (
    Mesh,
    arrow_factor,
    away_from,
    error_arrow,
    framing_camera,
    link_radius,
    mesh_poses,
    robot_capsules,
    speeds,
    visual_meshes,
)
from keo_service.core.estimator import Estimate
from keo_service.core.kinematics import Cell, tool_pose
from keo_service.live.status_view import EVENT_GAP_S, StatusEvents, StatusRates, adapter_counters

TIMELINE = "stream_time"
MAX_BATCH = 20_000  # rows kept between flushes at most; a flush is forced beyond
COLORS = {"measured": [150, 150, 150], "estimate": [230, 80, 30], "residual": [40, 110, 220]}
ROLL_AFTER_S = 600.0  # a new recording file every 10 minutes (wall time)
WINDOW_S = 30.0  # the plots show the newest this many seconds
SPEED_PERIOD_S = 0.01  # the tool speed is taken over steps of at least this (<= 100 Hz)
SCENE_PERIOD_S = 0.1  # the cell is drawn at most this often (stream time: 10 Hz)
STATUS_SEND_S = 1.0  # status rows are sent in columns this often
BAND_SE = 2.0  # the delay band: +- this many standard errors

UNITS = {"p": "mm", "r": "mrad"}

ERROR_ROOT = "keo/error"
SPEED = "keo/tool_speed"
DELAY = "keo/status/delay"
RATES = "keo/status/rate_hz"
REJECTS = "keo/status/rejects_per_s"
HELD = "keo/status/held_per_s"
LOG = "keo/log"


def rolled_path(rrd: Path, index: int) -> Path:
    """The file of the index-th roll: `rrd` itself first, then `<stem>-0001<suffix>`, ..."""
    return rrd if index == 0 else rrd.with_name(f"{rrd.stem}-{index:04d}{rrd.suffix}")


def error_entity(channel: str) -> str:
    return f"{ERROR_ROOT}/{channel}"


def display_scale(channel: str) -> float:
    return 1e3  # m -> mm, rad -> mrad


def _window(window_s: float) -> rrb.VisibleTimeRange:
    return rrb.VisibleTimeRange(
        TIMELINE,
        start=rrb.TimeRangeBoundary.cursor_relative(seconds=-window_s),
        end=rrb.TimeRangeBoundary.cursor_relative(),
    )


def _plot(origin: str, name: str, window_s: float, legend: bool = True) -> rrb.TimeSeriesView:
    return rrb.TimeSeriesView(
        origin=origin,
        name=name,
        time_ranges=_window(window_s),
        axis_x=rrb.TimeAxis(link=rrb.components.LinkAxis.LinkToGlobal),
        plot_legend=rrb.PlotLegend(corner=rrb.Corner2D.LeftTop, visible=legend),
    )


def blueprint(
    channels: Sequence[str],
    window_s: float = WINDOW_S,
    camera: tuple[np.ndarray, np.ndarray] | None = None,
) -> rrb.Blueprint:
    """The layout, for a 1600 x 1000 screen and up: the cell, four status plots and the
    text log on top, the error plots in two rows of three below (tall enough for their y
    labels; one time window for all, the newest `window_s` seconds), the tool speed under
    them across the width; side panels collapsed.
    `camera`: (eye, target) in the world frame."""
    errors = [_plot(f"/{error_entity(c)}", f"{c} [{UNITS[c[0]]}]", window_s) for c in channels]
    eye = None
    if camera is not None:
        eye = rrb.EyeControls3D(
            kind=rrb.Eye3DKind.Orbital,
            position=[float(v) for v in camera[0]],
            look_target=[float(v) for v in camera[1]],
            eye_up=[0.0, 0.0, 1.0],
        )
    cell = rrb.Spatial3DView(origin="/world", name="cell", eye_controls=eye)
    status = rrb.Grid(
        _plot(f"/{DELAY}", "delay in use [ms]", window_s),
        _plot(f"/{RATES}", "stream rates [Hz]", window_s),
        _plot(f"/{REJECTS}", "rejects, drops [1/s]", window_s),
        _plot(f"/{HELD}", "held steps [1/s]", window_s),
        grid_columns=2,
        name="status",
    )
    events = rrb.TextLogView(
        origin=f"/{LOG}",
        name="events",
        columns=rrb.TextLogColumns(  # the entity path is always keo/log: room for the text
            text_log_columns=[
                rrb.components.TextLogColumn("EntityPath", visible=False),
                rrb.components.TextLogColumn("LogLevel"),
                rrb.components.TextLogColumn("Body"),
            ]
        ),
    )
    return rrb.Blueprint(
        rrb.Vertical(
            rrb.Horizontal(cell, status, events, column_shares=[5, 5, 3]),
            rrb.Grid(*errors, grid_columns=3 if len(errors) > 3 else len(errors), name="error"),
            _plot(f"/{SPEED}", "tool speed [mm/s]", window_s, legend=False),
            row_shares=[3.6, 6.4, 1.6],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed"),
    )


class RerunLogger:
    """Collects estimates; `flush()` (called at display rate) sends them as columns."""

    def __init__(
        self,
        cell: Cell,
        rrd: Path | None = None,
        viewer: str | None = None,
        channels: Sequence[str] = ("px", "py", "pz", "rx", "ry", "rz"),
        recording_id: str | None = None,
        roll_after_s: float = ROLL_AFTER_S,
        urdf: str | None = None,
        window_s: float = WINDOW_S,
    ) -> None:
        self.cell = cell
        self._data = cell.robot.create_data()
        self._rrd = None if rrd is None else Path(rrd)
        self._viewer = viewer
        self._recording_id = recording_id or str(uuid.uuid4())
        self._roll_after_s = roll_after_s
        self._window_s = window_s
        self._meshes: list[Mesh] = []
        if urdf is not None:
            self._meshes = visual_meshes(cell.robot, urdf, [str(Path(urdf).parent)])
        self._camera = self._framing()
        self._arrow_factor = arrow_factor(cell.robot)
        self.files_opened = 0
        self._blueprint_channels = tuple(channels)
        self._static_done: set[str] = set()
        self._t: list[float] = []
        self._meas: list[np.ndarray] = []
        self._est: list[np.ndarray] = []
        self._speed_t: list[float] = []
        self._speed_p: list[np.ndarray] = []
        self._speed_last: tuple[float, np.ndarray] | None = None
        self._channels: tuple[str, ...] = ()
        self._scene: list[Estimate] = []  # estimates to draw the cell at (SCENE_PERIOD_S)
        self._scene_t = -np.inf
        self._flags: tuple[str, ...] = ()
        self._flag_run = 0
        self._flag_listed = False  # the current run's start is in the text log
        self._flag_last: dict[tuple[str, ...], float] = {}  # when each run was last listed
        self._flag_skipped: dict[tuple[str, ...], int] = {}
        self._events: list[tuple[float, str, str]] = []  # (t, level, text)
        self._rates = StatusRates()
        self._status_events = StatusEvents()
        self._status_rows: dict[str, tuple[list[float], list[list[float]]]] = {}
        self._status_sent = time.monotonic()
        self._last_t: float | None = None  # stream time of the newest estimate
        self._last_host_s = 0.0  # the host time (s) at which it came
        self.rows_logged = 0
        self._open()

    # ---- files and sinks ----------------------------------------------------------------

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
        self._rec.set_sinks(*sinks, default_blueprint=self.blueprint(self._blueprint_channels))
        self._opened_at = time.monotonic()
        self._rows_in_file = 0
        self.files_opened += 1
        self._static_done.clear()
        self._log_static()

    def blueprint(self, channels: Sequence[str]) -> rrb.Blueprint:
        return blueprint(channels, self._window_s, self._camera)

    def _roll_if_due(self) -> None:
        """Before a batch: a new file when this one is old enough and holds data."""
        if (
            self._rrd is None
            or self._rows_in_file == 0
            or time.monotonic() - self._opened_at < self._roll_after_s
        ):
            return
        self._send_status()
        self._end_stream()
        self._open()

    def _end_stream(self) -> None:
        """Everything logged so far to its sinks, then the file closed (and its index freed)."""
        self._rec.flush(timeout_sec=5.0)
        self._rec.disconnect()

    # ---- the static scene ----------------------------------------------------------------

    def _framing(self) -> tuple[np.ndarray, np.ndarray]:
        """Camera (eye, target) that frames the robot at its zero pose (clipped into its
        joint limits), its base and the tracker."""
        robot = self.cell.robot
        q = np.clip(np.zeros(robot.nq), robot.lower, robot.upper)
        T_bt = tool_pose(self.cell, self._data, q)
        caps = robot_capsules(self.cell, self._data, q, T_bt)
        points = [caps.starts, np.asarray([self.cell.T_bk.translation]), np.zeros((1, 3))]
        return framing_camera(np.vstack(points))

    def _log_static(self) -> None:
        rec = self._rec
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        T = self.cell.T_bk
        r = link_radius(self.cell.robot)
        rec.log(
            "world/tracker",
            rr.Transform3D(
                translation=T.translation, quaternion=pin.Quaternion(T.rotation).coeffs()
            ),
            rr.TransformAxes3D(4 * r),
            rr.Boxes3D(
                half_sizes=[[r, r, r]], colors=[[60, 60, 60]], labels=["tracker"], fill_mode="solid"
            ),
            static=True,
        )
        for i, mesh in enumerate(self._meshes):
            rec.log(f"world/robot/mesh/{i}", rr.Asset3D(path=mesh.path), static=True)
        rec.log(SPEED, rr.SeriesLines(names=["tool speed"], colors=[[40, 150, 80]]), static=True)
        rec.log(
            f"{DELAY}/in_use", rr.SeriesLines(names=["delay"], colors=[[230, 80, 30]]), static=True
        )
        rec.log(
            f"{DELAY}/band",
            rr.SeriesLines(
                names=[f"-{BAND_SE:g} se", f"+{BAND_SE:g} se"],
                colors=[[230, 170, 140], [230, 170, 140]],
                widths=[1.0, 1.0],
            ),
            static=True,
        )

    # ---- data in ---------------------------------------------------------------------------

    def add(self, estimate: Estimate) -> None:
        if estimate.flags != self._flags:
            self._flag_change(estimate)
        elif self._flags:
            self._flag_run += 1
        if not estimate.channels:
            return
        if estimate.channels != self._channels:
            self.flush()
            self._channels = estimate.channels
            # the layout follows the measurement: 3 plots for a single reflector, 6 for a probe
            if tuple(estimate.channels) != self._blueprint_channels:
                self._rec.send_blueprint(self.blueprint(estimate.channels))
                self._blueprint_channels = tuple(estimate.channels)
        n = len(estimate.channels)
        self._last_t = estimate.stamp
        self._last_host_s = time.time()
        self._t.append(estimate.stamp)
        self._meas.append(
            estimate.measured if estimate.measured is not None else np.full(n, np.nan)
        )
        self._est.append(estimate.estimate)
        if not estimate.held:
            self._speed_sample(estimate)
            if estimate.joints is not None and estimate.stamp - self._scene_t >= SCENE_PERIOD_S:
                self._scene.append(estimate)
                self._scene_t = estimate.stamp
        if len(self._t) >= MAX_BATCH:
            self.flush()

    def _flag_change(self, estimate: Estimate) -> None:
        """A run of flagged steps begins or ends: one text log entry each, not one per step;
        a run that begins within EVENT_GAP_S of the last one listed is counted instead, and
        the next one listed says how many were left out."""
        old, new = self._flags, estimate.flags
        if old and self._flag_listed:
            self._events.append(
                (estimate.stamp, "INFO", f"{', '.join(old)} ended after {self._flag_run} steps")
            )
        self._flag_listed = False
        if new:
            last = self._flag_last.get(new)
            if last is None or estimate.stamp - last >= EVENT_GAP_S:
                level = "INFO" if new == ("outside_calibrated_range",) else "WARN"
                text = f"flag: {', '.join(new)}"
                skipped = self._flag_skipped.pop(new, 0)
                if skipped:
                    text += f" ({skipped} shorter runs since the last entry not listed)"
                self._events.append((estimate.stamp, level, text))
                self._flag_last[new] = estimate.stamp
                self._flag_listed = True
            else:
                self._flag_skipped[new] = self._flag_skipped.get(new, 0) + 1
        self._flags = new
        self._flag_run = 0 if not new else 1

    def _speed_sample(self, estimate: Estimate) -> None:
        if estimate.joints is None:
            return
        last = self._speed_last
        if last is not None and estimate.stamp - last[0] < SPEED_PERIOD_S:
            return
        p = np.asarray(tool_pose(self.cell, self._data, estimate.joints).translation, dtype=float)
        self._speed_last = (estimate.stamp, p.copy())
        self._speed_t.append(estimate.stamp)
        self._speed_p.append(p.copy())

    # ---- data out --------------------------------------------------------------------------

    def flush(self, status: Mapping[str, object] | None = None) -> None:
        """Send what was collected: errors, the cell, tool speed and events now, status rows
        once every STATUS_SEND_S. `status`: a snapshot to add first (see `add_status`)."""
        if status is not None:
            self.add_status(status)
        if self._t:
            self._roll_if_due()
            self._send_errors()
        self._send_speed()
        self._send_events()
        if time.monotonic() - self._status_sent >= STATUS_SEND_S:
            self._send_status()

    def _send_errors(self) -> None:
        times = [rr.TimeColumn(TIMELINE, timestamp=np.asarray(self._t))]
        meas = np.asarray(self._meas, dtype=float)
        est = np.asarray(self._est, dtype=float)
        for i, c in enumerate(self._channels):
            entity = error_entity(c)
            if entity not in self._static_done:  # the series' style, once per file
                self._rec.log(
                    entity,
                    rr.SeriesLines(
                        names=["measured", "estimate", "residual"],
                        colors=[COLORS["measured"], COLORS["estimate"], COLORS["residual"]],
                        widths=[1.0, 2.0, 1.0],
                        visible_series=[True, True, False],
                    ),
                    static=True,
                )
                self._static_done.add(entity)
            k = display_scale(c)
            both = np.column_stack([meas[:, i], est[:, i], meas[:, i] - est[:, i]]) * k
            self._rec.send_columns(entity, indexes=times, columns=rr.Scalars.columns(scalars=both))
        self.rows_logged += len(self._t)
        self._rows_in_file += len(self._t)
        self._t, self._meas, self._est = [], [], []
        for estimate in self._scene:
            self._log_scene(estimate)
        self._scene = []

    def _send_speed(self) -> None:
        if len(self._speed_t) < 2:
            return
        t = np.asarray(self._speed_t)
        v = speeds(t, np.asarray(self._speed_p)) * 1e3  # mm/s
        self._rec.send_columns(
            SPEED,
            indexes=[rr.TimeColumn(TIMELINE, timestamp=t[1:])],
            columns=rr.Scalars.columns(scalars=v),
        )
        self._speed_t, self._speed_p = self._speed_t[-1:], self._speed_p[-1:]

    def _send_events(self) -> None:
        if not self._events:
            return
        t = np.asarray([e[0] for e in self._events])
        self._rec.send_columns(
            LOG,
            indexes=[rr.TimeColumn(TIMELINE, timestamp=t)],
            columns=rr.TextLog.columns(
                text=[e[2] for e in self._events], level=[e[1] for e in self._events]
            ),
        )
        self._events = []

    def _status_time(self, status: Mapping[str, object]) -> float:
        """Status on the samples' timeline: the newest estimate's stream time plus the host
        time since it was sent (the host time itself before any estimate)."""
        host_ns = status.get("host_ns")
        host_s = float(host_ns) * 1e-9 if isinstance(host_ns, int) else time.time()
        if self._last_t is None:
            return host_s
        return self._last_t + max(0.0, host_s - self._last_host_s)

    def _row(self, entity: str, t: float, values: list[float]) -> None:
        times, rows = self._status_rows.setdefault(entity, ([], []))
        times.append(t)
        rows.append(values)

    def add_status(self, status: Mapping[str, object]) -> None:
        """A status snapshot: its rows wait for the next send (STATUS_SEND_S), its events
        go out with the next flush."""
        t = self._status_time(status)
        for level, text in self._status_events.update(status, t):
            self._events.append((t, level, text))
        delay = status.get("delay_s")
        if isinstance(delay, float | int):
            self._row(f"{DELAY}/in_use", t, [float(delay) * 1e3])
            se = status.get("delay_se_s")
            if isinstance(se, float | int):
                band = [(delay - BAND_SE * se) * 1e3, (delay + BAND_SE * se) * 1e3]
                self._row(f"{DELAY}/band", t, band)
        rates = status.get("rates_hz")
        if isinstance(rates, Mapping):
            for name, value in rates.items():
                self._row(f"{RATES}/{name}", t, [float(value)])
        self._add_counter_rates(status, t)

    def _add_counter_rates(self, status: Mapping[str, object], t: float) -> None:
        """Rejects and held steps per second, the service's and the adapters' counters."""
        counters = status.get("counters")
        if not isinstance(counters, Mapping):
            return
        merged = dict(counters)
        adapters = status.get("adapters")
        if isinstance(adapters, Mapping):
            merged.update(adapter_counters(adapters))
        host_ns = status.get("host_ns")
        host_s = float(host_ns) * 1e-9 if isinstance(host_ns, int) else time.time()
        per_s = self._rates.update(merged, host_s)
        if per_s is not None:
            for group, root in (("rejects", REJECTS), ("held", HELD)):
                for reason, value in per_s[group].items():
                    self._row(f"{root}/{reason}", t, [value])

    def _send_status(self) -> None:
        self._status_sent = time.monotonic()
        for entity, (times, rows) in self._status_rows.items():
            if times:
                self._rec.send_columns(
                    entity,
                    indexes=[rr.TimeColumn(TIMELINE, timestamp=np.asarray(times))],
                    columns=rr.Scalars.columns(scalars=np.asarray(rows, dtype=float)),
                )
        self._status_rows = {}

    def _log_scene(self, latest: Estimate) -> None:
        if latest.joints is None or latest.measured is None:
            return
        rec = self._rec
        rec.set_time(TIMELINE, timestamp=latest.stamp)
        T_bt = tool_pose(self.cell, self._data, latest.joints)
        caps = robot_capsules(self.cell, self._data, latest.joints, T_bt)
        keep = [i for i, k in enumerate(caps.kinds) if not self._meshes or k == "tool"]
        palette = {"link": [245, 170, 40], "hub": [90, 90, 100], "tool": [170, 170, 170]}
        rec.log(
            "world/robot/links",
            rr.Capsules3D(
                translations=caps.starts[keep],
                quaternions=caps.quaternions[keep],
                lengths=caps.lengths[keep],
                radii=caps.radii[keep],
                colors=[palette[caps.kinds[i]] for i in keep],
                fill_mode="solid",
            ),
        )
        for i, T in enumerate(mesh_poses(self.cell, self._data, self._meshes)):
            rec.log(
                f"world/robot/mesh/{i}",
                rr.Transform3D(
                    translation=T.translation,
                    quaternion=pin.Quaternion(T.rotation).coeffs(),
                    scale=self._meshes[i].scale,
                ),
            )
        r = link_radius(self.cell.robot)
        factor = self._arrow_factor
        origin, vector, size = error_arrow(T_bt, np.asarray(latest.measured), factor)
        # the tool's label on the far side from the arrow, clear of the arrow's own label
        label_at = T_bt.rotation.T @ away_from(vector, 3 * r)
        rec.log(
            "world/tool",
            rr.Transform3D(
                translation=T_bt.translation, quaternion=pin.Quaternion(T_bt.rotation).coeffs()
            ),
            rr.TransformAxes3D(2 * r),
            rr.Points3D([label_at], radii=[0.1 * r], labels=["tool"]),
        )
        rec.log(
            "world/error",
            rr.Arrows3D(
                origins=[origin],
                vectors=[vector],
                radii=[0.4 * r],
                colors=[[220, 30, 30]],
                labels=[f"error {size * 1e3:.2f} mm (x{factor:g})"],
            ),
        )
        tip = origin + vector
        R = T_bt.rotation
        if len(latest.measured) == 6:
            R = R @ pin.exp3(np.asarray(latest.measured[3:6], dtype=float))
        rec.log(
            "world/sensor",
            rr.Transform3D(translation=tip, quaternion=pin.Quaternion(R).coeffs()),
            rr.TransformAxes3D(1.5 * r),
            rr.Points3D(
                [[0.0, 0.0, 0.0]],
                radii=[0.3 * r],
                labels=[f"sensor (x{factor:g})"],
            ),
        )

    def close(self) -> None:
        self.flush()
        self._send_status()
        self._end_stream()
