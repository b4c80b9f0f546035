"""ROS 2 over rmw_zenoh, checked against an independent peer (tests/ros2_peer.py: rosbags +
zenoh, no keo code) and against rosbags' own CDR reader. No ROS 2 installation exists here."""

from __future__ import annotations

import math
import struct
import time

import msgspec
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from keo_service.bench.demo import loopback_config
from keo_service.bench.procs import process_group
from keo_service.io.cell import robot_from_config
from keo_service.io.config import config_to_toml
from keo_service.live.bus import open_session
from keo_service.live.messages import EstimateMessage
from keo_service.live.ros2_bridge import EstimateBridge
from keo_service.sim.simulate import make_scenario, simulate
from tests import ros2_peer
from tests.conftest import wait_for_status

POSE_COV = "geometry_msgs/msg/PoseWithCovarianceStamped"


def _bridge(demo_config, **ros2):
    config = msgspec.structs.replace(
        demo_config, ros2=msgspec.structs.replace(demo_config.ros2, enabled=True, **ros2)
    )
    session = open_session("peer")
    return session, EstimateBridge(session, config)


def test_the_ros_message_and_keos_estimate_agree(demo_config):
    session, bridge = _bridge(demo_config)
    try:
        est = [1e-3, -2e-3, 0.5e-3, 2e-4, -1e-4, 3e-4]
        msg = EstimateMessage(
            stamp=1234.5678,
            host_ns=1,
            channels=["px", "py", "pz", "rx", "ry", "rz"],
            measured=est,
            estimate=est,
            flags=[],
            delay_s=0.0,
            seq=1,
        )
        noise = np.array([20e-6] * 3 + [50e-6] * 3)
        gains, period = [2.0] * 6, 0.01
        from keo_service.core.observer import estimate_variance

        ros = bridge.pose_message(msg, estimate_variance(noise, gains, period))
        raw = bridge.node.store.serialize_cdr(ros, POSE_COV)
        back = ros2_peer.STORE.deserialize_cdr(bytes(raw), POSE_COV)  # rosbags reads it back
    finally:
        bridge.close()
        session.close()
    assert raw[:4] == b"\x00\x01\x00\x00"  # CDR little endian encapsulation
    pose = back.pose.pose
    assert [pose.position.x, pose.position.y, pose.position.z] == pytest.approx(est[:3], abs=1e-12)
    o = pose.orientation
    rotvec = Rotation.from_quat([o.x, o.y, o.z, o.w]).as_rotvec()
    assert np.max(np.abs(rotvec - est[3:])) < 1e-9
    a = 1 - math.exp(-2.0 * period)  # the observer's step for L = 2 at 100 Hz
    expected = (math.sqrt(a / (2 - a)) * noise) ** 2
    assert np.diag(back.pose.covariance.reshape(6, 6)) == pytest.approx(expected, rel=1e-12)
    assert back.header.stamp.sec == 1234
    assert back.header.stamp.nanosec == pytest.approx(567_800_000, abs=1)
    assert back.header.frame_id == f"{demo_config.cell}_tool"


def test_a_single_reflector_publishes_unknown_orientation(demo_config):
    session, bridge = _bridge(demo_config)
    try:
        msg = EstimateMessage(
            stamp=1.0,
            host_ns=1,
            channels=["px", "py", "pz"],
            measured=[1e-3, 0.0, 0.0],
            estimate=[1e-3, 0.0, 0.0],
            flags=[],
            delay_s=0.0,
            seq=1,
        )
        ros = bridge.pose_message(msg, np.array([1e-10] * 3))
    finally:
        bridge.close()
        session.close()
    cov = np.asarray(ros.pose.covariance).reshape(6, 6)
    assert list(np.diag(cov)[3:]) == [-1.0, -1.0, -1.0]
    assert ros.pose.pose.orientation.w == 1.0


@pytest.mark.e2e
def test_estimate_from_ros2_inputs_alone_reaches_a_ros2_subscriber(
    demo_config, demo_cell, tmp_path
):
    robot = msgspec.structs.replace(demo_config.robot, protocol="ros2", clock="shared")
    tracker = msgspec.structs.replace(demo_config.tracker, protocol="ros2", clock="shared")
    ros2 = msgspec.structs.replace(demo_config.ros2, enabled=True, publish_tf=True)
    config = loopback_config(
        msgspec.structs.replace(demo_config, robot=robot, tracker=tracker, ros2=ros2)
    )
    cfg = tmp_path / "c.toml"
    cfg.write_text(config_to_toml(config))
    endpoint = config.bus.listen[0]
    run = simulate(demo_cell, make_scenario("paper-step", {"duration_s": "8"}), seed=4)
    truth = run.truth.mean(axis=0)
    joint_names = list(robot_from_config(config).joint_names)
    received: list[tuple[bytes, bytes | None, str]] = []
    with process_group(tmp_path) as procs:
        cfg_args = ["--config", str(cfg)]
        procs.start("service", ["run", *cfg_args])
        wait_for_status(config)
        procs.start("adapter-encoder", ["adapter", "encoder", *cfg_args])
        procs.start("adapter-tracker", ["adapter", "tracker", *cfg_args])
        peer = ros2_peer.Peer(endpoint)
        listener = peer.session.declare_subscriber(
            ros2_peer.key(f"/keo/{config.cell}/kinematic_error", POSE_COV),
            lambda s: received.append(
                (
                    s.payload.to_bytes(),
                    None if s.attachment is None else s.attachment.to_bytes(),
                    str(s.key_expr),
                )
            ),
        )
        try:
            time.sleep(2.0)  # adapters up, declarations through
            t0 = time.time() + 0.5
            player = peer.play(run, joint_names, t0)
            player.join(timeout=30)
            time.sleep(1.0)
            tokens = [
                str(r.ok.key_expr)
                for r in peer.session.liveliness().get("@ros2_lv/0/**", timeout=2.0)
                if r.ok is not None
            ]
        finally:
            listener.undeclare()
            peer.close()
        codes = procs.close()
    assert all(code == 0 for code in codes.values()), codes
    assert len(received) > 100
    payload, att, key_expr = received[-1]
    assert key_expr.startswith(f"0/keo/{config.cell}/kinematic_error/")
    assert att is not None
    assert len(att) == 33
    seq, source_ns, length = struct.unpack("<qqB", att[:17])
    assert length == 16
    assert seq >= len(received)
    assert abs(source_ns * 1e-9 - time.time()) < 60
    last = ros2_peer.STORE.deserialize_cdr(payload, POSE_COV).pose.pose
    p = np.array([last.position.x, last.position.y, last.position.z])
    o = last.orientation
    r = Rotation.from_quat([o.x, o.y, o.z, o.w]).as_rotvec()
    assert np.linalg.norm(p - truth[:3]) < 20e-6, (p, truth[:3])
    assert np.linalg.norm(r - truth[3:]) < 50e-6, (r, truth[3:])
    node = f"keo_{config.cell}"
    assert any(t.endswith(f"/NN/%/%/{node}") for t in tokens), tokens
    assert any(f"/MP/%/%/{node}/%keo%{config.cell}%kinematic_error/" in t for t in tokens), tokens
    assert any(f"/MP/%/%/{node}/%tf/tf2_msgs::msg::dds_::TFMessage_/" in t for t in tokens)
    assert any("/MS/" in t and "%joint_states" in t for t in tokens), tokens


