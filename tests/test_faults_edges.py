"""Faults at the edges, real processes: the recorder on a full disk, the Zenoh router killed
and restarted mid-stream. (A host clock step is driven through the clock mapping in
tests/test_clock_step.py: the real clock cannot be stepped from a test.)"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import threading
import time
from pathlib import Path

import msgspec
import pytest

from keo_service.bench.demo import loopback_config
from keo_service.bench.procs import free_port, process_group
from keo_service.io.config import config_to_toml
from keo_service.live.bus import session_for_client
from keo_service.live.messages import EstimateMessage, ServiceStatus, decode, topic
from tests.conftest import wait_until

pytestmark = pytest.mark.e2e


def _play(t0: float, duration: float) -> list[str]:
    return [
        "--scenario",
        "paper-step",
        "--seed",
        "3",
        "--t0",
        repr(t0),
        "--duration",
        repr(duration),
    ]


def _status(session, cell: str) -> ServiceStatus | None:
    for reply in session.get(topic(cell, "status"), timeout=2.0):
        if reply.ok is not None:
            try:  # the service answers with nothing until it has a status
                msg = decode(reply.ok.payload.to_bytes())
            except msgspec.DecodeError:
                continue
            if isinstance(msg, ServiceStatus):
                return msg
    return None


@contextlib.contextmanager
def full_disk(tmp_path: Path):
    """A directory whose disk is full: a 64 kB tmpfs when this process may mount one (root),
    else files that are links to /dev/full (every write fails with ENOSPC, as on a full
    disk). Yields (directory, how)."""
    mount = tmp_path / "small"
    mount.mkdir()
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(mount)],
        capture_output=True,
        check=False,
    )
    if done.returncode == 0:
        try:
            yield mount / "rec", "tmpfs of 64 kB"
        finally:
            subprocess.run(["umount", "-l", str(mount)], check=False)
        return
    out = tmp_path / "rec"
    out.mkdir()
    for name in ("encoder.csv", "tracker.csv"):
        os.symlink("/dev/full", out / name)
    yield out, "links to /dev/full"


def test_recorder_on_a_full_disk_stops_and_says_so_while_the_service_estimates(
    demo_config, tmp_path
):
    config = loopback_config(demo_config)
    cfg = tmp_path / "c.toml"
    cfg.write_text(config_to_toml(config))
    duration = 30.0  # the stream outlasts late adapters on a loaded machine (stopped at the end)
    t0 = time.time() + 4.0
    with full_disk(tmp_path) as (out, how), process_group(tmp_path) as procs:
        procs.start_cell(cfg, _play(t0, duration))
        recorder = procs.start("record", ["record", "--config", str(cfg), "--out", str(out)])
        session = session_for_client(config, retry_for=20)
        try:
            code = recorder.wait(timeout=t0 + duration - time.time())
            stopped_at = time.time()
            assert code == 1, procs.log("record")
            summary = json.loads(procs.log("record").strip().splitlines()[-1])
            assert "No space left on device" in summary["stopped"], summary
            assert "recording stopped" in procs.log("record")
            # the service keeps estimating after the recorder gave up
            first = _status(session, config.cell)
            time.sleep(1.5)
            second = _status(session, config.cell)
            assert first is not None
            assert second is not None
            assert second.counters["published"] > first.counters["published"] + 20
            assert stopped_at < t0 + duration - 1.5, "the disk must fill while data flows"
        finally:
            session.close()
    print(f"\nfull disk ({how}): recorder stopped after {summary['encoder_rows']} encoder and "
          f"{summary['tracker_rows']} tracker rows, {stopped_at - t0:.1f} s into the stream; "
          f"service published {second.counters['published'] - first.counters['published']} "
          "estimates in the 1.5 s after")  # fmt: skip


def _listening(endpoint: str, deadline: float) -> float:
    """When the router's TCP port accepts a connection again."""
    host, port = endpoint.removeprefix("tcp/").rsplit(":", 1)
    while time.time() < deadline:
        with contextlib.suppress(OSError), socket.create_connection((host, int(port)), 0.1):
            return time.time()
        time.sleep(0.01)
    raise AssertionError("the router did not come back")


class Arrivals:
    """Estimates as a user program sees them, with arrival times (a client of the router)."""

    def __init__(self, config) -> None:
        self.session = session_for_client(config, retry_for=20)
        self.times: list[float] = []
        self._lock = threading.Lock()
        self.sub = self.session.declare_subscriber(topic(config.cell, "estimate"), self._on)

    def _on(self, sample) -> None:
        with contextlib.suppress(msgspec.DecodeError):
            if isinstance(decode(sample.payload.to_bytes()), EstimateMessage):
                with self._lock:
                    self.times.append(time.time())

    def first_after(self, t: float) -> float | None:
        with self._lock:
            return next((a for a in self.times if a > t), None)

    def close(self) -> None:
        self.sub.undeclare()
        self.session.close()


def test_router_killed_and_restarted_mid_stream_everything_reconnects(demo_config, tmp_path):
    """Service, adapters and a user's subscriber are all clients of `keo router`; the router
    is killed (SIGKILL) mid-stream and started again on the same port 1 s later."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = loopback_config(demo_config)
    bus = msgspec.structs.replace(config.bus, mode="client", listen=[], connect=[endpoint])
    config = msgspec.structs.replace(config, bus=bus)
    cfg = tmp_path / "c.toml"
    cfg.write_text(config_to_toml(config))
    router = ["router", "--listen", endpoint]
    duration = 16.0
    t0 = time.time() + 4.0
    with process_group(tmp_path) as procs:
        procs.start("router", router)
        procs.start_cell(cfg, _play(t0, duration))
        watcher = Arrivals(config)
        try:
            # killed once estimates flow (the adapters may connect after t0 under load)
            wait_until(lambda: watcher.first_after(t0) is not None, 30, "estimates arrive")
            time.sleep(max(1.0, t0 + 5.0 - time.time()))
            procs.procs["router"].send_signal(signal.SIGKILL)
            procs.procs["router"].wait()
            killed = time.time()
            time.sleep(1.0)
            procs.start("router-again", router)
            started = time.time()
            back = _listening(endpoint, started + 10.0)
            deadline = back + 10.0
            while watcher.first_after(back) is None and time.time() < deadline:
                time.sleep(0.02)
            resumed = watcher.first_after(back)
            silent = [a for a in watcher.times if killed + 0.1 < a < back]
        finally:
            watcher.close()
        for name in ("service", "adapter-encoder", "adapter-tracker"):
            assert procs.procs[name].poll() is None, procs.log(name)
    assert resumed is not None, procs.log("service")
    assert silent == []  # nothing flows without the router
    print(f"\nrouter killed, restarted 1 s later: listening {back - started:.2f} s after its "
          f"start, estimates resumed {resumed - back:.2f} s after it listened")  # fmt: skip
    assert resumed - back < 2.0
