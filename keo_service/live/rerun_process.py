"""Rerun logging in its own process, so that it never holds the service's GIL.

In the service's process Rerun's calls hold the GIL at every flush (part of that in native
code, which no switch interval preempts): the samples that arrive meanwhile wait, and those
waits became the service's slowest answers (docs/performance.md, "Rerun in its own process").
Here the service only encodes each estimate (msgpack, cheap beside the estimate itself) into
a bounded buffer and writes the buffer to a pipe, a few times a second, without ever
blocking; this module's `main`, run as `python -m keo_service.live.rerun_process`, reads the
pipe and runs the `RerunLogger`.

The pipe carries frames: a 4-byte little-endian length, then the payload. The first payload
is the pickled `(cell, rrd, viewer, options)` from the parent (options: the URDF for its
meshes, the plots' time window); then msgpack arrays, an estimate as `_PipedEstimate` (the
fields of `Estimate`, named as there, in one array after its tag "e"), a status snapshot as
`_PipedStatus` (`["s", {...}]`). End of file is the only stop: the child ignores SIGINT and
SIGTERM (a supervisor that signals the whole group stops the service, and the service closes
the pipe), drains what is left, closes the recording and exits 0. A dead parent closes the
pipe too.
"""

from __future__ import annotations

import contextlib
import logging
import os
import pickle
import select
import signal
import socket
import subprocess
import sys
import time
import urllib.parse
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from keo_service.core.errors import KeoError
from keo_service.core.estimator import Estimate
from keo_service.core.kinematics import Cell
from keo_service.live.systemd import JsonFormatter, setup_logging

__all__ = ["OpenedViewer", "RerunWorker", "main", "open_viewer"]

log = logging.getLogger("keo.rerun")

HEADER = 4  # bytes of a frame's length
WRITE_AT = 16_384  # buffered bytes that trigger a write (about 60 estimates)
MAX_BUFFER = 4 << 20  # buffered bytes at most (about 15 s at 1 kHz); newer estimates dropped
READ_SIZE = 1 << 20
FLUSH_PERIOD_S = 0.1  # the child's flushes to Rerun with a viewer: display rate
# to a file alone, a batch a second: a tenth of the chunks (and their schemas and row
# headers), so a smaller file (docs/viewer.md has the sizes)
FILE_FLUSH_PERIOD_S = 1.0
NICENESS = 10  # added to the child's nice value
# the longest a shutdown waits for the child: below the 10 s a container runtime and most
# supervisors give a stopping process before they kill it
SHUTDOWN_MOST_S = 8.0
VIEWER_KINDS = ("auto", "native", "web")  # what `--viewer` takes besides a URL
VIEWER_START_S = 30.0  # a viewer's gRPC port must accept within this
WEB_SERVER_MEMORY = "512MiB"  # what the web viewer's server keeps for late browsers


def _frame(payload: bytes) -> bytes:
    return len(payload).to_bytes(HEADER, "little") + payload


class _PipedEstimate(msgspec.Struct, array_like=True, tag="e", frozen=True):
    """An `Estimate` on the pipe to the child: its fields, under its names."""

    stamp: float
    measured: list[float] | None
    estimate: list[float]
    flags: tuple[str, ...]
    joints: list[float] | None
    channels: tuple[str, ...]
    encoder_stamp: float | None = None
    device_stamp: float | None = None

    @classmethod
    def of(cls, est: Estimate) -> _PipedEstimate:
        joints = est.joints
        return cls(
            est.stamp,
            est.measured_values(),
            est.estimate_values(),
            est.flags,
            joints.tolist() if isinstance(joints, np.ndarray) else joints,
            est.channels,
            est.encoder_stamp,
            est.device_stamp,
        )

    def to_estimate(self) -> Estimate:
        return Estimate(
            self.stamp,
            self.measured,
            self.estimate,
            self.flags,
            self.encoder_stamp,
            self.channels,
            None if self.joints is None else np.asarray(self.joints, dtype=float),
            self.device_stamp,
        )


class _PipedStatus(msgspec.Struct, array_like=True, tag="s", frozen=True):
    snapshot: dict[str, Any]


