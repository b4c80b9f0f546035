"""Universal Robots RTDE: the codec, the clock mapping, the mock controller against an
independent client (ur_rtde, C++), and the adapter over real TCP."""

from __future__ import annotations

import asyncio
import json
import socket
import struct
import subprocess
import sys
import time
from types import SimpleNamespace

import msgspec
import numpy as np
import pytest

from keo_service.adapters import rtde
from keo_service.adapters.devices import RtdeEncoderAdapter
from keo_service.adapters.mock import MockSettings
from keo_service.adapters.mock_devices import MockRtdeController
from keo_service.bench.procs import free_port
from keo_service.core.clock import ClockMapper
from keo_service.live.bus import open_session
from keo_service.live.messages import JointSample, decode, topic
from tests.conftest import CONFIGS, keo

# ---- codec ------------------------------------------------------------------------------------


def test_packages_frame_and_resynchronise_after_garbage():
    recipe = rtde.Recipe(1, ("timestamp", "actual_q"), ("DOUBLE", "VECTOR6D"))
    data = rtde.data_package(recipe, {"timestamp": 12.5, "actual_q": (0.1,) * 6})
    stream = rtde.accepted(rtde.REQUEST_PROTOCOL_VERSION) + b"\xff\x00\x07garbage" + data
    decoder = rtde.RtdeDecoder()
    packages = [p for i in range(len(stream)) for p in decoder.feed(stream[i : i + 1])]
    assert [p.type for p in packages] == [rtde.REQUEST_PROTOCOL_VERSION, rtde.DATA_PACKAGE]
    assert decoder.counters["bad_header"] == 1
    assert decoder.counters["resync"] == 1
    values = recipe.unpack(packages[1].payload)
    assert values["timestamp"] == 12.5
    assert values["actual_q"] == (0.1,) * 6
    # the wire format itself, byte for byte: size includes the 3 header bytes, big endian
    assert data[:3] == struct.pack(">HB", 3 + 1 + 8 + 48, ord("U"))


def test_setup_request_with_a_trailing_comma_and_not_found_by_name():
    frequency, names = rtde.parse_setup_request(
        rtde.Package(rtde.CONTROL_PACKAGE_SETUP_OUTPUTS, struct.pack(">d", 125.0) + b"a,b,")
    )
    assert frequency == 125.0
    assert names == ["a", "b"]
    reply = rtde.RtdeDecoder().feed(rtde.outputs_reply(1, ["DOUBLE", "NOT_FOUND"]))[0]
    with pytest.raises(rtde.RtdeError, match="actual_qq"):
        rtde.parse_outputs_reply(reply, ["timestamp", "actual_qq"])


def test_text_message_and_short_data_package_are_errors_not_crashes():
    text = rtde.parse_text_message(rtde.RtdeDecoder().feed(rtde.text_message("hi", "ctl", 2))[0])
    assert (text.message, text.source, text.level) == ("hi", "ctl", 2)
    recipe = rtde.Recipe(1, ("timestamp",), ("DOUBLE",))
    with pytest.raises(rtde.RtdeError, match="recipe needs 9"):
        recipe.unpack(b"\x01\x00")


# ---- clock mapping ----------------------------------------------------------------------------


def _bursty_stream(
    seconds: float, drift_ppm: float, late_s: float, seed: int = 1, every_s: float = 0.1
):
    """500 Hz samples: true instants on the host clock, the controller's stamps, receipts."""
    rng = np.random.default_rng(seed)
    h = 50.0 + np.arange(int(seconds * 500)) / 500.0
    d = 7.0 + (h - 50.0) * (1 + drift_ppm * 1e-6)
    r = h + 0.0002 + rng.exponential(0.0001, h.size)
    at = 50.2
    while at < h[-1]:
        stall = rng.uniform(0.2, 1.0) * late_s
        held = (h >= at) & (h < at + stall)
        r[held] = np.maximum(r[held], at + stall)
        at += rng.exponential(every_s) + stall
    return h, d, np.maximum.accumulate(r)


