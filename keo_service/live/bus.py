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
import logging
import threading
import time
from collections.abc import AsyncIterator, Callable, Sequence
from typing import Any

import zenoh

from keo_service.core.errors import KeoError
from keo_service.live.access import access_control_for
from keo_service.live.backoff import Backoff

log = logging.getLogger("keo.bus")

DEFAULT_QUEUE = 10_000
# at most this many samples per call of a `deliver` handler: a backlog (a replay, a stall)
# is handed over in pieces with the loop's other work (status, timers, the delay fits'
# results) between them, instead of up to DEFAULT_QUEUE samples in one go
DRAIN_MOST = 256


# A DROP publisher waits this long on a full transmit queue before dropping (Zenoh's default
# is 1 ms, which loses samples in ordinary bursts such as a replay); it still never blocks the
# event loop for longer than this.
DROP_WAIT_US = 50_000


RECONNECT = {"period_init_ms": 200, "period_max_ms": 1000, "period_increase_factor": 2}


def make_zenoh_config(
    mode: str = "peer",
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    multicast: bool = False,
    tls: Any = None,
    access: dict[str, Any] | None = None,
) -> zenoh.Config:
    """`tls`: an object with tls_root_ca, tls_certificate, tls_private_key, tls_mtls (the
    [bus] config section), used for tls/ endpoints. `access`: Zenoh's access_control section
    (`keo_service.live.access`), enforced by this node on its links."""
    cfg = zenoh.Config()
    cfg.insert_json5("mode", json.dumps(mode))
    cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
    cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
    cfg.insert_json5("scouting/multicast/enabled", json.dumps(multicast))
    cfg.insert_json5(
        "transport/link/tx/queue/congestion_control/drop/wait_before_drop", json.dumps(DROP_WAIT_US)
    )
    # a session that lost its router (or service) retries every 0.2 s, then at most every
    # 1 s (Zenoh's defaults, 1 s doubling to 4 s, left a restarted router without its
    # clients for up to 4 s)
    cfg.insert_json5("connect/retry", json.dumps(RECONNECT))
    if tls is not None and tls.tls_root_ca:
        link = "transport/link/tls/"
        cfg.insert_json5(link + "root_ca_certificate", json.dumps(tls.tls_root_ca))
        if tls.tls_certificate:
            for side in ("listen", "connect"):
                cfg.insert_json5(f"{link}{side}_certificate", json.dumps(tls.tls_certificate))
                cfg.insert_json5(f"{link}{side}_private_key", json.dumps(tls.tls_private_key))
        cfg.insert_json5(link + "enable_mtls", json.dumps(bool(tls.tls_mtls)))
    if access is not None:
        cfg.insert_json5("access_control", json.dumps(access))
    return cfg


def open_session(
    mode: str = "peer",
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    multicast: bool = False,
    tls: Any = None,
    access: dict[str, Any] | None = None,
) -> zenoh.Session:
    return zenoh.open(make_zenoh_config(mode, listen, connect, multicast, tls, access))


def _zenoh_reason(exc: Exception) -> str:
    """Zenoh's error text without the Rust source location it ends with."""
    text = str(exc).split(" at /", 1)[0].strip().rstrip("!.").strip()
    return "" if text.startswith("Unable to connect to any of") else text


def _unreachable(endpoints: Sequence[str], exc: Exception, waited: float | None) -> KeoError:
    """One readable sentence: where, for how long, and which settings decide it."""
    reason = _zenoh_reason(exc)
    return KeoError(
        f"cannot reach the bus at {', '.join(endpoints)}"
        + (f" ({reason})" if reason else "")
        + (f" within {waited:g} s" if waited is not None else "")
        + ": nothing answers there (start `keo run` or a Zenoh router, or fix the config's "
        "bus.connect, or bus.listen when connect is empty; a client's connect_timeout_s sets "
        "how long it keeps trying)"
    )


def _log_retry(endpoints: Sequence[str], started: float, delay: float) -> None:
    # a service starting beside us is normal for a few seconds; longer is worth a warning
    level = logging.WARNING if time.monotonic() - started > 5.0 else logging.DEBUG
    log.log(level, "bus not reachable at %s; retrying in %.1f s", list(endpoints), delay)


def open_client(
    endpoints: Sequence[str],
    multicast: bool = False,
    tls: Any = None,
    retry_for: float | None = None,
    access: dict[str, Any] | None = None,
) -> zenoh.Session:
    """A Zenoh client session of `endpoints`, retried with `Backoff` for `retry_for` seconds
    (None: until it succeeds). Blocking: for scripts and threads; async code uses
    `open_client_async`. `access`: the leaf's access_control section (`leaf_access`)."""
    backoff, started = Backoff(maximum=2.0), time.monotonic()
    while True:
        try:
            return open_session("client", (), endpoints, multicast, tls, access)
        except zenoh.ZError as exc:
            delay = backoff.next_delay()
            if retry_for is not None and time.monotonic() + delay > started + retry_for:
                raise _unreachable(endpoints, exc, retry_for) from None
            _log_retry(endpoints, started, delay)
            time.sleep(delay)


