"""`AsyncSubscription.deliver`: the service's hand-off from Zenoh's thread to the event loop,
a function called in the loop's wake-up itself. Real Zenoh sessions on the loopback; what is
checked is what was put (every sample, in order), the bound per call, the loop's other work
between the pieces of a backlog, a close that ends the delivery, and a failing handler."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable
from typing import Any

import pytest

from keo_service.bench.procs import free_port
from keo_service.live.bus import DRAIN_MOST, AsyncSubscription, open_session

KEYS = ("keo/t/encoder", "keo/t/tracker")


def _sent(n: int) -> list[tuple[str, bytes]]:
    return [(KEYS[0] if i % 4 == 0 else KEYS[1], f"{i}".encode()) for i in range(n)]


def _with_sessions(body: Callable[[AsyncSubscription, Any], Awaitable[Any]]) -> Any:
    """Run `body(sub, put_all)` in a fresh loop: a listening session subscribed to both keys,
    and `put_all(samples)` that puts them from another session, in a worker thread."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"

    async def main() -> Any:
        listener = open_session("peer", listen=[endpoint])
        talker = open_session("peer", connect=[endpoint])
        try:
            sub = AsyncSubscription(listener, list(KEYS))
            pubs = {k: talker.declare_publisher(k) for k in KEYS}
            await asyncio.sleep(0.5)  # the sessions meet

            def put_all(samples: list[tuple[str, bytes]]) -> Awaitable[None]:
                def put() -> None:
                    for key, payload in samples:
                        pubs[key].put(payload)

                return asyncio.get_running_loop().run_in_executor(None, put)

            return await body(sub, put_all)
        finally:
            talker.close()
            listener.close()

    return asyncio.run(main())


async def _until(got: list[Any], n: int, within_s: float = 30.0) -> None:
    deadline = time.monotonic() + within_s
    while len(got) < n and time.monotonic() < deadline:
        await asyncio.sleep(0.01)


def test_deliver_hands_every_sample_in_order_in_bounded_calls_and_ends_at_close():
    """3000 samples over two keys, put in a burst: the calls, concatenated, are exactly what
    was put, none longer than `most`, fewer calls than samples; `close()` ends `deliver`."""
    sent = _sent(3000)

    async def body(sub: AsyncSubscription, put_all: Any) -> tuple[list[Any], list[int]]:
        got: list[tuple[str, bytes]] = []
        sizes: list[int] = []

        def handler(batch: list[tuple[str, bytes]]) -> None:
            sizes.append(len(batch))
            got.extend(batch)

        delivering = asyncio.ensure_future(sub.deliver(handler, most=50))
        await put_all(sent)
        await _until(got, len(sent))
        sub.close()
        await asyncio.wait_for(delivering, 10)  # returns, does not hang
        return got, sizes

    got, sizes = _with_sessions(body)
    assert got == sent
    assert max(sizes) <= 50
    assert len(sizes) < len(sent)


def test_a_backlog_is_handed_over_in_pieces_with_the_loops_other_work_between():
    """The handler holds the loop at its first call until the other 1999 of 2000 samples
    wait in the queue: the backlog comes in pieces of at most DRAIN_MOST, and another task of
    the loop runs between them (a drain of everything in one go would starve it)."""
    sent = _sent(2000)

    async def body(sub: AsyncSubscription, put_all: Any) -> tuple[list[Any], list[Any]]:
        got: list[tuple[str, bytes]] = []
        calls: list[tuple[int, int]] = []  # (size, ticks of the other task so far)
        ticks = 0

        async def other() -> None:
            nonlocal ticks
            while True:
                ticks += 1
                await asyncio.sleep(0)

        def handler(batch: list[tuple[str, bytes]]) -> None:
            if not got:  # a stall: the loop held until the rest waits in the queue
                deadline = time.monotonic() + 30  # (a loaded machine delivers slowly)
                while sub.pending < len(sent) - len(batch) and time.monotonic() < deadline:
                    time.sleep(0.01)
            calls.append((len(batch), ticks))
            got.extend(batch)

        ticker = asyncio.ensure_future(other())
        delivering = asyncio.ensure_future(sub.deliver(handler))
        await put_all(sent)
        await _until(got, len(sent))
        sub.close()
        await asyncio.wait_for(delivering, 10)
        ticker.cancel()
        return got, calls

    got, calls = _with_sessions(body)
    assert got == sent
    assert max(size for size, _ in calls) <= DRAIN_MOST
    full = [i for i, (size, _) in enumerate(calls) if size == DRAIN_MOST]
    assert full, "the stall left no backlog larger than one piece"
    # Zenoh's thread may schedule a wake-up of its own while a piece is handled (a race of a
    # few bytecodes), so two pieces can meet in one pass of the loop; never three
    for i in full:
        if i + 2 < len(calls):
            assert calls[i + 2][1] > calls[i][1], "no other task ran between three pieces"


def test_a_failing_handler_fails_deliver_and_gets_nothing_more():
    """The handler's exception comes out of `deliver` (the service's data-path task fails
    with it, and its supervisor reports it); the handler is not called again."""
    sent = _sent(20)

    async def body(sub: AsyncSubscription, put_all: Any) -> tuple[int, BaseException | None]:
        calls = 0

        def handler(batch: list[tuple[str, bytes]]) -> None:
            nonlocal calls
            calls += 1
            raise ValueError("broken handler")

        delivering = asyncio.ensure_future(sub.deliver(handler))
        await put_all(sent)
        error = None
        try:
            await asyncio.wait_for(delivering, 20)
        except ValueError as exc:
            error = exc
        await put_all(sent)
        await asyncio.sleep(0.3)
        sub.close()
        return calls, error

    calls, error = _with_sessions(body)
    assert isinstance(error, ValueError)
    assert calls == 1


def test_only_one_deliverer_at_a_time():
    async def body(sub: AsyncSubscription, _put_all: Any) -> None:
        first = asyncio.ensure_future(sub.deliver(lambda batch: None))
        await asyncio.sleep(0)
        with pytest.raises(RuntimeError, match="already"):
            await sub.deliver(lambda batch: None)
        sub.close()
        await asyncio.wait_for(first, 10)

    _with_sessions(body)
