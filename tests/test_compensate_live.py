"""Live corrections: the correction's frames and limits, the RTDE input recipe against its
documented bytes and against ur_rtde (an independent client), and the closed loop with the
mock UR: a controller that adds the correction in its input registers to its path, the real
arm the simulator knows, the tracker that sees that arm, and keo in between.
"""

from __future__ import annotations

import json
import math
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import msgspec
import numpy as np
import pinocchio as pin
import pytest

from keo_service.adapters import rtde
from keo_service.bench.demo import STARTUP_S, loopback_config
from keo_service.bench.procs import process_group
from keo_service.core.compensation import (
    CompensationLimits,
    CorrectionFilter,
    correction_to_send,
)
from keo_service.io.cell import cell_from_config
from keo_service.io.config import CompensationConfig, ModelConfig, config_to_toml, load_config
from keo_service.live.bus import open_session
from keo_service.live.messages import CorrectionMessage, decode, topic
from keo_service.sim.closed_loop import ClosedLoopCell
from keo_service.sim.simulate import angle_ripple, make_scenario
from tests.conftest import CONFIGS

# ---- the correction itself -------------------------------------------------------------------


def test_the_correction_undoes_the_error_transform_on_the_right_of_the_command():
    """T_goal * C * T_ts = T_goal: a controller commanded T_goal * C lands on T_goal (the real
    tool is the nominal one times T_ts)."""
    rng = np.random.default_rng(4)
    filt = CorrectionFilter(CompensationLimits(max_m=1.0, max_rad=1.0, max_rate_m_s=1e6))
    filt.step(0.0, [0.0] * 6, None)  # the first correction starts from zero (rate limit)
    for k in range(5):
        p, r = rng.normal(0, 2e-3, 3), rng.normal(0, 2e-3, 3)
        T_ts = pin.SE3(pin.exp3(r), p)
        c = filt.step(1.0 + k, [*p, *r], None)
        C = pin.SE3(pin.exp3(c.rotation), c.translation)
        goal = pin.SE3(pin.exp3(rng.normal(0, 1, 3)), rng.normal(0, 1, 3))
        landed = goal * C * T_ts
        assert np.linalg.norm(landed.translation - goal.translation) < 1e-12
        assert np.linalg.norm(pin.log3(goal.rotation.T @ landed.rotation)) < 1e-12
        assert c.valid
        assert np.allclose(c.feedforward[0], 0.0)


def test_size_and_rate_are_clamped_and_counted_and_invalid_is_zero():
    limits = CompensationConfig(max_mm=5.0, max_mrad=5.0, max_rate_mm_s=50.0).limits()
    filt = CorrectionFilter(limits)
    big = [0.02, 0.0, 0.0, 0.0, 0.0, 0.0]  # 20 mm error
    out = [filt.step(0.01 * k, big, None) for k in range(200)]
    sizes = [float(np.linalg.norm(c.translation)) for c in out]
    # ramps up at 50 mm/s from zero (nothing applied before), then holds at the 5 mm limit
    assert sizes[0] == 0.0
    assert sizes[1] == pytest.approx(0.5e-3, rel=1e-9)  # 50 mm/s for 10 ms
    assert sizes[4] == pytest.approx(2.0e-3, rel=1e-9)
    assert max(sizes) == pytest.approx(5e-3, rel=1e-12)
    assert out[-1].clamped
    assert np.allclose(out[-1].translation, [-5e-3, 0, 0])
    assert filt.counters["corrections_clamped_size"] == 200
    assert filt.counters["corrections_clamped_rate"] >= 9
    held = filt.step(2.01, big, None, invalid_reason="tracker_gap")
    assert not held.valid
    assert held.reason == "tracker_gap"
    assert np.all(held.translation == 0.0)
    assert filt.counters["corrections_invalid"] == 1
    # after an invalid step it ramps again from zero
    again = filt.step(2.02, big, None)
    assert np.linalg.norm(again.translation) == pytest.approx(0.5e-3, rel=1e-9)
    nan = filt.step(2.03, [math.nan] * 6, None)
    assert not nan.valid
    assert nan.reason == "non_finite_estimate"


