"""Live commands: run, adapter, mock, echo, status, record, replay, router. asyncio is
imported by the commands that run a loop: the offline commands start without it."""

from __future__ import annotations

import argparse
import json
import logging
import math
import signal
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from keo_service.cli import common
from keo_service.core.errors import ConfigError, KeoError


def _setup_logging(verbose: bool = False, fmt: str = "auto") -> None:
    from keo_service.live.systemd import setup_logging

    setup_logging(verbose, fmt)


def _install_stop(stop: Callable[[], None]) -> None:
    import asyncio

    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop)


def cmd_run(args: argparse.Namespace) -> int:
    import asyncio

    from keo_service.live.service import run_service

    config = common.load(args.config)
    _setup_logging(args.verbose, args.log_format)
    viewer, opened = args.viewer, None
    if viewer in VIEWER_KINDS:  # a bare --viewer (auto), native or web: open one
        from keo_service.live.rerun_process import open_viewer

        opened = open_viewer(viewer, args.viewer_port, args.web_port, args.viewer_bind)
        viewer = opened.grpc_url
        print(f"keo run: Rerun {opened.kind} viewer at {opened.url}", file=sys.stderr, flush=True)
    try:
        asyncio.run(
            run_service(config, rrd=args.rrd, viewer=viewer, viewer_window_s=args.viewer_window)
        )
    finally:
        if opened is not None:
            opened.close()
    return 0


VIEWER_KINDS = ("auto", "native", "web")  # as keo_service.live.rerun_process.VIEWER_KINDS


def add_viewer_options(p: argparse.ArgumentParser, url: bool) -> None:
    """`--viewer` and its ports, for keo run (`url`: it also takes a viewer's URL) and demo."""
    p.add_argument(
        "--viewer",
        nargs="?",
        const="auto",
        metavar="URL|native|web" if url else "native|web",
        help=(
            "stream to a running Rerun viewer at URL, e.g. rerun+http://127.0.0.1:9876/proxy; "
            if url
            else ""
        )
        + "bare: open one (a native window when there is a display, else the web viewer "
        "served on localhost, its URL printed); native or web: that one",
    )
    p.add_argument(
        "--viewer-port", type=int, default=9876, help="the opened viewer's gRPC port (9876)"
    )
    p.add_argument("--web-port", type=int, default=9090, help="the web viewer's page port (9090)")
    p.add_argument(
        "--viewer-bind",
        default="127.0.0.1",
        help="address the opened viewer listens on (127.0.0.1; 0.0.0.0 for other machines)",
    )
    p.add_argument(
        "--viewer-window",
        type=float,
        metavar="SECONDS",
        help="the plots show the newest SECONDS of data (30)",
    )


def cmd_adapter(args: argparse.Namespace) -> int:
    import asyncio

    from keo_service.adapters.devices import Ros2JointStateAdapter
    from keo_service.adapters.select import encoder_adapter_for, protocol_of, tracker_adapter_for
    from keo_service.io.cell import robot_from_config

    config = common.load(args.config)
    _setup_logging(args.verbose)
    robot = robot_from_config(config)
    nq = robot.nq
    fixed = protocol_of(config, "robot").joints
    if args.device == "encoder" and fixed and nq != fixed:
        raise ConfigError(
            config.source, "robot.urdf", f"{nq} joints; {config.robot.protocol} reports {fixed}"
        )

    def make() -> Any:
        if args.device == "tracker":
            return tracker_adapter_for(config)(config, nq)
        if config.robot.protocol == "ros2":
            return Ros2JointStateAdapter(config, list(robot.joint_names))
        adapter: Any = encoder_adapter_for(config)(config, nq)
        adapter.realtime = True  # the UDP servers (RSI, EGM) answer within the cycle
        return adapter

    async def main() -> None:
        async with make() as adapter:
            _install_stop(adapter.stop)
            await adapter.wait()
        if adapter.failure is not None:  # logged with its traceback when it happened
            raise KeoError(f"adapter stopped after an internal failure: {adapter.failure}")

    asyncio.run(main())
    return 0


