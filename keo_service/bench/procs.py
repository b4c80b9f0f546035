"""Start keo's own commands as child processes and stop them cleanly (demo, tests, bench)."""

from __future__ import annotations

import collections
import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

_GIVEN: collections.deque[int] = collections.deque(maxlen=256)  # the ports handed out last


def free_port() -> int:
    """A TCP port free on the loopback now, and none of the last ports this process was
    given: the kernel may hand the same port to two binds in a row once the first socket is
    closed, and two endpoints of one test then collide ("Address already in use")."""
    for _ in range(64):
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.bind(("127.0.0.1", 0))
            port = int(s.getsockname()[1])
        if port not in _GIVEN:
            _GIVEN.append(port)
            return port
    raise OSError("no free loopback port that was not just handed out (64 tries)")


class ProcessGroup:
    """Child processes that are all stopped (SIGTERM, then SIGKILL) when the group closes."""

    def __init__(self, log_dir: Path) -> None:
        self.log_dir = log_dir
        self.procs: dict[str, subprocess.Popen[bytes]] = {}

    def start(
        self, name: str, args: Sequence[str], module: str | None = "keo_service.cli"
    ) -> subprocess.Popen[bytes]:
        """`python -m module args` (module None: `python args`, e.g. ["-c", code]), its output
        in <log_dir>/<name>.log, unbuffered so that it can be read while it runs."""
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        command = [sys.executable, *(["-m", module] if module else []), *args]
        with (self.log_dir / f"{name}.log").open("wb") as log:
            proc = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, env=env)
        self.procs[name] = proc
        return proc

    def start_cell(
        self,
        config: Path,
        play: Sequence[str],
        service: Sequence[str] = (),
        tracker: Sequence[str] = (),
        relay_only: bool = False,
        robot: Sequence[str] = (),
        relay_math: bool = False,
        service_python: Sequence[str] = (),
    ) -> None:
        """The whole chain of one cell: service, mock robot and tracker playing `play`, and
        both adapters (names: service, mock-robot, mock-tracker, adapter-encoder/-tracker).
        `relay_only`: the bench's pass-through relay stands where the service would;
        `relay_math`: with the naive floor's math per tracker pose (`bench.relay --math`).
        `service_python`: the interpreter arguments that run keo's CLI in the service's
        process instead of `-m keo_service.cli` (a profiler: `["-c", CODE, ...]`); `run` and
        the service's arguments follow them."""
        cfg = ["--config", str(config)]
        if relay_only or relay_math:
            math = ["--math"] if relay_math else []
            self.start("service", [*cfg, *math], module="keo_service.bench.relay")
        elif service_python:
            args = [*service_python, "run", *cfg, *service]
            self.start("service", args, module=None)
        else:
            self.start("service", ["run", *cfg, *service])
        self.start("mock-robot", ["mock", "robot", *cfg, *play, *robot])
        self.start("mock-tracker", ["mock", "tracker", *cfg, *play, *tracker])
        self.start("adapter-encoder", ["adapter", "encoder", *cfg])
        self.start("adapter-tracker", ["adapter", "tracker", *cfg])

    def stop(self, name: str, timeout: float = 3.0) -> int | None:
        proc = self.procs.pop(name)
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        return proc.returncode

    def close(self, timeout: float = 3.0) -> dict[str, int | None]:
        """Stop every process still in the group: SIGTERM to all at once, SIGKILL to any still
        running `timeout` s later."""
        for proc in self.procs.values():
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + timeout
        codes = {}
        for name, proc in self.procs.items():
            try:
                proc.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            codes[name] = proc.returncode
        self.procs.clear()
        return codes

    def log(self, name: str) -> str:
        path = self.log_dir / f"{name}.log"
        return path.read_text(errors="replace") if path.exists() else ""


@contextlib.contextmanager
def process_group(log_dir: Path) -> Iterator[ProcessGroup]:
    group = ProcessGroup(log_dir)
    try:
        yield group
    finally:
        group.close()
