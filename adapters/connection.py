"""Reconnecting TCP client loop shared by the adapters. Bytes only; no parsing here."""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Awaitable, Callable

from keo_service.live.backoff import Backoff

log = logging.getLogger("keo.adapter")


async def run_tcp_client(
    name: str,
    host: str,
    port: int,
    handle: Callable[[asyncio.StreamReader, asyncio.StreamWriter], Awaitable[None]],
    stop: asyncio.Event,
    counters: dict[str, int],
    backoff: Backoff | None = None,
) -> None:
    """Connect, hand reader and writer to `handle` until the connection ends, reconnect;
    until `stop`. An exception in `handle` is logged as a connection error and retried with
    the backoff (a device that answers wrongly is a device problem, not a reason to die)."""
    backoff = backoff or Backoff()
    while not stop.is_set():
        try:
            reader, writer = await asyncio.open_connection(host, port, limit=1 << 16)
        except OSError as exc:
            counters["connect_failures"] = counters.get("connect_failures", 0) + 1
            delay = backoff.next_delay()
            log.warning(
                "%s: cannot connect to %s:%d (%s); retrying in %.2f s",
                name,
                host,
                port,
                exc.strerror or exc,
                delay,
            )
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), delay)
            continue
        counters["connections"] = counters.get("connections", 0) + 1
        log.info("%s: connected to %s:%d", name, host, port)
        backoff.reset()
        reading: asyncio.Task[None] = asyncio.ensure_future(handle(reader, writer))
        stopping = asyncio.create_task(stop.wait())
        try:
            await asyncio.wait({reading, stopping}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for task in (reading, stopping):
                task.cancel()
            writer.close()
            with contextlib.suppress(OSError):
                await writer.wait_closed()
        if reading.done() and not reading.cancelled() and reading.exception() is not None:
            log.warning("%s: connection error: %s", name, reading.exception())
        if not stop.is_set():
            counters["disconnects"] = counters.get("disconnects", 0) + 1
            log.warning("%s: connection to %s:%d lost; reconnecting", name, host, port)
            await asyncio.sleep(backoff.next_delay())
