"""KUKA RSI and ABB EGM: the codecs against datagrams of other implementations, the adapters
against the mock controllers over real UDP (reply times, stamps, corrections out)."""

from __future__ import annotations

import asyncio
import importlib.util
import json
import math
import re
import socket
import time
import xml.etree.ElementTree as ET
from pathlib import Path
from types import SimpleNamespace

import msgspec
import numpy as np
import pinocchio as pin
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from keo_service.adapters import abb_egm, kuka_rsi
from keo_service.adapters.devices import TrackerAdapter
from keo_service.adapters.egm import egm_pb2
from keo_service.adapters.mock import MockSettings
from keo_service.adapters.mock_udp import LiveTracker, MockEgmController, MockRsiController
from keo_service.adapters.select import encoder_adapter_for
from keo_service.adapters.udp_devices import CorrectionOutput, rkorr_of
from keo_service.bench.demo import loopback_config
from keo_service.bench.machine import machine_share, machine_ticks
from keo_service.bench.procs import process_group
from keo_service.core.kinematics import pose_error, quat_wxyz, tool_pose
from keo_service.io.config import CompensationConfig, config_to_toml, load_config
from keo_service.live.bus import open_session, session_for_client
from keo_service.live.client import Client
from keo_service.live.messages import CorrectionMessage, JointSample, decode, encode, topic
from keo_service.live.service import KeoService
from keo_service.sim.controller import tool_corrector
from keo_service.sim.simulate import make_scenario, simulate
from tests import egm_peer
from tests.conftest import wait_for_status, write_config
from tests.test_live import GAIN, check_converged, collect

FIXTURES = Path(__file__).parent / "fixtures" / "kuka_rsi"


def fixture(name: str) -> bytes:
    return (FIXTURES / name).read_bytes()


# ---- RSI codec against the open drivers' datagrams ---------------------------------------------


def test_rob_as_the_fzi_driver_parses_it():
    frame = kuka_rsi.RsiCodec().parse_rob(fixture("rob_kuka_rsi_driver.xml"))
    assert frame is not None
    assert frame.axes_deg == (0.1, 0.2, 0.3, 0.4, 0.5, 0.6)
    assert frame.tcp == (1.0, 2.0, 3.0, 0.5, 1.0, 1.5)
    assert frame.delay == 42
    assert frame.ipoc == 123645634563
    assert frame.external is None


def test_rob_as_the_kuka_experimental_simulator_sends_it():
    frame = kuka_rsi.RsiCodec().parse_rob(fixture("rob_kuka_rsi_simulator.xml"))
    assert frame is not None
    assert frame.axes_deg == (0.0, -90.0, 90.0, 0.0, 90.0, 0.0)
    assert frame.ipoc == 8
    assert frame.delay == 0