def test_correction_to_send_is_zero_when_none_stale_or_invalid():
    limits = CompensationConfig(
        max_mm=1.0, max_mrad=1.0, max_rate_mm_s=50.0, max_age_s=0.1
    ).limits()
    now = 10_000_000_000

    def msg(age_s: float, valid: bool = True, p=(2e-3, 0.0, 0.0)) -> CorrectionMessage:
        return CorrectionMessage(
            stamp=1.0,
            host_ns=now - int(age_s * 1e9),
            seq=1,
            translation=list(p),
            rotation=[0.0, 0.0, 1e-3],
            feedback_translation=list(p),
            feedback_rotation=[0.0, 0.0, 1e-3],
            feedforward_translation=[0.0] * 3,
            feedforward_rotation=[0.0] * 3,
            valid=valid,
        )

    zero = ([0.0] * 3, [0.0] * 3)
    assert correction_to_send(None, limits, now) == zero
    assert correction_to_send(msg(0.2), limits, now) == zero
    assert correction_to_send(msg(0.01, valid=False), limits, now) == zero
    p, r = correction_to_send(msg(0.01), limits, now)
    assert p == pytest.approx([1e-3, 0.0, 0.0])  # clamped to max_mm = 1
    assert r == pytest.approx([0.0, 0.0, 1e-3])


# ---- the RTDE input recipe ------------------------------------------------------------------


def test_input_recipe_bytes_as_documented():
    """UR's RTDE guide: CONTROL_PACKAGE_SETUP_INPUTS ('I', 73) carries the variable names,
    comma-separated; the controller answers the recipe id and the types; a DATA_PACKAGE
    ('U', 85) to the controller is the recipe id and the values, big endian."""
    names = rtde.input_double_registers(24)
    assert names == [f"input_double_register_{k}" for k in range(24, 30)]
    text = ",".join(names).encode()
    assert rtde.setup_inputs(names) == struct.pack(">HB", 3 + len(text), 73) + text
    reply = rtde.RtdeDecoder().feed(rtde.inputs_reply(2, ["DOUBLE"] * 6))[0]
    recipe = rtde.parse_inputs_reply(reply, names)
    values = [1e-3, -2e-3, 3e-3, 1e-4, -2e-4, 3e-4]
    data = rtde.data_package(recipe, dict(zip(names, values, strict=True)))
    assert data == struct.pack(">HBB6d", 3 + 1 + 48, 85, 2, *values)
    taken = rtde.RtdeDecoder().feed(rtde.inputs_reply(3, ["DOUBLE", "IN_USE"]))[0]
    with pytest.raises(rtde.RtdeError, match="already writes input_double_register_25"):
        rtde.parse_inputs_reply(taken, names[:2])


def _listening(port: int) -> bool:
    try:
        socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
    except OSError:
        return False
    return True