def test_mapped_stamps_keep_the_controllers_regularity_on_the_host_clock():
    h, d, r = _bursty_stream(30.0, drift_ppm=80.0, late_s=0.006)
    mapper = ClockMapper()
    mapped = np.array([mapper.map(di, ri) for di, ri in zip(d, r, strict=True)])
    after = h - h[0] > 10.0
    err = mapped[after] - h[after]
    receipt = r[after] - h[after]
    jitter = np.percentile(np.abs(err - np.median(err)), 99)
    receipt_jitter = np.percentile(np.abs(receipt - np.median(receipt)), 99)
    drift = np.polyfit(h[after], err, 1)[0]
    assert jitter < 0.25e-3
    assert receipt_jitter > 1e-3  # the receipt times carry the bursts
    assert np.max(np.abs(receipt - np.median(receipt))) > 4e-3
    assert abs(drift) < 5e-6
    assert mapper.state().drift_ppm == pytest.approx(-80.0, abs=5.0)


def test_a_controller_restart_is_detected_and_relearned_within_2_s():
    h, d, r = _bursty_stream(20.0, drift_ppm=0.0, late_s=0.002)
    d = np.where(h - h[0] > 8.0, d - 1000.0 + 3.0, d)  # restart: the controller clock starts over
    mapper = ClockMapper()
    mapped = np.array([mapper.map(di, ri) for di, ri in zip(d, r, strict=True)])
    assert mapper.steps == 1
    settled = h - h[0] > 10.0  # 2 s after the step
    err = mapped[settled] - h[settled]
    assert np.percentile(np.abs(err - np.median(err)), 99) < 0.25e-3
    assert abs(np.median(err)) < 1e-3


# ---- the mock controller against an independent client ---------------------------------------