def test_rob_in_the_manual_layout_with_external_axes():
    frame = kuka_rsi.RsiCodec().parse_rob(fixture("rob_manual_layout.xml"))
    assert frame is not None
    assert frame.axes_deg == (-1.5, -92.25, 95.0, 0.125, 87.5, -3.0)
    assert frame.external == (1250.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    assert frame.tcp == (445.0, -12.5, 930.25, 179.9, -0.5, 178.0)
    assert frame.ipoc == 4208862


def test_sen_byte_for_byte_as_the_fzi_driver_writes_it():
    ours = kuka_rsi.format_sen(
        123456, rkorr=None, sen_type="TestSenType", akorr=[0.0, 1.0, 2.0, 3.0, 4.0, 5.0]
    )
    assert ours == fixture("sen_kuka_rsi_driver_ak.xml")


def test_sen_with_rkorr_byte_for_byte_and_read_by_a_plain_xml_reader():
    ours = kuka_rsi.format_sen(123645634563, (1.5, -0.25, 0.0, 0.1, 0.0, -0.05))
    assert ours == fixture("sen_rkorr.xml")
    # read as the simulators read answers: ElementTree, find the element, float its attributes
    root = ET.fromstring(ours)
    assert root.tag == "Sen"
    assert root.attrib["Type"] == "ImFree"
    assert int(root.find("IPOC").text) == 123645634563
    rkorr = root.find("RKorr").attrib
    assert [float(rkorr[k]) for k in "XYZABC"] == [1.5, -0.25, 0.0, 0.1, 0.0, -0.05]


@pytest.mark.parametrize(
    ("data", "reason"),
    [
        (b"<Rob><AIPos A1='1'/><IPOC>1</IPOC></Rob>", "missing_field"),
        (
            b"<Rob><AIPos A1='1' A2='2' A3='3' A4='4' A5='5' A6='x'/><IPOC>1</IPOC></Rob>",
            "not_a_number",
        ),
        (
            b"<Rob><AIPos A1='1' A2='2' A3='3' A4='4' A5='5' A6='nan'/><IPOC>1</IPOC></Rob>",
            "non_finite",
        ),
        (b"<Rob><AIPos A1='1' A2='2' A3='3' A4='4' A5='5' A6='6'/></Rob>", "missing_field"),
        (
            b"<Rob><AIPos A1='1' A2='2' A3='3' A4='4' A5='5' A6='6'/><IPOC>-4</IPOC></Rob>",
            "not_a_number",
        ),
        (b"<Rob><AIPos", "malformed"),
        (b"<Sen/>", "unexpected_root"),
        (b'<?xml version="1.0"?><!DOCTYPE r [<!ENTITY a "aaaa">]><Rob>&a;</Rob>', "dtd"),
        (b"<Rob>" + b" " * 9000 + b"</Rob>", "too_long"),
    ],
)
def test_bad_rob_datagrams_are_counted_by_reason(data, reason):
    codec = kuka_rsi.RsiCodec()
    assert codec.parse_rob(data) is None
    assert codec.counters[reason] == 1
    assert codec.counters["rejected"] == 1
    assert codec.messages


def test_rkorr_angles_follow_kukas_zyx_convention():
    # a rotation of 2 mrad about the tool's z axis is A (about Z) only; about x is C only
    assert rkorr_of(np.array([0.001, 0.0, -0.002, 0.0, 0.0, 0.002])) == pytest.approx(
        (1.0, 0.0, -2.0, math.degrees(0.002), 0.0, 0.0)
    )
    *_, a, b, c = rkorr_of(np.array([0.0, 0.0, 0.0, 0.002, 0.0, 0.0]))
    assert (a, b, c) == pytest.approx((0.0, 0.0, math.degrees(0.002)))
    # and the composition R = Rz(A) Ry(B) Rx(C), checked with explicit matrices
    rotvec = np.array([0.3, -0.2, 0.1])
    _, _, _, a, b, c = rkorr_of(np.array([0, 0, 0, *rotvec]))
    ca, sa = math.cos(math.radians(a)), math.sin(math.radians(a))
    cb, sb = math.cos(math.radians(b)), math.sin(math.radians(b))
    cc, sc = math.cos(math.radians(c)), math.sin(math.radians(c))
    Rz = np.array([[ca, -sa, 0], [sa, ca, 0], [0, 0, 1]])
    Ry = np.array([[cb, 0, sb], [0, 1, 0], [-sb, 0, cb]])
    Rx = np.array([[1, 0, 0], [0, cc, -sc], [0, sc, cc]])
    assert Rz @ Ry @ Rx == pytest.approx(Rotation.from_rotvec(rotvec).as_matrix(), abs=1e-12)


# ---- EGM codec against the protobuf classes used directly --------------------------------------


def test_the_generated_classes_write_the_protobuf_wire_format():
    """A header written by hand from the protobuf encoding rules: seqno (field 1, varint) 1,
    tm (field 2) 1000, mtype (field 3) DATA = 2."""
    header = egm_pb2.EgmHeader(seqno=1, tm=1000, mtype=egm_pb2.EgmHeader.MSGTYPE_DATA)
    assert header.SerializeToString() == bytes([0x08, 0x01, 0x10, 0xE8, 0x07, 0x18, 0x02])


def test_egm_robot_from_the_peer_decodes_to_radians_and_counts_gaps():
    codec = abb_egm.EgmCodec()
    joints = [10.0, -45.5, 90.0, 0.25, 30.0, -179.0]
    frame = codec.parse_robot(egm_peer.robot_datagram(7, 123456, joints, external=[250.0]))
    assert frame is not None
    assert frame.seqno == 7
    assert frame.tm_ms == 123456
    assert frame.joints_rad == pytest.approx([math.radians(v) for v in joints], abs=0)
    assert frame.external == (250.0,)
    assert (frame.motors_on, frame.egm_running, frame.rapid_running) == (True, True, True)
    assert codec.parse_robot(egm_peer.robot_datagram(10, 123468, joints)) is not None
    assert codec.counters["seq_gap"] == 1
    assert codec.counters["lost"] == 2
    assert codec.parse_robot(egm_peer.robot_datagram(10, 123468, joints)) is None
    assert codec.counters["duplicate"] == 1
    assert codec.parse_robot(egm_peer.robot_datagram(9, 123464, joints)) is None
    assert codec.counters["out_of_order"] == 1
    assert codec.parse_robot(egm_peer.robot_datagram(11, 123472, joints)) is not None
    # a controller that counts anew: refused twice, then taken as a restart
    assert codec.parse_robot(egm_peer.robot_datagram(1, 50, joints)) is None
    assert codec.parse_robot(egm_peer.robot_datagram(2, 54, joints)) is None
    assert codec.parse_robot(egm_peer.robot_datagram(3, 58, joints)) is not None
    assert codec.counters["restarts"] == 1
    assert codec.parse_robot(egm_peer.robot_datagram(4, 62, joints)) is not None
    # the uint32 sequence number wraps
    codec.reset()
    assert codec.parse_robot(egm_peer.robot_datagram(2**32 - 1, 1, joints)) is not None
    assert codec.parse_robot(egm_peer.robot_datagram(0, 5, joints)) is not None
    assert codec.counters["seq_gap"] == 1


def test_egm_sensor_read_by_the_peer():
    data = abb_egm.format_sensor(41, 123456, (1.5, -2.0, 0.25), (0.5, 0.5, -0.5, 0.5))
    seqno, tm, mtype, pos, quat = egm_peer.read_sensor(data)
    assert (seqno, tm) == (41, 123456)
    assert mtype == egm_pb2.EgmHeader.MSGTYPE_CORRECTION
    assert pos == [1.5, -2.0, 0.25]
    assert quat == [0.5, 0.5, -0.5, 0.5]
    # no correction: the identity pose
    assert egm_peer.read_sensor(abb_egm.format_sensor(1, 2))[3:] == ([0.0] * 3, [1.0, 0, 0, 0])


@pytest.mark.parametrize(
    ("data", "reason"),
    [
        (b"\xff\xff\xff", "malformed"),
        (egm_pb2.EgmRobot(feedBack=egm_pb2.EgmFeedBack()).SerializeToString(), "missing_field"),
        (
            egm_pb2.EgmRobot(header=egm_pb2.EgmHeader(seqno=1, tm=1)).SerializeToString(),
            "missing_field",
        ),
        (egm_peer.robot_datagram(1, 1, [1.0, math.nan]), "non_finite"),
        (b"\x00" * 9000, "too_long"),
    ],
)
def test_bad_egm_datagrams_are_counted_by_reason(data, reason):
    codec = abb_egm.EgmCodec()
    assert codec.parse_robot(data) is None
    assert codec.counters[reason] == 1
    assert codec.counters["rejected"] == 1


# ---- the correction as sent: clamps and rates ----------------------------------------------------


def _correction(t, r, valid=True, reason=""):
    return encode(
        CorrectionMessage(
            stamp=0.0,
            host_ns=0,
            seq=1,
            translation=list(t),
            rotation=list(r),
            feedback_translation=list(t),
            feedback_rotation=list(r),
            feedforward_translation=[0.0] * 3,
            feedforward_rotation=[0.0] * 3,
            valid=valid,
            reason=reason,
        )
    )


def test_correction_is_clamped_rate_limited_and_ramps_to_zero_when_invalid():
    limits = CompensationConfig(max_mm=5.0, max_mrad=5.0, max_rate_mm_s=50.0)
    out = CorrectionOutput(limits)
    assert out.next(0.0).tolist() == [0.0] * 6  # none received: zero
    out.on_payload(_correction([0.010, 0.0, 0.0], [0.0, 0.0, 0.002]))
    now, sent = 0.0, np.zeros(6)
    for _ in range(100):  # 100 cycles of 4 ms: 0.4 s, enough to reach 5 mm at 50 mm/s
        now += 0.004
        step = out.next(now) - sent
        sent = sent + step
        assert np.linalg.norm(step[:3]) <= 50e-3 * 0.004 + 1e-12
    assert sent[:3] == pytest.approx([0.005, 0.0, 0.0])  # clamped to max_mm
    assert sent[3:] == pytest.approx([0.0, 0.0, 0.002])
    assert out.counters["correction_clamped"] > 0
    assert out.counters["correction_rate_limited"] > 0
    out.on_payload(_correction([0.001, 0, 0], [0, 0, 0], valid=False, reason="held step"))
    for _ in range(100):
        now += 0.004
        sent = out.next(now)
    assert sent.tolist() == [0.0] * 6
    assert "held step" in out.state()["reason"]
    out.on_payload(b"\x01garbage")
    assert out.counters["correction_undecodable"] == 1


# ---- the adapters against the mock controllers over real UDP -----------------------------------


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def udp_config(demo_config, protocol: str, correction: str = "none"):
    config = loopback_config(demo_config)
    robot = msgspec.structs.replace(
        config.robot, protocol=protocol, port=free_udp_port(), correction=correction, clock="device"
    )
    return msgspec.structs.replace(config, robot=robot)


def slow_track(seconds: float) -> SimpleNamespace:
    t = np.linspace(0.0, seconds, int(seconds * 100) + 1)
    q = np.column_stack([0.3 + 0.2 * np.sin(0.7 * t + k) for k in range(6)])
    return SimpleNamespace(t=t, q=q)


MOCKS = {"kuka_rsi": MockRsiController, "abb_egm": MockEgmController}


@pytest.mark.parametrize("protocol", ["kuka_rsi", "abb_egm"])
async def test_adapter_answers_every_cycle_and_stamps_from_the_controller_clock(
    demo_config, protocol
):
    """3 s at 250 Hz with 3 ms send jitter and 2 % of the datagrams lost on the way: every
    datagram answered, the lost ones counted as missed cycles, joints in rad, the stamps the
    controller's milliseconds mapped onto the host clock. Mock, adapter and subscriber share
    this process: the reply deadline is judged in the end-to-end test, where the adapter has
    its own process as deployed."""
    seconds, offset_ms = 3.0, 7_000_000
    config = udp_config(demo_config, protocol)
    track = slow_track(seconds)
    t0 = time.time() + 0.8
    mock = MOCKS[protocol](
        track,
        MockSettings(
            host="127.0.0.1",
            port=config.robot.port,
            t0=t0,
            jitter_ms=3.0,
            clock_offset_s=offset_ms * 1e-3,
            max_late=1_000_000,  # judged elsewhere: here the machine's load must not stop it
            seed=3,
        ),
        external=[1250.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        drop_probability=0.02,
    )
    service_side = open_session("peer", listen=config.bus.listen)
    samples: list[JointSample] = []
    sub = service_side.declare_subscriber(
        topic(config.cell, "encoder"), lambda s: samples.append(decode(s.payload.to_bytes()))
    )
    try:
        async with encoder_adapter_for(config)(config, 6) as adapter:
            await asyncio.sleep(0.3)  # the server is up before the controller starts
            await mock.start()
            await mock.played(timeout=t0 + seconds + 10.0 - time.time())
            deadline = time.monotonic() + 5.0  # the last answers and samples (late under load)
            while time.monotonic() < deadline:
                status = adapter.status()
                if status["counters"].get("replies") == len(samples) == mock.counters["sent"]:
                    break
                await asyncio.sleep(0.1)
            await mock.close()
    finally:
        sub.undeclare()
        service_side.close()
    sent = mock.counters["sent"]
    print(
        json.dumps(
            {
                "protocol": protocol,
                "sent": sent,
                "rtt_p99_ms": mock.rtt_percentile(99) * 1e3,
                "rtt_max_ms": max(mock.rtt_s) * 1e3,
                "late": mock.counters["late"],
                "adapter_reply_us": status["reply_us"],
            }
        )
    )
    assert sent > 0.95 * 250 * seconds
    assert not mock.stopped.is_set()
    assert len(samples) == sent
    assert status["counters"]["replies"] == sent
    assert mock.counters["answered"] + mock.counters["unanswered"] == sent
    assert mock.counters["stray_replies"] + mock.counters["answered"] == sent
    assert status["counters"]["missed_cycles"] == mock.counters["dropped"] > 0
    assert status["decoder"].get("rejected", 0) == 0
    assert status["cycle_ms"] == pytest.approx(4.0)
    if protocol == "abb_egm":
        assert status["decoder"]["lost"] == mock.counters["dropped"]
        assert status["robot_state"]["motors_on"] is True
    else:
        assert status["external_axes"] == [1250.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    assert all(len(s.joints) == 6 for s in samples)  # the external axis is not a joint
    device_ms = np.array([s.device_stamp for s in samples]) * 1e3
    scenario_t = (device_ms - offset_ms) * 1e-3
    assert np.allclose(scenario_t / 0.004, np.round(scenario_t / 0.004), atol=1e-6)
    expected_q = np.column_stack([np.interp(scenario_t, track.t, c) for c in track.q.T])
    assert np.abs(np.array([s.joints for s in samples]) - expected_q).max() < 1e-9
    assert {s.clock for s in samples} == {"device"}
    # the mapped stamps: the scenario instants on the host clock plus a small transport floor
    lag = np.array([s.stamp for s in samples]) - (t0 + scenario_t)
    late_part = lag[scenario_t > 1.0]
    jitter = np.percentile(np.abs(late_part - np.median(late_part)), 99)
    receipt = (np.array([s.host_ns for s in samples]) * 1e-9 - (t0 + scenario_t))[scenario_t > 1.0]
    receipt_jitter = np.percentile(np.abs(receipt - np.median(receipt)), 99)
    print(
        json.dumps(
            {
                "stamp_lag_median_ms": np.median(late_part) * 1e3,
                "p99_ms": jitter * 1e3,
                "receipt_p99_ms": receipt_jitter * 1e3,
            }
        )
    )
    assert 0.0 <= np.median(late_part) < 0.005
    # the sends scatter by up to 3 ms after the controller's instants: the receipt times carry
    # that, the mapped stamps much less (0.1-0.3 ms on a quiet machine; a machine stalled
    # for most of a second spoils both, the mapped ones less)
    assert receipt_jitter > 0.001
    assert jitter < 0.5 * receipt_jitter


async def test_the_controller_stops_the_robot_after_n_late_answers():
    """A sensor that answers five datagrams, then falls silent: after max_late cycles without
    an answer the mock stops the robot, as RSI does."""

    class FiveAnswers(asyncio.DatagramProtocol):
        def __init__(self) -> None:
            self.seen = 0
            self.codec = kuka_rsi.RsiCodec()
            # the first parse and answer of a fresh process take milliseconds (cold code),
            # which the first answers' 4 ms cycle cannot spare: taken before the cycle starts
            warm = self.codec.parse_rob(kuka_rsi.format_rob(0, [0.0] * 6))
            assert warm is not None
            kuka_rsi.format_sen(warm.ipoc)

        def connection_made(self, transport):
            self.transport = transport

        def datagram_received(self, data, addr):
            self.seen += 1
            frame = self.codec.parse_rob(data)
            if frame is not None and self.seen <= 5:
                self.transport.sendto(kuka_rsi.format_sen(frame.ipoc), addr)

    loop = asyncio.get_running_loop()
    transport, sensor = await loop.create_datagram_endpoint(
        FiveAnswers, local_addr=("127.0.0.1", 0)
    )
    port = transport.get_extra_info("sockname")[1]
    mock = MockRsiController(
        slow_track(5.0), MockSettings(host="127.0.0.1", port=port, max_late=10)
    )
    await mock.start()
    try:
        await asyncio.wait_for(mock.stopped.wait(), timeout=5.0)
    finally:
        await mock.close()
        transport.close()
    assert mock.counters["answered"] == 5
    # judged at each next send: a send delayed by the machine may judge two at once
    assert 10 <= mock.counters["late"] <= mock.counters["sent"] - 5 <= mock.counters["late"] + 1
    assert "10 late answers" in mock.stop_reason
    assert sensor.seen == mock.counters["sent"]


@pytest.mark.parametrize("protocol", ["kuka_rsi", "abb_egm"])
async def test_the_live_correction_reaches_the_controller_clamped_and_zero_when_invalid(
    demo_config, protocol
):
    config = udp_config(demo_config, protocol, correction=protocol)
    received: list[np.ndarray] = []

    def corrector(q: np.ndarray, c: np.ndarray) -> np.ndarray:
        received.append(c.copy())
        return q

    # what is judged is the correction's path, not the stop on late answers (tested above):
    # the mock and the adapter share this process, and on a loaded CI machine a stall of
    # 0.4 s made 100 answers in a row late and the mock controller stopped the robot
    settings = MockSettings(
        host="127.0.0.1", port=config.robot.port, t0=time.time() + 0.3, max_late=2500
    )
    mock = MOCKS[protocol](slow_track(30.0), settings, corrector=corrector)
    service_side = open_session("peer", listen=config.bus.listen)
    pub = service_side.declare_publisher(topic(config.cell, "correction"))

    async def hold(t, r, expect, valid=True):
        """Publish for 0.6 s and on until the controller applies `expect` (5 s at most: a
        loaded machine answers late, and late answers are not applied)."""
        start = time.monotonic()
        while time.monotonic() - start < 5.0:
            pub.put(_correction(t, r, valid=valid, reason="" if valid else "stale input"))
            await asyncio.sleep(0.02)
            close = np.allclose(mock.correction, expect, atol=2e-8, rtol=0)
            if close and time.monotonic() - start > 0.6:
                break
        return mock.correction.copy()

    try:
        async with encoder_adapter_for(config)(config, 6) as adapter:
            await asyncio.sleep(0.3)
            await mock.start()
            await asyncio.sleep(0.3)
            small_c = [0.001, -0.002, 0.0005, 0.002, -0.001, 0.0015]
            small = await hold(small_c[:3], small_c[3:], small_c)
            large = await hold([0.020, 0.0, 0.0], [0.0, 0.0, -0.010], [0.005, 0, 0, 0, 0, -0.005])
            invalid = await hold([0.001, 0.0, 0.0], [0.0, 0.0, 0.001], [0.0] * 6, valid=False)
            status = adapter.status()
            await mock.close()
    finally:
        pub.undeclare()
        service_side.close()
    # in the protocol's units and back (1e-6 mm / 1e-6 degree on RSI's wire)
    assert small == pytest.approx([0.001, -0.002, 0.0005, 0.002, -0.001, 0.0015], abs=2e-8)
    assert large == pytest.approx([0.005, 0, 0, 0, 0, -0.005], abs=2e-8)  # [compensation] 5/5
    assert invalid == pytest.approx([0.0] * 6, abs=1e-12)
    assert received  # the corrector ran
    steps = np.linalg.norm(np.diff(np.array(mock.received)[:, :3], axis=0), axis=1)
    # 50 mm/s at 4 ms: 0.2 mm per answer; the controller sees more only across answers it
    # judged late and dropped (a loaded machine)
    dropped = mock.counters["stray_replies"] + mock.counters["unanswered"]
    assert steps.max() <= 0.0002 * (1 + dropped) + 1e-9
    assert np.sum(steps > 0.0002 + 1e-9) <= dropped
    counters = status["correction"]["counters"]
    assert counters["correction_clamped"] > 0
    assert counters["correction_invalid"] > 0


# ---- end to end: real processes --------------------------------------------------------------


@pytest.mark.e2e
@pytest.mark.slow  # an acceptance run (> 9 s): .ci/run runs the slow tests after the default run
@pytest.mark.parametrize("protocol", ["kuka_rsi", "abb_egm"])
def test_joints_over_rsi_and_egm_to_an_estimate_with_every_reply_in_the_cycle(
    demo_config, demo_cell, tmp_path, protocol
):
    """keo run, keo adapter encoder/tracker and keo mock robot/tracker as processes: the
    estimate converges to the simulator's truth; the adapter's own work per answer (its
    thread's CPU time) stays far inside the 4 ms cycle; and the controller sees its answers
    within the cycle (p99) while the service runs, judged on a play where the machine had its
    CPUs. Six Python processes share two cores here. On a virtual machine whose hypervisor
    takes a fifth to a third of them (18-39 % steal measured in some plays) no process holds a
    4 ms cycle, keo's or any other, and the guest counts the stolen time into the thread's CPU
    time too; so a play with more than 2 % stolen is replayed (three plays at most), and the
    tail figures are reported, not judged, when every play was stolen. (At 5 %, plays with
    3.3 and 4.2 % stolen were judged and their p99 was 1.03-1.05 ms; plays with 0-1.3 %
    stolen give 0.2-0.6 ms.)"""
    plays = []
    for attempt in ("first", "second", "third"):
        play = _udp_chain_once(demo_config, demo_cell, tmp_path / attempt, protocol)
        plays.append(play)
        # keo's typical work per answer, on any machine: an eighth of the cycle at most
        assert play["adapter_reply_us"]["cpu_p50"] < 500.0, play
        if _quiet(play) and _within_cycle(play["controller"]):
            break
    print(json.dumps({"plays": plays}))
    judged = [p for p in plays if _quiet(p)]
    if not judged:
        print(json.dumps({"cycle_not_judged": "every play had > 2 % of the CPUs stolen"}))
        return
    play = judged[-1]
    assert play["adapter_reply_us"]["cpu_p99"] < 1000.0, play  # a quarter of the cycle
    summary = play["controller"]
    assert summary["rtt_p99_ms"] < 4.0
    # counted: a loaded machine may hold both sides up for a few cycles (seen: 0-14 of 998)
    assert summary["counters"].get("late", 0) <= 0.02 * summary["counters"]["sent"]


def _quiet(play: dict) -> bool:
    return play["machine"]["steal_pct"] <= 2.0


def _within_cycle(summary: dict) -> bool:
    counters = summary["counters"]
    return summary["rtt_p99_ms"] < 4.0 and counters.get("late", 0) <= 0.02 * counters["sent"]


def _udp_chain_once(demo_config, demo_cell, tmp_path, protocol) -> dict:
    """One play of the chain; asserts everything but the cycle, returns the controller's
    summary, the adapter's answer times and the machine's busy and stolen share."""
    tmp_path.mkdir(parents=True)
    duration = 4.0
    config = udp_config(demo_config, protocol)
    observer = msgspec.structs.replace(config.observer, gain=[GAIN] * 6)
    config = msgspec.structs.replace(config, observer=observer)
    run = simulate(demo_cell, make_scenario("paper-step", {"duration_s": repr(duration)}), seed=2)
    truth = run.truth.mean(axis=0)
    cfg = tmp_path / "udp.toml"
    cfg.write_text(config_to_toml(config))
    args = ["--config", str(cfg)]
    with process_group(tmp_path) as procs:
        procs.start("service", ["run", *args])
        procs.start("adapter-encoder", ["adapter", "encoder", *args])
        procs.start("adapter-tracker", ["adapter", "tracker", *args])
        wait_for_status(config, timeout=30.0)
        t0 = time.time() + 5.0  # the two mocks start in ~1.5 s unloaded, 3-5 s at load 7
        play = ["--scenario", "paper-step", "--seed", "2", "--t0", repr(t0)]
        play += ["--duration", repr(duration)]
        procs.start("mock-robot", ["mock", "robot", *args, *play, "--jitter-ms", "0.5"])
        procs.start("mock-tracker", ["mock", "tracker", *args, *play])
        client = session_for_client(config, retry_for=20)
        ticks = machine_ticks()
        try:
            estimates = asyncio.run(collect(config, t0 + duration + 0.3))
            machine = machine_share(ticks, machine_ticks())
            replies = [
                r.ok
                for r in client.get(topic(config.cell, "adapter/encoder/status"), timeout=3.0)
                if r.ok
            ]
        finally:
            client.close()
        mock_log = procs.log("mock-robot")
        assert procs.stop("mock-robot") == 0, mock_log
        summary = json.loads(procs.log("mock-robot").strip().splitlines()[-1])
    adapter = json.loads(replies[0].payload.to_bytes())
    play = {"controller": summary, "adapter_reply_us": adapter["reply_us"], "machine": machine}
    print(json.dumps(play))
    check_converged(estimates, truth, t0)
    counters = summary["counters"]
    sent = counters["sent"]
    # a mock started late under load plays from then on, as a real controller would
    assert summary["cycles"] > 250
    assert sent == summary["cycles"]
    assert summary["stopped"] == ""
    assert adapter["counters"]["replies"] >= counters["answered"]
    assert adapter["protocol"] == protocol
    assert adapter["decoder"].get("rejected", 0) == 0
    return play


# ---- the correction loop --------------------------------------------------------------------


# the service publishes keo/<cell>/correction itself once the compensation work is merged
SERVICE_PUBLISHES = importlib.util.find_spec("keo_service.live.compensation") is not None


def _inverse(error: np.ndarray) -> tuple[list[float], list[float]]:
    """C = T_ts^-1 for the error [p; rotation vector]: what keo's compensation sends as its
    feedback part (here computed by the test, standing in for the service's publisher)."""
    R = Rotation.from_rotvec(error[3:6])
    inverse = R.inv()
    return (-inverse.apply(error[:3])).tolist(), inverse.as_rotvec().tolist()


@pytest.mark.e2e
@pytest.mark.parametrize("protocol", ["kuka_rsi", "abb_egm"])
async def test_the_correction_loop_takes_a_constant_2_mm_2_mrad_error_below_0_05(
    demo_config, demo_cell, protocol
):
    """The robot's tool is off by a constant 2 mm / 2 mrad (tool frame). keo's service
    estimates it from the joints (over RSI / EGM) and a tracker that sees the true tool; the
    inverse of each estimate goes out as keo/<cell>/correction (by the service itself when it
    has the compensation work's publisher, keo_service.live.compensation; otherwise by this
    test, standing in for it with the same feedback part); the adapter
    sends it in the protocol's terms; the controller mock moves the joints so that its nominal
    tool is the programmed pose times the correction, and the tracker sees the true tool move.
    The remaining error of the true tool against the programmed pose ends below 0.05 mm and
    0.05 mrad."""
    error = np.array([1.2e-3, -1.0e-3, 1.2e-3, 1.0e-3, 1.5e-3, -0.6e-3])
    error[:3] *= 2e-3 / np.linalg.norm(error[:3])
    error[3:] *= 2e-3 / np.linalg.norm(error[3:])
    E = pin.SE3(pin.exp3(error[3:]), error[:3])
    config = udp_config(demo_config, protocol, correction=protocol)
    observer = msgspec.structs.replace(config.observer, gain=[GAIN] * 6)
    # the tracker below sees the tool as it is: the delay between the streams is the
    # transport alone, known to be well under a millisecond (delay_s = 0 would say "unknown",
    # and this motion, 0.01 rad at 0.5 rad/s, cannot find a delay: every estimate would be
    # flagged delay_unsettled and every correction held)
    timing = msgspec.structs.replace(config.timing, delay_s=0.0005, delay_se_s=0.0005)
    config = msgspec.structs.replace(config, observer=observer, timing=timing)
    cell = demo_cell
    data = cell.robot.create_data()
    seconds = 14.0  # at most: the test ends once the error stayed below the limits for 1 s
    t = np.linspace(0.0, seconds + 1.0, 1501)
    home = np.array([0.0, 0.3, 0.1, 0.0, -0.6, 0.0])
    track = SimpleNamespace(
        t=t, q=np.column_stack([home[k] + 0.01 * np.sin(0.5 * t + k) for k in range(6)])
    )
    T_kb = cell.T_bk.inverse()
    mock = MOCKS[protocol](
        track,
        # the deadline is judged with the adapter in its own process
        MockSettings(host="127.0.0.1", port=config.robot.port, max_late=1_000_000),
        corrector=tool_corrector(cell),
    )

    def true_tool(scenario_t: float) -> pin.SE3:
        programmed = tool_pose(cell, data, mock.joints_at(scenario_t))
        c = mock.correction_at(scenario_t)
        return programmed * pin.SE3(pin.exp3(c[3:]), c[:3]) * E

    def seen(scenario_t: float) -> tuple[list[float], list[float]]:
        T_ks = T_kb * true_tool(scenario_t)
        return T_ks.translation.tolist(), quat_wxyz(T_ks.rotation).tolist()

    published = 0

    async def compensate(pub) -> None:
        nonlocal published
        async with Client.from_config(config, connect_timeout_s=20) as keo:
            async for est in keo.estimates():
                if est.measured is None:
                    continue
                translation, rotation = _inverse(np.array(est.estimate))
                pub.put(
                    encode(
                        CorrectionMessage(
                            stamp=est.stamp,
                            host_ns=time.time_ns(),
                            seq=est.seq,
                            translation=translation,
                            rotation=rotation,
                            feedback_translation=translation,
                            feedback_rotation=rotation,
                            feedforward_translation=[0.0] * 3,
                            feedforward_rotation=[0.0] * 3,
                            valid=True,
                        )
                    )
                )
                published += 1

    async with KeoService(config):
        publisher = session_for_client(config, retry_for=20)
        pub = publisher.declare_publisher(topic(config.cell, "correction"))
        t0 = time.time() + 1.0
        mock.t0 = t0
        tracker = LiveTracker(seen, "127.0.0.1", config.tracker.port, t0, rate_hz=100.0)
        await tracker.start()
        try:
            async with (
                encoder_adapter_for(config)(config, 6) as adapter,
                TrackerAdapter(config, 6),
            ):
                await mock.start()
                stand_in = None if SERVICE_PUBLISHES else asyncio.create_task(compensate(pub))
                await asyncio.sleep(t0 + 3.0 - time.time())
                below = 0
                while time.time() < t0 + seconds and below < 4:
                    await asyncio.sleep(0.25)
                    now = time.time() - t0 - 0.05
                    e = pose_error(tool_pose(cell, data, mock.joints_at(now)), true_tool(now))
                    small = max(np.linalg.norm(e[:3]), np.linalg.norm(e[3:])) < 0.05e-3
                    below = below + 1 if small else 0
                status = adapter.status()
                if stand_in is not None:
                    stand_in.cancel()
                    await asyncio.gather(stand_in, return_exceptions=True)
                end = (time.time() - t0) - 0.05
                await mock.close()
        finally:
            await tracker.close()
            pub.undeclare()
            publisher.close()
    programmed = tool_pose(cell, data, mock.joints_at(end))
    remaining = pose_error(programmed, true_tool(end))
    first = pose_error(tool_pose(cell, data, mock.joints_at(0.0)), true_tool(0.0))
    print(
        json.dumps(
            {
                "protocol": protocol,
                "published_by": "service" if SERVICE_PUBLISHES else "test",
                "published": published,
                "before_mm": np.linalg.norm(first[:3]) * 1e3,
                "remaining_mm": np.linalg.norm(remaining[:3]) * 1e3,
                "remaining_mrad": np.linalg.norm(remaining[3:]) * 1e3,
                "after_s": end,
                "correction": status["correction"],
                "controller": mock.summary(),
            }
        )
    )
    # ~100 a second; fewer when the machine is loaded
    assert status["correction"]["counters"]["corrections_received"] > 20
    assert np.linalg.norm(first[:3]) == pytest.approx(2e-3, rel=1e-6)  # before: uncorrected
    assert np.linalg.norm(first[3:]) == pytest.approx(2e-3, rel=1e-6)
    assert np.linalg.norm(remaining[:3]) < 0.05e-3
    assert np.linalg.norm(remaining[3:]) < 0.05e-3
    assert not mock.stopped.is_set()


# ---- fuzzing: nothing escapes, every reject counted ----------------------------------------------


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=2000))
def test_random_bytes_never_raise_in_either_codec(data):
    rsi, egm = kuka_rsi.RsiCodec(), abb_egm.EgmCodec()
    frame = rsi.parse_rob(data)
    assert frame is not None or rsi.counters["rejected"] == 1
    robot = egm.parse_robot(data)
    assert robot is not None or egm.counters["rejected"] == 1
    if robot is not None:
        assert all(math.isfinite(v) for v in robot.joints_rad)


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=6, max_size=6),
    st.integers(0, 2**64 - 1),
)
def test_any_rob_values_are_read_back_or_refused_as_non_finite(axes, ipoc):
    rsi = kuka_rsi.RsiCodec()
    frame = rsi.parse_rob(kuka_rsi.format_rob(ipoc, axes))
    if all(math.isfinite(v) for v in axes):
        assert frame is not None
        assert frame.axes_deg == tuple(axes)  # repr round-trips every double
        assert frame.ipoc == ipoc
    else:
        assert frame is None
        assert rsi.counters["non_finite"] == 1


