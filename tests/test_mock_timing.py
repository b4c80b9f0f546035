"""The mock devices sample when they send, as a controller's cycle does. This process's timer
wakes 0.1-1.3 ms late (asyncio waits in whole milliseconds); a row planned for t but sent at
t + 0.6 ms used to describe t, so the mock's own lateness, moving with the host's load,
became part of every stream's transport time (the device-clock test's floors: encoder
200-300 us, tracker 400-550 us, walking 145 us within a run). Now a row that goes out on
time (not held by a planned stall) describes the instant it goes out: its stamp says that
instant and its pose is the simulated motion's there. The truth is the simulator's: the same
run sampled at 10 kHz."""

from __future__ import annotations

import asyncio
import json
import time

import numpy as np

from keo_service.adapters.mock import MockSettings
from keo_service.adapters.mock_devices import MockTracker
from keo_service.bench.procs import free_port
from keo_service.sim.simulate import make_scenario, simulate

OFFSET_S, DRIFT_PPM = 2000.0, -40.0
SETS = {
    "duration_s": "8",
    "tool_error_only": "true",
    "position_noise_m": "0",
    "rotation_noise_rad": "0",
    "delay_jitter_s": "0",
    "tracker_rate_std_hz": "0",
}


async def test_a_late_row_describes_the_instant_it_goes_out(demo_cell):
    played = simulate(demo_cell, make_scenario("path", SETS), seed=3)
    # the same robot, motion and tool error (drawn before the sample times), densely sampled
    dense = simulate(demo_cell, make_scenario("path", {**SETS, "tracker_rate_hz": "10000"}), 3)
    t0 = time.time() + 0.5
    port = free_port()
    mock = MockTracker(
        played.tracker,
        MockSettings(host="127.0.0.1", port=port, t0=t0, device_clock=(OFFSET_S, DRIFT_PPM)),
        instants=played.physical_t,
    )
    await mock.start()
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    rows: list[tuple[float, dict]] = []
    try:
        await reader.readuntil(b"\n")  # hello
        while time.time() < t0 + 3.5:
            line = await reader.readuntil(b"\n")
            rows.append((time.time(), json.loads(line)))
    finally:
        writer.close()
        await mock.close()
    assert len(rows) > 200
    receipt = np.array([r for r, _ in rows])
    described = np.array([(row["t"] - OFFSET_S) / (1 + DRIFT_PPM * 1e-6) for _, row in rows])
    planned = played.tracker.t[np.array([row["seq"] for _, row in rows]) - 1]
    # never the future, and (the timer being late) after the planned instant
    assert np.all(t0 + described <= receipt + 1e-7)
    late = described - planned
    assert np.all(late >= -1e-7)  # the stamps have 0.1 us on the wire
    assert np.median(late) > 50e-6  # the version before: exactly 0 for every row
    # the pose is the simulated motion's at the described instant (10 kHz truth, linear
    # interpolation between its samples: < 1 nm at this speed); from 1.2 s on: the motion's
    # ramp-in ends at 1 s with a step in acceleration, which no spline through 100 Hz rows
    # follows within a micrometre
    truth = np.column_stack([np.interp(described, dense.tracker.t, c) for c in dense.tracker.p.T])
    seen = np.array([row["p"] for _, row in rows]) * 1e-3  # millimetres on the wire
    moving = described > 1.2
    assert moving.sum() > 150
    assert np.max(np.linalg.norm(seen - truth, axis=1)[moving]) < 0.2e-6


async def test_a_device_clock_never_goes_back_when_this_process_wakes_late(demo_cell):
    """Planned stalls (rows held up to 20 ms, then out together) while this process is
    blocked for 60 ms at a time (a loaded machine): a row sent late on time describes the
    instant it goes out, and a held-up row after it used to describe its planned instant,
    earlier (a CI run saw device stamps go back by more than 50 ms: false clock steps). Now
    no described instant goes back, and each pose is still the motion's at its instant."""
    played = simulate(demo_cell, make_scenario("path", SETS), seed=3)
    dense = simulate(demo_cell, make_scenario("path", {**SETS, "tracker_rate_hz": "10000"}), 3)
    t0 = time.time() + 0.5
    port = free_port()
    settings = MockSettings(
        host="127.0.0.1",
        port=port,
        t0=t0,
        device_clock=(OFFSET_S, DRIFT_PPM),
        late_ms=20.0,
        burst_every_s=0.1,
    )
    mock = MockTracker(played.tracker, settings, instants=played.physical_t)
    await mock.start()
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    rows: list[dict] = []

    async def block_the_loop() -> None:
        while True:
            await asyncio.sleep(0.05)
            time.sleep(0.06)  # the whole process stalls: the mock wakes late

    blocker = asyncio.create_task(block_the_loop())
    try:
        await reader.readuntil(b"\n")  # hello
        while time.time() < t0 + 3.5:
            rows.append(json.loads(await reader.readuntil(b"\n")))
    finally:
        blocker.cancel()
        writer.close()
        await mock.close()
    described = np.array([(row["t"] - OFFSET_S) / (1 + DRIFT_PPM * 1e-6) for row in rows])
    assert len(rows) > 200
    assert np.all(np.diff(described) > 0)
    truth = np.column_stack([np.interp(described, dense.tracker.t, c) for c in dense.tracker.p.T])
    seen = np.array([row["p"] for row in rows]) * 1e-3
    moving = described > 1.2
    assert np.max(np.linalg.norm(seen - truth, axis=1)[moving]) < 0.2e-6
