"""A host clock step (NTP stepping the host clock) as the clock mapping sees it. The real
clock cannot be stepped from a test, so the step is synthetic: device stamps at 500 Hz (a UR
controller over RTDE) and host receipt times with transport jitter, the host's readings
shifted by 1 s at one instant. What an adapter's status shows is `ClockMapper.state()`
(adapters/devices.py puts it under "clock")."""

from __future__ import annotations

import numpy as np
import pytest

from keo_service.core.clock import ClockMapper

RATE = 500.0
STEP_AT = 12.0  # s of device time


def _stream(step_s: float, seconds: float = 30.0, seed: int = 2):
    rng = np.random.default_rng(seed)
    device = np.arange(0.0, seconds, 1.0 / RATE)
    latency = 3e-4 + rng.exponential(5e-4, device.size)
    host = 1.7e9 + device * (1 + 20e-6) + latency  # the host runs 20 ppm fast
    host = host + np.where(device >= STEP_AT, step_s, 0.0)
    mapper = ClockMapper()
    mapped, states = [], []
    for d, h in zip(device, host, strict=True):
        mapped.append(mapper.map(float(d), float(h)))
        states.append(mapper.state())
    return device, host, np.array(mapped), states


def _settled_after(device, mapped, step_s: float) -> float:
    """Seconds after the step from which every stamp is within 0.5 ms of the true line on
    the stepped host clock (the generator's own line: offset, 20 ppm, the 0.3 ms floor)."""
    line = 1.7e9 + device * (1 + 20e-6) + 3e-4 + np.where(device >= STEP_AT, step_s, 0.0)
    k = int(np.searchsorted(device, STEP_AT))
    bad = np.flatnonzero(np.abs(mapped[k:] - line[k:]) > 5e-4)
    assert np.all(np.abs(mapped[200:k] - line[200:k]) < 5e-4)  # before: on the line
    return float(device[k + bad[-1]] - STEP_AT) if bad.size else 0.0


def test_host_clock_stepping_back_is_a_step_relearned_and_stamps_never_go_back():
    device, _host, mapped, states = _stream(-1.0)
    k = int(np.searchsorted(device, STEP_AT))
    before = states[k - 1]
    assert before.steps == 0
    # seen after the confirmation samples (3 at 2 ms), relearned at once
    detected = next(i for i in range(k, len(states)) if states[i].steps == 1)
    assert detected - k <= 3
    # stamps never go back: the ones that would are placed just after the previous one and
    # counted, for as long as the stepped host time is behind the last stamp given (1 s)
    assert np.all(np.diff(mapped) > 0)
    held = states[-1].held_back - before.held_back
    assert held == pytest.approx(RATE * 1.0, rel=0.05)
    settled = _settled_after(device, mapped, -1.0)
    assert settled < 1.1
    assert states[-1].steps == 1
    assert states[-1].offset_s == pytest.approx(before.offset_s - 1.0, abs=2e-3)
    print(
        f"\nhost clock back 1 s: step seen after {detected - k} samples, {held} stamps held "
        f"back, on the stepped clock again after {settled:.2f} s; status clock: steps 1, "
        f"offset {before.offset_s - 1.7e9:+.4f} -> {states[-1].offset_s - 1.7e9:+.4f} s"
    )


def test_host_clock_stepping_forward_is_followed_within_the_window():
    # the mapping takes a forward step for late samples until the old minima leave its 20 s
    # window, then slews to the new line: 50 s of stream leave it time to settle
    device, _host, mapped, states = _stream(+1.0, seconds=50.0)
    k = int(np.searchsorted(device, STEP_AT))
    assert np.all(np.diff(mapped) > 0)  # never back
    gaps = np.diff(mapped)
    assert np.max(gaps) < 1.0  # no stamp jumps by the whole step at once
    settled = _settled_after(device, mapped, +1.0)
    assert settled < 20.0 + 1.0  # ClockMapper.window_s: the old minima leave it (module text)
    assert states[-1].offset_s == pytest.approx(states[k - 1].offset_s + 1.0, abs=2e-3)
    assert states[-1].steps <= 1
    print(
        f"\nhost clock forward 1 s: on the stepped clock after {settled:.2f} s (largest stamp "
        f"gap {np.max(gaps):.3f} s; steps {states[-1].steps}, held back "
        f"{states[-1].held_back}); status clock offset "
        f"{states[k - 1].offset_s - 1.7e9:+.4f} -> {states[-1].offset_s - 1.7e9:+.4f} s"
    )