def _port_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def test_ur_rtde_register_writes_decode_right_in_the_mock_controller(tmp_path):
    """ur_rtde's RTDEIOInterface (C++, Universal Robots' community client) sets up its input
    recipes and writes two double registers; the mock controller logs what it decoded."""
    import rtde_io  # ur-rtde, a test dependency

    if not _port_free(rtde.DEFAULT_PORT):
        pytest.skip("port 30004 is taken on this machine; ur_rtde cannot use another port")
    log_path = tmp_path / "mock.log"
    with log_path.open("w") as log:
        mock = subprocess.Popen(
            [
                *(sys.executable, "-m", "keo_service.cli", "mock", "robot"),
                *("--config", str(CONFIGS / "ur10_demo.toml"), "--scenario", "paper-step"),
                *("--duration", "30", "-v"),
            ],
            stdout=log,
            stderr=subprocess.STDOUT,
        )
        try:
            deadline = time.monotonic() + 30
            while _port_free(rtde.DEFAULT_PORT) and time.monotonic() < deadline:
                time.sleep(0.1)
            time.sleep(0.5)
            io = rtde_io.RTDEIOInterface("127.0.0.1")
            assert io.setInputDoubleRegister(18, 1.25)
            assert io.setInputDoubleRegister(22, -3.5e-4)
            time.sleep(0.5)
            io.disconnect()
        finally:
            mock.terminate()
            mock.wait(timeout=10)
    text = log_path.read_text()
    assert '"input_double_register_18": 1.25' in text, text[-2000:]
    assert '"input_double_register_22": -0.00035' in text, text[-2000:]
    assert "unknown_input_recipe" not in text


# ---- the closed loop --------------------------------------------------------------------------

PATH = {  # 0.1 m/s strokes of 0.25 m down and down again, 0.5 s dwells (about 7 s)
    "stroke_m": "0.25",
    "dwell_s": "0.5",
    "speed_m_s": "0.1",
    "geometric_errors": "false",
}
TOOL_ERROR = (1.2e-3, -1.0e-3, 1.2e-3, 1.2e-3, 1.0e-3, -1.2e-3)  # 1.97 mm / 1.97 mrad


def closed_loop_config(model: ModelConfig | None = None):
    base = load_config(CONFIGS / "ur10_demo.toml")
    config = loopback_config(base)
    robot = msgspec.structs.replace(config.robot, correction="rtde_registers", frequency_hz=125.0)
    config = msgspec.structs.replace(config, robot=robot)
    if model is not None:
        config = msgspec.structs.replace(config, model=model)
    return config


def run_closed_loop(
    tmp_path: Path,
    config,
    sets: dict[str, str],
    seed: int,
    seconds: float,
    mock_args: list[str],
):
    """The loop as deployed: `keo run`, both adapters and `keo mock robot
    --follow-corrections` (the mock UR and the tracker that sees its arm), each its own
    process over real TCP and Zenoh; the corrections on the bus gathered here (wall time of
    arrival, message). The mock writes the true errors it logged when it stops."""
    cfg = tmp_path / "cell.toml"
    cfg.write_text(config_to_toml(config), encoding="utf-8")
    summary = tmp_path / "errors.json"
    t0 = time.time() + 2 * STARTUP_S  # the adapters connect (and map clocks) before t0
    play = ["--scenario", "paper-vertical", "--seed", str(seed), "--t0", repr(t0)]
    for key, value in sets.items():
        play += ["--set", f"{key}={value}"]
    corrections: list[tuple[float, CorrectionMessage]] = []
    listener = open_session("peer", connect=list(config.bus.listen))
    sub = listener.declare_subscriber(
        topic(config.cell, "correction"),
        lambda s: corrections.append((time.time(), decode(s.payload.to_bytes()))),
    )
    c = ["--config", str(cfg)]
    try:
        with process_group(tmp_path) as procs:
            procs.start("service", ["run", *c])
            mock = ["mock", "robot", *c, *play, "--max-hz", "125", "--follow-corrections"]
            procs.start("mock", [*mock, "--summary", str(summary), *mock_args])
            # the adapters once the mock listens (a reconnect backs off up to seconds)
            deadline = time.monotonic() + 2 * STARTUP_S
            while not _listening(config.robot.port) and time.monotonic() < deadline:
                time.sleep(0.1)
            procs.start("adapter-encoder", ["adapter", "encoder", *c])
            procs.start("adapter-tracker", ["adapter", "tracker", *c])
            time.sleep(max(0.0, t0 + seconds - time.time()))
            codes = procs.close()
    finally:
        sub.undeclare()
        listener.close()
    assert all(code == 0 for code in codes.values()), codes
    doc = json.loads(summary.read_text())
    return SimpleNamespace(t0=t0, corrections=corrections, **doc)


