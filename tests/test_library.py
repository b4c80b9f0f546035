"""The offline work as library functions (`keo_service.estimate`, `calibrate_delay`,
`analyze`), the commands as a thin layer over them, the warning when a moving recording is
estimated with `timing.delay_s = 0`, and `keo view` (issue 50)."""

from __future__ import annotations

import heapq
import json
import re
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
from rerun.chunk import RrdReader

import keo_service
from keo_service.io.interchange import read_encoder, read_estimates, read_tracker
from tests.conftest import DEMO, keo

TRUE_DELAY_S = 0.028  # the simulator's mean delay (docs/design.md §7)


@pytest.fixture(scope="module")
def moving(tmp_path_factory) -> Path:
    """20 s of the reference experiment: vertical strokes at 100 mm/s with dwells (12 s hold
    too little of a change of speed to find the delay), 28 ms delay."""
    rec = tmp_path_factory.mktemp("moving")
    done = keo("simulate", "--config", str(DEMO), "--scenario", "paper-vertical", "--out",
               str(rec), "--set", "duration_s=20", "--seed", "5")  # fmt: skip
    assert done.returncode == 0, done.stderr
    return rec


def zero_delay_config(tmp_path: Path) -> Path:
    """The demo cell with `timing.delay_s = 0` (as a config without the key would have)."""
    text = DEMO.read_text()
    text = re.sub(r"(?m)^delay_s = .*$", "delay_s = 0.0", text)
    text = text.replace('urdf = "', f'urdf = "{DEMO.parent}/')
    path = tmp_path / "zero.toml"
    path.write_text(text)
    assert "delay_s = 0.0" in text
    return path


def test_the_library_is_in_the_public_surface():
    for name in ("estimate", "calibrate_delay", "analyze"):
        assert name in keo_service.__all__
        doc = getattr(keo_service, name).__doc__
        for section in ("Args:", "Returns:", "Raises:"):
            assert section in doc, (name, section)


def test_estimate_from_files_arrays_and_the_command_agree(moving, tmp_path):
    enc, trk = moving / "encoder.csv", moving / "tracker.csv"
    from_files = keo_service.estimate(DEMO, enc, trk, out=tmp_path / "lib.csv")
    e, k = read_encoder(enc), read_tracker(trk)
    from_arrays = keo_service.estimate(DEMO, (e.t, e.q), (k.t, k.p, k.quat))
    assert np.array_equal(from_files.stamp, from_arrays.stamp)
    assert np.array_equal(from_files.estimate, from_arrays.estimate)
    done = keo("estimate", "--config", str(DEMO), "--encoder", str(enc), "--tracker", str(trk),
               "--out", str(tmp_path / "cli.csv"), "--json")  # fmt: skip
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    assert summary["estimates"] == from_files.stamp.size
    assert summary["held"] == from_files.held
    assert summary["warnings"] == [] == from_files.warnings  # the demo config has its delay
    cli, lib = read_estimates(tmp_path / "cli.csv"), read_estimates(tmp_path / "lib.csv")
    assert np.array_equal(cli.estimate, lib.estimate)
    # the estimate is the injected error (truth.csv), within a tenth of its size: L = 1/s lags
    truth = np.loadtxt(moving / "truth.csv", delimiter=",", skiprows=1)
    size = np.max(np.abs(truth[-1, 1:4]))
    assert np.max(np.abs(from_files.estimate[-1, :3] - truth[-1, 1:4])) < 0.1 * size


def test_a_zero_delay_on_a_moving_recording_is_said_with_the_command_that_finds_it(
    moving, tmp_path
):
    config = zero_delay_config(tmp_path)
    enc, trk = moving / "encoder.csv", moving / "tracker.csv"
    done = keo("estimate", "--config", str(config), "--encoder", str(enc), "--tracker", str(trk),
               "--out", str(tmp_path / "est.csv"), "--json")  # fmt: skip
    assert done.returncode == 0, done.stderr
    warnings = json.loads(done.stdout)["warnings"]
    assert len(warnings) == 1
    assert "timing.delay_s is 0" in done.stderr
    command = f"keo calibrate-delay --config {config} --encoder {enc} --tracker {trk}"
    assert command in warnings[0]
    assert command in done.stderr
    # the speed it names is the scenario's (100 mm/s strokes)
    assert re.search(r"95th percentile (9\d|10\d) mm/s", warnings[0]), warnings[0]
    # and the command it names finds the injected delay
    found = keo_service.calibrate_delay(config, enc, trk)
    assert abs(found.delay_s - TRUE_DELAY_S) < 2e-3
    assert found.delay_se_s > 0


