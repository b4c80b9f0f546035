"""KUKA RSI and ABB EGM: the codecs against datagrams of other implementations, the adapters
against the mock controllers over real UDP (reply times, stamps, corrections out)."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from adapters import abb_egm, kuka_rsi
from adapters.egm import egm_pb2
from adapters.udp_devices import CorrectionOutput, rkorr_of
from keo_service.io.config import CompensationConfig
from keo_service.live.messages import CorrectionMessage, encode
from tests import egm_peer

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
