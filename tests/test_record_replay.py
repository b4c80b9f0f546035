"""Recording, replay and Rerun logging, end to end with real processes."""

from __future__ import annotations

import json
import signal
import threading
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
from rerun.chunk import RrdReader

from keo_service.bench.demo import loopback_config
from keo_service.bench.procs import process_group
from keo_service.io.config import config_to_toml
from keo_service.io.interchange import read_encoder, read_estimates, read_tracker
from keo_service.live.bus import session_for_client
from keo_service.live.messages import EstimateMessage, decode, topic
from keo_service.sim.simulate import make_scenario, simulate, write_run
from tests.conftest import keo, wait_for_status


def read_entity(path, entity: str) -> pa.Table:
    chunks = [
        c
        for c in RrdReader(str(path)).stream().filter(content=entity).to_chunks()
        if not c.is_static
    ]
    tables = [pa.Table.from_batches([c.to_record_batch()]) for c in chunks]
    return pa.concat_tables(tables, promote_options="default").sort_by("stream_time")


class EstimateCollector:
    """Collects estimates on a background Zenoh callback (no asyncio needed)."""

    def __init__(self, config) -> None:
        self.session = session_for_client(config, retry_for=10)
        self.items: list[EstimateMessage] = []
        self._lock = threading.Lock()
        self.sub = self.session.declare_subscriber(topic(config.cell, "estimate"), self._on)

    def _on(self, sample) -> None:
        msg = decode(sample.payload.to_bytes())
        with self._lock:
            self.items.append(msg)

    def wait_for(self, n: int, timeout: float) -> list[EstimateMessage]:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and len(self.items) < n:
            time.sleep(0.05)
        with self._lock:
            return list(self.items)

    def close(self) -> None:
        self.sub.undeclare()
        self.session.close()


@pytest.mark.parametrize("alignment", ["interpolate", "latest"])
def test_replay_through_the_service_equals_estimate_on_files(
    demo_config, demo_cell, tmp_path, alignment
):
    import msgspec

    timing = msgspec.structs.replace(demo_config.timing, alignment=alignment)
    config = loopback_config(msgspec.structs.replace(demo_config, timing=timing))
    cfg = tmp_path / "c.toml"
    cfg.write_text(config_to_toml(config))
    run = simulate(demo_cell, make_scenario("paper-vertical", {"duration_s": "9"}), seed=13)
    write_run(run, tmp_path / "rec")
    res = keo(
        "estimate",
        "--config",
        str(cfg),
        "--encoder",
        str(tmp_path / "rec/encoder.csv"),
        "--tracker",
        str(tmp_path / "rec/tracker.csv"),
        "--out",
        str(tmp_path / "est.csv"),
    )
    assert res.returncode == 0, res.stderr
    offline = read_estimates(tmp_path / "est.csv")
    rrd = tmp_path / "live.rrd"
    with process_group(tmp_path) as procs:
        procs.start("service", ["run", "--config", str(cfg), "--rrd", str(rrd)])
        wait_for_status(config)
        collector = EstimateCollector(config)
        time.sleep(0.3)
        replay = procs.start(
            "replay",
            ["replay", "--config", str(cfg), str(tmp_path / "rec"), "--as-fast-as-possible"],
        )
        assert replay.wait(timeout=60) == 0, procs.log("replay")
        live = collector.wait_for(offline.t.size, timeout=20)
        collector.close()
        assert procs.stop("service") == 0
    assert len(live) == offline.t.size
    t = np.array([e.stamp for e in live])
    est = np.array([e.estimate for e in live])
    meas = np.array([e.measured if e.measured is not None else [np.nan] * 6 for e in live])
    assert np.array_equal(t, offline.t)
    assert np.max(np.abs(est - offline.estimate)) <= 1e-12
    assert np.array_equal(np.isnan(meas), np.isnan(offline.measured))
    ok = ~np.isnan(meas)
    assert np.max(np.abs(meas[ok] - offline.measured[ok])) <= 1e-12

    # the Rerun recording holds exactly what was published, in mm / mrad
    for i, channel in enumerate(["px", "py", "pz", "rx", "ry", "rz"]):
        tbl = read_entity(rrd, f"/keo/error/{channel}")
        both = np.array(tbl.column("Scalars:scalars").to_pylist())
        assert np.allclose(both[:, 0], meas[:, i] * 1e3, rtol=0, atol=1e-9, equal_nan=True)
        values = both[:, 1]
        assert values.size == len(live)
        assert np.allclose(values, est[:, i] * 1e3, rtol=0, atol=1e-9)
        stamps = tbl.column("stream_time").cast(pa.int64()).to_numpy() * 1e-9
        assert np.allclose(stamps, t, atol=1e-6)
    entities = {c.entity_path for c in RrdReader(str(rrd)).stream().to_chunks()}
    for needed in (
        "/world/tool",
        "/world/sensor",
        "/world/robot/links",
        "/world/error",
        "/keo/tool_speed",
        "/keo/status/delay/in_use",
        "/keo/status/rate_hz/tracker",
        "/keo/log",
        "/keo/error/pz",
    ):
        assert needed in entities
    assert len(RrdReader(str(rrd)).blueprints()) == 1


