"""The bench relay's `--math` mode: the naive floor's error transform per tracker pose, checked
against an error injected into a synthetic pose (not against the code's own formula), and
the plain relay's zeros where the math has nothing to work on."""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from keo_service.bench.relay import naive_math_handler, relay_handler
from keo_service.io.cell import cell_from_config
from keo_service.io.config import load_config
from keo_service.live.messages import EstimateMessage, JointSample, TrackerSample, decode, encode
from keo_service.resources import demo_config_path


class _Pub:
    def __init__(self) -> None:
        self.sent: list[EstimateMessage] = []

    def put(self, payload: bytes) -> None:
        msg = decode(payload)
        assert isinstance(msg, EstimateMessage)
        self.sent.append(msg)


def _tracker(position: list[float], quaternion: list[float] | None, seq: int) -> bytes:
    return encode(
        TrackerSample(
            stamp=float(seq),
            host_ns=0,
            seq=seq,
            status="ok",
            position=position,
            quaternion=quaternion,
        )
    )


def test_math_relay_recovers_an_injected_error() -> None:
    cell = cell_from_config(load_config(str(demo_config_path())))
    q = np.array([0.3, -0.8, 1.1, 0.2, 0.9, -0.4])[: cell.robot.model.nq]
    # the truth: the sensor frame sits at tool * E in the base; the tracker sees it through
    # the base-to-tracker transform, so the pose it reports is T_bk^-1 * T_bt * E
    injected = pin.exp6(np.array([2e-4, -1e-4, 3e-4, 1e-4, -2e-4, 5e-5]))
    data = cell.robot.model.createData()
    pin.framesForwardKinematics(cell.robot.model, data, q)
    tool = data.oMf[cell.robot.flange_frame_id] * cell.T_nt
    seen = cell.T_bk.inverse() * tool * injected
    xyzw = pin.Quaternion(seen.rotation).coeffs().tolist()  # x y z w
    pub = _Pub()
    handle = naive_math_handler(pub, cell)
    joint = JointSample(stamp=0.0, host_ns=0, seq=1, joints=q.tolist())
    handle(
        [
            ("keo/c/tracker", _tracker(seen.translation.tolist(), [xyzw[3], *xyzw[:3]], 1)),
            ("keo/c/encoder", encode(joint)),
            ("keo/c/tracker", _tracker(seen.translation.tolist(), [xyzw[3], *xyzw[:3]], 2)),
            ("keo/c/tracker", _tracker(seen.translation.tolist(), None, 3)),
        ]
    )
    assert [m.seq for m in pub.sent] == [1, 2, 3]
    assert pub.sent[0].measured == [0.0] * 6  # no joints yet
    assert pub.sent[2].measured == [0.0] * 6  # a reflector: no orientation
    want = [*injected.translation, *pin.log3(injected.rotation)]
    np.testing.assert_allclose(pub.sent[1].measured, want, atol=1e-12)
    assert pub.sent[1].estimate == pub.sent[1].measured


def test_plain_relay_publishes_zeros_for_the_same_samples() -> None:
    pub = _Pub()
    handle = relay_handler(pub)
    handle([("keo/c/tracker", _tracker([1.0, 2.0, 3.0], [1.0, 0.0, 0.0, 0.0], 7))])
    assert len(pub.sent) == 1
    assert pub.sent[0].measured == [0.0] * 6
