"""Reconnecting TCP client loop shared by the adapters. Bytes only; no parsing here."""

from __future__ import annotations

import asyncio
import contextlib
import contextvars
import logging
from collections.abc import Awaitable, Callable
from dataclasses import dataclass

from keo_service.live.backoff import Backoff

log = logging.getLogger("keo.adapter")


@dataclass
class Device:
    """The device the calling adapter talks to: its config section ("robot", "tracker"), what
    it should be in words, and the newest connection problem (for the adapter's status)."""

    section: str = ""
    expected: str = ""
    last_error: str = ""


# set by the adapter before it starts its tasks (they inherit it), so that the messages here
# name the keys to fix and the adapter sees the newest problem
DEVICE: contextvars.ContextVar[Device | None] = contextvars.ContextVar(
    "keo_adapter_device", default=None
)


def _keys(name: str) -> str:
    device = DEVICE.get()
    section = device.section if device else {"encoder": "robot"}.get(name, name)
    return f"{section}.host and {section}.port"


def _expected() -> str:
    device = DEVICE.get()
    return f"; expected {device.expected}" if device and device.expected else ""


def _problem(text: str) -> None:
    device = DEVICE.get()
    if device is not None:
        device.last_error = text


def describe(exc: BaseException) -> str:
    """An exception in one readable phrase (a TimeoutError's text is empty)."""
    text = str(exc)
    if isinstance(exc, TimeoutError) and not text:
        return "no answer in time"
    return text or type(exc).__name__


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
            problem = (
                f"cannot connect to {host}:{port} ({exc.strerror or exc}): check {_keys(name)} "
                f"in the config{_expected()}"
            )
            _problem(problem)
            log.warning("%s: %s; retrying in %.2f s", name, problem, delay)
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
        error = reading.exception() if reading.done() and not reading.cancelled() else None
        if error is not None:
            counters["connection_errors"] = counters.get("connection_errors", 0) + 1
            problem = (
                f"connection to {host}:{port} failed: {describe(error)} (check {_keys(name)} "
                f"in the config{_expected()})"
            )
            _problem(problem)
            log.warning("%s: %s", name, problem)
        if not stop.is_set():
            counters["disconnects"] = counters.get("disconnects", 0) + 1
            log.warning("%s: connection to %s:%d lost; reconnecting", name, host, port)
            await asyncio.sleep(backoff.next_delay())