def _pair(text: str | None, option: str) -> tuple[float, float] | None:
    if text is None:
        return None
    try:
        a, b = (float(v) for v in text.split(":"))
    except ValueError:
        raise ConfigError(
            option, option.lstrip("-"), f"'{text}' is not A:B (two numbers)"
        ) from None
    return a, b


def _mock_settings(args: argparse.Namespace, protocol: str, period: float) -> Any:
    """`keo mock`'s options as the settings every mock is built from (adapters.mock)."""
    from keo_service.adapters.mock import MockSettings

    return MockSettings(
        device=args.device,
        protocol=protocol,
        host=args.host or "",  # "": the config's
        port=args.port or 0,  # 0: the config's, or the protocol's default
        t0=args.t0,
        loop=args.loop,
        period_s=period,
        seed=args.seed,
        resample=not args.as_planned,
        late_ms=args.late_ms,
        burst_every_s=args.burst_every,
        clock_offset_s=args.clock_offset,  # None: the mock's default
        clock_drift_ppm=args.clock_drift_ppm,
        max_hz=args.max_hz,
        cycle_ms=args.cycle_ms,
        jitter_ms=args.jitter_ms,
        max_late=args.max_late,
        wall_clock=args.wall_clock_device_time,
        beam_break=_pair(args.beam_break, "--beam-break"),
        clock_step=_pair(args.clock_step, "--clock-step"),
        device_clock=_pair(args.device_clock, "--device-clock"),
    )


def _on_the_grid(args: argparse.Namespace, period: float) -> float | None:
    """Without --t0, every mock of the scenario plays the same phase: t0 on the wall-clock
    grid of its period, looping; one period from now (None: for ever with --loop). Returns
    when to stop playing."""
    from keo_service.adapters.mock_devices import wall_clock_t0

    if args.t0 is not None:
        return None
    args.t0 = wall_clock_t0(period)
    until = None if args.loop else time.time() + period
    args.loop = True
    logging.getLogger("keo.mock").info(
        "%s: t0 on the wall-clock grid of the scenario's %.1f s period (any mock of this "
        "scenario agrees); playing %s",
        args.scenario,
        period,
        "for ever" if until is None else "one period (--loop: for ever)",
    )
    return until


def cmd_mock(args: argparse.Namespace) -> int:
    import asyncio

    import msgspec

    from keo_service.adapters.mock import build_mock
    from keo_service.io.cell import cell_from_config
    from keo_service.sim.simulate import make_scenario, simulate

    config = common.load(args.config)
    _setup_logging(args.verbose)
    overrides = common.parse_sets(args.set)
    if args.duration is not None:
        overrides["duration_s"] = repr(args.duration)
    if getattr(args, "position_only", False):
        overrides["position_only"] = "true"
    if getattr(args, "follow_corrections", False):
        return _mock_compensated_cell(args, config, overrides)
    run = simulate(
        cell_from_config(config), make_scenario(args.scenario, overrides), seed=args.seed
    )
    # both mocks simulate the same run: one period for both streams
    period = mock_period(run.encoder.t, run.tracker.t)
    until = _on_the_grid(args, period)
    device = config.robot if args.device == "robot" else config.tracker
    protocol = (args.protocol if args.device == "robot" else None) or device.protocol
    settings = msgspec.structs.replace(_mock_settings(args, protocol, period), play_until=until)
    mock = build_mock(settings, config, run)

    async def main() -> None:
        stop = asyncio.Event()
        _install_stop(stop.set)
        await mock.start()
        await stop.wait()
        await mock.close()
        summary = mock.summary()  # the UDP controllers: what they saw, as one JSON line
        if summary is not None:
            sys.stdout.write(json.dumps(summary) + "\n")

    asyncio.run(main())
    return 0


