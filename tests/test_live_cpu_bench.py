"""The in-process measure of the live path (`bench.live_path`): its cold mode runs the cache
pass before every piece of the loop's work and leaves it out of the figure, and the call
listing counts what `_handle` calls, by name. No timing is asserted here (speed goes
through `keo bench`); what is checked is where the pass runs and what is counted."""

from __future__ import annotations

from typing import Any

import pytest

from keo_service.bench import live_path
from keo_service.bench.demo import loopback_config
from keo_service.io.config import load_config
from keo_service.resources import demo_config_path


@pytest.fixture(scope="module")
def config() -> Any:
    return loopback_config(load_config(str(demo_config_path())))


@pytest.fixture(scope="module")
def wire(config: Any) -> list[tuple[float, str, bytes]]:
    return live_path.wire_samples(config, 0.6)


def test_cooler_passes_over_its_whole_buffer_each_call():
    cooler = live_path.Cooler(0.25)
    buffer = cooler._buffer
    assert len(buffer) == 1 << 18
    buffer[0] = 0
    cooler()
    cooler()
    assert cooler.passes == 2
    # every cache line written: the first byte of each 64-byte line is set
    assert set(buffer[0::64]) == {1}


def test_drive_cools_before_every_wake_up_and_not_inside_one(wire):
    """The relay's place (no service): one cache pass before each wake-up's handler call,
    none during it; every sample handled once, in order."""
    events: list[str] = []
    seen: list[bytes] = []

    def handle(batch: list[tuple[str, bytes]]) -> None:
        events.append("handle")
        seen.extend(payload for _key, payload in batch)

    def cool() -> None:
        events.append("cool")

    ran = live_path.drive(None, wire, handle=handle, cool=cool)
    wake_ups = events.count("handle")
    assert wake_ups > 1
    assert events == ["cool", "handle"] * wake_ups
    assert seen == [payload for _s, _k, payload in wire]
    assert ran["samples"] == len(wire)


def test_drive_cools_before_the_block_intake_and_the_delay_poll_too(config, wire):
    """With the service: the block intake (every 0.1 s of stream) and the delay poll (every
    0.25 s) each come after a cache pass of their own, as a wake-up does."""
    service = live_path.make_service(config)
    events: list[str] = []
    handle, feed = service._handle, service._feed_delay

    def cool() -> None:
        events.append("cool")

    def handle_logged(batch: list[tuple[str, bytes]]) -> None:
        events.append("handle")
        handle(batch)

    def feed_logged() -> None:
        events.append("feed")
        feed()

    service._feed_delay = feed_logged
    live_path.drive(service, wire, handle=handle_logged, cool=cool)
    work = [e for e in events if e != "cool"]
    assert work.count("feed") >= 5  # 0.6 s of stream: the status loop's blocks and the polls
    for i, event in enumerate(events):
        if event != "cool":
            assert events[i - 1] == "cool", f"{event} at {i} ran without a cache pass before it"
    assert service.estimator.counters["estimates"] > 0


def test_call_listing_counts_what_handle_calls_per_estimate(config, wire):
    """The listing's counts per estimate against the wire: the estimator's entry once per
    tracker sample, the decoder once per wire sample, the observer's step once per estimate
    (none is held in the bench's streams); the counting's own call left out."""
    listing = live_path.call_names(config, wire)
    listed, estimates = listing["per_estimate"], listing["estimates"]
    trackers = sum(1 for _s, key, _p in wire if key.endswith("/tracker"))
    assert listed["estimator.py:on_tracker"] == round(trackers / estimates, 3)
    assert listed["Decoder.decode (C)"] == round(len(wire) / estimates, 3)
    assert listed["observer.py:update"] == 1.0
    assert "sys.setprofile (C)" not in listed