def test_no_warning_for_stop_and_measure_data(tmp_path):
    rec = tmp_path / "static"
    done = keo("simulate", "--config", str(DEMO), "--scenario", "static-poses", "--out",
               str(rec), "--set", "poses=30", "--seed", "2")  # fmt: skip
    assert done.returncode == 0, done.stderr
    result = keo_service.estimate(
        zero_delay_config(tmp_path), rec / "encoder.csv", rec / "tracker.csv", quiet=True
    )
    assert result.warnings == []


def test_calibrate_delay_command_and_library_agree(moving):
    enc, trk = moving / "encoder.csv", moving / "tracker.csv"
    done = keo("calibrate-delay", "--config", str(DEMO), "--encoder", str(enc), "--tracker",
               str(trk), "--json")  # fmt: skip
    assert done.returncode == 0, done.stderr
    doc = json.loads(done.stdout)
    found = keo_service.calibrate_delay(DEMO, enc, trk)
    assert doc["delay_s"] == found.delay_s
    assert doc["delay_se_s"] == found.delay_se_s
    assert found.document() == {**doc, "reference_method": found.document()["reference_method"]}
    e, k = read_encoder(enc), read_tracker(trk)
    from_arrays = keo_service.calibrate_delay(DEMO, (e.t, e.q), (k.t, k.p, k.quat))
    assert from_arrays.delay_s == found.delay_s


def test_wrong_arrays_are_named():
    with pytest.raises(keo_service.KeoError, match=r"q \(n, 6\)"):
        keo_service.estimate(DEMO, (np.zeros(3), np.zeros((3, 5))), (np.zeros(1), np.zeros((1, 3))))


@pytest.mark.slow
def test_analyze_says_when_the_delay_is_zero(tmp_path):
    rec = tmp_path / "rec"
    done = keo("simulate", "--config", str(DEMO), "--scenario", "path", "--out", str(rec),
               "--set", "duration_s=12", "--seed", "3")  # fmt: skip
    assert done.returncode == 0, done.stderr
    config = zero_delay_config(tmp_path)
    result = keo_service.analyze(
        config, rec / "encoder.csv", rec / "tracker.csv", tmp_path / "an", quiet=True
    )
    assert len(result.warnings) == 1
    assert "keo calibrate-delay --config" in result.warnings[0]
    on_disk = json.loads((tmp_path / "an" / "report.json").read_text())
    assert on_disk["warnings"] == result.warnings
    assert "**Warning**: timing.delay_s is 0" in result.report_path.read_text()
    assert result.model_path.is_file()
    assert result.final["validation"]["pos_rms_mm"] < result.baseline["validation"]["pos_rms_mm"]


# ---- keo view ------------------------------------------------------------------------------


def read_entity(path: Path, entity: str) -> pa.Table:
    chunks = [
        c
        for c in RrdReader(str(path)).stream().filter(content=entity).to_chunks()
        if not c.is_static
    ]
    table = pa.concat_tables(
        [pa.Table.from_batches([c.to_record_batch()]) for c in chunks], promote_options="default"
    )
    return table.sort_by("stream_time")


def write_mcap(rec: Path, out: Path) -> None:
    """The simulated recording as a ROS 2 MCAP folder (what `keo record --format mcap`
    writes: JointState and PoseStamped)."""
    from keo_service.io.cell import cell_from_config
    from keo_service.io.config import load_config
    from keo_service.io.mcap_files import McapWriter

    names = cell_from_config(load_config(DEMO)).robot.joint_names
    writer = McapWriter(out, names, "demo")
    e, k = read_encoder(rec / "encoder.csv"), read_tracker(rec / "tracker.csv")
    assert k.quat is not None
    joints = ((t, 0, i) for i, t in enumerate(e.t))
    poses = ((t, 1, i) for i, t in enumerate(k.t))
    for t, stream, i in heapq.merge(joints, poses):
        if stream == 0:
            writer.joints(float(t), list(e.q[i]), None)
        else:
            writer.pose(float(t), list(k.p[i]), list(k.quat[i]))
    writer.close()


