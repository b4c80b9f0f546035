"""Wire codecs: MotoROS simple message and the tracker line protocol."""

from __future__ import annotations

import json
import math
import struct

import msgspec
import pytest

from keo_service.adapters.line_protocol import LineProtocolParser, format_hello, format_pose
from keo_service.adapters.simple_message import (
    JointFeedback,
    RobotStatusFrame,
    SimpleMessageDecoder,
    encode_joint_feedback,
    encode_robot_status,
)
from keo_service.live.messages import EstimateMessage, JointSample, TrackerSample, decode, encode

Q = [0.1, -0.2, 0.3, -0.4, 0.5, -0.6]


@pytest.mark.parametrize("order", ["little", "big"])
def test_joint_feedback_roundtrip_in_both_byte_orders(order):
    frame = encode_joint_feedback(Q, order, velocities=[0.01] * 6)
    assert len(frame) == 148  # length field 144 + itself
    prefix = "<" if order == "little" else ">"
    assert struct.unpack(f"{prefix}iiii", frame[:16]) == (144, 15, 1, 0)
    dec = SimpleMessageDecoder(order)
    (fb,) = dec.feed(frame)
    assert isinstance(fb, JointFeedback)
    assert fb.positions[:6] == pytest.approx(Q, abs=1e-7)  # float32 on the wire
    assert fb.velocities is not None
    assert fb.velocities[0] == pytest.approx(0.01)


def test_frames_split_anywhere_are_reassembled():
    data = encode_joint_feedback(Q) + encode_robot_status() + encode_joint_feedback(Q)
    dec = SimpleMessageDecoder()
    out = []
    for i in range(len(data)):
        out += dec.feed(data[i : i + 1])
    assert [type(f) for f in out] == [JointFeedback, RobotStatusFrame, JointFeedback]


def test_garbage_between_frames_is_skipped_and_counted():
    garbage = bytes(range(200, 256)) * 3
    data = (
        encode_joint_feedback(Q)
        + garbage
        + encode_joint_feedback(Q)
        + b"\x00" * 5
        + encode_robot_status()
    )
    dec = SimpleMessageDecoder()
    out = dec.feed(data)
    assert [type(f) for f in out] == [JointFeedback, JointFeedback, RobotStatusFrame]
    assert dec.counters["rejected"] > 0
    assert all(
        f.positions[:6] == pytest.approx(Q, abs=1e-7) for f in out if isinstance(f, JointFeedback)
    )


def test_wrong_byte_order_is_refused_with_a_hint():
    dec = SimpleMessageDecoder("big")
    assert dec.feed(encode_joint_feedback(Q, "little") * 3) == []
    assert dec.counters["bad_length"] > 0
    assert any("robot.byte_order" in m for m in dec.messages)


def test_unknown_type_is_skipped_and_truncated_frame_counted():
    unknown = struct.pack("<iiii", 56, 10, 1, 0) + b"\x00" * 44  # JOINT_POSITION: skipped
    dec = SimpleMessageDecoder()
    out = dec.feed(unknown + encode_joint_feedback(Q) + encode_joint_feedback(Q)[:50])
    assert len(out) == 1
    assert dec.counters["unknown_type"] == 1
    dec.reset()
    assert dec.counters["truncated"] == 1


def test_impossible_positions_are_refused():
    dec = SimpleMessageDecoder()
    bad = encode_joint_feedback([math.nan, 0, 0, 0, 0, 0])
    assert dec.feed(bad + encode_joint_feedback(Q))[0].positions[0] == pytest.approx(0.1)
    assert dec.counters["bad_value"] == 1