def _numbers(text: str | None, option: str, n: int) -> tuple[float, ...] | None:
    if text is None:
        return None
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != n or not all(math.isfinite(v) for v in values):
        raise ConfigError(
            option, option.lstrip("-"), f"'{text}' is not {n} comma-separated numbers"
        )
    return values


def _mock_compensated_cell(args: argparse.Namespace, config: Any, overrides: dict[str, str]) -> int:
    """`keo mock robot --follow-corrections`: a UR controller (RTDE) that follows the
    scenario's tool path plus the correction in its input registers, and the tracker that
    sees the arm it moves, in one process (they share the arm)."""
    import asyncio
    import json

    from keo_service.adapters.mock import MockSettings
    from keo_service.adapters.mock_devices import MockRtdeController, MockTracker
    from keo_service.io.cell import cell_from_config
    from keo_service.sim.closed_loop import ClosedLoopCell
    from keo_service.sim.simulate import make_scenario, simulate

    if (args.protocol or config.robot.protocol) != "rtde":
        raise ConfigError("--follow-corrections", "protocol", "needs the rtde robot protocol")
    cell = cell_from_config(config)
    scenario = make_scenario(args.scenario, overrides)
    closed = ClosedLoopCell(
        cell,
        scenario,
        args.seed,
        tool_error=_numbers(args.tool_error, "--tool-error", 6),
        joint_offsets=_numbers(args.joint_offsets, "--joint-offsets", cell.robot.nq),
    )
    run = simulate(cell, scenario, seed=args.seed)  # the tracker's sample times
    robot = MockRtdeController(
        run.encoder,
        MockSettings(
            host=args.host or config.robot.host,
            port=args.port or config.robot.endpoint_port,
            t0=args.t0,
            max_hz=args.max_hz,
            clock_offset_s=args.clock_offset,
            seed=args.seed,
        ),
        follow=closed.joints,
        correction_register=config.robot.correction_register,
    )
    tracker = MockTracker(
        run.tracker,
        MockSettings(
            host=args.host or config.tracker.host,
            port=config.tracker.port,
            t0=args.t0,
            beam_break=_pair(args.beam_break, "--beam-break"),
        ),
        pose_at=closed.sensor,
    )

    async def main() -> None:
        stop = asyncio.Event()
        _install_stop(stop.set)
        await robot.start()
        tracker.t0 = robot.t0
        await tracker.start()
        await stop.wait()
        await robot.close()
        await tracker.close()

    asyncio.run(main())
    if args.summary is not None:
        doc = {
            "summary": closed.summary(),
            "series": closed.series(),
            # each change of the correction registers: wall time, the six values
            "register_writes": [[w, list(v)] for w, v in robot.input_log],
        }
        args.summary.write_text(json.dumps(doc), encoding="utf-8")
    return 0


def mock_period(*times: Any) -> float:
    """The scenario's period for looping mocks: its last row (of either stream) plus a tenth
    of a second, on a 0.1 s grid so that every mock of the same run computes the same."""
    last = max(float(t[-1]) for t in times if len(t))
    return math.ceil(last * 10.0 + 1.0) / 10.0


def cmd_echo(args: argparse.Namespace) -> int:
    import asyncio

    import msgspec

    from keo_service.live.bus import AsyncSubscription, session_for_client_async
    from keo_service.live.messages import decode

    config = common.load(args.config)
    if args.count is not None and args.count < 1:
        raise ConfigError("--count", "count", "must be >= 1")

    async def main() -> None:
        # SIGTERM's default action ends the process while it waits for the bus
        session = await session_for_client_async(config)
        sub = AsyncSubscription(session, [args.key])
        stop = asyncio.Event()

        def stop_echo() -> None:
            stop.set()
            sub.close()  # ends the iteration below; `finally` closes nothing twice

        _install_stop(stop_echo)
        seen = 0
        try:
            async for key, payload in sub:
                try:
                    msg: Any = decode(payload)
                    doc = msgspec.to_builtins(msg)
                except msgspec.DecodeError as exc:
                    doc = _json_object(key, payload) or {
                        "key": key,
                        "error": f"undecodable payload: {exc}",
                        "bytes": len(payload),
                    }
                if args.json:
                    sys.stdout.write(json.dumps(doc, allow_nan=False, default=str) + "\n")
                else:
                    sys.stdout.write(f"{key}: {_human(doc)}\n")
                sys.stdout.flush()
                seen += 1
                if args.count is not None and seen >= args.count:
                    break
        finally:
            sub.close()
            session.close()

    asyncio.run(main())
    return 0


