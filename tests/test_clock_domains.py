"""Clock domains ([robot] / [tracker] clock): the one stamping rule (core.clock.Stamper), the
config's check, and a line-protocol tracker adapter under each domain over real TCP."""

from __future__ import annotations

import asyncio
import time

import msgspec
import numpy as np
import pytest

from keo_service.adapters.devices import TrackerAdapter
from keo_service.adapters.line_protocol import format_hello, format_pose
from keo_service.bench.procs import free_port
from keo_service.core.clock import SHARED_AHEAD_TOLERANCE_S, Stamper
from keo_service.core.errors import ConfigError
from keo_service.fit.stamp_lines import Anchor
from keo_service.io.config import load_config
from keo_service.live.bus import open_session
from keo_service.live.messages import TrackerSample, decode, topic
from tests.conftest import keo, write_config

GOOD = """
[robot]
urdf = "@ROBOTS@/mh180.urdf"
"""


# ---- shared: the stamp is the sample's time, checked, never remapped ---------------------------


def test_shared_stamps_are_used_as_they_are():
    s = Stamper("shared", max_age_s=0.5, epoch=7)
    receipts = 1000.0 + np.arange(200) * 0.01
    # a transport that takes 0.4-1.9 ms, different per sample: the stamps stay untouched
    stamps = receipts - 0.0004 - 0.0015 * np.random.default_rng(1).random(200)
    out = [s.stamp(float(d), float(r)) for d, r in zip(stamps, receipts, strict=True)]
    assert [o.stamp for o in out] == stamps.tolist()  # exactly: no offset, no fit
    assert all(o.flags == () for o in out)
    assert s.epoch == 7
    assert s.counters == {}
    state = s.state()
    assert state["domain"] == "shared"
    assert state["epoch"] == 7


def test_a_shared_stamp_ahead_of_its_receipt_is_counted_and_flagged_not_moved():
    s = Stamper("shared", max_age_s=0.5)
    within = s.stamp(100.0 + 0.5 * SHARED_AHEAD_TOLERANCE_S, 100.0)
    ahead = s.stamp(100.01 + 3e-3, 100.01)
    assert within.flags == ()
    assert ahead.stamp == 100.013
    assert ahead.flags == ("stamp_ahead",)
    assert s.counters["stamp_ahead"] == 1
    assert "ahead of its receipt" in s.last["stamp_ahead"]


def test_a_shared_stamp_older_than_max_stamp_age_is_counted_and_flagged():
    s = Stamper("shared", max_age_s=0.2)
    fresh = s.stamp(100.0, 100.19)
    old = s.stamp(100.01, 100.25)
    assert fresh.flags == ()
    assert old.stamp == 100.01
    assert old.flags == ("stamp_old",)
    assert s.counters["stamp_old"] == 1
    assert "timing.max_stamp_age_s" in s.last["stamp_old"]


def test_a_shared_stamp_going_back_starts_a_new_epoch():
    s = Stamper("shared", epoch=3)
    s.stamp(50.0, 50.001)
    s.stamp(50.01, 50.011)
    same = s.stamp(50.01, 50.012)  # a repeated stamp is not a restart
    back = s.stamp(10.0, 50.02)  # the publisher restarted with another time base
    assert same.flags == ()
    assert "stamp_back" in back.flags
    assert back.stamp == 10.0
    assert s.epoch == 4


def test_a_sample_without_device_time_is_stamped_on_receipt_and_counted():
    s = Stamper("shared")
    out = s.stamp(None, 42.0)
    assert out.stamp == 42.0
    assert out.flags == ("no_device_time",)
    assert s.counters["no_device_time"] == 1


# ---- device: mapped onto the host clock -------------------------------------------------------


def test_device_stamps_are_mapped_and_a_clock_step_starts_a_new_epoch():
    s = Stamper("device", epoch=0)
    rng = np.random.default_rng(2)
    device = 5000.0 + np.arange(1500) * 0.002  # its own clock, 500 Hz for 3 s
    receipt = 1.7e9 + (device - 5000.0) + 0.001 + 0.003 * rng.random(device.size)
    out = [s.stamp(float(d), float(r)) for d, r in zip(device, receipt, strict=True)]
    assert "clock_relearning" in out[0].flags  # no line yet: offset from one block
    assert out[-1].flags == ()
    t = np.array([o.stamp for o in out])
    # on the host clock, with the device's regularity: the floor (1 ms) stays in the offset
    err = t[-500:] - (1.7e9 + device[-500:] - 5000.0)
    assert np.all(np.abs(err - 0.001) < 0.3e-3), (err.min(), err.max())
    state = s.state()
    assert state["domain"] == "device"
    assert {"offset_s", "drift_ppm", "residual_s"} <= state.keys()
    # the controller restarts: its clock starts again at 0
    stepped = [s.stamp(0.002 * k, 1.7e9 + 3.1 + 0.002 * k) for k in range(5)]
    assert s.epoch == 1
    assert any("clock_step" in o.flags for o in stepped)
    assert s.counters["clock_step"] == 1