def test_line_protocol_converts_units_and_refuses_bad_poses():
    p = LineProtocolParser()
    assert p.parse(format_pose(1, 0.0, [1.0, 2.0, 3.0], [1, 0, 0, 0])) is None  # before hello
    assert p.counters["no_hello"] == 1
    p.parse(format_hello("mm"))
    pose = p.parse(format_pose(2, 0.1, [1000.0, 2000.0, -500.0], [1, 0, 0, 0]))
    assert pose is not None
    assert pose.position == pytest.approx((1.0, 2.0, -0.5))
    assert p.parse(format_pose(3, 0.2, [1.0, 2.0, 3.0], [0.9, 0, 0, 0])) is None
    assert p.counters["not_unit_quaternion"] == 1
    assert (
        p.parse(b'{"type": "pose", "seq": 4, "t": 0.3, "p": [NaN, 0, 0], "q": [1, 0, 0, 0]}')
        is None
    )
    assert p.parse(b'{"type": "pose", "seq": 5, "t": Infinity, "p": [0, 0, 0]}') is None
    assert p.counters["non_finite"] == 2
    assert p.parse(format_pose(1, 0.4, [1, 2, 3], [1, 0, 0, 0])) is None  # seq went back
    assert p.counters["out_of_order"] == 1
    gap = p.parse(format_pose(6, 0.5, None, None, status="beam_broken"))
    assert gap is not None
    assert gap.status == "beam_broken"
    assert gap.position is None
    reflector = p.parse(format_pose(7, 0.6, [1.0, 0.0, 0.0], None))
    assert reflector is not None
    assert reflector.quaternion is None
    assert p.parse(b"{not json") is None
    assert p.counters["malformed"] == 1
    assert p.parse(json.dumps({"type": "hello", "length_unit": "inch"}).encode()) is None
    assert p.counters["bad_hello"] == 1


def test_messages_roundtrip_and_refuse_other_versions():
    js = JointSample(stamp=1.5, host_ns=1_500_000_000, seq=3, joints=Q)
    assert decode(encode(js)) == js
    ts = TrackerSample(stamp=1.6, host_ns=1, seq=1, status="beam_broken")
    assert decode(encode(ts)) == ts
    est = EstimateMessage(
        stamp=1.0,
        host_ns=1,
        channels=["px", "py", "pz"],
        measured=None,
        estimate=[0.0, 0.0, 0.0],
        flags=["encoder_stale"],
        delay_s=0.0,
        seq=1,
    )
    assert decode(encode(est)) == est
    foreign = msgspec.msgpack.encode({"type": "keo.joint/3", "stamp": 1.0})  # a later version
    with pytest.raises(msgspec.DecodeError, match=r"keo\.joint/3"):
        decode(foreign)


def test_rejects_say_where_in_the_stream_they_were():
    """issue 50: a reject names its place, from the bytes as sent: the simple message decoder
    the byte offset in the connection, the line parser the line number and its first byte;
    both count afresh on a new connection."""
    good = encode_joint_feedback(Q)
    bad = encode_joint_feedback([math.nan, 0, 0, 0, 0, 0])
    garbage = b"\xfe" * 7
    dec = SimpleMessageDecoder()
    dec.feed(good + good[:30])  # split inside the second frame
    dec.feed(good[30:] + bad + garbage + good)
    assert dec.counters["bad_value"] == 1
    assert dec.messages[0].endswith(f"(byte {2 * len(good)} of the connection)"), dec.messages
    assert dec.messages[1].endswith(f"(byte {3 * len(good)} of the connection)"), dec.messages
    dec.feed(good[:20])
    dec.reset()  # the connection ends inside a frame: counted where that frame began
    assert dec.messages[-1].endswith(f"(byte {4 * len(good) + 7} of the connection)")
    dec.feed(bad)  # a new connection: offsets from 0
    assert dec.messages[-1].endswith("(byte 0 of the connection)")

    lines = [format_hello("mm"), format_pose(1, 0.1, [1.0, 2.0, 3.0], [1.0, 0, 0, 0])]
    lines += [b"not json\n", format_pose(2, 0.2, [1.0, 2.0, 3.0], [1.0, 0, 0, 0])]
    lines += [b'{"type": "pose", "seq": 3, "t": 0.3, "p": [1, 2], "q": [1, 0, 0, 0]}\n']
    parser = LineProtocolParser()
    for line in lines:
        parser.parse(line)
    offsets = [sum(len(x) for x in lines[:k]) for k in range(len(lines))]
    assert list(parser.messages) == [
        m for m in parser.messages if m.endswith(" of the connection)")
    ]
    assert parser.messages[0].startswith("not JSON")
    assert parser.messages[0].endswith(f"(line 3 at byte {offsets[2]} of the connection)")
    assert parser.messages[1].endswith(f"(line 5 at byte {offsets[4]} of the connection)")
    parser.reset()
    parser.parse(b"{}\n")
    assert parser.messages[-1].endswith("(line 1 at byte 0 of the connection)")