def _port_free(port: int) -> bool:
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def test_ur_rtde_reads_timestamp_and_actual_q_from_the_mock_controller(tmp_path):
    import rtde_receive  # ur-rtde, a test dependency

    if not _port_free(rtde.DEFAULT_PORT):
        pytest.skip("port 30004 is taken on this machine; ur_rtde cannot use another port")
    cfg = CONFIGS / "ur10_demo.toml"
    mock = subprocess.Popen(
        [
            *(sys.executable, "-m", "keo_service.cli", "mock", "robot", "--config", str(cfg)),
            *("--scenario", "paper-step", "--duration", "20", "--t0", repr(time.time() + 3.0)),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    try:
        deadline = time.monotonic() + 20
        while _port_free(rtde.DEFAULT_PORT) and time.monotonic() < deadline:
            time.sleep(0.1)
        time.sleep(3.0)  # the play has started
        receiver = rtde_receive.RTDEReceiveInterface("127.0.0.1", 500.0, ["timestamp", "actual_q"])
        time.sleep(0.5)
        first, q = receiver.getTimestamp(), receiver.getActualQ()
        time.sleep(1.0)
        second = receiver.getTimestamp()
        receiver.disconnect()
    finally:
        mock.terminate()
        mock.wait(timeout=5)
    assert len(q) == 6
    assert all(np.isfinite(q))
    assert any(abs(v) > 1e-3 for v in q)
    assert first > 1000.0  # the controller's own clock (offset 1000 s at the play's start)
    assert second - first == pytest.approx(1.0, abs=0.2)


# ---- the adapter over real TCP ----------------------------------------------------------------


@pytest.mark.slow
async def test_adapter_maps_a_drifting_bursty_controller_onto_the_host_clock(demo_config):
    """80 ppm fast controller clock, delivery up to 6 ms late in bursts, 22 s over TCP; the
    numbers are judged on the 12 s after the first 10 s (the README prints them)."""
    seconds, drift_ppm, offset = 22.0, 80.0, 500.0
    t = np.linspace(0.0, seconds, 1201)
    q = np.column_stack([0.2 * np.sin(0.5 * t + k) for k in range(6)])
    robot = msgspec.structs.replace(
        demo_config.robot, protocol="rtde", clock="device", port=free_port(), host="127.0.0.1"
    )
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    bus = msgspec.structs.replace(demo_config.bus, listen=[endpoint], connect=[])
    config = msgspec.structs.replace(demo_config, robot=robot, bus=bus)
    t0 = time.time() + 1.0
    mock = MockRtdeController(
        SimpleNamespace(t=t, q=q),
        MockSettings(
            host="127.0.0.1",
            port=robot.port,
            t0=t0,
            clock_offset_s=offset,
            clock_drift_ppm=drift_ppm,
            late_ms=6.0,
            burst_every_s=0.2,
        ),
    )
    await mock.start()
    service_side = open_session("peer", listen=[endpoint])
    samples: list[JointSample] = []
    sub = service_side.declare_subscriber(
        topic(config.cell, "encoder"), lambda s: samples.append(decode(s.payload.to_bytes()))
    )
    try:
        async with RtdeEncoderAdapter(config, 6) as adapter:
            await asyncio.sleep(t0 + seconds + 0.5 - time.time())
            status = adapter.status()
    finally:
        sub.undeclare()
        service_side.close()
        await mock.close()
    # every package the controller sent arrived (a loaded machine connects late: the count
    # the controller sent, not the scenario's, is what the adapter could have)
    assert len(mock.sent) > 0.6 * 500 * seconds
    assert len(samples) > 0.99 * len(mock.sent)
    device_stamp = np.array([s.device_stamp for s in samples])
    true = t0 + (device_stamp - offset) / (1 + drift_ppm * 1e-6)  # the true sampling instants
    mapped = np.array([s.stamp for s in samples]) - true
    receipt = np.array([s.host_ns for s in samples]) * 1e-9 - true
    after = true - t0 > 10.0
    jitter = np.percentile(np.abs(mapped[after] - np.median(mapped[after])), 99)
    receipt_jitter = np.percentile(np.abs(receipt[after] - np.median(receipt[after])), 99)
    drift = np.polyfit(true[after], mapped[after], 1)[0]
    print(
        json.dumps(
            {
                "mapped_jitter_p99_ms": jitter * 1e3,
                "receipt_jitter_p99_ms": receipt_jitter * 1e3,
                "mapped_drift_ppm": drift * 1e6,
                "clock": status["clock"],
            }
        )
    )
    assert jitter < 0.25e-3
    assert receipt_jitter > 1e-3
    # the reported drift is the last 10 s window's fit: under CI load its block minima wait
    # for a core too (seen: -73.5 ppm); the stamps themselves are judged just above
    assert status["clock"]["drift_ppm"] == pytest.approx(-drift_ppm, abs=12.0)
    assert status["controller"] == "5.15.0.0"
    assert status["decoder"].get("rejected", 0) == 0
    # the controller runs 80 ppm fast; the mapped stamps keep a sixth of that at most (seen
    # here: 1-3 ppm alone, 5.3 and 9.9 ppm under a full suite's load; unmapped: 80)
    assert abs(drift) < 13e-6


@pytest.mark.slow  # an acceptance run (> 9 s): .ci/run runs the slow tests after the default run
def test_demo_with_a_ur10_over_rtde_converges_to_the_injected_truth():
    res = keo("demo", "--robot", "ur10", "--duration", "14", "--json", timeout=120)
    assert res.returncode == 0, res.stderr
    summary = json.loads(res.stdout)
    assert summary["robot"] == "ur10"
    assert summary["rates_hz"]["encoder"] == pytest.approx(500.0, rel=0.05)
    assert summary["final_error_pos_mm"] < 0.02, summary
    assert summary["final_error_rot_mrad"] < 0.02, summary
    assert all(code == 0 for code in summary["exit_codes"].values())


def test_mapped_stamps_never_go_back_while_the_fit_learns():
    """The first samples of a connection wait longest: as faster ones arrive the offset
    drops by milliseconds, which must not send a stamp before its predecessor."""
    d = np.arange(200) * 0.001
    lag = np.maximum(0.010 - np.arange(200) * 0.002, 0.0002)  # 2 ms less each 1 ms
    mapper = ClockMapper()
    out = np.array([mapper.map(di, di + 5.0 + li) for di, li in zip(d, lag, strict=True)])
    assert np.all(np.diff(out) > 0)
    assert mapper.held_back > 0
    assert out[-1] - (d[-1] + 5.0) == pytest.approx(0.0002, abs=1e-5)