async def open_client_async(
    endpoints: Sequence[str],
    multicast: bool = False,
    tls: Any = None,
    retry_for: float | None = None,
    access: dict[str, Any] | None = None,
) -> zenoh.Session:
    """`open_client` without blocking the event loop: each attempt runs in a thread (Zenoh
    fails an unreachable endpoint within milliseconds) and the waits are `asyncio.sleep`, so
    a cancelled caller (SIGTERM) stops at once."""
    backoff, started = Backoff(maximum=2.0), time.monotonic()
    while True:
        try:
            return await asyncio.to_thread(
                open_session, "client", (), endpoints, multicast, tls, access
            )
        except zenoh.ZError as exc:
            delay = backoff.next_delay()
            if retry_for is not None and time.monotonic() + delay > started + retry_for:
                raise _unreachable(endpoints, exc, retry_for) from None
            _log_retry(endpoints, started, delay)
            await asyncio.sleep(delay)


def leaf_access(config: Any) -> dict[str, Any] | None:
    """The access_control section of a leaf session (adapter, client, echo, record, a service
    behind a router): its hub relays, the rest is judged by role (docs/design.md §6)."""
    return access_control_for(config, hub=False)


def session_for_client(config: Any, retry_for: float | None = None) -> zenoh.Session:
    """A session for leaf processes (adapters, echo, record, clients): a Zenoh client of
    bus.connect (or bus.listen). Leaf processes are clients, not peers: a listening peer (the
    service) or a router forwards between its clients, while two peers that do not listen
    never meet. Once open, Zenoh itself reconnects when the service or router restarts.
    With bus.access_control the leaf enforces the rights too (`leaf_access`)."""
    bus = config.bus
    return open_client(
        config.bus_endpoints(), bus.multicast_scouting, bus, retry_for, leaf_access(config)
    )


async def session_for_client_async(config: Any, retry_for: float | None = None) -> zenoh.Session:
    """`session_for_client` for async code: never blocks the event loop."""
    bus = config.bus
    return await open_client_async(
        config.bus_endpoints(), bus.multicast_scouting, bus, retry_for, leaf_access(config)
    )


def session_for_service(config: Any) -> zenoh.Session:
    """The service's session as [bus] says: a listening peer (the embedded default), or a
    client of a router, which it waits for like any client. Either way it enforces [bus]
    access control on its links: as a hub when it listens, else as a leaf."""
    bus = config.bus
    if bus.mode == "client":
        return session_for_client(config)  # before the loop runs: blocking is fine here
    access = access_control_for(config, hub=bool(bus.listen))
    return open_session(bus.mode, bus.listen, bus.connect, bus.multicast_scouting, bus, access)


def output_publisher(
    session: zenoh.Session, key: str, local_subscribers: bool = True
) -> zenoh.Publisher:
    """An express publisher of the service's output on `key` (its estimates, corrections).
    Without `local_subscribers` it sends to other sessions only: a session the service opened
    for itself has no subscriber of its own outputs, but its data subscription is a wildcard
    on the cell's prefix (for the publishers' order across keys), which would get each
    message back on Zenoh's callback thread only to drop it: a thread wake-up and the GIL
    taken once more per message."""
    where = None if local_subscribers else zenoh.Locality.REMOTE
    return session.declare_publisher(key, express=True, allowed_destination=where)


