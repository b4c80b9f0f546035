"""A daemon that cannot fail silently: faults injected into a real `keo run` process, an honest
watchdog, SIGTERM in every waiting state, and the client against a live chain."""

from __future__ import annotations

import contextlib
import itertools
import os
import signal
import socket
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable
from pathlib import Path

import msgspec
import pytest

from keo_service import Client, ClientError, EstimateMessage, ServiceStatus, SyncClient
from keo_service.bench.demo import loopback_config
from keo_service.bench.procs import free_port, process_group
from keo_service.io.config import Config, config_to_toml
from keo_service.live.bus import session_for_client
from keo_service.live.messages import TrackerSample, encode, topic
from tests.conftest import wait_for_status

pytestmark = pytest.mark.e2e

# Runs `keo run` in a child with one fault patched in (a test-only monkeypatch, DESIGN of the
# daemon issue): PATCH is executed first, then the real CLI.
RUNNER = """
import sys
{patch}
from keo_service.cli import main
sys.exit(main(["run", "--config", *sys.argv[1:]]))
"""

RAISE_IN_ESTIMATOR = """
from keo_service.core.estimator import Estimator
def broken(self, *args, **kwargs):
    raise RuntimeError("injected fault in the estimator")
Estimator.on_tracker = broken
"""

STALL_CONSUMER = """
import asyncio
from keo_service.live.service import KeoService
async def stuck(self):
    async for _key, _payload in self._sub:
        await asyncio.Event().wait()   # the data path hangs; the event loop stays free
KeoService._consume = stuck
"""


def _config_file(demo_config: Config, tmp_path: Path) -> tuple[Config, Path]:
    config = loopback_config(demo_config)
    path = tmp_path / "c.toml"
    path.write_text(config_to_toml(config))
    return config, path


def _start_patched(
    patch: str,
    cfg: Path,
    log: Path,
    env: dict[str, str] | None = None,
    options: tuple[str, ...] = (),
):
    code = RUNNER.format(patch=textwrap.dedent(patch))
    return subprocess.Popen(
        [sys.executable, "-c", code, str(cfg), *options],
        stdout=log.open("wb"),
        stderr=subprocess.STDOUT,
        env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})},
    )


def _tracker_samples(config: Config, n: int) -> None:
    session = session_for_client(config, retry_for=10)
    try:
        pub = session.declare_publisher(topic(config.cell, "tracker"))
        time.sleep(0.3)  # declaration reaches the service
        for i in range(n):
            t = time.time()
            msg = TrackerSample(
                stamp=t,
                host_ns=time.time_ns(),
                seq=i,
                position=[1.0, 0.0, 1.0],
                quaternion=[1.0, 0.0, 0.0, 0.0],
            )
            pub.put(encode(msg))
            time.sleep(0.01)
    finally:
        session.close()


def _exit_after_fault(
    proc: subprocess.Popen, config: Config, log: Path, fault: Callable[[], None]
) -> tuple[int, float, str]:
    """Once the service answers, `fault()`; then its exit code, seconds from the fault to
    the exit, and its log."""
    try:
        wait_for_status(config)
        fault()
        faulted = time.monotonic()
        rc = proc.wait(timeout=10)
        exited_after = time.monotonic() - faulted
    finally:
        if proc.poll() is None:
            proc.kill()
    return rc, exited_after, log.read_text()


def test_a_fault_in_the_data_path_stops_the_service_with_its_cause(demo_config, tmp_path):
    config, cfg = _config_file(demo_config, tmp_path)
    log = tmp_path / "service.log"
    proc = _start_patched(RAISE_IN_ESTIMATOR, cfg, log)
    rc, exited_after, text = _exit_after_fault(
        proc, config, log, lambda: _tracker_samples(config, 1)
    )
    assert rc == 1, text
    assert exited_after < 2.0, exited_after
    assert "injected fault in the estimator" in text
    assert "keo.service.consume" in text  # the failed task is named
    assert "Traceback" in text