def test_record_writes_what_the_devices_sent_and_survives_a_kill(demo_config, demo_cell, tmp_path):
    config = loopback_config(demo_config)
    cfg = tmp_path / "c.toml"
    cfg.write_text(config_to_toml(config))
    duration = 6.0
    run = simulate(
        demo_cell, make_scenario("paper-vertical", {"duration_s": repr(duration)}), seed=4
    )
    t0 = time.time() + 4.0
    play = [
        "--scenario",
        "paper-vertical",
        "--seed",
        "4",
        "--t0",
        repr(t0),
        "--duration",
        repr(duration),
    ]
    with process_group(tmp_path) as procs:
        procs.start_cell(cfg, play)  # the service is the bus endpoint everyone joins
        # a recorder that is killed hard half-way, and one that runs to the end
        killed = procs.start(
            "killed", ["record", "--config", str(cfg), "--out", str(tmp_path / "killed")]
        )
        full = procs.start(
            "full",
            [
                "record",
                "--config",
                str(cfg),
                "--out",
                str(tmp_path / "full"),
                "--duration",
                repr(t0 + duration + 1.0 - time.time()),
            ],
        )
        time.sleep(max(0.0, t0 + 3.0 - time.time()))
        killed.send_signal(signal.SIGKILL)
        killed_at = time.time()
        assert full.wait(timeout=30) == 0, procs.log("full")
    enc = read_encoder(tmp_path / "full/encoder.csv", nq=6)
    trk = read_tracker(tmp_path / "full/tracker.csv")
    assert enc.t.size == pytest.approx(run.encoder.t.size, abs=2)
    assert trk.t.size == pytest.approx(run.tracker.t.size, abs=2)
    # joints went through float32 on the MotoROS wire; positions through millimetres in JSON
    n = min(enc.t.size, run.encoder.t.size)
    assert np.max(np.abs(enc.q[-n:] - run.encoder.q[-n:])) < 1e-6
    m = min(trk.t.size, run.tracker.t.size)
    assert np.max(np.abs(trk.p[-m:] - run.tracker.p[-m:])) < 1e-12
    assert np.max(np.abs(trk.quat[-m:] - run.tracker.quat[-m:])) < 1e-12
    # the stamps keep the scenario's spacing (real-time playback, host receipt time)
    assert np.median(np.diff(trk.t)) == pytest.approx(np.median(np.diff(run.tracker.t)), rel=0.1)
    # the killed recorder lost at most about a second of data
    cut = read_tracker(tmp_path / "killed/tracker.csv")
    assert cut.t.size > 0
    assert killed_at - cut.t[-1] < 1.5
    assert json.loads(procs.log("full").strip().splitlines()[-1])["tracker_rows"] == trk.t.size


def test_service_tracks_the_delay_online(demo_config, demo_cell, tmp_path):
    import msgspec

    from keo_service.live.messages import ServiceStatus

    timing = msgspec.structs.replace(demo_config.timing, delay_s=0.0, track_delay=True)
    config = loopback_config(msgspec.structs.replace(demo_config, timing=timing))
    cfg = tmp_path / "c.toml"
    cfg.write_text(config_to_toml(config))
    run = simulate(demo_cell, make_scenario("path", {"duration_s": "120"}), seed=12)
    write_run(run, tmp_path / "rec")
    with process_group(tmp_path) as procs:
        procs.start("service", ["run", "--config", str(cfg)])
        wait_for_status(config)
        replay = procs.start(
            "replay",
            ["replay", "--config", str(cfg), str(tmp_path / "rec"), "--as-fast-as-possible"],
        )
        assert replay.wait(timeout=120) == 0, procs.log("replay")
        session = session_for_client(config, retry_for=5)
        try:
            reply = next(
                r.ok for r in session.get(topic(config.cell, "status"), timeout=3.0) if r.ok
            )
        finally:
            session.close()
        status = decode(reply.payload.to_bytes())
        assert procs.stop("service") == 0
    assert isinstance(status, ServiceStatus)
    assert status.delay_s == pytest.approx(0.028, abs=1e-3), status.delay_tracking
    assert status.delay_tracking is not None
    assert status.counters["delay_fits_accepted"] >= 3, status.delay_tracking
    assert status.delay_se_s is not None
    assert abs(status.delay_s - 0.028) < max(3 * status.delay_se_s, 1e-4)  # it knows how well
    assert "delay tracking: fit" in procs.log("service")


def test_viewer_url_streams_to_a_running_viewer(demo_config, demo_cell, tmp_path):
    """--viewer: the service streams to a Rerun gRPC endpoint (here Rerun's own headless
    `rerun --save`, which writes what a viewer would receive)."""
    import shutil
    import subprocess
    import sys

    from keo_service.bench.procs import free_port

    rerun_bin = shutil.which("rerun", path=str(Path(sys.executable).parent))
    assert rerun_bin, "the rerun-sdk wheel ships the rerun binary"
    port = free_port()
    received = tmp_path / "viewer.rrd"
    viewer = subprocess.Popen(
        [rerun_bin, "--save", str(received), "--port", str(port)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    config = loopback_config(demo_config)
    cfg = tmp_path / "c.toml"
    cfg.write_text(config_to_toml(config))
    run = simulate(demo_cell, make_scenario("paper-step", {"duration_s": "3"}), seed=2)
    write_run(run, tmp_path / "rec")
    try:
        time.sleep(2.0)
        with process_group(tmp_path) as procs:
            procs.start(
                "service",
                ["run", "--config", str(cfg), "--viewer", f"rerun+http://127.0.0.1:{port}/proxy"],
            )
            wait_for_status(config)
            replay = procs.start(
                "replay",
                ["replay", "--config", str(cfg), str(tmp_path / "rec"), "--as-fast-as-possible"],
            )
            assert replay.wait(timeout=60) == 0
            time.sleep(1.0)
            assert procs.stop("service") == 0
    finally:
        viewer.send_signal(signal.SIGINT)
        viewer.wait(timeout=10)
    tbl = read_entity(received, "/keo/error/px")
    assert tbl.num_rows == run.tracker.t.size
