"""The benchmark's transport floor: a stand-in for `keo run` that moves the same messages over
the same bus plumbing and does no estimation.

It opens the bus as the service does, takes the encoder and tracker streams through the same
`AsyncSubscription`, decodes every sample and answers each tracker sample with an estimate
message (zeros) on the estimate topic. `keo bench` runs the whole chain once with the service
and once with this relay: the difference is what keo's own work adds on that machine.
Run as `python -m keo_service.bench.relay --config FILE`.

`--math` makes it the naive floor of the math in the live chain: each tracker pose also gets
the error transform the naive in-process floor computes (`bench.hot_path.floor_pass`: forward
kinematics at the newest encoder sample's joints, the tool and sensor poses, the error and its
rotation's log), published in the message. No interpolation, observer, delay tracking, status
or validation: what any estimator in this stack must do per sample, and no more. Its CPU and
latency over the plain relay's bound from below what the service can reach.
"""

from __future__ import annotations

import argparse
import asyncio
import signal
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import pinocchio as pin

from keo_service.core.kinematics import POSE_CHANNELS, Cell
from keo_service.io.cell import cell_from_config
from keo_service.io.config import Config, load_config
from keo_service.live.bus import AsyncSubscription, session_for_service
from keo_service.live.messages import (
    EstimateMessage,
    JointSample,
    TrackerSample,
    decode,
    encode,
    topic,
)
from keo_service.live.sinks import estimate_publisher


class NaiveMath:
    """The naive floor's math per tracker pose (the module's `--math`): the newest encoder
    sample's joints kept (`joints`), and for a pose the error transform from the tool to the
    sensor frame, its translation and rotation vector; zeros for a pose without orientation
    or before any joints, as the plain relay publishes."""

    def __init__(self, cell: Cell) -> None:
        self._model, self._data = cell.robot.model, cell.robot.create_data()
        self._flange, self._T_nt, self._T_bk = cell.robot.flange_frame_id, cell.T_nt, cell.T_bk
        self._zeros = [0.0] * len(POSE_CHANNELS)
        self.joints: np.ndarray | None = None

    def error(self, msg: TrackerSample) -> list[float]:
        quat = msg.quaternion
        if self.joints is None or quat is None or msg.position is None:
            return self._zeros
        pin.framesForwardKinematics(self._model, self._data, self.joints)
        T_bt = self._data.oMf[self._flange] * self._T_nt
        xyzquat = np.array([*msg.position, quat[1], quat[2], quat[3], quat[0]])
        err = T_bt.actInv(self._T_bk * pin.XYZQUATToSE3(xyzquat))
        return [*err.translation.tolist(), *pin.log3(err.rotation).tolist()]


def relay_handler(
    pub: Any, math: NaiveMath | None = None
) -> Callable[[list[tuple[str, bytes]]], None]:
    """The relay's work per wake-up: decode each sample, and for each tracker pose put a
    zero estimate message on `pub` (anything with `put(bytes)`). Also what
    `bench.live_path` runs in process as the floor beside the service's `_handle`. `math`:
    the naive floor's error in the message instead of zeros (`naive_math_handler`)."""
    channels = list(POSE_CHANNELS)
    zeros = [0.0] * len(channels)
    seq = 0

    def handle(batch: list[tuple[str, bytes]]) -> None:
        nonlocal seq
        for _key, payload in batch:
            msg = decode(payload)
            if not isinstance(msg, TrackerSample) or msg.position is None:
                if math is not None and isinstance(msg, JointSample):
                    math.joints = np.asarray(msg.joints, dtype=float)
                continue
            seq += 1
            values = zeros if math is None else math.error(msg)
            out = EstimateMessage(
                stamp=msg.stamp,
                host_ns=time.time_ns(),
                channels=channels,
                measured=values,
                estimate=values,
                flags=[],
                delay_s=0.0,
                seq=seq,
                device_stamp=msg.device_stamp,
            )
            pub.put(encode(out))

    return handle


def naive_math_handler(pub: Any, cell: Cell) -> Callable[[list[tuple[str, bytes]]], None]:
    """`relay_handler` with the naive floor's math per tracker pose (`NaiveMath`): what any
    estimator in this stack does per sample, and no more."""
    return relay_handler(pub, NaiveMath(cell))


async def relay(config: Config, math: bool = False) -> None:
    session = session_for_service(config)
    # published as the service's own session does (its estimates not delivered back to it)
    pub = estimate_publisher(session, config.cell, local_subscribers=False)
    sub = AsyncSubscription(session, [topic(config.cell, "encoder"), topic(config.cell, "tracker")])
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, sub.close)
    # the service's own hand-off from Zenoh's thread to the loop
    handler = naive_math_handler(pub, cell_from_config(config)) if math else relay_handler(pub)
    await sub.deliver(handler)
    session.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", required=True)
    parser.add_argument(
        "--math", action="store_true", help="the naive floor's math per tracker pose too"
    )
    args = parser.parse_args()
    asyncio.run(relay(load_config(args.config), math=args.math))


if __name__ == "__main__":
    main()
