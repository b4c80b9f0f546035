"""Long-running commands stop on SIGINT and SIGTERM with exit 0 and no traceback: `keo echo`
(which once closed its subscription twice and died of zenoh's "Undeclared subscriber") and
`keo mock robot|tracker`, once running and while still starting."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time

import pytest

from keo_service.bench.demo import loopback_config
from keo_service.io.config import config_to_toml
from keo_service.live.bus import open_session
from keo_service.live.messages import JointSample, encode, topic


def _start(args: list[str]) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, "-m", "keo_service.cli", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )


def _listening(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


def _wait(what: str, ready, timeout: float = 60.0) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if ready():
            return
        time.sleep(0.1)
    raise AssertionError(f"{what} did not get ready")


def _stop(proc: subprocess.Popen[bytes], name: str) -> None:
    proc.send_signal(signal.SIGINT if name.endswith("INT") else signal.SIGTERM)


def _start_all(cfg: str, play: list[str]) -> tuple[dict[str, subprocess.Popen[bytes]], list[int]]:
    """Two echoes and two mock robots and trackers (one per signal), and the mock ports."""
    procs = {f"echo {sig}": _start(["echo", "keo/*/encoder", "--config", cfg]) for sig in SIGS}
    ports = []
    for sig in SIGS:
        for device in ("robot", "tracker"):
            ports.append(_free())
            procs[f"mock {device} {sig}"] = _start(
                ["mock", device, *play, "--port", str(ports[-1])]
            )
    return procs, ports


def _signal_while_starting(play: list[str], early: dict[str, subprocess.Popen[bytes]]) -> None:
    """Mocks signalled while they compute their scenario (Pinocchio loaded, the socket not yet
    open): once `keo mock` died of SIGTERM there."""
    for sig in SIGS:
        early[f"early {sig}"] = _start(["mock", "robot", *play, "--port", str(_free())])
    for name, proc in early.items():
        _wait(f"{name} computing", lambda pid=proc.pid: _loaded(pid, "pinocchio"))
        _stop(proc, name)


SIGS = ("INT", "TERM")


@pytest.mark.e2e
def test_echo_and_mocks_exit_0_on_sigint_and_sigterm(demo_config, tmp_path):
    config = loopback_config(demo_config)
    cfg = tmp_path / "c.toml"
    cfg.write_text(config_to_toml(config))
    play = ["--config", str(cfg), "--scenario", "paper-step", "--loop"]
    peer = open_session("peer", listen=config.bus.listen)  # the bus echo subscribes on
    procs: dict[str, subprocess.Popen[bytes]] = {}
    early: dict[str, subprocess.Popen[bytes]] = {}
    try:
        procs, ports = _start_all(str(cfg), play)
        _signal_while_starting(play, early)
        # running: echo prints what it receives, the mocks listen
        sample = encode(JointSample(stamp=1.0, host_ns=1, seq=1, joints=[0.0] * 6))

        def echoed() -> bool:
            peer.put(topic(config.cell, "encoder"), sample)
            return all(_has_line(procs[f"echo {s}"]) for s in SIGS)

        _wait("echo", echoed)
        for port in ports:
            _wait(f"mock on {port}", lambda p=port: _listening(p))
        for name, proc in procs.items():
            _stop(proc, name)
        procs.update(early)
        results = {}
        for name, proc in procs.items():
            _out, err = proc.communicate(timeout=20)
            results[name] = (proc.returncode, err.decode(errors="replace"))
    finally:
        for proc in [*procs.values(), *early.values()]:
            if proc.poll() is None:
                proc.kill()
        peer.close()
    bad = {n: (c, e[-300:]) for n, (c, e) in results.items() if c != 0 or "Traceback" in e}
    assert not bad, bad


_LINES: dict[int, bool] = {}


def _has_line(proc: subprocess.Popen[bytes]) -> bool:
    """Whether the process printed a line (reads one without blocking once it is there)."""
    if _LINES.get(proc.pid):
        return True
    assert proc.stdout is not None
    os.set_blocking(proc.stdout.fileno(), False)
    try:
        data = proc.stdout.read1(65536)  # type: ignore[attr-defined]
    except BlockingIOError:
        data = b""
    if data:
        _LINES[proc.pid] = True
    return bool(data)


def _loaded(pid: int, library: str) -> bool:
    """Whether a process has mapped a shared library whose path contains `library`."""
    try:
        with open(f"/proc/{pid}/maps", encoding="utf-8", errors="replace") as f:
            return library in f.read()
    except OSError:
        return False


def _free() -> int:
    from keo_service.bench.procs import free_port

    return free_port()


def test_an_async_subscription_closes_once():
    import asyncio

    from keo_service.live.bus import AsyncSubscription

    async def main() -> None:
        session = open_session("peer", listen=[])
        try:
            sub = AsyncSubscription(session, ["keo/x/encoder"])
            sub.close()
            sub.close()  # the stop handler and `finally` both close: no ZError
        finally:
            session.close()

    asyncio.run(main())


def test_output_to_a_closed_pipe_ends_quietly():
    """`keo gain ... | head`: the reader takes one line and closes the pipe; keo ends as a Unix
    filter does (128 + SIGPIPE, the code a shell reports for `yes | head`), without the
    BrokenPipeError traceback it once printed, then and again at the interpreter's exit."""
    gains = [str(g) for g in range(1, 3001)]  # ~180 kB: more than a pipe's buffer holds
    proc = subprocess.Popen(
        [sys.executable, "-m", "keo_service.cli", "gain", "--rate", "100", "--gain", *gains],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    assert proc.stdout is not None
    assert proc.stderr is not None
    first = proc.stdout.readline()
    proc.stdout.close()  # what `head -1` does after its line
    err = proc.stderr.read().decode()
    code = proc.wait(timeout=60)
    assert first.startswith(b"rate 100 Hz")
    assert code == 128 + signal.SIGPIPE, err
    assert "Traceback" not in err
    assert "BrokenPipeError" not in err
    assert err == ""


@pytest.mark.e2e
def test_echo_to_a_closed_pipe_ends_quietly(demo_config, tmp_path):
    """`keo echo KEY | head -1` on a live bus: once the reader is gone, the next sample ends
    the echo (128 + SIGPIPE, no traceback) instead of it running on unseen or crashing."""
    config = loopback_config(demo_config)
    cfg = tmp_path / "c.toml"
    cfg.write_text(config_to_toml(config))
    peer = open_session("peer", listen=config.bus.listen)
    proc = _start(["echo", "keo/*/encoder", "--config", str(cfg)])
    try:
        sample = encode(JointSample(stamp=1.0, host_ns=1, seq=1, joints=[0.0] * 6))

        def echoed() -> bool:
            peer.put(topic(config.cell, "encoder"), sample)
            return _has_line(proc)

        _wait("echo", echoed)
        assert proc.stdout is not None
        proc.stdout.close()  # the reader took its line and went

        def ended() -> bool:
            peer.put(topic(config.cell, "encoder"), sample)
            return proc.poll() is not None

        _wait("echo to end", ended, timeout=20.0)
        assert proc.stderr is not None
        err = proc.stderr.read().decode(errors="replace")
    finally:
        if proc.poll() is None:
            proc.kill()
        peer.close()
    assert proc.returncode == 128 + signal.SIGPIPE, err[-500:]
    assert "Traceback" not in err