@pytest.mark.e2e
@pytest.mark.slow  # 17 s of a live correction loop; the default run stays under 10 min
def test_a_constant_tool_error_is_compensated_and_stops_when_the_beam_breaks(tmp_path):
    config = closed_loop_config()
    brk = 8.0
    out = run_closed_loop(
        tmp_path,
        config,
        {**PATH, "duration_s": "10"},
        seed=5,
        seconds=9.0,
        mock_args=["--tool-error", ",".join(map(repr, TOOL_ERROR)), "--beam-break", f"{brk}:0.6"],
    )
    series = out.series
    t = np.array(series["t"])
    pos, rot = np.array(series["pos_mm"]), np.array(series["rot_mrad"])
    assert max(series["pos_uncompensated_mm"]) == pytest.approx(1.97, abs=0.01)
    closed_at = out.summary["loop_closed_at_s"]
    assert closed_at is not None
    assert closed_at < 2.0
    late = (t >= closed_at + 5.0) & (t < brk)
    moving = late & (t > 4.0) & (t < 6.8)  # the second stroke, at 0.1 m/s
    print(
        f"loop closed at {closed_at:.3f} s; from 5 s later: max {pos[late].max():.4f} mm, "
        f"{rot[late].max():.4f} mrad (uncompensated 1.97 / 1.97)"
    )
    assert moving.sum() > 50
    assert pos[late].max() < 0.05
    assert rot[late].max() < 0.05
    # the beam breaks at scenario time brk: the registers fall to zero within 0.1 s
    broke = out.t0 + brk
    zeroed = [w for w, values in out.register_writes if w >= broke and not any(values)]
    assert zeroed, out.register_writes[-5:]
    print(f"registers zero {1e3 * (zeroed[0] - broke):.1f} ms after the beam broke")
    assert zeroed[0] - broke < 0.1
    invalid = [m for w, m in out.corrections if w >= broke and not m.valid]
    assert invalid
    assert invalid[0].reason == "tracker_gap"


def _ripple_model(closed: ClosedLoopCell, scenario, offsets) -> ModelConfig:
    """The true effects as a [model] section: the joint offsets and, for the rippling joints,
    the ripple sampled every 10 mrad over the path's range (a joint map)."""
    lo, hi = closed.q_grid.min(axis=0) - 0.05, closed.q_grid.max(axis=0) + 0.05
    knots, values = [], []
    rippled = {int(k) - 1 for k in scenario.ripple_joints.split(",")}
    for j in range(6):
        if j in rippled:
            k = np.arange(lo[j], hi[j], 0.01)
            q = np.zeros((k.size, 6))
            q[:, j] = k
            knots.append(k.tolist())
            values.append([float(angle_ripple(scenario, row)[j]) for row in q])
        else:
            knots.append([])
            values.append([])
    return ModelConfig(
        effects=["joint_offsets", "joint_maps"],
        joint_offsets=list(offsets),
        map_knots=knots,
        map_values=values,
    )


