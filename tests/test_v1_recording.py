"""Recordings written by the code of wire schema 1 still read: `keo estimate` and `keo replay`
give what that code gave on them, to the byte.

tests/fixtures/v1_recording/ holds a recording made by that code's recorders (interchange CSV
and ROS 2 MCAP) and the estimate files its `keo estimate` wrote; its `keo replay` through its
`keo run` published exactly the rows of the `--streaming` files (see make_v1_recording.py).
"""

from __future__ import annotations

import json
import re
import threading
import time
from pathlib import Path

import msgspec
import numpy as np
import pytest

from keo_service.bench.demo import loopback_config
from keo_service.bench.procs import process_group
from keo_service.core.estimator import Estimator
from keo_service.io.cell import cell_from_config, estimator_settings
from keo_service.io.config import config_to_toml
from keo_service.io.interchange import write_estimate_table
from keo_service.io.mcap_files import McapWriter
from keo_service.live.bus import session_for_client
from keo_service.live.messages import (
    SCHEMA_VERSION,
    EstimateMessage,
    JointSample,
    TrackerSample,
    decode,
    encode,
    estimate_message,
    topic,
)
from keo_service.live.recorder import McapRecorder, Recorder, replay_plan
from keo_service.offline.estimate import estimate_files, write_estimates
from keo_service.sim.simulate import make_scenario, simulate
from tests.conftest import keo, wait_for_status

V1 = Path(__file__).parent / "fixtures" / "v1_recording"
FILES = {
    "csv": (V1 / "csv" / "encoder.csv", V1 / "csv" / "tracker.csv"),
    "mcap": (V1 / "mcap" / "keo", V1 / "mcap" / "keo"),
}
ROWS = 193  # estimates in each expected file


def test_schema_1_payloads_are_refused_naming_their_version():
    """Live payloads of schema 1 (what that code's adapters put on the bus) do not decode as
    schema 2: the error names the version tag, no wrong numbers come through."""
    payloads = msgspec.msgpack.decode((V1 / "payloads_v1.msgpack").read_bytes())
    tags = sorted(msgspec.msgpack.decode(p)["type"] for p in payloads)
    assert tags == ["keo.estimate/1", "keo.joint/1", "keo.tracker/1"]
    assert SCHEMA_VERSION == 2
    for payload in payloads:
        tag = msgspec.msgpack.decode(payload)["type"]
        with pytest.raises(msgspec.DecodeError, match=re.escape(f"Invalid value '{tag}'")):
            decode(payload)


def _schema2_payloads(config) -> list[bytes]:
    """The samples and estimates make_v1_recording.py put through schema 1's recorders, as
    schema-2 messages (the same simulated run, stamps, device stamps, clock fields, gaps)."""
    cell = cell_from_config(config)
    run = simulate(cell, make_scenario("paper-vertical", {"duration_s": "2"}), seed=32)
    enc, trk = run.encoder, run.tracker
    estimator = Estimator(cell, estimator_settings(config))
    payloads: list[bytes] = []
    plan = replay_plan(enc.t, trk.t)
    seq = {"enc": 0, "trk": 0, "est": 0}
    for kind, i, stamp in zip(plan.kinds, plan.index, plan.t, strict=True):
        t = float(stamp)
        host_ns = round(t * 1e9) + 1_700_000_000_000_000_000
        if kind == 0:
            seq["enc"] += 1
            q = enc.q[i].tolist()
            sample = JointSample(
                stamp=t,
                host_ns=host_ns,
                seq=seq["enc"],
                joints=q,
                velocities=[0.0] * len(q),
                device_stamp=t - 1000.0,
                clock="shared",
            )
            payloads.append(encode(sample))
            out = estimator.on_encoder(t, q)
        else:
            seq["trk"] += 1
            p, quat = trk.p[i].tolist(), trk.quat[i].tolist()
            if seq["trk"] % 97 == 0:
                gap = TrackerSample(
                    stamp=t, host_ns=host_ns, seq=seq["trk"], status="beam_broken", clock="device"
                )
                payloads.append(encode(gap))
                seq["trk"] += 1
            pose = TrackerSample(
                stamp=t,
                host_ns=host_ns,
                seq=seq["trk"],
                position=p,
                quaternion=quat,
                device_stamp=t + 5.0,
                clock="device",
            )
            payloads.append(encode(pose))
            out = estimator.on_tracker(t, p, quat, device_stamp=t + 5.0)
        for est in out:
            seq["est"] += 1
            message = estimate_message(
                est, host_ns=host_ns, seq=seq["est"], delay_s=estimator.delay.at(est.stamp)
            )
            assert message.device_stamp == est.stamp + 5.0  # the tracker's, end to end
            payloads.append(encode(message))
    return payloads