class RerunWorker:
    """The service's end: `submit` never blocks and never raises; what does not fit the
    bounded buffer is dropped and counted in `dropped`. A child that dies is reported by
    `failure` (its own error is in the log, on the same stderr) for the service's supervisor.
    """

    def __init__(
        self,
        cell: Cell,
        rrd: Path | None = None,
        viewer: str | None = None,
        max_buffer: int = MAX_BUFFER,
        urdf: str | Path | None = None,
        window_s: float | None = None,
    ) -> None:
        options = {"urdf": None if urdf is None else str(urdf), "window_s": window_s}
        self._init = pickle.dumps((cell, None if rrd is None else str(rrd), viewer, options))
        self._max_buffer = max_buffer
        self._buffer = bytearray()
        self._unsent = 0  # bytes buffered since the last write was tried
        self._encode = msgspec.msgpack.Encoder().encode
        self._proc: subprocess.Popen[bytes] | None = None
        self._fd = -1
        self._failure: BaseException | None = None
        self._closing = False
        self.dropped = 0

    def start(self) -> None:
        # the child logs as the service does (JSON lines under journald)
        formatters = [h.formatter for h in logging.getLogger().handlers]
        log_format = "json" if any(isinstance(f, JsonFormatter) for f in formatters) else "text"
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "keo_service.live.rerun_process", log_format],
            stdin=subprocess.PIPE,
            stdout=subprocess.DEVNULL,
        )
        assert self._proc.stdin is not None
        self._fd = self._proc.stdin.fileno()
        self._buffer[:0] = _frame(self._init)  # first, ahead of anything submitted before
        os.set_blocking(self._fd, False)
        self._write()

    def submit(self, item: Estimate | dict[str, object]) -> None:
        """An estimate, or a status snapshot (plain dict). Never blocks."""
        if isinstance(item, dict):
            payload = self._encode(_PipedStatus(item))
        else:
            payload = self._encode(_PipedEstimate.of(item))
        if len(self._buffer) + HEADER + len(payload) > self._max_buffer:
            self.dropped += 1
            return
        self._buffer += _frame(payload)
        self._unsent += HEADER + len(payload)
        # one write per WRITE_AT bytes submitted, also while a backlog waits for the child (a
        # child still starting, or one that cannot keep up): not a refused write per estimate
        if self._unsent >= WRITE_AT or isinstance(item, dict):
            self._write()

    def _write(self) -> None:
        """As much of the buffer as the pipe takes now."""
        self._unsent = 0
        if self._fd < 0 or not self._buffer or self._failure is not None:
            return
        try:
            written = os.write(self._fd, self._buffer)
        except BlockingIOError:
            return
        except OSError as exc:  # the child is gone (BrokenPipeError)
            self._failure = exc
            self._buffer.clear()
            return
        del self._buffer[:written]

    @property
    def failure(self) -> BaseException | None:
        """Why the child is gone (its exit code, also when a write found the pipe broken
        first), or None."""
        proc = self._proc
        if proc is not None and not self._closing and not isinstance(self._failure, RuntimeError):
            code = proc.poll()
            if code is not None:
                failure = RuntimeError(
                    f"the Rerun logging process exited with code {code}; its error is logged above"
                )
                failure.__cause__ = self._failure  # a broken pipe, if a write saw it first
                self._failure = failure
        return self._failure

    def close(self, timeout: float = 1.5, most: float = SHUTDOWN_MOST_S) -> None:
        """Write what is buffered, close the pipe and wait for the child to finish the
        recording; a child that takes longer is killed, with a warning.

        Args:
            timeout: twice the time the buffer's writing waits for a child that reads
                nothing (a child still starting); each write the child takes starts that wait
                anew, so a child that is slow (niced, on a loaded machine) but reading gets
                its whole backlog.
            most: the whole close never takes longer than this (a supervisor's stop
                timeout is the next limit).
        """
        self._closing = True
        proc = self._proc
        if proc is None or proc.stdin is None:
            return
        start = time.monotonic()
        end = start + most
        drain_until = min(end, start + timeout / 2)
        while self._buffer and self._failure is None and time.monotonic() < drain_until:
            select.select([], [self._fd], [], max(0.0, drain_until - time.monotonic()))
            left = len(self._buffer)
            self._write()
            if len(self._buffer) < left:  # progress: the child reads, give it time again
                drain_until = min(end, time.monotonic() + timeout / 2)
        if self._buffer:
            log.warning(
                "Rerun logging: %d bytes of estimates not written at shutdown", len(self._buffer)
            )
        with contextlib.suppress(OSError):  # the child may be gone already
            proc.stdin.close()
        # the child's exit: up to `most` (its progress is not visible from here; a slow child
        # still writing the file's end is the usual case, a hung one the rare)
        try:
            proc.wait(max(0.1, end - time.monotonic()))
        except subprocess.TimeoutExpired:
            log.warning(
                "Rerun logging did not finish within %.1f s of the shutdown; stopped, its file "
                "may lack the end",
                time.monotonic() - start,
            )
            proc.kill()
            proc.wait()


