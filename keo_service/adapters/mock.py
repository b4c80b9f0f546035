"""What every mock device shares: the `MockDevice` protocol (its lifecycle), the settings one
is built from (`MockSettings`, one unit per quantity) and `build_mock`, which asks the protocol
table (io.protocols) which mock plays a device's protocol.

`keo mock` and the tests build mocks through here, so that the command knows no protocol by
name: each mock module offers one builder per protocol, `(settings, config, run) -> MockDevice`,
and the table's row names it.
"""

from __future__ import annotations

import asyncio
import logging
import time
from typing import Any, Literal, Protocol, runtime_checkable

import msgspec

from keo_service.adapters.select import mock_factory
from keo_service.io.config import Config
from keo_service.io.protocols import protocol_for

__all__ = ["MockDevice", "MockSettings", "TaskMock", "TcpMockServer", "build_mock"]

log = logging.getLogger("keo.mock")


@runtime_checkable
class MockDevice(Protocol):
    """A simulated device playing a scenario on its real wire format.

    `play_until`: wall time (s since the epoch) after which it sends nothing more (None: no
    limit). `start` opens its socket (or session) and begins playing at `t0`; `close` stops
    it; `summary` is what it saw, for the command to print as one JSON line (None: nothing to
    say: the TCP servers and the ROS 2 drivers).
    """

    play_until: float | None

    async def start(self) -> None: ...

    async def close(self) -> None: ...

    def summary(self) -> dict[str, object] | None: ...


class MockSettings(msgspec.Struct, frozen=True, kw_only=True):
    """How a mock plays, for any protocol; each knob is read by the mocks it applies to.

    Times in seconds (an instant: seconds since the epoch) unless the name says ms; the
    device clock's offset in seconds for every protocol.
    """

    host: str  # where a server listens, or where a UDP controller sends ("": the config's)
    port: int  # 0: the config's, or the protocol's default (through build_mock)
    device: Literal["robot", "tracker"] = "robot"  # for build_mock: which device plays
    protocol: str = ""  # for build_mock: the row of the protocol table whose mock plays
    t0: float | None = None  # wall time of scenario time 0 (None: 0.5 s after the start)
    loop: bool = False  # play the scenario again every period_s
    period_s: float | None = None  # None: the last row's time plus a little
    play_until: float | None = None
    seed: int = 0
    # a row that goes out late describes the instant it goes out (False: as planned)
    resample: bool = True
    # delivery stalls (rtde, line): longest stall and the mean time between them
    late_ms: float = 0.0
    burst_every_s: float = 0.0
    # the device's own clock: its reading at scenario time 0 and its rate error
    clock_offset_s: float | None = None  # None: the mock's default
    clock_drift_ppm: float = 0.0
    max_hz: float = 500.0  # rtde: 500 on e-Series, 125 on CB3
    # kuka_rsi, abb_egm: the controller's cycle, its send jitter, late answers before a stop
    cycle_ms: float = 4.0
    jitter_ms: float = 0.0
    max_late: int = 100
    # the line-protocol tracker: device time = wall clock at sending (latency benchmarks),
    # (start, seconds) of a broken beam, (at, step) of a jump of its clock, its own
    # free-running clock (offset s, drift ppm)
    wall_clock: bool = False
    beam_break: tuple[float, float] | None = None
    clock_step: tuple[float, float] | None = None
    device_clock: tuple[float, float] | None = None


def build_mock(settings: MockSettings, config: Config, run: Any) -> MockDevice:
    """The mock of `settings.protocol` for `settings.device`, playing the simulated `run`
    (`sim.simulate.SimulatedRun`: its encoder and tracker tracks) on the config's cell."""
    row = protocol_for(settings.device, settings.protocol)
    device = config.robot if settings.device == "robot" else config.tracker
    # the config's endpoint when it is this protocol's device, else the protocol's default
    port = settings.port or (device.port if device.protocol == row.name else row.port)
    settings = msgspec.structs.replace(settings, host=settings.host or device.host, port=port)
    mock: MockDevice = mock_factory(row)(settings, config, run)
    return mock


class TcpMockServer:
    """The lifecycle every TCP mock shares: listen on `host:port`, take `t0` 0.5 s after the
    start when none is given, stop listening on `close`. Subclasses serve `_on_client`."""

    kind = "mock"  # in the log line that says where it listens
    host: str
    port: int
    t0: float | None
    play_until: float | None = None
    _server: asyncio.Server | None = None

    async def start(self) -> None:
        self._server = await asyncio.start_server(self._on_client, self.host, self.port)
        if self.t0 is None:
            self.t0 = time.time() + 0.5
        log.info(
            "%s listening on %s:%d, playing from t0=%.3f", self.kind, self.host, self.port, self.t0
        )

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()

    def summary(self) -> dict[str, object] | None:
        return None

    async def _on_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        raise NotImplementedError


class TaskMock:
    """The lifecycle of a mock that plays from a task of its own (the UDP controllers, the
    ROS 2 drivers): `played` waits for its end, `_stop_task` cancels it."""

    play_until: float | None = None
    _task: asyncio.Task[None] | None = None

    async def played(self, timeout: float) -> None:
        """Until the scenario is played to its end (or `play_until`, or the robot stopped)."""
        if self._task is not None:
            await asyncio.wait({self._task}, timeout=timeout)

    async def _stop_task(self) -> None:
        if self._task is not None:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)
