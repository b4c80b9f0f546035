"""The service's own estimates and corrections do not come back to it (issue 48): its data
subscription is a wildcard on the cell's prefix, and a message delivered to its own session
would wake Zenoh's callback thread once more per message, only to be dropped there. Other
processes still get every one."""

from __future__ import annotations

import asyncio
import time

import msgspec
import pytest

from keo_service.bench.demo import loopback_config
from keo_service.bench.live_path import wire_samples
from keo_service.live.bus import AsyncSubscription, session_for_client
from keo_service.live.messages import topic


@pytest.mark.parametrize("output", ["estimate", "correction"])
async def test_the_service_gets_none_of_its_output_back_and_other_sessions_get_it(
    demo_config, monkeypatch, output
):
    from keo_service.live.service import KeoService

    config = loopback_config(demo_config)
    if output == "correction":  # the correction path runs only with an output configured
        robot = msgspec.structs.replace(config.robot, correction="rtde_registers")
        config = msgspec.structs.replace(config, robot=robot)
    wire = wire_samples(config, 1.0)
    keys_seen: list[str] = []
    on_sample = AsyncSubscription._on_sample

    def seen(self: AsyncSubscription, sample: object) -> None:
        keys_seen.append(str(sample.key_expr))  # type: ignore[attr-defined]
        on_sample(self, sample)  # type: ignore[arg-type]

    monkeypatch.setattr(AsyncSubscription, "_on_sample", seen)
    received: list[int] = []
    async with KeoService(config) as service:
        client = session_for_client(config)
        try:
            listener = client.declare_subscriber(
                topic(config.cell, output), lambda _sample: received.append(1)
            )
            await asyncio.sleep(0.5)  # the sessions meet
            for _stamp, key, payload in wire:
                client.put(key, payload)
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline and (
                service.estimator.counters.get("estimates", 0) < 900 or len(received) < 900
            ):
                await asyncio.sleep(0.05)
            estimates = service.estimator.counters.get("estimates", 0)
            listener.undeclare()
        finally:
            client.close()
    assert estimates >= 900, estimates  # ~1000 tracker samples in the second of wire
    assert len(received) >= 900, len(received)  # another session got them
    own = [k for k in keys_seen if k.endswith(f"/{output}")]
    assert not own, f"{len(own)} of the service's own {output} messages came back to it"
    assert sum(k.endswith("/tracker") for k in keys_seen) >= 900
