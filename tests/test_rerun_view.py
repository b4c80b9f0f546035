"""The live view as a person reads it: the blueprint's views, status as rates, events in the
text log, the robot's drawing against the URDF's published numbers, the error arrow, and
`--viewer` opening Rerun's web viewer."""

from __future__ import annotations

import os
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pinocchio as pin
import pyarrow as pa
import pytest
import rerun.blueprint as rrb
from rerun.chunk import RrdReader

from keo_service.cli import build_parser
from keo_service.core.display import (
    arrow_factor,
    error_arrow,
    framing_camera,
    robot_capsules,
    speeds,
)
from keo_service.core.errors import KeoError
from keo_service.core.estimator import Estimate
from keo_service.core.kinematics import POSE_CHANNELS, Cell, load_robot
from keo_service.live.rerun_logger import RerunLogger, blueprint

from .conftest import CONFIGS


def _views(container: object) -> list[object]:
    out = []
    for part in getattr(container, "contents", []):
        if isinstance(part, rrb.View):
            out.append(part)
        else:
            out.extend(_views(part))
    return out


def _table(rrd: Path, entity: str) -> pa.Table | None:
    chunks = [
        c
        for c in RrdReader(str(rrd)).stream().to_chunks()
        if not c.is_static and c.entity_path == entity
    ]
    if not chunks:
        return None
    tables = [pa.Table.from_batches([c.to_record_batch()]) for c in chunks]
    return pa.concat_tables(tables, promote_options="default").sort_by("stream_time")


def _entities(rrd: Path) -> set[str]:
    return {c.entity_path for c in RrdReader(str(rrd)).stream().to_chunks()}


# ---- the blueprint ---------------------------------------------------------------------------