@pytest.mark.e2e
@pytest.mark.slow  # an acceptance run (> 9 s): .ci/run runs the slow tests after the default run
def test_a_pose_dependent_error_with_a_model_falls_tenfold(tmp_path):
    offsets = (8e-4, -1e-3, 1.2e-3, -8e-4, 1e-3, -6e-4)  # rad: about 1 mm at the tool
    sets = {**PATH, "ripple_rad": "0.0005", "ripple_joints": "2,3"}
    scenario = make_scenario("paper-vertical", sets)
    cell = cell_from_config(closed_loop_config())
    # the same arm as the mock's (same scenario and seed): the model is its truth
    closed = ClosedLoopCell(cell, scenario, seed=6, joint_offsets=offsets)
    config = closed_loop_config(_ripple_model(closed, scenario, offsets))
    out = run_closed_loop(
        tmp_path,
        config,
        sets,
        seed=6,
        seconds=7.5,
        mock_args=["--joint-offsets", ",".join(map(repr, offsets))],
    )
    s = out.summary
    print(s)
    assert s["loop_closed_at_s"] is not None
    # judged from 2 s after the loop closed (the summary's own window is 5 s: recomputed)
    series = out.series
    t = np.array(series["t"])
    after = t >= s["loop_closed_at_s"] + 2.0
    rms = lambda name: float(np.sqrt(np.mean(np.square(np.array(series[name])[after]))))  # noqa: E731
    without, with_ = rms("pos_uncompensated_mm"), rms("pos_mm")
    print(f"pose-dependent error: {without:.4f} mm RMS without, {with_:.4f} mm with")
    assert without > 0.5
    assert with_ * 10 < without
    assert rms("rot_mrad") * 10 < rms("rot_uncompensated_mrad")
    ff = [m for _w, m in out.corrections if m.valid]
    assert ff
    assert max(np.linalg.norm(m.feedforward_translation) for m in ff) > 5e-4


# ---- on the wire: keo/<cell>/correction and the ROS 2 PoseStamped ---------------------------


def test_the_correction_goes_out_on_the_bus_and_as_a_ros2_pose(demo_config):
    """A correction for one estimate: the msgspec message on keo/<cell>/correction and the
    same transform as geometry_msgs/msg/PoseStamped on /keo/<cell>/correction, read with an
    independent peer (rosbags + zenoh, tests/ros2_peer.py)."""
    from keo_service.core.estimator import Estimate
    from keo_service.live.compensation import CorrectionPublisher
    from keo_service.live.ros2 import Ros2Node
    from tests import ros2_peer

    config = msgspec.structs.replace(
        loopback_config(demo_config),
        ros2=msgspec.structs.replace(demo_config.ros2, enabled=True),
    )
    endpoint = config.bus.listen[0]
    session = open_session("peer", listen=[endpoint])
    peer = open_session("peer", connect=[endpoint])
    got_bus: list[CorrectionMessage] = []
    got_ros: list[bytes] = []
    sub_bus = peer.declare_subscriber(
        topic(config.cell, "correction"), lambda s: got_bus.append(decode(s.payload.to_bytes()))
    )
    sub_ros = peer.declare_subscriber(
        ros2_peer.key(f"/keo/{config.cell}/correction", "geometry_msgs/msg/PoseStamped"),
        lambda s: got_ros.append(s.payload.to_bytes()),
    )
    node = Ros2Node(session, "keo_test", 0, "jazzy")
    publisher = CorrectionPublisher(config, session, node)
    est = [1e-3, -2e-3, 0.5e-3, 2e-4, -1e-4, 3e-4]
    channels = ("px", "py", "pz", "rx", "ry", "rz")
    try:
        time.sleep(0.5)
        for k in range(3):  # the first ramps up from zero (rate limit); the third is whole
            t = 100.0 + k
            publisher.publish(Estimate(t, est, est, (), t, channels))
            time.sleep(0.2)  # 50 mm/s: 10 mm may change in 0.2 s
        deadline = time.monotonic() + 5
        while (len(got_bus) < 3 or len(got_ros) < 3) and time.monotonic() < deadline:
            time.sleep(0.05)
    finally:
        publisher.close()
        node.close()
        sub_bus.undeclare()
        sub_ros.undeclare()
        peer.close()
        session.close()
    last = got_bus[-1]
    assert last.valid
    T_ts = pin.SE3(pin.exp3(np.array(est[3:])), np.array(est[:3]))
    C = T_ts.inverse()
    assert last.translation == pytest.approx(C.translation.tolist(), abs=1e-15)
    assert last.rotation == pytest.approx(pin.log3(C.rotation).tolist(), abs=1e-15)
    ros = ros2_peer.STORE.deserialize_cdr(got_ros[-1], "geometry_msgs/msg/PoseStamped")
    p, o = ros.pose.position, ros.pose.orientation
    assert [p.x, p.y, p.z] == pytest.approx(last.translation, abs=1e-15)
    rotvec = pin.log3(pin.Quaternion(o.w, o.x, o.y, o.z).toRotationMatrix())
    assert rotvec.tolist() == pytest.approx(last.rotation, abs=1e-12)
    assert ros.header.frame_id == f"{config.cell}_tool"
    assert ros.header.stamp.sec == 102


