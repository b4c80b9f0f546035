"""MotoROS gives no device time: joint samples are stamped on receipt, and frames that reach
the host in one read must still get distinct, increasing stamps (two equal stamps make the
estimator reject the second as a duplicate)."""

from __future__ import annotations

import asyncio
import itertools
import time

import msgspec
import pytest

from keo_service.adapters.devices import EncoderAdapter
from keo_service.adapters.simple_message import encode_joint_feedback, encode_robot_status
from keo_service.bench.procs import free_port
from keo_service.core.clock import ReceiptStamps
from keo_service.live.bus import open_session
from keo_service.live.messages import JointSample, decode, topic


def test_frames_read_together_are_spread_back_to_the_previous_stamp():
    stamps = ReceiptStamps()
    assert stamps.place(10.0, 1) == [10.0]
    assert stamps.place(10.1, 3) == pytest.approx([10.0 + 0.1 / 3, 10.0 + 0.2 / 3, 10.1])
    assert stamps.held_back == 0


def test_a_receipt_time_that_goes_back_is_placed_after_the_previous_stamp():
    stamps = ReceiptStamps()
    stamps.place(10.0, 1)
    out = stamps.place(9.5, 2)  # the host clock stepped back half a second
    assert out[0] > 10.0
    assert out[1] > out[0]
    assert stamps.held_back == 1
    assert stamps.place(10.2, 1) == [10.2]


def test_the_first_read_with_several_frames_gives_distinct_stamps():
    out = ReceiptStamps().place(5.0, 4)
    assert out[-1] == 5.0
    assert all(b > a for a, b in itertools.pairwise(out))


async def test_adapter_stamps_coalesced_frames_apart_over_tcp(demo_config):
    """A controller that writes three JOINT_FEEDBACK frames (and a status) in one TCP write,
    then single frames 40 ms apart: every published sample has its own increasing stamp."""
    robot = msgspec.structs.replace(demo_config.robot, port=free_port(), host="127.0.0.1")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    bus = msgspec.structs.replace(demo_config.bus, listen=[endpoint], connect=[])
    config = msgspec.structs.replace(demo_config, robot=robot, bus=bus)
    sent = asyncio.Event()

    async def controller(_r: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await asyncio.sleep(0.5)
        burst = b"".join(encode_joint_feedback([0.01 * k] * 6) for k in range(3))
        writer.write(burst + encode_robot_status())
        await writer.drain()
        for k in range(3, 8):
            await asyncio.sleep(0.04)
            writer.write(encode_joint_feedback([0.01 * k] * 6))
            await writer.drain()
        sent.set()
        await asyncio.sleep(1.0)
        writer.close()

    server = await asyncio.start_server(controller, "127.0.0.1", robot.port)
    service_side = open_session("peer", listen=[endpoint])
    samples: list[JointSample] = []
    sub = service_side.declare_subscriber(
        topic(config.cell, "encoder"), lambda s: samples.append(decode(s.payload.to_bytes()))
    )
    try:
        async with EncoderAdapter(config, 6) as adapter:
            await asyncio.wait_for(sent.wait(), timeout=15)
            deadline = time.time() + 5
            while len(samples) < 8 and time.time() < deadline:
                await asyncio.sleep(0.05)
            status = adapter.status()
    finally:
        sub.undeclare()
        service_side.close()
        server.close()
    assert [round(s.joints[0], 3) for s in samples] == [0.01 * k for k in range(8)]
    stamps = [s.stamp for s in samples]
    assert all(b > a for a, b in itertools.pairwise(stamps)), stamps
    assert status["counters"]["coalesced_frames"] >= 2
    assert status["stamps_held_back"] == 0
