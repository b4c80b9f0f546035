"""Recording, replay and Rerun logging, end to end with real processes."""

from __future__ import annotations

import contextlib
import json
import re
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
from tests.conftest import keo, wait_for_adapters, wait_for_status, wait_until

SENT = re.compile(r"client \d+: sent (\d+) rows, from row (\d+) of \d+")


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
        assert procs.stop("service", timeout=15.0) == 0  # the Rerun child may take up to 8 s
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


def sent_rows(mock_log: str) -> list[tuple[int, int]]:
    """What a mock says it sent, per client: (first row, number of rows)."""
    return [(int(m[2]), int(m[1])) for m in SENT.finditer(mock_log)]


def csv_rows(path: Path) -> int:
    return max(0, path.read_bytes().count(b"\n") - 1) if path.exists() else 0


def test_record_writes_what_the_devices_sent_and_survives_a_kill(demo_config, demo_cell, tmp_path):
    """No timing assumed: the devices play a long scenario until stopped and say what they
    sent; the recording must hold exactly that (processes start late on a loaded machine)."""
    config = loopback_config(demo_config)
    cfg = tmp_path / "c.toml"
    cfg.write_text(config_to_toml(config))
    duration = 20.0  # longer than the test needs: the mocks are stopped before the end
    run = simulate(
        demo_cell, make_scenario("paper-vertical", {"duration_s": repr(duration)}), seed=4
    )
    args = ["--config", str(cfg)]
    mocks = ("mock-robot", "mock-tracker")
    with process_group(tmp_path) as procs:
        # the service (the bus endpoint everyone joins) and two recorders, ready before the
        # devices play: one recorder is killed hard half-way, one runs to the end
        procs.start("service", ["run", *args])
        killed = procs.start("killed", ["record", *args, "--out", str(tmp_path / "killed")])
        procs.start("full", ["record", *args, "--out", str(tmp_path / "full")])
        wait_for_status(config)
        wait_until(
            lambda: all((tmp_path / d / "encoder.csv").exists() for d in ("killed", "full")),
            30,
            "both recorders subscribed",
        )
        # the rows exactly as simulated (not read off the motion when they go out late)
        play = ["--scenario", "paper-vertical", "--seed", "4", "--duration", repr(duration)]
        play += ["--as-planned"]
        play += ["--t0", repr(time.time() + 2.0)]
        for device, adapter in (("robot", "encoder"), ("tracker", "tracker")):
            procs.start(f"mock-{device}", ["mock", device, *args, *play])
            procs.start(f"adapter-{adapter}", ["adapter", adapter, *args])
        # one recorder killed once both streams have flowed a while; the devices stopped 1 s on
        wait_for_adapters(config, ("encoder", "tracker"), ("receiving",))
        time.sleep(2.5)
        killed.send_signal(signal.SIGKILL)
        killed_at = time.time()
        time.sleep(1.0)
        for mock in mocks:
            assert procs.stop(mock) == 0, procs.log(mock)
        sent_enc, sent_trk = (sent_rows(procs.log(mock)) for mock in mocks)
        n_enc = sum(n for _, n in sent_enc)
        n_trk = sum(n for _, n in sent_trk)
        # the full recorder has everything once it flushes (each second); stopped then
        with contextlib.suppress(AssertionError):
            wait_until(
                lambda: (
                    csv_rows(tmp_path / "full/encoder.csv") >= n_enc
                    and csv_rows(tmp_path / "full/tracker.csv") >= n_trk
                ),
                10,
                "all rows recorded",
            )
        assert procs.stop("full") == 0, procs.log("full")
    enc = read_encoder(tmp_path / "full/encoder.csv", nq=6)
    trk = read_tracker(tmp_path / "full/tracker.csv")
    # every row the devices sent, none more, none less
    recorded = {"encoder": int(enc.t.size), "tracker": int(trk.t.size)}
    assert recorded == {"encoder": n_enc, "tracker": n_trk}, (sent_enc, sent_trk)
    assert n_enc >= 100, sent_enc  # the 3.5 s played at 40 Hz
    assert n_trk >= 250, sent_trk  # and at 100 Hz
    # joints went through float32 on the MotoROS wire; positions through millimetres in JSON
    want_q = np.concatenate([run.encoder.q[a : a + n] for a, n in sent_enc])
    assert np.max(np.abs(enc.q - want_q)) < 1e-6
    want_p = np.concatenate([run.tracker.p[a : a + n] for a, n in sent_trk])
    want_quat = np.concatenate([run.tracker.quat[a : a + n] for a, n in sent_trk])
    assert np.max(np.abs(trk.p - want_p)) < 1e-12
    assert np.max(np.abs(trk.quat - want_quat)) < 1e-12
    # the stamps keep the scenario's spacing (real-time playback, host receipt time)
    assert np.median(np.diff(trk.t)) == pytest.approx(np.median(np.diff(run.tracker.t)), rel=0.1)
    # the killed recorder, killed while the devices sent, lost at most about a second
    assert trk.t[-1] > killed_at + 0.5
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
    import socket
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
        # until the headless viewer listens (it took over 2 s once on a loaded machine, and
        # what was sent before went nowhere)
        deadline = time.monotonic() + 30.0
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1.0).close()
                break
            except OSError:
                assert time.monotonic() < deadline, "the headless Rerun viewer never listened"
                time.sleep(0.1)
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
            # the Rerun child runs only on time nobody else wants (SCHED_IDLE): a stop waits
            # while it reads (up to 8 s), and the wait here leaves it the viewer's share
            time.sleep(3.0)
            assert procs.stop("service", timeout=15.0) == 0
    finally:
        viewer.send_signal(signal.SIGINT)
        viewer.wait(timeout=10)
    tbl = read_entity(received, "/keo/error/px")
    assert tbl.num_rows == run.tracker.t.size