def test_feedforward_is_the_models_inverse_and_invalid_outside_its_range(demo_cell):
    """With a model, the feedforward undoes the model's own error at the joints (the model's
    tool pose times C_ff is the nominal one, checked with Pinocchio), and joints beyond a
    joint map's knots make the correction not valid."""
    from keo_service.core.compensation import ToolModel
    from keo_service.core.kinematics import flange_pose
    from keo_service.core.model_corrections import ModelCorrections

    empty = (np.array([]), np.array([]))
    corr = ModelCorrections(
        6,
        joint_offsets=np.array([1e-3, -2e-3, 5e-4, 1e-3, -1e-3, 2e-3]),
        maps=(empty, (np.array([0.0, 0.5, 1.0]), np.array([0.0, 8e-4, 0.0])), *[empty] * 4),
    )
    model = ToolModel(demo_cell.robot, corr, demo_cell.T_nt.homogeneous)
    filt = CorrectionFilter(CompensationLimits(max_m=1.0, max_rad=1.0, max_rate_m_s=1e6), model)
    q = np.array([0.1, 0.4, 0.1, 0.2, -1.0, 0.3])
    filt.step(0.0, [0.0] * 6, q)
    c = filt.step(1.0, [0.0] * 6, q)
    assert c.valid
    assert np.linalg.norm(c.translation) > 1e-3  # millimetres of model error undone
    data = demo_cell.robot.create_data()
    q_model = q + corr.joint_offsets + corr.map_error(q)
    T_model = flange_pose(demo_cell.robot, data, q_model) * demo_cell.T_nt
    T_nominal = flange_pose(demo_cell.robot, data, q) * demo_cell.T_nt
    landed = T_model * pin.SE3(pin.exp3(c.rotation), c.translation)
    assert np.linalg.norm(landed.translation - T_nominal.translation) < 1e-12
    assert np.linalg.norm(pin.log3(T_nominal.rotation.T @ landed.rotation)) < 1e-12
    outside = q.copy()
    outside[1] = 1.2  # beyond joint 2's map (0 .. 1 rad)
    c = filt.step(2.0, [0.0] * 6, outside)
    assert not c.valid
    assert c.reason == "outside_calibrated_range"
    assert np.all(c.translation == 0.0)


@pytest.mark.parametrize("angle", [0.0, 1e-12, 1e-8, 3e-8, 1e-3, 0.5, 3.0])
def test_a_corrections_inverse_is_pinocchios_inverse(angle):
    """`invert` (Rodrigues on plain floats, one per live correction) gives the inverse
    transform Pinocchio gives (SE3 of exp3, inverted), from tiny angles through the series'
    threshold to nearly a half turn."""
    import numpy as np
    import pinocchio as pin

    from keo_service.core.compensation import invert

    rng = np.random.default_rng(7)
    for _ in range(50):
        axis = rng.normal(size=3)
        r = axis / np.linalg.norm(axis) * angle
        p = rng.normal(0.0, 2e-3, 3)
        want = pin.SE3(pin.exp3(r), p).inverse()
        got_p, got_r = invert(p, r)
        assert np.max(np.abs(got_p - want.translation)) <= 1e-15
        assert np.max(np.abs(pin.exp3(got_r) - want.rotation)) <= 1e-15
