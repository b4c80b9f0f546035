"""Zenoh sessions and the hand-off from Zenoh's threads to asyncio. No math here.

Zenoh delivers samples on its own threads. The callback only appends to a bounded deque and
schedules at most one wake-up of the event loop; the loop drains the deque. When the deque is
full the oldest sample is dropped and counted.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import json
import threading
from collections.abc import AsyncIterator, Sequence
from typing import Any

import zenoh

DEFAULT_QUEUE = 10_000


def make_zenoh_config(
    mode: str = "peer",
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    multicast: bool = False,
) -> zenoh.Config:
    cfg = zenoh.Config()
    cfg.insert_json5("mode", json.dumps(mode))
    cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
    cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
    cfg.insert_json5("scouting/multicast/enabled", json.dumps(multicast))
    return cfg


def open_session(
    mode: str = "peer",
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    multicast: bool = False,
) -> zenoh.Session:
    return zenoh.open(make_zenoh_config(mode, listen, connect, multicast))


def session_for_client(config: Any) -> zenoh.Session:
    """A session for adapters and clients: connects to bus.connect (or bus.listen)."""
    return open_session(config.bus.mode, (), config.bus_endpoints(), config.bus.multicast_scouting)


class AsyncSubscription:
    """Samples of several key expressions, in arrival order, as an async iterator of
    (key, payload bytes)."""

    def __init__(
        self, session: zenoh.Session, keys: Sequence[str], maxlen: int = DEFAULT_QUEUE
    ) -> None:
        self._loop = asyncio.get_running_loop()
        self._buf: collections.deque[tuple[str, bytes]] = collections.deque(maxlen=maxlen)
        self._wake = asyncio.Event()
        self._scheduled = threading.Event()
        self._closed = False
        self.dropped = 0
        self._subs = [session.declare_subscriber(k, self._on_sample) for k in keys]

    def _on_sample(self, sample: zenoh.Sample) -> None:  # zenoh thread: no zenoh calls, no blocking
        if len(self._buf) == self._buf.maxlen:
            self.dropped += 1
        self._buf.append((str(sample.key_expr), sample.payload.to_bytes()))
        if not self._scheduled.is_set():
            self._scheduled.set()
            with contextlib.suppress(RuntimeError):  # the loop closed during shutdown
                self._loop.call_soon_threadsafe(self._set_wake)

    def _set_wake(self) -> None:
        self._scheduled.clear()
        self._wake.set()

    async def __aiter__(self) -> AsyncIterator[tuple[str, bytes]]:
        while True:
            while self._buf:
                yield self._buf.popleft()
            if self._closed:
                return
            self._wake.clear()
            if self._buf:
                continue
            await self._wake.wait()

    def close(self) -> None:
        self._closed = True
        for sub in self._subs:
            sub.undeclare()
        self._loop.call_soon_threadsafe(self._wake.set)