def test_the_blueprint_holds_the_views_a_person_needs_and_rerun_accepts_it(tmp_path):
    bp = blueprint(POSE_CHANNELS, window_s=45.0, camera=(np.array([1, 2, 3]), np.zeros(3)))
    views = _views(bp.root_container)
    by_origin = {str(v.origin): v for v in views}
    for c in POSE_CHANNELS:
        view = by_origin[f"/keo/error/{c}"]
        assert isinstance(view, rrb.TimeSeriesView)
        unit = "mm" if c.startswith("p") else "mrad"
        assert view.name == f"{c} [{unit}]"
    assert isinstance(by_origin["/world"], rrb.Spatial3DView)
    assert isinstance(by_origin["/keo/tool_speed"], rrb.TimeSeriesView)
    assert "mm/s" in str(by_origin["/keo/tool_speed"].name)
    for status in ("delay", "rate_hz", "rejects_per_s", "held_per_s"):
        assert isinstance(by_origin[f"/keo/status/{status}"], rrb.TimeSeriesView)
    assert isinstance(by_origin["/keo/log"], rrb.TextLogView)
    # one time window for every plot: the newest 45 s, linked, legends in a corner
    plots = [v for v in views if isinstance(v, rrb.TimeSeriesView)]
    assert len(plots) == 11
    for view in plots:
        props = view.properties
        ranges = props["VisibleTimeRanges"].ranges.as_arrow_array()
        (window,) = ranges.to_pylist()
        assert window["timeline"] == "stream_time"
        assert window["range"] == {"start": -45_000_000_000, "end": 0}  # ns
        for end in ("start", "end"):  # both relative to the time cursor (the newest data)
            kind = ranges.field("range").field(end).type_codes.to_pylist()
            assert kind == [1]  # CursorRelative
        assert props["TimeAxis"].link.as_arrow_array().to_pylist() == [2]  # LinkToGlobal
        assert props["PlotLegend"].corner.as_arrow_array().to_pylist() == [1]  # LeftTop
    # side panels collapsed
    for panel in (bp.blueprint_panel, bp.selection_panel, bp.time_panel):
        assert panel is not None
        assert panel.state == "collapsed"
    # Rerun's own tool reads it back as a valid blueprint file
    path = tmp_path / "keo.rbl"
    bp.save("keo", str(path))
    verify = [sys.executable, "-m", "rerun_cli", "rrd", "verify", str(path)]
    done = subprocess.run(verify, check=False, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr


def test_a_single_reflector_gets_three_error_plots():
    views = _views(blueprint(("px", "py", "pz")).root_container)
    errors = [v for v in views if str(v.origin).startswith("/keo/error/")]
    assert [str(v.origin) for v in errors] == ["/keo/error/px", "/keo/error/py", "/keo/error/pz"]


# ---- status: rates, never totals; events in the text log ----------------------------------


def _status(host_s: float, counters: dict[str, int], health: str = "ok") -> dict[str, object]:
    return {
        "health": health,
        "host_ns": int(host_s * 1e9),
        "delay_s": 0.028,
        "rates_hz": {"encoder": 250.0, "tracker": 1000.0},
        "counters": counters,
        "messages": [],
    }


def _pose_estimate(t: float) -> Estimate:
    e = [1e-4] * 6
    return Estimate(t, e, e, (), t, POSE_CHANNELS, np.zeros(6))


def test_rejects_and_held_steps_are_rates_per_second_one_series_per_reason(demo_cell, tmp_path):
    rrd = tmp_path / "s.rrd"
    sink = RerunLogger(demo_cell, rrd=rrd)
    base = 1_700_000_000.0
    totals = [
        {"estimates": 0, "rejected": 0, "tracker_stamp_not_increasing": 0, "held_tracker_gap": 0,
         "decode_errors": 0},
        {"estimates": 500, "rejected": 40, "tracker_stamp_not_increasing": 40},
        {"estimates": 1000, "rejected": 40, "tracker_stamp_not_increasing": 40,
         "held_tracker_gap": 5},
        {"estimates": 9000, "rejected": 140, "tracker_stamp_not_increasing": 140,
         "held_tracker_gap": 5},
    ]  # fmt: skip
    for k, counters in enumerate(totals):
        sink.add(_pose_estimate(100.0 + k))
        sink.flush(_status(base + 0.5 * k, counters))  # every half second
    sink.close()
    rejects = _table(rrd, "/keo/status/rejects_per_s/tracker_stamp_not_increasing")
    assert rejects is not None
    values = [row[0] for row in rejects.column("Scalars:scalars").to_pylist()]
    assert values == pytest.approx([80.0, 0.0, 200.0])  # 40 in 0.5 s, none, 100 in 0.5 s
    held = _table(rrd, "/keo/status/held_per_s/tracker_gap")
    assert held is not None
    # its series from the snapshot where it first counted: 5 in 0.5 s, then none
    assert [r[0] for r in held.column("Scalars:scalars").to_pylist()] == pytest.approx([10.0, 0.0])
    total = _table(rrd, "/keo/status/held_per_s/total")
    assert total is not None  # always there: a zero line when there is nothing
    entities = _entities(rrd)
    # no running total anywhere: not the counters, not the work done, not their sum
    assert not any("counters" in e for e in entities)
    assert "/keo/status/rejects_per_s/estimates" not in entities
    assert "/keo/status/rejects_per_s/rejected" not in entities
    assert "/keo/status/rejects_per_s/decode_errors" not in entities  # never happened
    rates = _table(rrd, "/keo/status/rate_hz/tracker")
    assert rates is not None
    assert {r[0] for r in rates.column("Scalars:scalars").to_pylist()} == {1000.0}
    delay = _table(rrd, "/keo/status/delay/in_use")
    assert delay is not None
    assert [r[0] for r in delay.column("Scalars:scalars").to_pylist()] == pytest.approx([28.0] * 4)
    assert _table(rrd, "/keo/status/delay/band") is None  # no standard error: no band


def test_the_delay_band_is_drawn_when_its_standard_error_is_known(demo_cell, tmp_path):
    rrd = tmp_path / "d.rrd"
    sink = RerunLogger(demo_cell, rrd=rrd)
    status = _status(1.0, {}) | {"delay_se_s": 0.0015}
    sink.add(_pose_estimate(5.0))
    sink.flush(status)
    sink.close()
    band = _table(rrd, "/keo/status/delay/band")
    assert band is not None
    assert band.column("Scalars:scalars").to_pylist() == [pytest.approx([25.0, 31.0])]


def _log_entries(rrd: Path) -> list[tuple[str, str]]:
    log = _table(rrd, "/keo/log")
    assert log is not None
    texts = log.column("TextLog:text").to_pylist()
    levels = log.column("TextLog:level").to_pylist()
    return [(lv[0], tx[0]) for lv, tx in zip(levels, texts, strict=True)]


def test_the_text_log_receives_health_changes_and_runs_of_flags(demo_cell, tmp_path):
    rrd = tmp_path / "h.rrd"
    sink = RerunLogger(demo_cell, rrd=rrd)
    sink.add(_pose_estimate(10.0))
    now = time.time()  # status snapshots carry the host time; estimates their stream time
    sink.flush(_status(now + 1.5, {}, health="ok"))
    held = Estimate(10.01, None, [0.0] * 6, ("tracker_gap",), None, POSE_CHANNELS)
    for i in range(5):
        sink.add(Estimate(10.01 + i * 0.001, None, [0.0] * 6, held.flags, None, POSE_CHANNELS))
    sink.add(_pose_estimate(10.02))
    sink.flush(_status(now + 3.0, {}, health="stale"))
    sink.flush(_status(now + 4.5, {"encoder_reconnects": 1}, health="ok"))
    sink.close()
    entries = _log_entries(rrd)
    assert ("WARN", "health ok -> stale") in entries
    assert ("INFO", "health stale -> ok") in entries
    assert ("WARN", "flag: tracker_gap") in entries
    assert ("INFO", "tracker_gap ended after 5 steps") in entries
    assert ("WARN", "encoder_reconnects +1 (now 1)") in entries


def test_adapter_reconnections_and_clock_resets_reach_the_text_log(demo_cell, tmp_path):
    """As an adapter reports itself in the service's status: its counters (a lost
    connection counted as `disconnects`) and its clock (domain, epoch: a fresh start)."""
    rrd = tmp_path / "a.rrd"
    sink = RerunLogger(demo_cell, rrd=rrd)
    sink.add(_pose_estimate(10.0))
    now = time.time()

    def adapter(disconnects: int, epoch: int) -> dict[str, object]:
        counters = {"disconnects": disconnects, "frames": 1000 * epoch}
        return {"encoder": {"counters": counters, "clock": {"domain": "device", "epoch": epoch}}}

    sink.add_status(_status(now + 1.0, {}) | {"adapters": adapter(0, 0)})
    sink.add_status(_status(now + 2.0, {}) | {"adapters": adapter(1, 1)})
    sink.close()
    entries = _log_entries(rrd)
    assert ("WARN", "encoder.disconnects +1 (now 1)") in entries
    assert ("WARN", "encoder: clock epoch 0 -> 1") in entries
    assert not any("frames" in text for _lv, text in entries)  # throughput is no event
    rates = _table(rrd, "/keo/status/rejects_per_s/encoder.disconnects")
    assert rates is not None  # and the loss is drawn as a rate


def test_a_flapping_health_is_summed_up_not_listed_change_by_change(demo_cell, tmp_path):
    rrd = tmp_path / "f.rrd"
    sink = RerunLogger(demo_cell, rrd=rrd)
    sink.add(_pose_estimate(10.0))
    now = time.time()
    for k in range(30):  # 3 s of snapshots at 10 Hz, the health flipping at each
        sink.add_status(_status(now + 0.1 * k, {}, health="stale" if k % 2 else "ok"))
    sink.add_status(_status(now + 4.0, {}, health="ok"))  # then it settles
    sink.close()
    health = [text for _level, text in _log_entries(rrd) if text.startswith("health")]
    assert 3 <= len(health) <= 6  # about one a second, not 30
    assert health[-1].startswith("health stale -> ok")  # the one it settled on
    assert "changes since the last entry" in " ".join(health)
    # the flags of held steps that come and go: a run a second at most
    sink = RerunLogger(demo_cell, rrd=tmp_path / "g.rrd")
    for k in range(200):  # 2 s of stream time, a held step every fifth
        flags = ("encoder_stale",) if k % 5 == 0 else ()
        measured = None if flags else [1e-4] * 6
        sink.add(Estimate(10.0 + 0.01 * k, measured, [1e-4] * 6, flags, None, POSE_CHANNELS))
    sink.close()
    starts = [t for _lv, t in _log_entries(tmp_path / "g.rrd") if t.startswith("flag:")]
    assert len(starts) == 2  # 40 runs in 2 s
    assert "shorter runs since the last entry not listed" in starts[1]


# ---- the scene ------------------------------------------------------------------------------


def _cell(urdf: str) -> Cell:
    return Cell(load_robot(CONFIGS / "robots" / urdf), pin.SE3.Identity(), pin.SE3.Identity())


def test_the_mh180_is_drawn_through_its_published_joint_centres():
    """At the zero pose the links run through the joint centres of the MH180's joint table
    (S at z 0.650, L at x 0.325, U 1.150 above L, R 0.300 above U, B 1.225 ahead of R, T
    0.225 ahead of B): numbers from the data sheet, not from the code."""
    cell = _cell("mh180.urdf")
    data = cell.robot.create_data()
    q = np.zeros(6)
    T_bt = pin.SE3(np.eye(3), np.array([1.775, 0.0, 2.100]))
    caps = robot_capsules(cell, data, q, T_bt)
    links = [i for i, k in enumerate(caps.kinds) if k == "link"]
    ends = []
    for i in links:
        R = pin.Quaternion(caps.quaternions[i][3], *caps.quaternions[i][:3]).matrix()
        ends.append((caps.starts[i], caps.starts[i] + R @ [0.0, 0.0, caps.lengths[i]]))
    centres = [
        (0.0, 0.0, 0.0),
        (0.0, 0.0, 0.650),
        (0.325, 0.0, 0.650),
        (0.325, 0.0, 1.800),
        (0.325, 0.0, 2.100),
        (1.550, 0.0, 2.100),
        (1.775, 0.0, 2.100),
    ]
    for (start, end), a, b in zip(ends, centres[:-1], centres[1:], strict=True):
        assert start == pytest.approx(a, abs=1e-9)
        assert end == pytest.approx(b, abs=1e-9)
    assert caps.kinds.count("hub") == 6
    assert np.all(caps.radii > 0.05)  # a 3.9 m robot's links: thick enough to be seen


def test_the_error_arrow_is_the_measured_offset_turned_into_the_base_frame_and_magnified():
    turn = pin.rpy.rpyToMatrix(0.0, 0.0, np.pi / 2)  # tool x is base y
    T_bt = pin.SE3(turn, np.array([1.0, 2.0, 3.0]))
    origin, vector, size = error_arrow(T_bt, np.array([1e-3, 0.0, 2e-3, 0.1, 0.0, 0.0]), 200.0)
    assert origin == pytest.approx([1.0, 2.0, 3.0])
    assert vector == pytest.approx([0.0, 0.2, 0.4], abs=1e-12)
    assert size == pytest.approx(np.sqrt(5) * 1e-3)


def test_the_magnification_is_a_round_number_fitted_to_the_robot():
    # 1 mm drawn at a tenth of the reach or a little more
    assert arrow_factor(_cell("mh180.urdf").robot) == 500.0  # reach 3.9 m: 1 mm -> 0.5 m
    assert arrow_factor(_cell("ur10.urdf").robot) == 200.0  # reach 1.5 m: 1 mm -> 0.2 m


def test_tool_speed_from_successive_positions():
    t = np.array([0.0, 0.01, 0.02, 0.02])
    p = np.array([[0, 0, 0], [0.003, 0.004, 0], [0.006, 0.008, 0], [0.006, 0.008, 0]], float)
    v = speeds(t, p)
    assert v[:2] == pytest.approx([0.5, 0.5])
    assert np.isnan(v[2])  # no time passed: no speed


def test_the_default_camera_sees_the_robot_and_the_tracker():
    points = np.array([[0.0, 0.0, 0.0], [1.8, 0.0, 2.1], [4.0, 0.5, 0.0], [0.3, -0.4, 1.0]])
    eye, target = framing_camera(points)
    look = (target - eye) / np.linalg.norm(target - eye)
    for p in points:
        to_p = (p - eye) / np.linalg.norm(p - eye)
        # inside the view (the screenshot in docs/ shows the view as drawn)
        assert np.degrees(np.arccos(np.clip(to_p @ look, -1, 1))) < 45.0
    assert eye[2] > target[2]  # from above


def test_a_urdf_with_meshes_is_drawn_with_them(demo_cell, tmp_path):
    """A link with a visual mesh (here an OBJ cube) becomes an asset that moves with its joint."""
    (tmp_path / "cube.obj").write_text(
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 0 1\nv 1 0 1\nv 1 1 1\nv 0 1 1\n"
        "f 1 2 3 4\nf 5 6 7 8\nf 1 2 6 5\nf 2 3 7 6\nf 3 4 8 7\nf 4 1 5 8\n"
    )
    urdf = tmp_path / "one.urdf"
    urdf.write_text(
        '<robot name="one"><link name="base_link"/>'
        '<link name="arm"><visual><origin xyz="0 0 0.5"/><geometry>'
        '<mesh filename="cube.obj" scale="0.1 0.1 1.0"/></geometry></visual></link>'
        '<link name="tool0"/>'
        '<joint name="j1" type="revolute"><parent link="base_link"/><child link="arm"/>'
        '<axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>'
        '<joint name="f" type="fixed"><parent link="arm"/><child link="tool0"/>'
        '<origin xyz="1 0 0"/></joint></robot>'
    )
    cell = Cell(load_robot(urdf), pin.SE3.Identity(), pin.SE3.Identity())
    rrd = tmp_path / "m.rrd"
    sink = RerunLogger(cell, rrd=rrd, urdf=str(urdf))
    sink.add(Estimate(1.0, [1e-3, 0, 0], [1e-3, 0, 0], (), 1.0, ("px", "py", "pz"), np.zeros(1)))
    sink.flush()
    sink.close()
    chunks = list(RrdReader(str(rrd)).stream().to_chunks())
    static = {c.entity_path for c in chunks if c.is_static}
    assert "/world/robot/mesh/0" in static
    moving = _table(rrd, "/world/robot/mesh/0")
    assert moving is not None
    (row,) = moving.column("Transform3D:translation").to_pylist()
    assert row == [pytest.approx([0, 0, 0.5])]  # the visual's origin, joint at zero
    assert _table(rrd, "/world/error") is not None


# ---- opening a viewer -----------------------------------------------------------------------


def test_a_bare_viewer_flag_opens_one_and_a_url_keeps_its_meaning():
    parser = build_parser()
    cfg = ["--config", "c.toml"]
    assert parser.parse_args(["run", *cfg, "--viewer"]).viewer == "auto"
    url = "rerun+http://10.0.0.5:9876/proxy"
    assert parser.parse_args(["run", *cfg, "--viewer", url]).viewer == url
    assert parser.parse_args(["run", *cfg]).viewer is None
    assert parser.parse_args(["demo", "--viewer"]).viewer == "auto"
    assert parser.parse_args(["demo", "--viewer", "web", "--web-port", "1"]).web_port == 1


def test_an_unknown_viewer_kind_is_refused():
    from keo_service.live.rerun_process import open_viewer

    with pytest.raises(KeoError, match="none of auto, native, web"):
        open_viewer("vr")


@pytest.mark.e2e
def test_the_web_viewer_is_served_on_localhost(monkeypatch):
    from keo_service.bench.procs import free_port
    from keo_service.live.rerun_process import open_viewer

    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    grpc_port, web_port = free_port(), free_port()
    viewer = open_viewer("auto", grpc_port, web_port)  # no display: the web viewer
    try:
        assert viewer.kind == "web"
        assert viewer.grpc_url == f"rerun+http://127.0.0.1:{grpc_port}/proxy"
        assert viewer.url.startswith(f"http://127.0.0.1:{web_port}/?url=rerun%2Bhttp")
        deadline = time.monotonic() + 20.0
        while True:
            try:
                with urllib.request.urlopen(viewer.url, timeout=5.0) as page:
                    body = page.read().decode()
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)
        assert "<html" in body.lower()
    finally:
        viewer.close()
    assert viewer.process is not None
    assert viewer.process.poll() is not None  # the server stops with keo,
    with pytest.raises(ProcessLookupError):  # Rerun's binary under the wrapper too
        os.killpg(viewer.process.pid, 0)