def _human(doc: dict[str, Any]) -> str:
    if "estimate" in doc and "stamp" in doc:
        est = ", ".join(f"{v * 1e3:+.4f}" for v in doc["estimate"])
        flags = f" [{','.join(doc['flags'])}]" if doc.get("flags") else ""
        return f"t={doc['stamp']:.4f} estimate(mm/mrad)=[{est}]{flags}"
    return json.dumps(doc, default=str)


def cmd_status(args: argparse.Namespace) -> int:
    import msgspec

    from keo_service.live.client import ClientError, SyncClient
    from keo_service.live.messages import AdapterStatus
    from keo_service.live.status_view import adapter_lines, status_table

    config = common.load(args.config)
    adapters: dict[str, AdapterStatus] = {}
    try:
        with SyncClient.from_config(config, connect_timeout_s=args.timeout) as keo:
            # the adapters answer for themselves: state, rate, counters, newest rejects
            adapters = keo.adapters(timeout=min(5.0, args.timeout))
            status = keo.status(timeout=args.timeout)
    except ClientError as exc:
        print(f"keo status: {exc}", file=sys.stderr)
        if adapters and args.json:
            doc = {"adapters": msgspec.to_builtins(adapters)}
            sys.stdout.write(json.dumps(doc, indent=2, default=str) + "\n")
        elif adapters:
            sys.stdout.write("\n".join(adapter_lines(msgspec.to_builtins(adapters))) + "\n")
        return 1
    # the adapters' own answers are newer than what the service kept of their last change
    doc = msgspec.to_builtins(msgspec.structs.replace(status, adapters=adapters or status.adapters))
    if args.json:
        sys.stdout.write(json.dumps(doc, indent=2, default=str) + "\n")
    else:
        sys.stdout.write(status_table(doc))
    return 0


def _json_object(key: str, payload: bytes) -> dict[str, Any] | None:
    """A JSON object payload (an adapter's status put on a change of state) with its key, or
    None for anything else."""
    try:
        doc = json.loads(payload)
    except ValueError:
        return None
    return {"key": key, **doc} if isinstance(doc, dict) else None


def cmd_router(args: argparse.Namespace) -> int:
    import asyncio

    from keo_service.live.access import access_control_for
    from keo_service.live.bus import open_session

    _setup_logging()
    config = common.load(args.config) if args.config else None
    tls = config.bus if config is not None else None
    access = access_control_for(config) if config is not None else None
    session = open_session(
        "router", listen=args.listen, connect=args.connect or (), tls=tls, access=access
    )
    logging.getLogger("keo.router").info("zenoh router listening on %s", args.listen)
    stop = asyncio.Event()

    async def main() -> None:
        _install_stop(stop.set)
        await stop.wait()

    try:
        asyncio.run(main())
    finally:
        session.close()
    return 0


def _add_stall_and_clock_args(p: argparse.ArgumentParser) -> None:
    """keo mock: late delivery in stalls (RTDE and the tracker) and the tracker's own clock."""
    p.add_argument(
        "--as-planned",
        action="store_true",
        help="motoros, rtde, tracker: send every row as simulated, describing its planned "
        "instant however late it goes out (default: a row that goes out late, as this "
        "process's timer makes it by up to a millisecond, describes the instant it goes out)",
    )
    p.add_argument(
        "--late-ms", type=float, default=0.0, help="rtde, tracker: longest delivery stall (ms)"
    )
    p.add_argument(
        "--burst-every",
        type=float,
        default=0.0,
        help="rtde, tracker: mean seconds between stalls",
    )
    p.add_argument(
        "--device-clock",
        metavar="OFFSET:PPM",
        help="tracker: stamp each pose with its own free-running clock, OFFSET s at scenario "
        "time 0 and running PPM fast (default: seconds since the connection, read at sending)",
    )


