"""A configured delay moves only when the fits show it should (issue 45: automation may only
improve on what the user configured).

The tracker's stamps here are right (the injected delay is exactly the one configured), but its
device clock runs 12.5 ppm slow against the host, and its young clock mapping, with the drift
still held at zero, follows that by moving its line's offset: 375 us over 30 s. The mapped
stamps stay right; only the line the mapping reports moved. A delay fitted under one line is
carried along such moves (it describes the stamps of that line), but a configured delay was
calibrated under no line keo saw: carried along the mapping's learning it drifted off a right
value with no fit behind it (in the issue's cell, run as processes: 122 us, 25 um / 25 urad
worse than with tracking off)."""

from __future__ import annotations

import numpy as np

from keo_service.fit.delay_online import OnlineDelayTracker
from keo_service.sim.delay_study import StreamCase, case_streams

TRUTH = 0.030
SLOW_PPM = 12.5


def _feed(cell, streams, configured_s: float, configured_se_s: float | None) -> np.ndarray:
    """The delay in use at each tracker sample, the tracker's samples carrying the lines
    their young mapping reports (offset moving, drift held at zero)."""
    tracker = OnlineDelayTracker(cell, prior_s=configured_s, prior_se_s=configured_se_s)
    in_use = np.empty(streams.trk_t.size)
    k = 0
    for i, t in enumerate(streams.trk_t):
        while k < streams.enc_t.size and streams.enc_t[k] <= t:
            tracker.add_encoder(float(streams.enc_t[k]), streams.enc_q[k])
            k += 1
        device = float(t) * (1.0 - SLOW_PPM * 1e-6)
        tracker.add_tracker(
            float(t), streams.trk_p[i], streams.trk_quat[i], device_stamp=device, clock_drift=0.0
        )
        if tracker.due():
            tracker.combine(tracker.measure(tracker.snapshot(), tracker.delay_now()))
        now = tracker.delay_now()
        in_use[i] = configured_s if now is None else now
    return in_use


def test_a_configured_delay_is_not_carried_along_a_young_mappings_line(demo_cell):
    streams = case_streams(demo_cell, StreamCase("motoros", "line100", "all_slow"), 0)
    in_use = _feed(demo_cell, streams, TRUTH, 0.0005)
    speed = np.linalg.norm(streams.tool_v, axis=1)
    harm = np.abs(in_use - TRUTH) * speed
    late = streams.trk_t > streams.trk_t[-1] - 5.0
    # the stamps need 30 ms throughout: the configured value, kept, does no harm; a change
    # may come only from fits, and they see 30 ms too
    assert np.sqrt(np.mean(harm[late] ** 2)) <= 10e-6, (in_use[late].min(), in_use[late].max())


def test_a_configured_delay_is_not_confirmed_by_a_young_mappings_fits(demo_cell):
    """The outside check of issue 45 again, run as processes (docs/timing-delay.md): the first
    fits, of a young mapping and the motion's slow start, "confirmed" the configured delay,
    and from then on it followed the young line's learning (110-176 us in 40 s, up to 41 um
    worse than tracking off). Here a device-clock encoder's precise fits in the first seconds
    confirmed it on the code before: 345 us off at the end, 73 um at the tool. A fit
    confirms only once its mapping is no longer young."""
    for seed in (0, 1):
        streams = case_streams(demo_cell, StreamCase("rtde", "line100", "all_slow"), seed)
        in_use = _feed(demo_cell, streams, TRUTH, 0.0005)
        harm = np.abs(in_use - TRUTH) * np.linalg.norm(streams.tool_v, axis=1)
        assert harm.max() <= 10e-6, (seed, in_use.min(), in_use.max())