def test_the_recorders_write_the_v1_recording_from_the_same_samples(demo_config, tmp_path):
    """The same samples as schema-2 messages: `keo record`'s two recorders write what schema
    1's wrote, byte for byte (CSV and MCAP), with the same counts."""
    cell = cell_from_config(demo_config)
    nq = cell.robot.nq
    csv_rec = Recorder(tmp_path / "csv", nq)
    mcap_rec = McapRecorder(McapWriter(tmp_path / "mcap", cell.robot.joint_names, "demo"), nq)
    for payload in _schema2_payloads(demo_config):
        csv_rec.on_payload(payload)
        mcap_rec.on_payload(payload)
    csv_rec.close()
    mcap_rec.close()
    for name in (
        "csv/encoder.csv",
        "csv/tracker.csv",
        "mcap/keo/keo.mcap",
        "mcap/keo/metadata.yaml",
    ):
        assert (tmp_path / name).read_bytes() == (V1 / name).read_bytes(), name
    stats = json.loads((V1 / "expected" / "record_stats.json").read_text())
    assert csv_rec.stats.__dict__ == stats["csv"]
    assert mcap_rec.stats.__dict__ == stats["mcap"]


@pytest.mark.parametrize("streaming", [False, True], ids=["batch", "streaming"])
@pytest.mark.parametrize("kind", ["csv", "mcap"])
def test_estimate_on_a_v1_recording_writes_what_v1_wrote(demo_config, tmp_path, kind, streaming):
    encoder, tracker = FILES[kind]
    result = estimate_files(demo_config, encoder, tracker, streaming=streaming)
    out = tmp_path / "est.csv"
    write_estimates(out, result)
    expected = V1 / "expected" / f"estimate_{kind}{'_streaming' if streaming else ''}.csv"
    assert out.read_bytes() == expected.read_bytes()


def test_keo_estimate_command_on_a_v1_recording(demo_config, tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_text(config_to_toml(demo_config))
    encoder, tracker = FILES["csv"]
    out = tmp_path / "est.csv"
    res = keo(
        *("estimate", "--config", str(cfg), "--encoder", str(encoder)),
        *("--tracker", str(tracker), "--out", str(out)),
    )
    assert res.returncode == 0, res.stderr
    assert out.read_bytes() == (V1 / "expected" / "estimate_csv.csv").read_bytes()


def _replay(config, cfg: Path, directory: Path, logs: Path) -> list[EstimateMessage]:
    """`keo replay` of `directory` into a fresh `keo run`: what it published."""
    items: list[EstimateMessage] = []
    lock = threading.Lock()

    def on(sample) -> None:
        msg = decode(sample.payload.to_bytes())
        with lock:
            items.append(msg)

    with process_group(logs) as procs:
        procs.start("service", ["run", "--config", str(cfg)])
        wait_for_status(config)
        session = session_for_client(config, retry_for=10)
        sub = session.declare_subscriber(topic(config.cell, "estimate"), on)
        try:
            time.sleep(0.3)
            replay = procs.start(
                "replay", ["replay", "--config", str(cfg), str(directory), "--as-fast-as-possible"]
            )
            assert replay.wait(timeout=60) == 0, procs.log("replay")
            deadline = time.monotonic() + 10  # the replay waited for the service: margin only
            while time.monotonic() < deadline and len(items) < ROWS:
                time.sleep(0.05)
            time.sleep(0.2)  # and nothing more comes
        finally:
            sub.undeclare()
            session.close()
        assert procs.stop("service") == 0
    with lock:
        return list(items)


@pytest.mark.e2e
@pytest.mark.parametrize("kind", ["csv", "mcap"])
def test_replay_of_a_v1_recording_publishes_what_v1_published(demo_config, tmp_path, kind):
    config = loopback_config(demo_config)
    cfg = tmp_path / "c.toml"
    cfg.write_text(config_to_toml(config))
    live = _replay(config, cfg, V1 / kind, tmp_path)
    assert len(live) == ROWS
    out = tmp_path / "replayed.csv"
    write_estimate_table(
        out,
        np.array([e.stamp for e in live]),
        np.array([[np.nan] * 6 if e.measured is None else e.measured for e in live]),
        np.array([e.estimate for e in live]),
        ["|".join(e.flags) for e in live],
        live[0].channels,
    )
    expected = V1 / "expected" / f"estimate_{kind}_streaming.csv"
    assert out.read_bytes() == expected.read_bytes()