@pytest.mark.parametrize("protocol", ["kuka_rsi", "abb_egm"])
async def test_a_restarted_controller_starts_a_new_clock_epoch(demo_config, protocol):
    """A controller that restarts (new socket, its counter from a new value, EGM's seqno from
    0 again) is followed: its samples carry the next clock epoch, none is refused for good."""
    config = udp_config(demo_config, protocol)
    service_side = open_session("peer", listen=config.bus.listen)
    samples: list[JointSample] = []
    sub = service_side.declare_subscriber(
        topic(config.cell, "encoder"), lambda s: samples.append(decode(s.payload.to_bytes()))
    )
    try:
        async with encoder_adapter_for(config)(config, 6) as adapter:
            await asyncio.sleep(0.3)
            for offset_ms in (9_000_000, 1_000):  # the second: counting from near zero
                mock = MOCKS[protocol](
                    slow_track(0.6),
                    MockSettings(
                        host="127.0.0.1",
                        port=config.robot.port,
                        t0=time.time() + 0.1,
                        clock_offset_s=offset_ms * 1e-3,
                        max_late=1_000_000,
                    ),
                )
                await mock.start()
                await asyncio.sleep(0.9)
                await mock.close()
            status = adapter.status()
    finally:
        sub.undeclare()
        service_side.close()
    epochs = [s.clock_epoch for s in samples]
    first = [s for s in samples if s.device_stamp > 1000.0]
    second = [s for s in samples if s.device_stamp < 1000.0]
    assert len(first) > 100
    assert len(second) > 100
    (epoch,) = {s.clock_epoch for s in first}  # the adapter's start (ms), one epoch
    # (a machine stalled at the new start can make the clock mapping relearn once more)
    assert min(s.clock_epoch for s in second) == epoch + 1
    assert epochs == sorted(epochs)
    assert status["counters"]["sessions"] == 1
    assert status["decoder"].get("rejected", 0) == 0