@pytest.mark.parametrize("form", ["csv", "mcap"])
def test_view_writes_the_recording_and_its_estimates_to_a_rerun_file(moving, tmp_path, form):
    directory = moving
    if form == "mcap":
        directory = tmp_path / "mcap"
        write_mcap(moving, directory)
    rrd = tmp_path / "view.rrd"
    done = keo("view", str(directory), "--config", str(DEMO), "--out", str(rrd), "--json")
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    est = keo_service.estimate(DEMO, moving / "encoder.csv", moving / "tracker.csv")
    assert summary["estimates"] == est.stamp.size
    for i, channel in enumerate(est.channels):
        table = read_entity(rrd, f"/keo/error/{channel}")
        both = np.array(table.column("Scalars:scalars").to_pylist())
        assert both.shape[0] == est.stamp.size
        scale = 1e3  # mm, mrad
        assert np.allclose(both[:, 1], est.estimate[:, i] * scale, rtol=0, atol=1e-6)
        stamps = table.column("stream_time").cast(pa.int64()).to_numpy() * 1e-9
        assert np.allclose(stamps, est.stamp, atol=1e-6)
    entities = {c.entity_path for c in RrdReader(str(rrd)).stream().to_chunks()}
    for needed in ("/world/tool", "/world/robot/links", "/world/error", "/keo/tool_speed"):
        assert needed in entities
    assert len(RrdReader(str(rrd)).blueprints()) == 1
    if form == "csv":  # without --config: the demo cell, said so (docs/design.md §6's form)
        done = keo("view", str(directory), "--out", str(tmp_path / "b.rrd"))
        assert done.returncode == 0, done.stderr
        assert "keo view: no --config; using " in done.stderr
        assert "(the demo cell)" in done.stderr


def test_view_refuses_a_folder_without_a_recording(tmp_path):
    done = keo("view", str(tmp_path), "--config", str(DEMO), "--out", str(tmp_path / "x.rrd"))
    assert done.returncode == 1
    assert "no encoder.csv and no tracker.csv and no MCAP recording" in done.stderr
    done = keo("view", str(tmp_path), "--config", str(DEMO), "--out", str(tmp_path / "x.txt"))
    assert done.returncode == 2
    assert "--out" in done.stderr


def test_each_library_function_reads_each_file_once(moving, monkeypatch, tmp_path):
    """The warning's check and the work share one read (as the commands always did)."""
    from keo_service.io import interchange
    from keo_service.offline import analyze as analyze_module
    from keo_service.offline import recording

    calls: list[str] = []

    def counted(reader):
        def read(path, *args, **kwargs):
            calls.append(Path(path).name)
            return reader(path, *args, **kwargs)

        return read

    monkeypatch.setattr(recording, "read_encoder", counted(interchange.read_encoder))
    monkeypatch.setattr(recording, "read_tracker", counted(interchange.read_tracker))
    given = []

    def run_analysis(config, encoders, trackers, out, registration_only, recordings=None):
        given.append(recordings)
        return {"effects": [], "baseline": {}, "final": {}}

    monkeypatch.setattr(analyze_module, "run_analysis", run_analysis)
    enc, trk = moving / "encoder.csv", moving / "tracker.csv"
    config = zero_delay_config(tmp_path)
    for call in (
        lambda: keo_service.estimate(DEMO, enc, trk),
        lambda: keo_service.calibrate_delay(DEMO, enc, trk),
        lambda: keo_service.analyze(config, enc, trk, tmp_path / "an", quiet=True),
    ):
        calls.clear()
        call()
        assert sorted(calls) == ["encoder.csv", "tracker.csv"]
    (recordings,) = given
    assert len(recordings) == 1  # the analysis got what was read for the warning
