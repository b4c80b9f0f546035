"""Live commands: run, adapter, mock, echo, status, record, replay, router. asyncio is
imported by the commands that run a loop: the offline commands start without it."""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
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
    asyncio.run(run_service(config, rrd=args.rrd, viewer=args.viewer))
    return 0


def cmd_adapter(args: argparse.Namespace) -> int:
    import asyncio

    from adapters.devices import (
        Ros2JointStateAdapter,
        encoder_adapter_for,
        tracker_adapter_for,
    )
    from keo_service.io.cell import robot_from_config

    config = common.load(args.config)
    _setup_logging(args.verbose)
    robot = robot_from_config(config)
    nq = robot.nq
    if args.device == "encoder" and config.robot.protocol == "rtde" and nq != 6:
        raise ConfigError(
            config.source, "robot.urdf", f"{nq} joints; a UR controller (rtde) reports 6"
        )

    def make() -> Any:
        if args.device == "tracker":
            return tracker_adapter_for(config)(config, nq)
        if config.robot.protocol == "ros2":
            return Ros2JointStateAdapter(config, list(robot.joint_names))
        return encoder_adapter_for(config)(config, nq)

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


def cmd_mock(args: argparse.Namespace) -> int:
    import asyncio

    from adapters.mock_devices import MockRobot, MockRtdeController, MockTracker
    from keo_service.io.cell import cell_from_config
    from keo_service.sim.simulate import make_scenario, simulate

    config = common.load(args.config)
    _setup_logging(args.verbose)
    overrides = common.parse_sets(args.set)
    if args.duration is not None:
        overrides["duration_s"] = repr(args.duration)
    if getattr(args, "position_only", False):
        overrides["position_only"] = "true"
    run = simulate(
        cell_from_config(config), make_scenario(args.scenario, overrides), seed=args.seed
    )
    server: MockRobot | MockTracker | MockRtdeController
    protocol = args.protocol or config.robot.protocol
    if args.device == "robot" and protocol == "rtde":
        server = MockRtdeController(
            run.encoder,
            args.host or config.robot.host,
            args.port or (config.robot.endpoint_port if config.robot.protocol == "rtde" else 30004),
            args.t0,
            max_hz=args.max_hz,
            clock_offset_s=args.clock_offset,
            clock_drift_ppm=args.clock_drift_ppm,
            late_ms=args.late_ms,
            burst_every_s=args.burst_every,
            seed=args.seed,
        )
    elif args.device == "robot":
        server = MockRobot(
            run.encoder,
            args.host or config.robot.host,
            args.port or config.robot.endpoint_port,
            config.robot.byte_order,
            args.t0,
            args.loop,
        )
    else:
        server = MockTracker(
            run.tracker,
            args.host or config.tracker.host,
            args.port or config.tracker.port,
            args.t0,
            args.loop,
            wall_clock=args.wall_clock_device_time,
            beam_break=_pair(args.beam_break, "--beam-break"),
            clock_step=_pair(args.clock_step, "--clock-step"),
            device_clock=_pair(args.device_clock, "--device-clock"),
            late_ms=args.late_ms,
            burst_every_s=args.burst_every,
            seed=args.seed,
        )

    async def main() -> None:
        stop = asyncio.Event()
        _install_stop(stop.set)
        await server.start()
        await stop.wait()
        await server.close()

    asyncio.run(main())
    return 0


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
            sub.close()

        _install_stop(stop_echo)
        seen = 0
        try:
            async for key, payload in sub:
                try:
                    msg: Any = decode(payload)
                    doc = msgspec.to_builtins(msg)
                except msgspec.DecodeError as exc:
                    doc = {
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

    config = common.load(args.config)
    try:
        with SyncClient.from_config(config, connect_timeout_s=args.timeout) as keo:
            status = keo.status(timeout=args.timeout)
    except ClientError as exc:
        print(f"keo status: {exc}", file=sys.stderr)
        return 1
    doc = msgspec.to_builtins(status)
    sys.stdout.write(json.dumps(doc, indent=2, default=str) + "\n")
    return 0


def cmd_router(args: argparse.Namespace) -> int:
    import asyncio

    from keo_service.live.bus import open_session

    _setup_logging()
    tls = common.load(args.config).bus if args.config else None
    session = open_session("router", listen=args.listen, connect=args.connect or (), tls=tls)
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


def register(add: common.AddCommand) -> None:
    p = add("run", cmd_run, "the service (daemon)")
    p.add_argument("--rrd", type=Path, help="save a Rerun recording here")
    p.add_argument(
        "--viewer",
        metavar="URL",
        help="stream to a running Rerun viewer, e.g. rerun+http://127.0.0.1:9876/proxy",
    )
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

    p = add("mock", cmd_mock, "a device simulator speaking the real wire format", config=False)
    p.add_argument("device", choices=["robot", "tracker"])
    p.add_argument("--config", required=True)
    p.add_argument("--scenario", required=True)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--t0", type=float, help="wall time (epoch s) of scenario time 0")
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
        choices=["motoros", "rtde"],
        help="robot: the wire format (default: the config's robot.protocol)",
    )
    p.add_argument("--max-hz", type=float, default=500.0, help="rtde: 500 e-Series, 125 CB3")
    p.add_argument(
        "--clock-offset", type=float, default=1000.0, help="rtde: controller clock at t0"
    )
    p.add_argument("--clock-drift-ppm", type=float, default=0.0, help="rtde: controller clock rate")
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
    p.add_argument(
        "--wall-clock-device-time",
        action="store_true",
        help="tracker: send the wall clock as device time (latency benchmarks)",
    )
    p.add_argument("-v", "--verbose", action="store_true")

    p = add("echo", cmd_echo, "print what arrives on a key expression", config=False)
    p.add_argument("key")
    p.add_argument("--config", required=True)
    p.add_argument("--json", action="store_true", help="one JSON document per line")
    p.add_argument("--count", type=int)

    p = add("status", cmd_status, "query a service's status")
    p.add_argument("--timeout", type=float, default=5.0)

    _register_recording(add)

    p = add("router", cmd_router, "a Zenoh router for setups without zenohd", config=False)
    p.add_argument("--listen", action="append", required=True, metavar="ENDPOINT")
    p.add_argument("--config", help="take TLS settings ([bus] tls_*) from this config")
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
    return 0


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