def _rerun_child(service_pid: int, timeout: float = 20.0) -> int:
    """The pid of the Rerun process `keo run --rrd` started."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for entry in Path("/proc").iterdir():
            if not entry.name.isdigit():
                continue
            with contextlib.suppress(OSError):
                stat = (entry / "stat").read_text().rsplit(")", 1)[1].split()
                cmdline = (entry / "cmdline").read_bytes()
                if int(stat[1]) == service_pid and b"keo_service.live.rerun_process" in cmdline:
                    return int(entry.name)
        time.sleep(0.1)
    raise AssertionError("no Rerun process under the service")


def test_a_dead_rerun_process_stops_the_service_with_its_cause(demo_config, tmp_path):
    config, cfg = _config_file(demo_config, tmp_path)
    log = tmp_path / "service.log"
    rrd = tmp_path / "run.rrd"
    proc = _start_patched("", cfg, log, options=("--rrd", str(rrd)))
    rc, exited_after, text = _exit_after_fault(
        proc, config, log, lambda: os.kill(_rerun_child(proc.pid), signal.SIGKILL)
    )
    assert rc == 1, text
    assert exited_after < 2.0, exited_after
    assert "Rerun logging failed" in text
    assert "exited with code -9" in text
    assert "keo.service.viz" in text  # the failed task is named


def test_a_stalled_data_path_withholds_the_watchdog(demo_config, tmp_path):
    config, cfg = _config_file(demo_config, tmp_path)
    sock_path = str(tmp_path / "notify.sock")
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    listener.bind(sock_path)
    listener.settimeout(0.1)
    log = tmp_path / "service.log"
    env = {"NOTIFY_SOCKET": sock_path, "WATCHDOG_USEC": "400000"}
    proc = _start_patched(STALL_CONSUMER, cfg, log, env)

    def pings(seconds: float) -> int:
        n, end = 0, time.monotonic() + seconds
        while time.monotonic() < end:
            with contextlib.suppress(TimeoutError):
                n += listener.recv(4096).decode() == "WATCHDOG=1"
        return n

    try:
        wait_for_status(config)
        idle = pings(1.0)  # no input: idle on purpose, pings go on
        _tracker_samples(config, 5)  # the first sample hangs the data path, the rest wait
        pings(0.5)  # the watchdog period (0.2 s) passes
        stalled = pings(1.5)
        with ClientContext(config) as keo:  # the loop itself still answers
            assert keo.status().cell == config.cell
    finally:
        proc.send_signal(signal.SIGTERM)
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(timeout=5)
        if proc.poll() is None:
            proc.kill()
        listener.close()
    assert idle >= 3, idle
    assert stalled == 0, stalled
    assert "data path stalled" in log.read_text()


def ClientContext(config: Config) -> SyncClient:
    return SyncClient.from_config(config, connect_timeout_s=5.0)


@pytest.mark.parametrize(
    "command",
    [
        ["adapter", "encoder"],
        ["adapter", "tracker"],
        ["echo", "keo/x/estimate"],
        ["record", "--out", "{tmp}/rec"],
        ["status", "--timeout", "30"],
        ["run"],
    ],
    ids=lambda c: " ".join(c[:2]),
)
def test_every_process_stops_within_2_s_of_sigterm_while_its_peer_is_absent(
    demo_config, tmp_path, command
):
    # a client-mode config whose router is not there: everything waits for a peer
    config = loopback_config(demo_config)
    bus = msgspec.structs.replace(
        config.bus, mode="client", connect=[f"tcp/127.0.0.1:{free_port()}"]
    )
    config = msgspec.structs.replace(config, bus=bus)
    cfg = tmp_path / "c.toml"
    cfg.write_text(config_to_toml(config))
    args = [a.replace("{tmp}", str(tmp_path)) for a in command]
    if args[0] == "echo":
        args = [*args, "--config", str(cfg)]
    else:
        args = (
            [*args[:2], "--config", str(cfg), *args[2:]]
            if args[0] == "adapter"
            else [
                args[0],
                "--config",
                str(cfg),
                *args[1:],
            ]
        )
    proc = subprocess.Popen(
        [sys.executable, "-m", "keo_service.cli", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    try:
        time.sleep(3.0)  # imports done, now retrying the absent peer
        assert proc.poll() is None, proc.communicate()[0]
        proc.send_signal(signal.SIGTERM)
        sent = time.monotonic()
        proc.wait(timeout=10)
        took = time.monotonic() - sent
    finally:
        if proc.poll() is None:
            proc.kill()
    assert took < 2.0, (args, took)


async def test_client_against_a_live_chain(demo_config, tmp_path):
    config, cfg = _config_file(demo_config, tmp_path)
    t0 = time.time() + 4.0
    # played longer than the clients need (stopped when they have it): the adapters may
    # connect seconds after t0 on a loaded machine
    play = ["--scenario", "paper-step", "--seed", "2", "--t0", repr(t0), "--duration", "30"]
    with process_group(tmp_path) as procs:
        procs.start_cell(cfg, play)
        endpoint = config.bus.listen[0]
        async with Client(endpoint, cell=config.cell) as keo:
            status = await keo.status(timeout=20)
            assert isinstance(status, ServiceStatus)
            assert status.cell == config.cell
            received: list[EstimateMessage] = []
            async for est in keo.estimates():
                received.append(est)
                if len(received) == 100:
                    break
            latest = await keo.latest()
        with SyncClient(endpoint, cell=config.cell) as sync_keo:
            sync_received = list(itertools.islice(sync_keo.estimates(timeout=5.0), 50))
            sync_status = sync_keo.status()
        procs.close()
    assert all(isinstance(e, EstimateMessage) for e in received)
    assert all(len(e.estimate) == 6 and e.channels[0] == "px" for e in received)
    stamps = [e.stamp for e in received]
    assert stamps == sorted(stamps)
    assert latest is not None
    assert latest.stamp >= stamps[-1]
    assert len(sync_received) == 50
    assert sync_received[0].stamp > stamps[0]
    assert sync_status.health in {"ok", "stale"}, sync_status.health


async def test_client_says_when_no_service_answers():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with pytest.raises(Exception, match="cannot reach the bus"):
        async with Client(endpoint, cell="nobody", connect_timeout_s=0.5):
            pass
    # a bus without a keo service on it: status names the key it asked
    from keo_service.live.bus import open_session

    peer = open_session("peer", listen=[endpoint])
    try:
        async with Client(endpoint, cell="nobody") as keo:
            with pytest.raises(ClientError, match="keo/nobody/status"):
                await keo.status(timeout=0.5)
            assert await keo.latest(timeout=0.3) is None
    finally:
        peer.close()


async def test_a_fault_in_the_recorder_ends_the_recording_with_its_cause(tmp_path, monkeypatch):
    import asyncio

    from keo_service.core.errors import KeoError
    from keo_service.live.bus import open_session
    from keo_service.live.recorder import Recorder, record

    def broken(self, payload: bytes) -> None:
        raise RuntimeError("injected fault in the recorder")

    monkeypatch.setattr(Recorder, "on_payload", broken)
    session = open_session("peer", listen=[f"tcp/127.0.0.1:{free_port()}"])
    try:
        stop = asyncio.Event()
        recording = asyncio.create_task(record(session, "rec", tmp_path, 6, stop))
        await asyncio.sleep(0.3)
        session.put(topic("rec", "encoder"), b"anything")
        with pytest.raises(KeoError, match="injected fault in the recorder"):
            async with asyncio.timeout(2.0):
                await recording
    finally:
        session.close()


def test_rates_of_a_burst_handled_at_one_instant_do_not_crash_the_status():
    """The first encoder sample releases every tracker sample that waited for it: their
    estimates are published at one instant, and the status (10 Hz) once divided by the
    zero span of those ticks and stopped the service (seen under CI load)."""
    from keo_service.live.service import RateMeter

    meter = RateMeter()
    for _ in range(5):
        meter.tick(10.0)
    assert meter.rate(10.0) == 0.0
    meter.tick(10.5)
    assert meter.rate(10.5) == 5 / 0.5
    assert meter.rate(13.0) == 0.0  # nothing for over 2 s
