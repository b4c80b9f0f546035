"""keo's client API: what a user program needs to follow a running `keo run`.

    async with Client("tcp/127.0.0.1:7447", cell="demo") as keo:
        async for est in keo.estimates():      # EstimateMessage: stamp, measured, estimate, flags
            ...
        latest = await keo.latest()            # the service's latest estimate (a query)
        status = await keo.status()            # ServiceStatus

    with SyncClient("tcp/127.0.0.1:7447", cell="demo") as keo:   # scripts, no asyncio
        for est in keo.estimates(timeout=5.0):
            ...

Only an endpoint and the cell's name are needed (no URDF, no config file); `from_config` takes
both from a keo config. Samples reach the caller through a bounded queue: Zenoh's threads
only append (the oldest sample is dropped and counted in `dropped` when the caller falls
behind); the caller's code runs on its own loop or thread, never on Zenoh's.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator, Iterator, Sequence
from pathlib import Path
from typing import Any, Self, TypeVar

import msgspec
import zenoh

from keo_service.core.errors import KeoError
from keo_service.io.config import Config, load_config
from keo_service.live.bus import (
    AsyncSubscription,
    BlockingSubscription,
    leaf_access,
    open_client,
    open_client_async,
)
from keo_service.live.messages import (
    AdapterStatus,
    EstimateMessage,
    Message,
    ServiceStatus,
    decode,
    topic,
)

__all__ = ["Client", "ClientError", "SyncClient"]

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
DEFAULT_QUEUE = 1000

_M = TypeVar("_M", bound=msgspec.Struct)


class ClientError(KeoError):
    """The bus or the service did not answer as expected.

    Its message says what was asked, where (the endpoint or key) and what was expected, so
    that a script can print it as it is. A `KeoError`: `except KeoError` catches it too.
    """


def _endpoints(endpoint: str | Sequence[str]) -> list[str]:
    return [endpoint] if isinstance(endpoint, str) else list(endpoint)


def _key(cell: str, channel: str) -> str:
    """A keo channel name ("encoder", "tracker", "estimate", ...) or a full key expression."""
    return channel if "/" in channel else topic(cell, channel)


def _decode_as(payload: bytes, kind: type[_M]) -> _M | None:
    try:
        msg = decode(payload)
    except msgspec.DecodeError:
        return None
    return msg if isinstance(msg, kind) else None


def _query(session: zenoh.Session, key: str, kind: type[_M], timeout: float) -> _M | None:
    """The first reply on `key` that decodes as `kind`, asking again until `timeout`."""
    deadline = time.monotonic() + timeout
    while True:
        remaining = deadline - time.monotonic()
        for reply in session.get(key, timeout=max(0.05, min(1.0, remaining))):
            if reply.ok is not None:
                msg = _decode_as(reply.ok.payload.to_bytes(), kind)
                if msg is not None:
                    return msg
        if time.monotonic() >= deadline:
            return None
        time.sleep(min(0.1, max(0.0, deadline - time.monotonic())))


def query_adapters(session: zenoh.Session, cell: str, timeout: float) -> dict[str, AdapterStatus]:
    """Each adapter's own status (keo/<cell>/adapter/<name>/status): its state, rate,
    counters and newest reject messages, by adapter name, sorted.

    Args:
        session: an open Zenoh session on the cell's bus.
        cell: the config's `cell`.
        timeout: seconds to wait for the answers; adapters that do not answer within it are
            missing, and an answer that is not an adapter's status is left out.
    """
    out: dict[str, AdapterStatus] = {}
    for reply in session.get(topic(cell, "adapter/*/status"), timeout=timeout):
        if reply.ok is None:
            continue
        try:
            doc = AdapterStatus.from_json(reply.ok.payload.to_bytes())
        except msgspec.DecodeError:
            continue
        out[doc.adapter] = doc
    return dict(sorted(out.items()))


class _Settings(msgspec.Struct, frozen=True):
    endpoints: list[str]
    cell: str
    queue_size: int
    connect_timeout_s: float | None
    multicast: bool = False
    tls: Any = None
    access: dict[str, Any] | None = None  # [bus] access control, as a leaf enforces it

    @classmethod
    def from_config(cls, config: Config, **kw: Any) -> _Settings:
        return cls(
            endpoints=config.bus_endpoints(),
            cell=config.cell,
            queue_size=kw.pop("queue_size", DEFAULT_QUEUE),
            connect_timeout_s=kw.pop("connect_timeout_s", 20.0),
            multicast=config.bus.multicast_scouting,
            tls=config.bus,
            access=leaf_access(config),
        )


def _config(config: Config | str | Path) -> Config:
    return config if isinstance(config, Config) else load_config(config)


class _ClientBase:
    """What both clients share: where the service is and how much to buffer."""

    def __init__(
        self,
        endpoint: str | Sequence[str] = DEFAULT_ENDPOINT,
        *,
        cell: str = "cell1",
        queue_size: int = DEFAULT_QUEUE,
        connect_timeout_s: float | None = 20.0,
    ) -> None:
        self._settings = _Settings(_endpoints(endpoint), cell, queue_size, connect_timeout_s)
        self._session: zenoh.Session | None = None
        self._subscriptions: list[AsyncSubscription] = []
        self._dropped_closed = 0

    @classmethod
    def from_config(cls, config: Config | str | Path, **kw: Any) -> Self:
        """A client for the cell of a keo config, so a script needs no endpoint of its own.

        Args:
            config: a config file's path, or a loaded `Config`; its `bus.connect` (else
                `bus.listen`), `cell`, TLS and access settings are used.
            **kw: `queue_size` and `connect_timeout_s` (seconds) as for the constructor.

        Returns:
            The client, not yet open (use it as a context manager).

        Raises:
            ConfigError: the config cannot be read (naming the key).
        """
        client = cls(**kw)
        client._settings = _Settings.from_config(_config(config), **kw)
        return client

    @property
    def cell(self) -> str:
        """The cell whose keys (keo/<cell>/...) the client reads."""
        return self._settings.cell

    @property
    def dropped(self) -> int:
        """Samples dropped because the caller iterated more slowly than they arrived."""
        return self._dropped_closed + sum(s.dropped for s in self._subscriptions)

    def _open_session(self) -> zenoh.Session:
        if self._session is None:
            raise ClientError(f"use the {type(self).__name__} inside its `with` block")
        return self._session


class Client(_ClientBase):
    """An async context manager that owns one Zenoh client session and its subscriptions
    (`async with Client(...) as keo:`), so that closing it ends every iteration it started.

    Args:
        endpoint: where the service (or a router) listens, e.g. "tcp/127.0.0.1:7447", or a
            list of such endpoints.
        cell: the cell whose keys are read (the config's `cell`).
        queue_size: samples buffered per iteration before the oldest is dropped (counted in
            `dropped`): a slow reader never holds up the bus.
        connect_timeout_s: seconds to keep trying to reach the bus (None: until it answers).

    Raises:
        ClientError: on entering, when the bus cannot be reached within
            `connect_timeout_s` (the text names the endpoint and the keys to check).
    """

    async def __aenter__(self) -> Self:
        if self._session is not None:
            raise ClientError("this Client is already open (it is not re-entrant)")
        s = self._settings
        try:
            self._session = await open_client_async(
                s.endpoints, s.multicast, s.tls, retry_for=s.connect_timeout_s, access=s.access
            )
        except KeoError as exc:
            raise ClientError(str(exc)) from None
        return self

    async def __aexit__(self, *exc: object) -> None:
        for sub in self._subscriptions:
            self._dropped_closed += sub.dropped
            sub.close()
        self._subscriptions.clear()
        session, self._session = self._session, None
        if session is not None:
            await asyncio.to_thread(session.close)

    async def samples(self, channel: str) -> AsyncIterator[Message]:
        """Every decodable keo message on a channel, in arrival order; what is not a keo
        message (a foreign payload on a wildcard key) is skipped.

        Args:
            channel: "encoder", "tracker", "estimate", "robot_status", "correction", or a
                full key expression.

        Returns:
            An async iterator of the messages (`keo_service.live.messages`, SI units).
        """
        sub = AsyncSubscription(
            self._open_session(), [_key(self.cell, channel)], maxlen=self._settings.queue_size
        )
        self._subscriptions.append(sub)
        try:
            async for _key_expr, payload in sub:
                try:
                    yield decode(payload)
                except msgspec.DecodeError:
                    continue  # a foreign payload on a wildcard key: not ours to type
        finally:
            if sub in self._subscriptions:
                self._subscriptions.remove(sub)
                self._dropped_closed += sub.dropped
                sub.close()

    async def estimates(self) -> AsyncIterator[EstimateMessage]:
        """The service's estimates as they are published (`stamp` s; `measured`, `estimate`:
        m and rad, px py pz rx ry rz)."""
        async for msg in self.samples("estimate"):
            if isinstance(msg, EstimateMessage):
                yield msg

    async def latest(self, timeout: float = 2.0) -> EstimateMessage | None:
        """The service's latest estimate, for a client that joins late.

        Args:
            timeout: seconds to wait for the answer.

        Returns:
            The estimate, or None when the service has none yet or does not answer.
        """
        session = self._open_session()
        return await asyncio.to_thread(
            _query, session, topic(self.cell, "estimate"), EstimateMessage, timeout
        )

    async def adapters(self, timeout: float = 2.0) -> dict[str, AdapterStatus]:
        """Each adapter's own status, asked of the adapters themselves.

        Args:
            timeout: seconds to wait for the answers.

        Returns:
            The status by adapter name ("encoder", "tracker"); an adapter that does not
            answer within `timeout` is missing.
        """
        session = self._open_session()
        return await asyncio.to_thread(query_adapters, session, self.cell, timeout)

    async def status(self, timeout: float = 5.0) -> ServiceStatus:
        """The service's status: health, rates, the delay in use, counters, adapters.

        Args:
            timeout: seconds to wait for the answer.

        Returns:
            The status (`ServiceStatus`).

        Raises:
            ClientError: no service answered within `timeout`.
        """
        session = self._open_session()
        key = topic(self.cell, "status")
        status = await asyncio.to_thread(_query, session, key, ServiceStatus, timeout)
        if status is None:
            raise ClientError(f"no keo service answered on {key} within {timeout:g} s")
        return status


class SyncClient(_ClientBase):
    """`Client` for scripts without asyncio: a context manager (`with SyncClient(...) as
    keo:`) that owns one Zenoh client session. Iteration blocks the caller's thread, never
    Zenoh's: samples wait in a bounded queue until the caller takes them.

    Args:
        endpoint: where the service (or a router) listens, e.g. "tcp/127.0.0.1:7447", or a
            list of such endpoints.
        cell: the cell whose keys are read (the config's `cell`).
        queue_size: samples buffered per iteration before the oldest is dropped (counted in
            `dropped`): a slow reader never holds up the bus.
        connect_timeout_s: seconds to keep trying to reach the bus (None: until it answers).

    Raises:
        ClientError: on entering, when the bus cannot be reached within
            `connect_timeout_s` (the text names the endpoint and the keys to check).
    """

    def __enter__(self) -> Self:
        s = self._settings
        try:
            self._session = open_client(
                s.endpoints, s.multicast, s.tls, retry_for=s.connect_timeout_s, access=s.access
            )
        except KeoError as exc:
            raise ClientError(str(exc)) from None
        return self

    def __exit__(self, *exc: object) -> None:
        session, self._session = self._session, None
        if session is not None:
            session.close()

    def samples(self, channel: str, timeout: float | None = None) -> Iterator[Message]:
        """Messages on a channel or key expression, as `Client.samples`.

        Args:
            channel: a channel name or a full key expression.
            timeout: the iteration ends when nothing arrived for this many seconds (None:
                never).

        Returns:
            An iterator of the messages.
        """
        sub = BlockingSubscription(
            self._open_session(), _key(self.cell, channel), maxlen=self._settings.queue_size
        )
        try:
            while (item := sub.get(timeout)) is not None:
                try:
                    yield decode(item[1])
                except msgspec.DecodeError:
                    continue
        finally:
            self._dropped_closed += sub.dropped
            sub.close()

    def estimates(self, timeout: float | None = None) -> Iterator[EstimateMessage]:
        """The service's estimates as they are published, as `Client.estimates`.

        Args:
            timeout: the iteration ends when no estimate arrived for this many seconds
                (None: never).

        Returns:
            An iterator of the estimates (`stamp` s; `measured`, `estimate`: m and rad,
            px py pz rx ry rz).
        """
        for msg in self.samples("estimate", timeout):
            if isinstance(msg, EstimateMessage):
                yield msg

    def latest(self, timeout: float = 2.0) -> EstimateMessage | None:
        """The service's latest estimate, for a script that joins late, as `Client.latest`.

        Args:
            timeout: seconds to wait for the answer.

        Returns:
            The estimate, or None when the service has none yet or does not answer.
        """
        return _query(self._open_session(), topic(self.cell, "estimate"), EstimateMessage, timeout)

    def adapters(self, timeout: float = 2.0) -> dict[str, AdapterStatus]:
        """Each adapter's own status, asked of the adapters themselves, as `Client.adapters`.

        Args:
            timeout: seconds to wait for the answers.

        Returns:
            The status by adapter name ("encoder", "tracker"); an adapter that does not
            answer within `timeout` is missing.
        """
        return query_adapters(self._open_session(), self.cell, timeout)

    def status(self, timeout: float = 5.0) -> ServiceStatus:
        """The service's status (health, rates, the delay in use, counters, adapters), as
        `Client.status`.

        Args:
            timeout: seconds to wait for the answer.

        Returns:
            The status (`ServiceStatus`).

        Raises:
            ClientError: no service answered within `timeout` seconds.
        """
        key = topic(self.cell, "status")
        status = _query(self._open_session(), key, ServiceStatus, timeout)
        if status is None:
            raise ClientError(f"no keo service answered on {key} within {timeout:g} s")
        return status
