"""The benchmark's transport floor: a stand-in for `keo run` that moves the same messages over
the same bus plumbing and does no estimation.

It opens the bus as the service does, takes the encoder and tracker streams through the same
`AsyncSubscription`, decodes every sample and answers each tracker sample with an estimate
message (zeros) on the estimate topic. `keo bench` runs the whole chain once with the service
and once with this relay: the difference is what keo's own work adds on that machine.
Run as `python -m keo_service.bench.relay --config FILE`.
"""

from __future__ import annotations

import argparse
import asyncio
import signal
import time
from collections.abc import Callable
from typing import Any

from keo_service.core.kinematics import POSE_CHANNELS
from keo_service.io.config import Config, load_config
from keo_service.live.bus import AsyncSubscription, session_for_service
from keo_service.live.messages import EstimateMessage, TrackerSample, decode, encode, topic
from keo_service.live.sinks import estimate_publisher


def relay_handler(pub: Any) -> Callable[[list[tuple[str, bytes]]], None]:
    """The relay's work per wake-up: decode each sample, and for each tracker pose put a
    zero estimate message on `pub` (anything with `put(bytes)`). Also what
    `bench.live_path` runs in process as the floor beside the service's `_handle`."""
    channels = list(POSE_CHANNELS)
    zeros = [0.0] * len(channels)
    seq = 0

    def handle(batch: list[tuple[str, bytes]]) -> None:
        nonlocal seq
        for _key, payload in batch:
            msg = decode(payload)
            if not isinstance(msg, TrackerSample) or msg.position is None:
                continue
            seq += 1
            out = EstimateMessage(
                stamp=msg.stamp,
                host_ns=time.time_ns(),
                channels=channels,
                measured=zeros,
                estimate=zeros,
                flags=[],
                delay_s=0.0,
                seq=seq,
                device_stamp=msg.device_stamp,
            )
            pub.put(encode(out))

    return handle


async def relay(config: Config) -> None:
    session = session_for_service(config)
    # published as the service's own session does (its estimates not delivered back to it)
    pub = estimate_publisher(session, config.cell, local_subscribers=False)
    sub = AsyncSubscription(session, [topic(config.cell, "encoder"), topic(config.cell, "tracker")])
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, sub.close)
    # the service's own hand-off from Zenoh's thread to the loop
    await sub.deliver(relay_handler(pub))
    session.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", required=True)
    asyncio.run(relay(load_config(parser.parse_args().config)))


if __name__ == "__main__":
    main()