@dataclass
class OpenedViewer:
    """A viewer keo started: `grpc_url` is where the recording goes (`--viewer URL`'s
    meaning), `url` what a person opens (the web page, or the gRPC URL of a native viewer)."""

    kind: str
    grpc_url: str
    url: str
    process: subprocess.Popen[bytes] | None

    def close(self) -> None:
        """Stop a web viewer's server (a native viewer's window stays: the person closes it)."""
        proc = self.process
        if proc is None or self.kind != "web":
            return
        # the whole group: `python -m rerun_cli` runs Rerun's binary as its own child
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGTERM)
        deadline = time.monotonic() + 5.0
        while _group_alive(proc.pid) and time.monotonic() < deadline:
            proc.poll()  # reaps the wrapper once it exits
            time.sleep(0.05)
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


def _group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def has_display() -> bool:
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def grpc_url(host: str, port: int) -> str:
    return f"rerun+http://{host}:{port}/proxy"


def web_url(host: str, web_port: int, grpc: str) -> str:
    return f"http://{host}:{web_port}/?url={urllib.parse.quote(grpc, safe='')}"


def _accepts(host: str, port: int) -> bool:
    with contextlib.suppress(OSError), socket.create_connection((host, port), timeout=0.5):
        return True
    return False


def open_viewer(
    kind: str = "auto", grpc_port: int = 9876, web_port: int = 9090, bind: str = "127.0.0.1"
) -> OpenedViewer:
    """Start Rerun's viewer for a live stream: `native` (a window; `auto` picks it when a
    display is there) listening on `grpc_port`, or `web`: Rerun's server for the web viewer,
    gRPC on `grpc_port` and the page on `web_port`, bound to `bind` (loopback by default:
    from another machine, tunnel both ports). Returns once the gRPC port accepts (a sink
    that connects earlier waits seconds and then fails). A native viewer already listening
    on the port is used as it is. Raises KeoError when the viewer does not come up."""
    if kind not in VIEWER_KINDS:
        raise KeoError(f"--viewer: '{kind}' is none of {', '.join(VIEWER_KINDS)} nor a URL")
    if kind == "auto":
        kind = "native" if has_display() else "web"
    host = "127.0.0.1" if bind in ("0.0.0.0", "::") else bind
    grpc = grpc_url(host, grpc_port)
    if kind == "native" and _accepts(host, grpc_port):
        log.info("a Rerun viewer already listens on %s; streaming to it", grpc)
        return OpenedViewer(kind, grpc, grpc, None)
    cli = [sys.executable, "-m", "rerun_cli", "--bind", bind, "--port", str(grpc_port)]
    if kind == "web":
        cli += ["--serve-web", "--web-viewer-port", str(web_port)]
        cli += ["--server-memory-limit", WEB_SERVER_MEMORY]
    else:
        cli += ["--expect-data-soon"]
    proc = subprocess.Popen(
        cli,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        start_new_session=True,  # a group of its own: a window outlives keo, and close()
    )  # stops a web server's group (the wrapper and Rerun's binary)
    deadline = time.monotonic() + VIEWER_START_S
    while not _accepts(host, grpc_port):
        if proc.poll() is not None:
            raise KeoError(f"the Rerun viewer exited with code {proc.returncode} at start")
        if time.monotonic() > deadline:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
            raise KeoError(f"the Rerun viewer did not listen on {grpc} within {VIEWER_START_S:g} s")
        time.sleep(0.1)
    url = web_url(host, web_port, grpc) if kind == "web" else grpc
    return OpenedViewer(kind, grpc, url, proc)