def test_a_mapped_stamp_comes_with_its_lines_drift():
    """A consumer carries a mapped stamp onto a later line from (stamp, device stamp, the
    line's drift): within a block (the line does not move) the next stamp is exactly where
    the previous one's line puts it (after the first block, whose least lag so far moves
    the line at every sample). Stamps not on a mapping's line say so by having none."""
    s = Stamper("device")
    rng = np.random.default_rng(4)
    device = 5000.0 + np.arange(3000) * 0.002  # 6 s, so that the drift is fitted (not held)
    receipt = 1.7e9 + (device - 5000.0) * (1 + 30e-6) + 0.001 + 0.003 * rng.random(device.size)
    out = [s.stamp(float(d), float(r)) for d, r in zip(device, receipt, strict=True)]
    assert not s.mapper.learning
    block = np.floor(device / s.mapper.block_s)
    carried = 0
    for k in range(250, device.size):
        prev = out[k - 1]
        if block[k] != block[k - 1] or prev.drift is None or out[k].drift is None:
            continue
        line = Anchor(prev.stamp, float(device[k - 1]), prev.drift)
        assert float(line.at(np.array([device[k]]))[0]) == pytest.approx(out[k].stamp, abs=1e-6)
        carried += 1
    assert carried > 2500
    assert out[-1].drift == pytest.approx(30e-6, abs=5e-6)  # host per device second
    assert Stamper("shared").stamp(1.7e9, 1.7e9 + 1e-3).drift is None
    assert Stamper("receipt").stamp(5.0, 1.7e9).drift is None


# ---- receipt: the host's receipt time, device time only kept aside ----------------------------


def test_receipt_stamps_ignore_the_device_time():
    s = Stamper("receipt")
    a = s.stamp(123.0, 1000.0)
    b = s.stamp(124.0, 1000.01)
    assert (a.stamp, b.stamp) == (1000.0, 1000.01)
    together = s.stamp_received_together(3, 1000.04)
    assert [round(x.stamp, 6) for x in together] == [1000.02, 1000.03, 1000.04]


def test_restart_bumps_the_epoch_and_an_unknown_domain_is_refused():
    s = Stamper("device", epoch=10)
    s.restart()
    s.restart()
    assert s.epoch == 12
    with pytest.raises(ValueError, match="clock domain"):
        Stamper("ptp")


# ---- config ---------------------------------------------------------------------------------


def test_protocol_defaults_and_an_impossible_domain_is_a_config_error(tmp_path):
    config = load_config(write_config(tmp_path, GOOD))
    assert (config.robot.clock, config.tracker.clock) == ("receipt", "device")
    ros = load_config(
        write_config(
            tmp_path,
            GOOD + 'protocol = "ros2"\n[tracker]\nprotocol = "ros2"\n',
            "r.toml",
        )
    )
    assert (ros.robot.clock, ros.tracker.clock) == ("shared", "shared")
    forced = load_config(
        write_config(
            tmp_path, GOOD + 'protocol = "rtde"\nclock = "shared"\n[tracker]\nclock = "receipt"\n'
        )
    )
    assert (forced.robot.clock, forced.tracker.clock) == ("shared", "receipt")
    for domain in ("shared", "device"):
        bad = write_config(tmp_path, GOOD + f'clock = "{domain}"\n', "bad.toml")
        with pytest.raises(ConfigError) as info:
            load_config(bad)
        assert info.value.key == "robot.clock"
        result = keo("simulate", "--config", str(bad), "--scenario", "paper-step", "--out", "x")
        assert result.returncode == 2
        assert "robot.clock" in result.stderr
        assert "motoros" in result.stderr


# ---- the line-protocol tracker adapter under each domain, over real TCP -----------------------


