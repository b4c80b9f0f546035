"""The service's status cycle leaves the event loop to the data path between its steps
(issue 48): a sample that arrives while the cycle runs is handled after the step it arrived
in, not after the whole cycle."""

from __future__ import annotations

import asyncio

from keo_service.bench.demo import loopback_config


def test_a_sample_arriving_in_the_status_cycle_waits_for_one_step_only(demo_config):
    """The cycle's steps recorded in order; a data path's wake-up (what Zenoh's thread
    schedules with `call_soon_threadsafe`) is scheduled from inside the first step and
    another from inside the second. Each must run before the step after the one it arrived
    in (before this change the cycle ran all its steps in one go and the samples waited)."""
    from keo_service.live.service import KeoService

    service = KeoService(loopback_config(demo_config))
    order: list[str] = []

    async def cycle() -> None:
        loop = asyncio.get_running_loop()

        def feed() -> None:
            order.append("delay block")
            loop.call_soon_threadsafe(order.append, "sample")

        def snapshot() -> None:
            order.append("snapshot")
            service.stop()

        service._feed_delay = feed  # type: ignore[method-assign]

        def tool_speed(_last: object) -> None:
            order.append("tool speed")
            loop.call_soon_threadsafe(order.append, "second sample")

        service._tool_speed.sample = tool_speed  # type: ignore[method-assign]
        service._refresh_status = snapshot  # type: ignore[method-assign]
        await asyncio.wait_for(service._status_loop(), 5.0)

    asyncio.run(cycle())
    assert order == [
        "delay block",
        "sample",
        "tool speed",
        "second sample",
        "snapshot",
    ]
