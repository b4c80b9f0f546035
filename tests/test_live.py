"""The live chain: mock devices, adapters, service and a subscriber over real TCP and Zenoh.

`test_chain_in_one_process` runs every component on one asyncio loop (fast plumbing test);
`test_chain_as_processes` runs each as its own OS process, as deployed.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import re
import time

import msgspec
import numpy as np
import pytest

from keo_service.adapters.devices import EncoderAdapter, TrackerAdapter
from keo_service.adapters.mock import MockSettings
from keo_service.adapters.mock_devices import MockRobot, MockTracker
from keo_service.bench.demo import loopback_config
from keo_service.bench.procs import process_group
from keo_service.core.observer import noise_gain
from keo_service.io.config import config_to_toml
from keo_service.live.bus import session_for_client
from keo_service.live.client import Client
from keo_service.live.messages import EstimateMessage, ServiceStatus, decode, topic
from keo_service.live.service import KeoService
from keo_service.sim.simulate import make_scenario, simulate
from tests.conftest import REPO, wait_for_adapters, wait_for_status, wait_until

GAIN = 5.0  # time constant 0.2 s
POSITION_NOISE = 20e-6
ROTATION_NOISE = 50e-6


@pytest.fixture
def live_config(demo_config):
    config = loopback_config(demo_config)
    observer = msgspec.structs.replace(config.observer, gain=[GAIN] * 6)
    return msgspec.structs.replace(config, observer=observer)


def check_converged(estimates: list[EstimateMessage], truth: np.ndarray, t_start: float) -> None:
    """After five time constants every channel is within 5 sigma of the truth (noise band)."""
    good = [e for e in estimates if e.measured is not None]
    assert len(good) > 100, f"only {len(good)} estimates"
    first = good[0].stamp
    late = [e for e in good if e.stamp > first + 5.0 / GAIN + 0.5]
    assert len(late) > 50
    period = float(np.median(np.diff([e.stamp for e in good])))
    band = noise_gain(GAIN, period)
    err = np.array([e.estimate for e in late]) - truth
    limit = 5 * band * np.array([POSITION_NOISE] * 3 + [ROTATION_NOISE] * 3)
    assert np.all(np.abs(err) < limit), (np.abs(err).max(axis=0), limit)
    assert np.max(np.abs(truth[:3])) > 5e-4  # the injected error is large against the band
    assert t_start < first


def readme_snippets(endpoint: str, cell: str) -> list[str]:
    """The README's client examples (async and sync), pointed at this test's service."""
    readme = (REPO / "README.md").read_text()
    blocks = [b for b in re.findall(r"```python\n(.*?)```", readme, re.S) if "Client(" in b]
    return [
        code.replace("tcp/127.0.0.1:7447", endpoint).replace('cell="demo"', f'cell="{cell}"')
        for code in blocks
    ]


async def collect(config, until: float, span: float | None = None) -> list[EstimateMessage]:
    """Estimates until `until` (wall clock), or with `span` until `span` s of stamps from the
    first one, through the client API."""
    out: list[EstimateMessage] = []
    async with Client.from_config(config, connect_timeout_s=20) as keo:

        async def gather() -> None:
            async for est in keo.estimates():
                out.append(est)
                if span is not None and est.stamp > out[0].stamp + span:
                    return

        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(gather(), timeout=until - time.time())
        assert keo.dropped == 0
    return out


async def test_chain_in_one_process(live_config, demo_cell):
    run = simulate(demo_cell, make_scenario("paper-step", {"duration_s": "3.5"}), seed=21)
    truth = run.truth.mean(axis=0)
    t0 = time.time() + 1.0
    robot = MockRobot(
        run.encoder, MockSettings(host="127.0.0.1", port=live_config.robot.port, t0=t0)
    )
    tracker = MockTracker(
        run.tracker, MockSettings(host="127.0.0.1", port=live_config.tracker.port, t0=t0)
    )
    await robot.start()
    await tracker.start()
    try:
        async with (
            KeoService(live_config) as service,
            EncoderAdapter(live_config, 6),
            TrackerAdapter(live_config, 6),
        ):
            estimates = await collect(live_config, t0 + 3.7)
            status = service.status()
    finally:
        await robot.close()
        await tracker.close()
    check_converged(estimates, truth, t0)
    assert status.counters["published"] == len(estimates)
    assert status.counters.get("rejected", 0) == 0
    seqs = [e.seq for e in estimates]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))  # none lost on the way


def test_chain_as_processes(live_config, demo_cell, tmp_path):
    # played longer than needed: 6 s of estimates from the first one, whenever the adapters
    # connect (seconds after t0 on a loaded machine); the devices are stopped then
    duration = 30.0
    run = simulate(demo_cell, make_scenario("paper-step", {"duration_s": repr(duration)}), seed=2)
    truth = run.truth.mean(axis=0)
    cfg = tmp_path / "live.toml"
    cfg.write_text(config_to_toml(live_config))
    t0 = time.time() + 5.0
    play = [
        "--scenario",
        "paper-step",
        "--seed",
        "2",
        "--t0",
        repr(t0),
        "--duration",
        repr(duration),
    ]
    with process_group(tmp_path) as procs:
        procs.start_cell(cfg, play)
        client = session_for_client(live_config, retry_for=20)
        try:
            alive = client.liveliness().declare_subscriber(
                f"keo/{live_config.cell}/alive/**", history=True
            )
            estimates = asyncio.run(collect(live_config, t0 + duration, span=6.0))
            for mock in ("mock-robot", "mock-tracker"):
                procs.stop(mock)
            # the status is a snapshot the service renews every 0.1 s (later under load)
            deadline = time.monotonic() + 10.0
            while True:
                replies = [
                    r.ok for r in client.get(topic(live_config.cell, "status"), timeout=3.0) if r.ok
                ]
                status = decode(replies[0].payload.to_bytes())
                assert isinstance(status, ServiceStatus)
                if status.counters["tracker_samples"] >= len(estimates) or (
                    time.monotonic() > deadline
                ):
                    break
                time.sleep(0.2)
            tokens = [s.key_expr for s in iter(alive.try_recv, None)]
        finally:
            client.close()
        started = time.monotonic()
        code = procs.stop("service")
        stop_time = time.monotonic() - started
        logs = {name: procs.log(name) for name in ("service", "adapter-encoder", "adapter-tracker")}
    assert code == 0, logs["service"]
    assert stop_time < 2.0
    check_converged(estimates, truth, t0)
    assert status.cell == live_config.cell
    assert status.delay_s == pytest.approx(0.028)
    assert status.gains == [GAIN] * 6
    assert status.counters["tracker_samples"] >= len(estimates) - 5
    assert status.last_estimate is not None
    assert any(str(k).endswith("alive/service") for k in tokens)
    assert all(len(e.estimate) == 6 and len(e.channels) == 6 for e in estimates)


@pytest.mark.slow  # 17 s; the default run stays under 10 min on 2 cores
def test_echo_prints_estimates_as_json(live_config, demo_cell, tmp_path):
    """The clients first, then the devices, which play until every client has had what it
    needs: nothing assumes when a process is up (they start late on a loaded machine)."""
    cfg = tmp_path / "live.toml"
    cfg.write_text(config_to_toml(live_config))
    args = ["--config", str(cfg)]
    snippets = readme_snippets(live_config.bus.listen[0], live_config.cell)
    assert len(snippets) == 2
    with process_group(tmp_path) as procs:
        procs.start("service", ["run", *args])
        echo_args = [f"keo/{live_config.cell}/estimate", *args, "--json", "--count", "20"]
        echo = procs.start("echo", ["echo", *echo_args])
        # the async example stops at seq 200: it listens from the first estimate on; it
        # prints the service's status first, then subscribes
        examples = [procs.start("example-0", ["-c", snippets[0]], module=None)]
        wait_for_status(live_config)
        wait_until(lambda: procs.log("example-0").strip(), 60, "the async example connected")
        # the tracker (each of its samples makes an estimate) once joint angles flow
        play = ["--scenario", "paper-step", "--seed", "3", "--duration", "60"]
        play += ["--t0", repr(time.time() + 1.0)]
        for device, adapter in (("robot", "encoder"), ("tracker", "tracker")):
            procs.start(f"mock-{device}", ["mock", device, *args, *play])
            procs.start(f"adapter-{adapter}", ["adapter", adapter, *args])
            if adapter == "encoder":
                wait_for_adapters(live_config, ("encoder",), ("receiving",), timeout=60)
        # the sync example ends after 10 s without an estimate: started once they flow
        wait_until(lambda: echo.poll() is not None, 60, "echo printed its estimates")
        examples.append(procs.start("example-1", ["-c", snippets[1]], module=None))
        wait_until(
            lambda: examples[0].poll() is not None and procs.log("example-1").count(" ok ") > 50,
            60,
            "the examples have their estimates",
        )
        for mock in ("mock-robot", "mock-tracker"):
            procs.stop(mock)
        examples[1].wait(timeout=30)  # it ends 10 s after the last estimate
    for i, example in enumerate(examples):
        log = procs.log(f"example-{i}")
        assert example.returncode == 0, log
        example_lines = [ln for ln in log.splitlines() if ln.strip()]
        assert len(example_lines) > 50
        assert sum(" ok " in line for line in example_lines) > 50
    assert echo.returncode == 0, procs.log("echo")
    lines = [ln for ln in procs.log("echo").splitlines() if ln.startswith("{")]
    assert len(lines) == 20
    docs = [json.loads(line) for line in lines]
    for doc in docs:
        assert isinstance(doc["stamp"], float)
        assert len(doc["estimate"]) == 6
        # a held step (no encoder data yet for its time) says why instead of a measurement
        assert (doc["measured"] is None) == bool(doc["flags"])
    assert sum(doc["measured"] is not None for doc in docs) >= 15


def test_position_only_tracker_live(live_config, demo_cell, tmp_path):
    """A single-reflector tracker through the live chain: 3 channels everywhere, Rerun too."""
    from rerun.chunk import RrdReader

    cfg = tmp_path / "live.toml"
    cfg.write_text(config_to_toml(live_config))
    t0 = time.time() + 4.0
    # played longer than echo needs (stopped once it has its estimates): the adapters may
    # connect seconds after t0 on a loaded machine
    play = ["--scenario", "paper-step", "--seed", "3", "--t0", repr(t0), "--duration", "30"]
    rrd = tmp_path / "po.rrd"
    with process_group(tmp_path) as procs:
        procs.start_cell(cfg, play, service=["--rrd", str(rrd)], tracker=["--position-only"])
        echo = procs.start(
            "echo",
            [
                "echo",
                f"keo/{live_config.cell}/estimate",
                "--config",
                str(cfg),
                "--json",
                "--count",
                "50",
            ],
        )
        echo.wait(timeout=30)
        time.sleep(0.5)
        assert procs.stop("service", timeout=15.0) == 0  # the Rerun child may take up to 8 s
    docs = [json.loads(ln) for ln in procs.log("echo").splitlines() if ln.startswith("{")]
    assert len(docs) == 50
    for doc in docs:
        assert doc["channels"] == ["px", "py", "pz"]
        assert len(doc["estimate"]) == 3
        assert doc["measured"] is None or len(doc["measured"]) == 3
    entities = {c.entity_path for c in RrdReader(str(rrd)).stream().to_chunks()}
    assert "/keo/error/px" in entities
    assert "/keo/error/rx" not in entities