async def test_mcap_recording_reads_back_with_mcap_and_rosbags_and_estimates_alike(
    demo_config, demo_cell, tmp_path
):
    import asyncio

    from mcap.reader import make_reader
    from rosbags.rosbag2 import Reader

    from keo_service.io.mcap_files import McapWriter
    from keo_service.live.messages import JointSample, TrackerSample, encode, topic
    from keo_service.live.recorder import record
    from keo_service.offline.estimate import estimate_files
    from keo_service.sim.simulate import write_run

    run = simulate(demo_cell, make_scenario("paper-step", {"duration_s": "4"}), seed=5)
    names = list(demo_cell.robot.joint_names)
    session = open_session("peer")
    out = tmp_path / "rec"
    try:
        stop = asyncio.Event()
        writer = McapWriter(out, names, demo_config.cell)
        recording = asyncio.create_task(
            record(session, demo_config.cell, out, len(names), stop, mcap=writer)
        )
        await asyncio.sleep(0.3)
        events = sorted(
            [(float(t), 0, i) for i, t in enumerate(run.encoder.t)]
            + [(float(t), 1, i) for i, t in enumerate(run.tracker.t)]
        )
        for k, (t, kind, i) in enumerate(events):
            if kind == 0:
                msg = JointSample(stamp=t, host_ns=0, seq=k, joints=run.encoder.q[i].tolist())
                session.put(topic(demo_config.cell, "encoder"), encode(msg))
            else:
                pose = TrackerSample(
                    stamp=t,
                    host_ns=0,
                    seq=k,
                    position=run.tracker.p[i].tolist(),
                    quaternion=run.tracker.quat[i].tolist(),
                )
                session.put(topic(demo_config.cell, "tracker"), encode(pose))
            if k % 100 == 0:
                await asyncio.sleep(0.01)
        est = EstimateMessage(
            stamp=1.0,
            host_ns=0,
            channels=["px", "py", "pz", "rx", "ry", "rz"],
            measured=[0.0] * 6,
            estimate=[1e-3, 0, 0, 0, 0, 1e-4],
            flags=[],
            delay_s=0.0,
            seq=1,
        )
        session.put(topic(demo_config.cell, "estimate"), encode(est))
        await asyncio.sleep(0.5)
        stop.set()
        stats = await recording
    finally:
        session.close()
    assert stats.encoder_rows == run.encoder.t.size
    assert stats.tracker_rows == run.tracker.t.size
    mcap_file = out / "keo" / "keo.mcap"
    counts: dict[tuple[str, str], int] = {}
    with mcap_file.open("rb") as f:
        for schema, channel, _message in make_reader(f).iter_messages():
            assert schema.encoding == "ros2msg"
            assert channel.message_encoding == "cdr"
            counts[(channel.topic, schema.name)] = counts.get((channel.topic, schema.name), 0) + 1
    assert counts[("/joint_states", "sensor_msgs/msg/JointState")] == run.encoder.t.size
    assert counts[("/lasertracker/pose", "geometry_msgs/msg/PoseStamped")] == run.tracker.t.size
    assert counts[(f"/keo/{demo_config.cell}/kinematic_error", POSE_COV)] == 1
    with Reader(out / "keo") as bag:  # rosbags reads it as a rosbag2
        assert {c.msgtype for c in bag.connections} >= {
            "sensor_msgs/msg/JointState",
            "geometry_msgs/msg/PoseStamped",
        }
    # keo estimate on the MCAP recording equals keo estimate on the same samples as CSV
    write_run(run, tmp_path / "csv")
    from_csv = estimate_files(
        demo_config, tmp_path / "csv/encoder.csv", tmp_path / "csv/tracker.csv"
    )
    from_mcap = estimate_files(demo_config, out, out)
    assert from_csv.table.stamp.size == from_mcap.table.stamp.size > 0
    assert float(np.max(np.abs(from_csv.table.estimate - from_mcap.table.estimate))) < 1e-9