# ---- the child -------------------------------------------------------------------------------


class _Frames:
    """Frames out of a byte stream that arrives in arbitrary pieces."""

    def __init__(self) -> None:
        self._data = bytearray()

    def feed(self, data: bytes) -> list[bytes]:
        self._data += data
        out = []
        start = 0
        while len(self._data) - start >= HEADER:
            size = int.from_bytes(self._data[start : start + HEADER], "little")
            if len(self._data) - start - HEADER < size:
                break
            out.append(bytes(self._data[start + HEADER : start + HEADER + size]))
            start += HEADER + size
        del self._data[:start]
        return out


def _read_frames(fd: int, frames: _Frames, timeout: float | None) -> list[bytes] | None:
    """Whole frames read within `timeout` (possibly none), or None at end of file."""
    ready, _w, _x = select.select([fd], [], [], timeout)
    if not ready:
        return []
    data = os.read(fd, READ_SIZE)
    if not data:
        return None
    return frames.feed(data)


def _serve(fd: int) -> None:
    from keo_service.live.rerun_logger import WINDOW_S, RerunLogger  # rerun: only in this process

    frames = _Frames()
    pending: list[bytes] = []
    while not pending:
        got = _read_frames(fd, frames, None)
        if got is None:
            return  # closed before it began
        pending = got
    cell, rrd, viewer, options = pickle.loads(pending.pop(0))  # from our own parent
    window_s = options.get("window_s")
    sink = RerunLogger(
        cell,
        rrd=None if rrd is None else Path(rrd),
        viewer=viewer,
        urdf=options.get("urdf"),
        window_s=WINDOW_S if window_s is None else window_s,
    )
    # set up (Rerun imported, the recording opened) on a share of the CPU, then idle time
    # only: under SCHED_IDLE on a loaded machine the setup itself could take longer than a
    # short run, and the stop found a process that had read nothing
    _yield_to_the_data_path()
    decode = msgspec.msgpack.Decoder(_PipedEstimate | _PipedStatus).decode
    period = FLUSH_PERIOD_S if viewer is not None else FILE_FLUSH_PERIOD_S
    next_flush = time.monotonic() + period
    while True:
        for payload in pending:
            item = decode(payload)
            if isinstance(item, _PipedStatus):  # every snapshot: rates, events at its period
                sink.add_status(item.snapshot)
                continue
            sink.add(item.to_estimate())
        if time.monotonic() >= next_flush:
            sink.flush()
            next_flush = time.monotonic() + period
        got = _read_frames(fd, frames, max(0.0, next_flush - time.monotonic()))
        if got is None:
            break
        pending = got
    sink.close()


def _share_less() -> None:
    """While the process sets up: a real-time policy inherited from the service (systemd's
    CPUSchedulingPolicy) dropped, and a nice value, so that it shares a core less than the
    data path but still gets on."""
    with contextlib.suppress(OSError, AttributeError):
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    with contextlib.suppress(OSError):
        os.nice(NICENESS)


def _yield_to_the_data_path() -> None:
    """The display is worth less than the estimates: once set up, this process runs only on
    time no other process wants (SCHED_IDLE: a waking service, adapter or subscriber takes
    the core at once, where a nice value only shares it less). Set on every thread there is
    (the imports started some: numpy's BLAS pool; the recording its own); threads started
    later inherit it. Where the policy is refused, the nice value stays."""
    with contextlib.suppress(OSError, AttributeError):
        for task in os.listdir("/proc/self/task"):
            with contextlib.suppress(ProcessLookupError):  # a thread that ended meanwhile
                os.sched_setscheduler(int(task), os.SCHED_IDLE, os.sched_param(0))


def main() -> int:
    # the parent decides when this ends, by closing the pipe (see the module's docstring)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    _share_less()
    setup_logging(fmt=sys.argv[1] if len(sys.argv) > 1 else "text")
    try:
        _serve(sys.stdin.fileno())
    except Exception as exc:  # logged with its cause; the parent sees the exit code
        log.error("Rerun logging failed: %s: %s", type(exc).__name__, exc, exc_info=exc)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