class AsyncSubscription:
    """Samples of several key expressions, in arrival order: handed to a function on the
    event loop (`deliver`), or as an async iterator of (key, payload bytes).

    Zenoh runs each subscriber's callback on its own thread, so two subscribers can deliver
    out of order relative to each other. To keep the publisher's order across keys (replay
    relies on it), several keys under one prefix share one wildcard subscriber and are
    filtered here.

    The hand-off: Zenoh's thread appends to a bounded deque (the oldest dropped and counted
    when full) and, when no wake-up is pending already, schedules one on the loop
    (`call_soon_threadsafe`); that wake-up takes what waits. `deliver` runs its function in
    that very callback: no task switch, no future and no second pass of the loop per
    wake-up, which an awaited event costs (docs/performance.md).
    """

    def __init__(
        self, session: zenoh.Session, keys: Sequence[str], maxlen: int = DEFAULT_QUEUE
    ) -> None:
        self._loop = asyncio.get_running_loop()
        self._buf: collections.deque[tuple[str, bytes]] = collections.deque(maxlen=maxlen)
        self._wake = asyncio.Event()
        # a wake-up is scheduled and has not run yet: set on Zenoh's thread, cleared on the
        # loop before it takes the deque (a plain flag: each read or write is atomic under
        # the GIL, and a sample appended after the clear is either taken by that wake-up or
        # finds the flag clear and schedules another)
        self._scheduled = False
        self._closed = False
        self._handler: Callable[[list[tuple[str, bytes]]], None] | None = None
        self._most = DRAIN_MOST
        self._done: asyncio.Future[None] | None = None
        self.dropped = 0
        self._wanted: frozenset[str] | None = None
        keys = list(keys)
        prefixes = {k.rsplit("/", 1)[0] for k in keys}
        if len(keys) > 1 and len(prefixes) == 1 and not any("*" in k for k in keys):
            self._wanted = frozenset(keys)
            keys = [f"{prefixes.pop()}/*"]
        self._subs = [session.declare_subscriber(k, self._on_sample) for k in keys]

    def _on_sample(self, sample: zenoh.Sample) -> None:  # zenoh thread: no zenoh calls, no blocking
        key = str(sample.key_expr)
        if self._wanted is not None and key not in self._wanted:
            return
        buf = self._buf
        if len(buf) == buf.maxlen:
            self.dropped += 1
        buf.append((key, sample.payload.to_bytes()))
        if not self._scheduled:
            self._scheduled = True
            with contextlib.suppress(RuntimeError):  # the loop closed during shutdown
                self._loop.call_soon_threadsafe(self._ready)

    @property
    def pending(self) -> int:
        """Samples received and not yet taken."""
        return len(self._buf)

    def _ready(self) -> None:
        """The wake-up, on the loop: the deliver function gets what waits (at most `most`
        samples; the rest in the loop's next pass, after whatever else is ready, so a backlog
        never holds the loop), or the iterating task is woken."""
        self._scheduled = False
        handler, done = self._handler, self._done
        if handler is None or done is None or done.done():
            self._wake.set()
            return
        buf = self._buf
        n = len(buf)
        if n:
            popleft = buf.popleft
            batch = [popleft()] if n == 1 else [popleft() for _ in range(min(n, self._most))]
            try:
                handler(batch)
            except Exception as exc:  # the deliverer's caller gets it (its task fails)
                self._handler = None
                done.set_exception(exc)
                return
            if buf:  # the rest in the loop's next pass, unless Zenoh's thread asked already
                if not self._scheduled:
                    self._scheduled = True
                    self._loop.call_soon(self._ready)
                return
        if self._closed:
            done.set_result(None)

    async def deliver(
        self, handler: Callable[[list[tuple[str, bytes]]], None], most: int = DRAIN_MOST
    ) -> None:
        """Call `handler` on the event loop with the samples as they arrive, in arrival
        order, as lists of (key, payload): at each wake-up what arrived since, at most `most`
        a call. Returns once `close()` was called and what was received is handed over;
        raises what `handler` raised (nothing is handed over after that). The handler runs
        between the loop's other work, so it must not block. One deliverer at a time."""
        if self._handler is not None:
            raise RuntimeError("this subscription delivers to a handler already")
        self._done = self._loop.create_future()
        self._handler, self._most = handler, max(1, most)
        self._scheduled = True  # what waits already, and a close before this call
        self._loop.call_soon(self._ready)
        try:
            await self._done
        finally:
            self._handler = None

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
        """Undeclare and end the iteration (or `deliver`, once what waits is handed over); a
        second call does nothing (Zenoh refuses to undeclare a subscriber twice)."""
        if self._closed:
            return
        self._closed = True
        for sub in self._subs:
            sub.undeclare()
        self._loop.call_soon_threadsafe(self._ready)


class BlockingSubscription:
    """The same hand-off for plain threads: the callback appends to a bounded deque (oldest
    dropped and counted) and notifies; `get(timeout)` waits in the caller's thread. No user
    code ever runs on Zenoh's threads."""

    def __init__(self, session: zenoh.Session, key: str, maxlen: int = DEFAULT_QUEUE) -> None:
        self._buf: collections.deque[tuple[str, bytes]] = collections.deque(maxlen=maxlen)
        self._ready = threading.Condition()
        self.dropped = 0
        self._sub = session.declare_subscriber(key, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:  # zenoh thread
        with self._ready:
            if len(self._buf) == self._buf.maxlen:
                self.dropped += 1
            self._buf.append((str(sample.key_expr), sample.payload.to_bytes()))
            self._ready.notify()

    def get(self, timeout: float | None) -> tuple[str, bytes] | None:
        """The next (key, payload), or None when nothing arrived within `timeout` seconds."""
        with self._ready:
            if not self._ready.wait_for(lambda: bool(self._buf), timeout):
                return None
            return self._buf.popleft()

    def close(self) -> None:
        self._sub.undeclare()