def test_the_documented_configs_load(tmp_path):
    """docs/robots.md's config examples are valid keo configs with the documented meaning."""
    text = (Path(__file__).parent.parent / "docs" / "robots.md").read_text()
    blocks = re.findall(r"```toml\n(.*?)```", text, re.S)
    assert len(blocks) == 2
    loaded = []
    for i, block in enumerate(blocks):
        body = re.sub(r'urdf = ".*?"', 'urdf = "@ROBOTS@/mh180.urdf"', block)
        loaded.append(load_config(write_config(tmp_path, body, f"doc{i}.toml")))
    rsi, egm = (c.robot for c in loaded)
    assert (rsi.protocol, rsi.port, rsi.clock, rsi.correction) == (
        "kuka_rsi",
        49152,
        "device",
        "kuka_rsi",
    )
    assert (egm.protocol, egm.port, egm.clock, egm.correction) == (
        "abb_egm",
        6510,
        "device",
        "abb_egm",
    )


def test_an_rsi_delay_too_large_for_an_integer_is_a_counted_reject():
    """Found by `keo selftest --fuzz`: `D="1e999"` parses as a float (inf) that no int holds;
    it was an OverflowError out of the decoder, now a reject like any other bad number."""
    codec = kuka_rsi.RsiCodec()
    datagram = (
        b'<Rob Type="KUKA"><AIPos A1="0" A2="-90" A3="90" A4="0" A5="0" A6="0"/>'
        b'<Delay D="1e999"/><IPOC>1000</IPOC></Rob>'
    )
    assert codec.parse_rob(datagram) is None
    assert codec.counters["not_a_number"] == 1
    assert "1e999" in codec.messages[-1]