def _register_mock(add: common.AddCommand) -> None:
    """`keo mock`: its protocols are the protocol table's (io.protocols)."""
    from keo_service.io.protocols import names as protocol_names

    p = add("mock", cmd_mock, "a device simulator speaking the real wire format", config=False)
    p.add_argument("device", choices=["robot", "tracker"])
    p.add_argument("--config", required=True)
    p.add_argument("--scenario", default="path", help="default: path (every joint moving, 60 s)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--t0",
        type=float,
        help="wall time (epoch s) of scenario time 0 (default: the start of the current "
        "scenario period since the epoch, the same for every mock of the scenario)",
    )
    p.add_argument("--duration", type=float, help="play only this many seconds of the scenario")
    p.add_argument("--loop", action="store_true", help="play the scenario again and again")
    p.add_argument("--host", help="bind address (default: the config's, loopback)")
    p.add_argument("--port", type=int)
    p.add_argument("--set", action="append", metavar="KEY=VALUE")
    p.add_argument("--position-only", action="store_true", help="a single-reflector tracker")
    p.add_argument(
        "--beam-break",
        metavar="START:SECONDS",
        help="tracker: report beam_broken for SECONDS from scenario time START",
    )
    p.add_argument(
        "--clock-step",
        metavar="AT:STEP",
        help="tracker: its own clock jumps by STEP seconds at scenario time AT",
    )
    p.add_argument(
        "--protocol",
        choices=protocol_names("robot"),
        help="robot: the wire format (default: the config's robot.protocol); ros2: "
        "JointState over rmw_zenoh on the config's bus (the tracker's ros2: its protocol)",
    )
    p.add_argument("--max-hz", type=float, default=500.0, help="rtde: 500 e-Series, 125 CB3")
    p.add_argument(
        "--clock-offset",
        type=float,
        help="rtde, kuka_rsi, abb_egm: the controller clock's reading at t0, seconds "
        "(default: rtde 1000, kuka_rsi and abb_egm 5000)",
    )
    p.add_argument("--clock-drift-ppm", type=float, default=0.0, help="rtde: controller clock rate")
    _add_stall_and_clock_args(p)
    p.add_argument("--cycle-ms", type=float, default=4.0, help="kuka_rsi/abb_egm: cycle (ms)")
    p.add_argument("--jitter-ms", type=float, default=0.0, help="kuka_rsi/abb_egm: send jitter")
    p.add_argument(
        "--max-late", type=int, default=100, help="kuka_rsi/abb_egm: late answers before a stop"
    )
    p.add_argument(
        "--wall-clock-device-time",
        action="store_true",
        help="tracker: send the wall clock as device time (latency benchmarks)",
    )
    p.add_argument(
        "--follow-corrections",
        action="store_true",
        help="robot (rtde): follow the path plus the correction in the input registers "
        "(robot.correction_register on); serves the tracker that sees this arm too",
    )
    p.add_argument("--tool-error", metavar="X,Y,Z,RX,RY,RZ", help="with corrections: m, rad")
    p.add_argument("--joint-offsets", metavar="Q1,...", help="with corrections: the arm's (rad)")
    p.add_argument("--summary", type=Path, help="with corrections: the true errors as JSON")
    p.add_argument("-v", "--verbose", action="store_true")