async def _tracker_samples(demo_config, domain: str, lines: list[bytes]) -> list[TrackerSample]:
    tracker = msgspec.structs.replace(
        demo_config.tracker, clock=domain, port=free_port(), host="127.0.0.1"
    )
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    bus = msgspec.structs.replace(demo_config.bus, listen=[endpoint], connect=[])
    config = msgspec.structs.replace(demo_config, tracker=tracker, bus=bus)
    done = asyncio.Event()

    async def device(_r: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await asyncio.sleep(0.5)
        for line in [format_hello("m"), *lines]:
            writer.write(line)
            await writer.drain()
            await asyncio.sleep(0.01)
        done.set()
        await asyncio.sleep(0.5)
        writer.close()

    server = await asyncio.start_server(device, "127.0.0.1", tracker.port)
    service_side = open_session("peer", listen=[endpoint])
    samples: list[TrackerSample] = []
    sub = service_side.declare_subscriber(
        topic(config.cell, "tracker"), lambda s: samples.append(decode(s.payload.to_bytes()))
    )
    try:
        async with TrackerAdapter(config, 6) as adapter:
            await asyncio.wait_for(done.wait(), timeout=15)
            deadline = time.time() + 5
            while len(samples) < len(lines) and time.time() < deadline:
                await asyncio.sleep(0.05)
            status = adapter.status()
    finally:
        sub.undeclare()
        service_side.close()
        server.close()
    assert status["clock"]["domain"] == domain
    return samples


def _line(seq: int, t: float) -> bytes:
    return format_pose(seq, t, [1.0, 2.0, 3.0], [1.0, 0.0, 0.0, 0.0])


async def test_line_tracker_under_each_domain(demo_config):
    now = time.time()
    shared_stamps = [now + 0.6 + 0.01 * k for k in range(5)]
    shared = await _tracker_samples(
        demo_config, "shared", [_line(k, t) for k, t in enumerate(shared_stamps)]
    )
    assert [s.stamp for s in shared] == shared_stamps  # used as they are
    assert {s.clock for s in shared} == {"shared"}
    assert len({s.clock_epoch for s in shared}) == 1
    # stamps from a clock 10 s behind: old, flagged, kept
    stale = await _tracker_samples(
        demo_config, "shared", [_line(k, time.time() - 10 + 0.01 * k) for k in range(3)]
    )
    assert all("stamp_old" in s.flags for s in stale)
    receipt = await _tracker_samples(demo_config, "receipt", [_line(k, 5.0 + k) for k in range(3)])
    assert [s.device_stamp for s in receipt] == [5.0, 6.0, 7.0]
    assert all(abs(s.stamp - s.host_ns * 1e-9) < 1e-6 for s in receipt)
    device = await _tracker_samples(
        demo_config, "device", [_line(k, 5.0 + 0.01 * k) for k in range(3)]
    )
    assert all(s.clock == "device" for s in device)
    assert all(abs(s.stamp - s.host_ns * 1e-9) < 0.1 for s in device)  # mapped onto the host clock


# ---- the service: which domain each stream declares ------------------------------------------


async def test_the_service_records_declared_domains_and_warns_on_a_mismatch(demo_config):
    from keo_service.bench.demo import loopback_config
    from keo_service.live.bus import session_for_client
    from keo_service.live.messages import JointSample, encode
    from keo_service.live.service import KeoService

    config = loopback_config(demo_config)  # robot.clock "receipt" (motoros), tracker "device"
    async with KeoService(config) as service:
        client = session_for_client(config)
        try:
            await asyncio.sleep(0.3)
            enc = JointSample(
                stamp=1.0, host_ns=1, seq=1, joints=[0.0] * 6, clock="device", clock_epoch=5
            )
            trk = TrackerSample(
                stamp=1.0,
                host_ns=1,
                seq=1,
                position=[1.0, 0.0, 0.0],
                quaternion=[1.0, 0, 0, 0],
                clock="device",
                flags=["stamp_old"],
            )
            client.put(topic(config.cell, "encoder"), encode(enc))
            client.put(topic(config.cell, "tracker"), encode(trk))
            client.put(topic(config.cell, "tracker"), b"not msgpack")
            deadline = time.time() + 5
            while service.received < 2 and time.time() < deadline:
                await asyncio.sleep(0.05)
            await asyncio.sleep(0.2)  # the bad payload came last
            status = service.status()
            estimator_messages = list(service.estimator.messages)
        finally:
            client.close()
    # the service's own findings are in its status, not in the estimator's reject log
    assert any("undecodable payload" in m for m in status.messages)
    assert not any("undecodable" in m or "clock domain" in m for m in estimator_messages)
    assert status.clock_domains == {"encoder": "device", "tracker": "device"}
    assert status.counters["tracker_stamp_old"] == 1
    mismatch = [m for m in status.messages if "clock domain" in m]
    assert len(mismatch) == 1  # the encoder's: "device" where the config says "receipt"
    assert "robot.clock is 'receipt'" in mismatch[0]
    assert "timing.delay_s" in mismatch[0]


def test_calibrate_delay_writes_the_domains_it_ran_under(demo_cell, tmp_path):
    import json

    from keo_service.sim.simulate import make_scenario, simulate, write_run
    from tests.conftest import DEMO

    scenario = make_scenario("paper-vertical", {"duration_s": "10"})
    write_run(simulate(demo_cell, scenario, seed=5), tmp_path)
    files = ["--encoder", str(tmp_path / "encoder.csv"), "--tracker", str(tmp_path / "tracker.csv")]
    res = keo("calibrate-delay", "--config", str(DEMO), *files, "--json")
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout)["clocks"] == {"robot.clock": "receipt", "tracker.clock": "device"}
    text = keo("calibrate-delay", "--config", str(DEMO), *files)
    assert "clock domains: robot.clock = receipt, tracker.clock = device" in text.stdout
