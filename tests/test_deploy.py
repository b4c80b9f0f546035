"""Deployment: systemd notify and reload, the compose file's commands run as processes, many
cells through one router, TLS and mutual TLS with certificates made here."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import msgspec
import pytest
import yaml

from keo_service.bench.procs import free_port, process_group
from keo_service.core.errors import KeoError
from keo_service.io.config import config_to_toml, load_config
from keo_service.live.bus import session_for_client
from keo_service.live.client import SyncClient
from keo_service.live.messages import EstimateMessage, ServiceStatus, decode
from keo_service.sim.simulate import make_scenario, simulate, write_run
from tests.conftest import CONFIGS, REPO, wait_for_status

pytestmark = pytest.mark.e2e


def test_systemd_notify_watchdog_reload_and_stop(demo_config, tmp_path):
    from keo_service.bench.demo import loopback_config

    config = loopback_config(demo_config)
    cfg = tmp_path / "c.toml"
    cfg.write_text(config_to_toml(config))
    sock_path = str(tmp_path / "notify.sock")
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    listener.bind(sock_path)
    listener.settimeout(0.2)
    env = {
        **os.environ,
        "NOTIFY_SOCKET": sock_path,
        "WATCHDOG_USEC": "400000",
        "PYTHONUNBUFFERED": "1",
    }
    log = (tmp_path / "service.log").open("wb")
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "keo_service.cli",
            "run",
            "--config",
            str(cfg),
            "--log-format",
            "json",
        ],
        stdout=log,
        stderr=subprocess.STDOUT,
        env=env,
    )
    env.pop("WATCHDOG_USEC")
    messages: list[str] = []

    def drain(seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            with contextlib.suppress(TimeoutError):
                messages.append(listener.recv(4096).decode())

    try:
        drain(8.0)
        assert any(m.startswith("READY=1") for m in messages), messages
        assert sum(m == "WATCHDOG=1" for m in messages) >= 3
        # SIGHUP: gains applied live, a changed port reported as needing a restart
        assert config.observer.gain == [2.0] * 6
        changed = msgspec.structs.replace(
            config,
            observer=msgspec.structs.replace(config.observer, gain=[3.0] * 6),
            robot=msgspec.structs.replace(config.robot, port=config.robot.port + 1),
        )
        text = config_to_toml(changed)
        cfg.write_text(text)
        proc.send_signal(signal.SIGHUP)
        drain(1.0)
        assert "RELOADING=1" in messages
        status = _status(config)
        assert status.gains == [3.0] * 6
        # a broken file on reload keeps the running config
        assert "    3.0,\n" in text
        cfg.write_text(text.replace("    3.0,\n", "    -3.0,\n", 1))
        proc.send_signal(signal.SIGHUP)
        drain(1.0)
        assert _status(config).gains == [3.0] * 6
        proc.send_signal(signal.SIGTERM)
        code = proc.wait(timeout=3)
        drain(0.3)
    finally:
        if proc.poll() is None:
            proc.kill()
        listener.close()
    assert code == 0
    assert "STOPPING=1" in messages
    lines = [
        json.loads(line)
        for line in (tmp_path / "service.log").read_text().splitlines()
        if line.startswith("{")
    ]
    assert any("robot.port" in entry["msg"] and "restart" in entry["msg"] for entry in lines)
    assert any("observer.gain[0]" in entry["msg"] and entry["level"] == "ERROR" for entry in lines)
    assert all({"ts", "level", "logger", "msg"} <= entry.keys() for entry in lines)


def _status(config) -> ServiceStatus:
    with SyncClient.from_config(config, connect_timeout_s=10) as keo:
        return keo.status(timeout=3.0)


def compose_commands() -> dict[str, list[str]]:
    doc = yaml.safe_load((REPO / "docker" / "compose.yaml").read_text())
    return {name: list(svc["command"]) for name, svc in doc["services"].items()}


def cell_config(tmp_path: Path, cell: str, router: str) -> Path:
    """configs/compose.toml with the container host names mapped to loopback."""
    text = (CONFIGS / "compose.toml").read_text()
    text = text.replace('cell = "cell1"', f'cell = "{cell}"')
    text = text.replace('"mock-robot"', '"127.0.0.1"').replace('"mock-tracker"', '"127.0.0.1"')
    text = text.replace("port = 50241", f"port = {free_port()}")
    text = text.replace("port = 5005", f"port = {free_port()}")
    text = text.replace("tcp/router:7447", router)
    text = text.replace('"robots/mh180.urdf"', f'"{CONFIGS / "robots" / "mh180.urdf"}"')
    path = tmp_path / f"{cell}.toml"
    path.write_text(text)
    return path


def localize(command: list[str], cfg: Path, router: str, tmp_path: Path) -> list[str]:
    out = []
    for original in command:
        arg = original.replace("/etc/keo/compose.toml", str(cfg))
        arg = arg.replace("tcp/0.0.0.0:7447", router)
        arg = arg.replace("/var/lib/keo/", str(tmp_path) + "/")
        out.append("127.0.0.1" if arg == "0.0.0.0" else arg)
    return out


def test_compose_commands_two_cells_through_a_router(tmp_path):
    commands = compose_commands()
    assert set(commands) >= {
        "router",
        "service",
        "adapter-encoder",
        "adapter-tracker",
        "mock-robot",
        "mock-tracker",
    }
    router = f"tcp/127.0.0.1:{free_port()}"
    cells = {c: cell_config(tmp_path, c, router) for c in ("cell1", "cell2")}
    with process_group(tmp_path) as procs:
        procs.start("router", localize(commands["router"], cells["cell1"], router, tmp_path))
        for cell, cfg in cells.items():
            work = tmp_path / cell
            work.mkdir()
            for name in (
                "service",
                "adapter-encoder",
                "adapter-tracker",
                "mock-robot",
                "mock-tracker",
            ):
                procs.start(f"{cell}-{name}", localize(commands[name], cfg, router, work))
        config1 = load_config(cells["cell1"])
        # eleven processes start at once (each imports numpy, pinocchio and zenoh): on a
        # loaded 2-core machine the router answered after more than 20 s once
        wait_for_status(config1, timeout=60.0)
        wait_for_status(load_config(cells["cell2"]), timeout=60.0)
        # a client elsewhere subscribes to keo/*/estimate and sees every cell
        seen: dict[str, int] = {}
        session = session_for_client(config1, retry_for=10)
        try:
            sub = session.declare_subscriber(
                "keo/*/estimate",
                lambda s: seen.__setitem__(str(s.key_expr), seen.get(str(s.key_expr), 0) + 1),
            )
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline and not all(
                seen.get(f"keo/{c}/estimate", 0) > 50 for c in cells
            ):
                time.sleep(0.2)
            sub.undeclare()
        finally:
            session.close()
        # a client that joins late gets each cell's latest estimate by query
        late = session_for_client(config1, retry_for=10)
        try:
            replies = [r.ok for r in late.get("keo/*/estimate", timeout=3.0) if r.ok]
        finally:
            late.close()
        codes = {n: procs.stop(n) for n in [f"{c}-service" for c in cells]}
    assert all(seen.get(f"keo/{c}/estimate", 0) > 50 for c in cells), seen
    by_cell = {str(r.key_expr): decode(r.payload.to_bytes()) for r in replies}
    assert set(by_cell) == {f"keo/{c}/estimate" for c in cells}
    assert all(isinstance(m, EstimateMessage) for m in by_cell.values())
    assert codes == {"cell1-service": 0, "cell2-service": 0}
    assert (tmp_path / "cell1" / "run.rrd").stat().st_size > 0


def make_certs(tmp_path: Path) -> dict[str, Path]:
    def run(*args: str) -> None:
        subprocess.run(["openssl", *args], check=True, capture_output=True, cwd=tmp_path)

    run(
        "req",
        "-x509",
        "-newkey",
        "rsa:2048",
        "-nodes",
        "-days",
        "2",
        "-subj",
        "/CN=keo test CA",
        "-keyout",
        "ca.key",
        "-out",
        "ca.pem",
    )
    for name in ("router", "client"):
        (tmp_path / f"{name}.ext").write_text(
            "subjectAltName=DNS:localhost,IP:127.0.0.1\nbasicConstraints=CA:FALSE\n"
        )
        run(
            "req",
            "-newkey",
            "rsa:2048",
            "-nodes",
            "-subj",
            "/CN=localhost",
            "-keyout",
            f"{name}.key",
            "-out",
            f"{name}.csr",
        )
        run(
            "x509",
            "-req",
            "-in",
            f"{name}.csr",
            "-CA",
            "ca.pem",
            "-CAkey",
            "ca.key",
            "-CAcreateserial",
            "-days",
            "2",
            "-out",
            f"{name}.pem",
            "-extfile",
            f"{name}.ext",
        )
    return {
        n: tmp_path / n for n in ("ca.pem", "router.pem", "router.key", "client.pem", "client.key")
    }


@pytest.mark.parametrize("mtls", [False, True])
def test_tls_and_mutual_tls(demo_config, demo_cell, tmp_path, mtls):
    certs = make_certs(tmp_path)
    endpoint = f"tls/localhost:{free_port()}"

    def config_for(name: str, cert: str, key: str, mode: str) -> Path:
        bus = msgspec.structs.replace(
            demo_config.bus,
            mode=mode,
            listen=[endpoint] if mode == "peer" else [],
            connect=[endpoint] if mode == "client" else [],
            tls_root_ca=str(certs["ca.pem"]),
            tls_certificate=cert,
            tls_private_key=key,
            tls_mtls=mtls and bool(cert),  # the anonymous client has nothing to show
        )
        path = tmp_path / f"{name}.toml"
        path.write_text(config_to_toml(msgspec.structs.replace(demo_config, bus=bus)))
        return path

    router_cfg = config_for("router", str(certs["router.pem"]), str(certs["router.key"]), "peer")
    client_cfg = config_for("client", str(certs["client.pem"]), str(certs["client.key"]), "client")
    anonymous_cfg = config_for("anonymous", "", "", "client")
    run = simulate(demo_cell, make_scenario("paper-step", {"duration_s": "3"}), seed=5)
    write_run(run, tmp_path / "rec")
    with process_group(tmp_path) as procs:
        procs.start("router", ["router", "--listen", endpoint, "--config", str(router_cfg)])
        procs.start("service", ["run", "--config", str(client_cfg)])
        client = load_config(client_cfg)
        wait_for_status(client)
        replay = procs.start(
            "replay",
            ["replay", "--config", str(client_cfg), str(tmp_path / "rec"), "--as-fast-as-possible"],
        )
        assert replay.wait(timeout=60) == 0, procs.log("replay")
        status = _status(client)
        assert status.counters["published"] > 100
        anonymous = load_config(anonymous_cfg)
        if mtls:
            with pytest.raises(KeoError, match="cannot reach the bus"):
                session_for_client(anonymous, retry_for=2.0)
        else:
            session = session_for_client(anonymous, retry_for=5.0)
            session.close()
    # the plain-TCP port is not there: nothing speaks unencrypted on this endpoint
    plain = msgspec.structs.replace(client.bus, connect=[endpoint.replace("tls/", "tcp/")])
    with pytest.raises(KeoError):
        session_for_client(msgspec.structs.replace(client, bus=plain), retry_for=1.0)