def register(add: common.AddCommand) -> None:
    p = add("run", cmd_run, "the service (daemon)")
    p.add_argument("--rrd", type=Path, help="save a Rerun recording here")
    add_viewer_options(p, url=True)
    p.add_argument(
        "--log-format",
        choices=["auto", "text", "json"],
        default="auto",
        help="json: one JSON object per line (auto: json under journald)",
    )
    p.add_argument("-v", "--verbose", action="store_true")

    p = add("adapter", cmd_adapter, "a device adapter (its own process)", config=False)
    p.add_argument("device", choices=["encoder", "tracker"])
    p.add_argument("--config", required=True)
    p.add_argument("-v", "--verbose", action="store_true")

    _register_mock(add)

    p = add("echo", cmd_echo, "print what arrives on a key expression", config=False)
    p.add_argument("key")
    p.add_argument("--config", required=True)
    p.add_argument("--json", action="store_true", help="one JSON document per line")
    p.add_argument("--count", type=int)

    p = add("status", cmd_status, "query a service's status (a table; --json: the document)")
    p.add_argument("--timeout", type=float, default=5.0)
    p.add_argument(
        "--json",
        action="store_true",
        help="print the status document as JSON (ServiceStatus with `adapters`), for scripts",
    )

    _register_recording(add)

    p = add("router", cmd_router, "a Zenoh router for setups without zenohd", config=False)
    p.add_argument("--listen", action="append", required=True, metavar="ENDPOINT")
    p.add_argument(
        "--config", help="take TLS settings ([bus] tls_*) and access control from this config"
    )
    p.add_argument("--connect", action="append", metavar="ENDPOINT")


def cmd_record(args: argparse.Namespace) -> int:
    import asyncio

    from keo_service.io.cell import robot_from_config
    from keo_service.live.bus import session_for_client_async
    from keo_service.live.recorder import record

    config = common.load(args.config)
    _setup_logging()
    robot = robot_from_config(config)
    nq = robot.nq

    async def main() -> dict[str, Any]:
        # SIGTERM's default action ends the process while it waits for the bus
        session = await session_for_client_async(config)
        stop = asyncio.Event()
        _install_stop(stop.set)
        mcap = None
        if args.format == "mcap":
            from keo_service.io.mcap_files import McapWriter

            mcap = McapWriter(
                args.out,
                robot.joint_names,
                config.cell,
                config.robot.joint_states_topic,
                config.tracker.pose_topic,
                config.ros2.distro,
            )
        try:
            stats = await record(session, config.cell, args.out, nq, stop, args.duration, mcap=mcap)
        finally:
            session.close()
        return stats.__dict__

    stats = asyncio.run(main())
    print(json.dumps({"out": str(args.out), **stats}))
    return 1 if stats.get("stopped") else 0  # e.g. the disk filled up


def cmd_replay(args: argparse.Namespace) -> int:
    import asyncio

    from keo_service.io.cell import robot_from_config
    from keo_service.live.bus import session_for_client_async
    from keo_service.live.recorder import replay

    config = common.load(args.config)
    robot = robot_from_config(config)

    async def main() -> dict[str, Any]:
        # SIGTERM's default action ends the process while it waits for the bus
        session = await session_for_client_async(config)
        stop = asyncio.Event()
        _install_stop(stop.set)
        try:
            await asyncio.sleep(0.5)  # let the declarations reach the service
            return await replay(
                session,
                config.cell,
                args.directory,
                robot.nq,
                args.as_fast_as_possible,
                stop,
                joint_names=robot.joint_names,
            )
        finally:
            session.close()

    print(json.dumps(asyncio.run(main())))
    return 0


def _register_recording(add: common.AddCommand) -> None:
    p = add("record", cmd_record, "raw encoder and tracker streams to the interchange files")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    p.add_argument(
        "--format",
        choices=["csv", "mcap"],
        default="csv",
        help="csv: encoder.csv, tracker.csv; mcap: a ROS 2 MCAP recording in OUT/keo/",
    )

    p = add("replay", cmd_replay, "recorded interchange files back onto the bus", config=False)
    p.add_argument("--config", required=True)
    p.add_argument("directory", type=Path)
    p.add_argument(
        "--as-fast-as-possible",
        action="store_true",
        help="as fast as the service takes them (paced by its status)",
    )
