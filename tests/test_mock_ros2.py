"""keo's ROS 2 mocks (`keo mock robot|tracker` with the ros2 protocol) as a ROS 2 node sees
them: decoded by pyzeros (PyPI, its own key expressions, type hashes and CDR decoder), their
liveliness tokens and attachments read against rmw_zenoh's design document, stamped with the
wall clock (ROS time on one host), looping. The end-to-end run from one `keo init` config
(mocks, adapters, `keo run`, estimates) is in tests/test_newuser.py."""

from __future__ import annotations

import asyncio
import itertools
import json
import struct
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import msgspec
import numpy as np
import pytest
import pyzeros  # noqa: F401  (a test dependency: fail loudly when it is missing)
import zenoh

from keo_service.adapters.mock import MockSettings
from keo_service.bench.procs import free_port, process_group
from keo_service.io.config import load_config
from tests.conftest import keo, wait_for_status

REPO = Path(__file__).resolve().parent.parent
# UR10 joints as universal_robot's URDF names them (written here, not read from keo)
UR10_JOINTS = [
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
]
# the RIHS01 hashes of the Jazzy definitions (ros2/common_interfaces), as rmw_zenoh keys them
JOINT_STATE_HASH = "RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e"
POSE_STAMPED_HASH = "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8"


def _client(endpoint: str) -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(conf)


@pytest.mark.e2e
def test_ros2_mocks_from_an_init_config_are_read_by_pyzeros_on_the_wall_clock(tmp_path):
    """`keo init --robot ur10 --robot-protocol ros2 --tracker-protocol ros2`, then `keo run`
    and both mocks with no other flag, started 1.5 s apart: a pyzeros node receives
    JointState and PoseStamped on the default topics, stamped with the wall clock; the
    liveliness tokens name the drivers' nodes and publishers as rmw_zenoh writes them."""
    port = free_port()
    cfg = tmp_path / "cell" / "cell.toml"
    result = keo(
        *("init", "--robot", "ur10", "--robot-protocol", "ros2", "--tracker-protocol", "ros2"),
        *("--out", str(cfg), "--listen", f"tcp/127.0.0.1:{port}", "--cell", "roscell"),
    )
    assert result.returncode == 0, result.stderr
    endpoint = f"tcp/127.0.0.1:{port}"
    c = ["--config", str(cfg)]
    with process_group(tmp_path) as procs:
        procs.start("service", ["run", *c])
        procs.start("mock-robot", ["mock", "robot", *c])
        time.sleep(1.5)  # by hand, at different moments
        procs.start("mock-tracker", ["mock", "tracker", *c])
        wait_for_status(load_config(cfg), timeout=30.0)  # the bus is up (a loaded machine)
        deadline = time.monotonic() + 30.0
        tokens: list[str] = []
        attachments: list[bytes] = []
        session = _client(endpoint)
        try:
            sub = session.declare_subscriber(
                "0/joint_states/**",
                lambda s: attachments.append(s.attachment.to_bytes() if s.attachment else b""),
            )
            while time.monotonic() < deadline and len(tokens) < 4:
                tokens = [
                    str(r.ok.key_expr) for r in session.liveliness().get("@ros2_lv/0/**") if r.ok
                ]
                tokens = [t for t in tokens if "keo_mock_" in t]
                time.sleep(0.5)
            listened = subprocess.run(
                [sys.executable, "-m", "tests.pyzeros_listener", endpoint, "4"],
                capture_output=True,
                text=True,
                timeout=90,
                cwd=REPO,
                check=False,
            )
            sub.undeclare()
        finally:
            session.close()
        logs = {n: procs.log(n) for n in ("service", "mock-robot", "mock-tracker")}
    assert listened.returncode == 0, listened.stderr
    docs = [json.loads(line) for line in listened.stdout.splitlines()]
    joints = [d for d in docs if d.get("topic") == "/joint_states"]
    poses = [d for d in docs if d.get("topic") == "/lasertracker/pose"]
    # the scenario's ~40 Hz joint states and ~100 Hz poses over 4 s (a loaded machine: less)
    assert len(joints) > 60, (len(joints), logs)
    assert len(poses) > 150, (len(poses), logs)
    assert all(d["name"] == UR10_JOINTS for d in joints)
    assert all(len(d["position"]) == len(d["velocity"]) == 6 for d in joints)
    # ROS time is the host's wall clock: each stamp is when it was sent, within milliseconds
    for stream in (joints, poses):
        lag = np.array([d["received"] - d["stamp"] for d in stream])
        assert 0.0 <= np.median(lag) < 0.02, np.percentile(lag, [0, 50, 100])
        assert np.all(np.diff([d["stamp"] for d in stream]) > 0)
    # the velocities are those of the positions over the stamps (path scenario: smooth)
    q = np.array([d["position"] for d in joints])
    t = np.array([d["stamp"] for d in joints])
    dq = np.array([d["velocity"] for d in joints])
    mid = (dq[1:] + dq[:-1]) / 2
    finite_diff = np.diff(q, axis=0) / np.diff(t)[:, None]
    steady = np.diff(t) < 0.05  # neighbours (not across a pass boundary or a lost sample)
    assert np.abs(finite_diff - mid)[steady].max() < 0.05
    assert 0.05 < np.abs(dq).max() < 3.2  # moving, within a UR10's joint speeds (rad/s)
    # the poses: a unit quaternion in the tracker frame, metres from the tracker
    assert all(d["frame_id"] == "tracker" for d in poses)
    assert all(abs(np.linalg.norm(d["q_xyzw"]) - 1.0) < 1e-9 for d in poses)
    assert all(0.3 < np.linalg.norm(d["p"]) < 10.0 for d in poses)
    # rmw_zenoh's liveliness tokens: each node (NN) and its publisher (MP) with the topic,
    # the DDS type name, the type hash and the default QoS
    joined = "\n".join(tokens)
    assert "/NN/%/%/keo_mock_robot_driver" in joined, tokens
    assert "/NN/%/%/keo_mock_tracker_driver" in joined, tokens
    assert (
        f"/MP/%/%/keo_mock_robot_driver/%joint_states/sensor_msgs::msg::dds_::JointState_/"
        f"{JOINT_STATE_HASH}/"
    ) in joined, tokens
    assert (
        f"/MP/%/%/keo_mock_tracker_driver/%lasertracker%pose/"
        f"geometry_msgs::msg::dds_::PoseStamped_/{POSE_STAMPED_HASH}/"
    ) in joined, tokens
    # the attachment: int64 sequence, int64 source time (ns), 16, the 16-byte gid
    assert attachments
    assert all(len(a) == 33 for a in attachments)
    fields = [struct.unpack("<qqB16s", a) for a in attachments]
    # the sequence numbers each message: strictly rising; the listener may lose a few
    # under load (seen: 7 of 279 at load 8, a jump 272 -> 279), so gaps are allowed, not many
    sequence = [f[0] for f in fields]
    assert all(b > a for a, b in itertools.pairwise(sequence)), sequence
    assert sequence[-1] - sequence[0] + 1 - len(sequence) <= len(sequence) // 10, sequence
    assert all(f[2] == 16 for f in fields)
    assert len({f[3] for f in fields}) == 1  # one publisher, one gid
    assert abs(fields[-1][1] * 1e-9 - time.time()) < 60.0


