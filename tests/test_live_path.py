"""The service's data path as issue 48 left it: samples taken in batches from the Zenoh
hand-off (every one, in order), and the correction cycle present only when a correction
output is configured."""

from __future__ import annotations

import asyncio
import time

import msgspec
import pytest

from keo_service.bench.demo import loopback_config
from keo_service.live.bus import AsyncSubscription, open_session


def test_batches_deliver_every_sample_in_the_publishers_order_across_keys():
    """Two keys under one prefix, 3000 samples put from another session in bursts: the
    batches, concatenated, are exactly what was put, in order; a burst comes as few
    batches (not one per sample)."""
    from keo_service.bench.procs import free_port

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    sent = [
        (("keo/t/encoder" if i % 4 == 0 else "keo/t/tracker"), f"{i}".encode()) for i in range(3000)
    ]

    async def main() -> tuple[list[tuple[str, bytes]], int]:
        listener = open_session("peer", listen=[endpoint])
        talker = open_session("peer", connect=[endpoint])
        try:
            sub = AsyncSubscription(listener, ["keo/t/encoder", "keo/t/tracker"])
            pubs = {k: talker.declare_publisher(k) for k in ("keo/t/encoder", "keo/t/tracker")}
            await asyncio.sleep(0.5)  # the sessions meet

            def put_all() -> None:
                for key, payload in sent:
                    pubs[key].put(payload)

            putter = asyncio.get_running_loop().run_in_executor(None, put_all)
            got: list[tuple[str, bytes]] = []
            batches = 0
            deadline = time.monotonic() + 20
            async for batch in sub.batches():
                batches += 1
                got.extend(batch)
                if len(got) >= len(sent) or time.monotonic() > deadline:
                    break
            await putter
            sub.close()
            return got, batches
        finally:
            talker.close()
            listener.close()

    got, batches = asyncio.run(main())
    assert got == sent
    assert batches < len(sent)


@pytest.mark.parametrize("correction", ["none", "rtde_registers"])
def test_the_correction_cycle_runs_only_with_a_correction_output(demo_config, correction):
    from keo_service.live.service import KeoService

    config = loopback_config(demo_config)
    robot = msgspec.structs.replace(config.robot, correction=correction)
    config = msgspec.structs.replace(config, robot=robot)

    async def main() -> tuple[list[str], list[str]]:
        async with KeoService(config) as service:
            names = [s.name for s in service.sinks.sinks]
            tasks = [t.get_name() for t in service._tasks]
        return names, tasks

    names, tasks = asyncio.run(main())
    if correction == "none":
        assert names == ["bus"]
        assert "keo.service.correction" not in tasks
    else:
        assert names == ["bus", "correction"]
        assert "keo.service.correction" in tasks
