"""The device clock mapping (core.clock) on synthetic (device stamp, receipt) pairs whose truth
is known: each sample's true instant on the host clock, the device clock's offset and drift,
the latency floor, bursts of late delivery, seconds-long rises in latency and restarts of the
mapping (a new adapter process) or of the device clock. The error of a mapped stamp is
`mapped - (true instant + floor)`: the floor cannot be seen from the host and stays in the
offset by design."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest

from keo_service.core.clock import ClockMapper

FLOOR_S = 150e-6


@dataclass
class Stream:
    h: np.ndarray  # true instants, host clock
    d: np.ndarray  # device stamps
    r: np.ndarray  # receipts, host clock


def stream(
    seconds: float,
    rate_hz: float = 500.0,
    drift_ppm: float = 80.0,
    seed: int = 1,
    jitter_s: float = 50e-6,
    late_s: float = 0.006,
    burst_every_s: float = 1.0,
    rise: tuple[float, float, float] | None = None,
    start_h: float = 100.0,
    lucky: float = 0.0,
    wake_s: tuple[float, float] = (0.0, 0.0),
) -> Stream:
    """Samples at `rate_hz`: latency = floor + exponential jitter, stalls up to `late_s` every
    `burst_every_s` on average (the samples held go out together), and `rise` = (start s,
    seconds, extra latency s) of a rise in latency lasting seconds (a loaded host)."""
    rng = np.random.default_rng(seed)
    h = start_h + np.arange(int(seconds * rate_hz)) / rate_hz
    d = 7.0 + (h - start_h) * (1.0 + drift_ppm * 1e-6)
    # a receiving process that was asleep wakes up 60-180 us later; one sample in `lucky`
    # finds it awake (measured on a loaded loopback: block minima 80-270 us)
    asleep = rng.uniform(size=h.size) >= lucky
    wake = np.where(asleep, rng.uniform(wake_s[0], wake_s[1], h.size), 0.0)
    r = h + FLOOR_S + rng.exponential(jitter_s, h.size) + wake
    if rise is not None:
        a, length, extra = rise
        inside = (h >= start_h + a) & (h < start_h + a + length)
        r[inside] += extra
    at = start_h + float(rng.uniform(0, burst_every_s))
    while late_s > 0 and at < h[-1]:
        stall = float(rng.uniform(0.2, 1.0)) * late_s
        held = (h >= at) & (h < at + stall)
        r[held] = np.maximum(r[held], at + stall)
        at += float(rng.exponential(burst_every_s)) + stall
    return Stream(h, d, np.maximum.accumulate(r))


def connection_start(s: Stream, at_s: float, extra_s: float = 0.002, decay_s: float = 0.15):
    """A new connection at `at_s` into the stream: its first samples wait longer (a backlog,
    a process that has just started), decaying over `decay_s`."""
    keep = s.h >= s.h[0] + at_s
    h, d, r = s.h[keep], s.d[keep], s.r[keep].copy()
    r += extra_s * np.exp(-(h - h[0]) / decay_s)
    return Stream(h, d, np.maximum.accumulate(r))


def mapped_errors(mapper: ClockMapper, s: Stream) -> np.ndarray:
    out = np.array([mapper.map(di, ri) for di, ri in zip(s.d, s.r, strict=True)])
    return out - (s.h + FLOOR_S)


@pytest.mark.parametrize("drift_ppm", [80.0, -40.0])
def test_steady_stamps_sit_on_the_floor(drift_ppm):
    s = stream(40.0, drift_ppm=drift_ppm, rate_hz=500.0 if drift_ppm > 0 else 100.0)
    mapper = ClockMapper()
    err = mapped_errors(mapper, s)
    after = s.h - s.h[0] > 10.0
    # the stamps keep the device's regularity: within 12 us of the floor (a block's least
    # latency is a few us above it at 100 Hz), never below it by more than 2 us; the receipts
    # are off by milliseconds in the bursts
    assert np.max(err[after]) < 12e-6
    assert np.min(err[after]) > -2e-6
    assert np.max(s.r - s.h - FLOOR_S) > 1e-3
    assert mapper.state().drift_ppm == pytest.approx(-drift_ppm, abs=1.0)
    assert not mapper.state().drift_held


@pytest.mark.parametrize("drift_ppm", [80.0, -40.0])
def test_a_restarted_mapping_holds_its_drift_until_the_span_supports_one(drift_ppm):
    """A new adapter process maps the same device clock from scratch, its first samples
    waiting 2 ms longer. The first version fitted a drift from its first two blocks and the
    stamps swung by hundreds of us; held, the swing is the drift over the hold window."""
    s = connection_start(stream(12.0, drift_ppm=drift_ppm, seed=3), at_s=2.0)
    mapper = ClockMapper()
    err = mapped_errors(mapper, s)
    since = s.h - s.h[0]
    # the connection's backlog cannot be undone while it lasts (2 ms decaying over 0.15 s:
    # 2.5 us left after 1 s); until the blocks span 4 s the drift is held (zero) and the
    # offset taken from the newest 1 s: measured 11..51 us off over 6 runs of 80 ppm at 500 Hz
    # and -40 ppm at 100 Hz (the first version, fitting a drift from two blocks: -1234..-11 us
    # in 1-3 s); from 5 s on within 2 us (first version: up to 92 us in 3-10 s)
    learning = (since > 1.0) & (since < 4.5)
    assert np.max(np.abs(err[learning])) < 60e-6
    assert np.max(np.abs(err[since > 5.0])) < 10e-6
    assert np.all(np.diff(err + s.h) > 0)  # never back


def test_the_drift_before_a_device_clock_step_is_kept_as_the_prior():
    s = stream(30.0, drift_ppm=80.0, seed=4)
    step = s.h - s.h[0] > 15.0
    d = np.where(step, s.d - 5.0, s.d)  # the device clock jumps back 5 s (a controller restart)
    mapper = ClockMapper()
    out = np.array([mapper.map(di, ri) for di, ri in zip(d, s.r, strict=True)])
    err = out - (s.h + FLOOR_S)
    assert mapper.steps == 1
    relearn = step & (s.h - s.h[0] < 17.5)
    assert mapper.prior_drift == pytest.approx(-80e-6, abs=1e-6)
    # three samples go by before the step is confirmed; then the held drift is the right one
    assert np.max(np.abs(err[relearn][5:])) < 15e-6


@pytest.mark.parametrize("loaded", [False, True])
def test_a_rise_in_latency_lasting_seconds_does_not_move_the_stamps(loaded):
    """The host is loaded for 3 s: every sample waits 300 us longer. The first version's
    least-squares line followed it: -105..+285 us (issue 31 saw +35 us, then a -10 us
    undershoot, with a smaller rise). Measured now: within 1.2 us on a steady floor, and
    -10..+20 us when the block minima themselves scatter by 120 us (a loaded host)."""
    kw = {"lucky": 0.002, "wake_s": (60e-6, 180e-6)} if loaded else {}
    s = stream(40.0, seed=0, rise=(20.0, 3.0, 300e-6), **kw)
    err = mapped_errors(ClockMapper(), s)
    after = s.h - s.h[0] > 10.0
    ref = np.median(err[after & (s.h - s.h[0] < 19.0)])
    assert np.max(np.abs(err[after] - ref)) < (30e-6 if loaded else 3e-6)


def test_a_new_floor_lasting_longer_than_the_window_is_followed():
    s = stream(50.0, seed=6, rise=(15.0, 35.0, 200e-6))  # from 15 s on, 200 us more
    err = mapped_errors(ClockMapper(), s)
    late = s.h - s.h[0] > 36.0  # window_s (20 s) after the change, and a second for the drift
    assert np.median(err[late]) == pytest.approx(200e-6, abs=15e-6)


def test_a_clock_step_is_still_detected_and_relearned():
    s = stream(20.0, drift_ppm=0.0, late_s=0.002, burst_every_s=0.1, seed=7)
    d = np.where(s.h - s.h[0] > 8.0, s.d - 1000.0 + 3.0, s.d)
    mapper = ClockMapper()
    out = np.array([mapper.map(di, ri) for di, ri in zip(d, s.r, strict=True)])
    assert mapper.steps == 1
    settled = s.h - s.h[0] > 10.0
    assert np.max(np.abs(out[settled] - s.h[settled] - FLOOR_S)) < 15e-6
    assert not math.isnan(mapper.state().residual_s)


@pytest.mark.parametrize(("drift_ppm", "rate_hz"), [(80.0, 500.0), (-40.0, 100.0)])
def test_steady_stamps_on_a_loaded_host_keep_still(drift_ppm, rate_hz):
    """Block minima scattering by 120 us with rare lucky samples (a loaded host): the mapped
    stamps stay within 15 us of their median (measured 3.4-9.3 us; the first version's
    least-squares line 6.6-22.9 us)."""
    s = stream(60.0, drift_ppm=drift_ppm, rate_hz=rate_hz, lucky=0.002, wake_s=(60e-6, 180e-6))
    err = mapped_errors(ClockMapper(), s)
    after = s.h - s.h[0] > 10.0
    assert np.max(np.abs(err[after] - np.median(err[after]))) < 15e-6


@pytest.mark.parametrize(("rate_hz", "drift_ppm"), [(100.0, -40.0), (500.0, 80.0)])
def test_a_stretch_of_faster_delivery_does_not_move_the_stamps(rate_hz, drift_ppm):
    """For 8 s of a minute the host answers 140 us faster (its other core awake, a quiet
    spell): a floor that moved for a while, not a clock. The offset is the median of the
    window's block minima, so the stamps stay put: measured 3-6 us over three seeds; the
    mean of the lowest half (the version before) followed the spell by 112-116 us."""
    s = stream(60.0, rate_hz=rate_hz, drift_ppm=drift_ppm, rise=(30.0, 8.0, -140e-6))
    err = mapped_errors(ClockMapper(), s)
    t = s.h - s.h[0]
    before = np.median(err[(t > 20.0) & (t < 30.0)])
    assert np.max(np.abs(err[t > 30.0] - before)) < 20e-6


@pytest.mark.parametrize(
    ("rise", "tolerance_s"), [((0.0, 10.4, 0.07), 60e-6), ((5.0, 12.0, 0.06), 5e-6)]
)
def test_a_host_that_ran_behind_for_seconds_is_no_clock_step(rise, tolerance_s):
    """The host falls 60-70 ms behind the stream for 10-12 s (a loaded CI machine: the case a
    CI run caught, two false steps at 10.4 s and stamps off by 0.64 ms p99), then catches up.
    No step is called: the lag comes back down a sample period per sample, to where it was or
    below. Once caught up the stamps sit on the floor again: within `tolerance_s` of the
    truth (60 us while the drift is learned anew after a backlog from the start)."""
    s = stream(25.0, seed=0, rise=rise, late_s=0.006, burst_every_s=0.2)
    mapper = ClockMapper()
    err = mapped_errors(mapper, s)
    assert mapper.steps == 0
    caught_up = s.h - s.h[0] > rise[0] + rise[1] + 1.0
    assert np.max(np.abs(err[caught_up])) < tolerance_s


def test_a_forward_device_clock_step_after_a_backlog_is_still_a_step():
    """After a 70 ms backlog (3-10 s) the device clock jumps 60 ms ahead at 14 s: the lag
    falls at once, below anything the window saw: one step, relearned."""
    s = stream(25.0, drift_ppm=0.0, seed=3, rise=(3.0, 7.0, 0.07), late_s=0.002)
    jumped = s.h - s.h[0] > 14.0
    d = np.where(jumped, s.d + 0.06, s.d)
    mapper = ClockMapper()
    out = np.array([mapper.map(di, ri) for di, ri in zip(d, s.r, strict=True)])
    assert mapper.steps == 1
    settled = s.h - s.h[0] > 16.0
    assert np.max(np.abs(out[settled] - s.h[settled] - FLOOR_S)) < 15e-6