async def test_the_ros2_mock_loops_with_the_stamps_running_on(demo_config):
    """A 1.2 s track looped with a 1.3 s period: JointStates keep coming through three
    passes, their stamps the wall clock (never back), each pass from the track's start."""
    from ros2_pyterfaces.cyclone.all_msgs import JointState

    from keo_service.adapters.mock_ros2 import MockRos2Driver
    from keo_service.live.bus import open_session

    port = free_port()
    bus = msgspec.structs.replace(demo_config.bus, listen=[f"tcp/127.0.0.1:{port}"], connect=[])
    config = msgspec.structs.replace(demo_config, bus=bus)
    track = SimpleNamespace(
        t=np.arange(0.0, 1.2, 0.02),
        q=np.tile(np.linspace(0, 1, 60)[:, None], (1, 6)),
    )
    got: list[tuple[float, float, float]] = []  # arrival, stamp, joint 0

    def on_sample(sample: zenoh.Sample) -> None:
        msg = JointState.deserialize(sample.payload.to_bytes())
        stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        got.append((time.time(), stamp, float(msg.position[0])))

    peer = open_session("peer", listen=bus.listen)
    sub = peer.declare_subscriber("0/joint_states/**", on_sample)
    t0 = time.time() + 0.3
    settings = MockSettings(host="", port=0, t0=t0, loop=True, period_s=1.3)
    mock = MockRos2Driver(config, "/joint_states", settings, joints=track, names=UR10_JOINTS)
    try:
        await mock.start()
        await asyncio.sleep(4.5)  # three passes and more
        await mock.close()
    finally:
        sub.undeclare()
        peer.close()
    assert got, "nothing arrived"
    arrival, stamp, q0 = (np.array(c) for c in zip(*got, strict=True))
    assert stamp[-1] - t0 > 3.0  # still publishing in the third pass
    assert len(got) > 2.5 * track.t.size
    assert np.all(np.diff(stamp) > 0)
    assert np.median(arrival - stamp) < 0.01
    # each stamp is t0 + pass * 1.3 s + a row's time, and carries that row's joints
    # (stamps are whole nanoseconds of an epoch time: a few hundred ns off the grid)
    in_pass = (stamp - t0 + 0.005) % 1.3 - 0.005
    assert np.abs(q0 - np.interp(in_pass, track.t, track.q[:, 0])).max() < 1e-5
    assert np.abs(in_pass / 0.02 - np.round(in_pass / 0.02)).max() < 1e-3


def test_position_only_tracker_mock_publishes_point_stamped(tmp_path):
    """A single-reflector tracker (--position-only): geometry_msgs/PointStamped on the pose
    topic, as keo's ROS 2 tracker adapter reads it."""
    port = free_port()
    cfg = tmp_path / "cell.toml"
    result = keo(
        *("init", "--robot", "ur10", "--robot-protocol", "ros2", "--tracker-protocol", "ros2"),
        *("--out", str(cfg), "--listen", f"tcp/127.0.0.1:{port}", "--cell", "pcell"),
    )
    assert result.returncode == 0, result.stderr
    config = load_config(cfg)
    from ros2_pyterfaces.cyclone.all_msgs import PointStamped

    from keo_service.live.bus import open_session

    got: list[tuple[str, object]] = []
    peer = open_session("peer", listen=config.bus.listen)
    sub = peer.declare_subscriber(
        "0/lasertracker/pose/**",
        lambda s: got.append((str(s.key_expr), PointStamped.deserialize(s.payload.to_bytes()))),
    )
    with process_group(tmp_path) as procs:
        procs.start("mock-tracker", ["mock", "tracker", "--config", str(cfg), "--position-only"])
        deadline = time.monotonic() + 30.0
        while time.monotonic() < deadline and len(got) < 20:
            time.sleep(0.2)
        log = procs.log("mock-tracker")
    sub.undeclare()
    peer.close()
    assert len(got) >= 20, log
    assert all("geometry_msgs::msg::dds_::PointStamped_" in key for key, _ in got)
    assert all(msg.header.frame_id == "tracker" for _, msg in got)  # type: ignore[attr-defined]
