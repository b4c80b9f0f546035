"""Issue 45: the online delay never turns a right setup wrong, and finds an unknown delay
while saying it is not settled. In-process streams stamped as the adapters stamp them (a
MotoROS encoder stamped on receipt through `ReceiptStamps`, 40 Hz, sent 25 +/- 3 ms apart; a
line-protocol tracker at 100 Hz with 10 um / 10 urad noise; an MH180 moving all joints
slowly), the delay injected (30 ms), so every number is judged against the truth.

The harm a delay does is |v| |delay in use - injected| (and |w| for the orientation), RMS over
the last second: the offset the delay adds to the measured error there (docs/design.md §3)."""

from __future__ import annotations

import numpy as np
import pytest

from keo_service.sim.delay_study import StreamCase, case_streams, delay_harm, run_tracker

TRUTH = 0.030


def _right_delay_no_worse_than_tracking_off(demo_cell, streams):
    """The right delay configured (30 ms, 0.5 ms): tracking on ends at most 10 um / 10 urad
    worse than tracking off on the same streams. The run with tracking on."""
    run = run_tracker(demo_cell, streams, TRUTH, 0.0005)
    off = run_tracker(demo_cell, streams, TRUTH, 0.0005, track=False)
    on_m, on_rad = delay_harm(streams, run, float(streams.trk_t[-1]))
    off_m, off_rad = delay_harm(streams, off, float(streams.trk_t[-1]))
    assert on_m <= off_m + 10e-6, run.decisions
    assert on_rad <= off_rad + 10e-6, run.decisions
    return run


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_right_configured_delay_is_never_made_worse(demo_cell, seed):
    """The issue's first run: delay_s = 0.030 configured right; a fit 4.7 se off was taken at
    once and the right ones refused (0.76 mm / 1.29 mrad after 25 s). Before this change the
    delay in use left 30 ms here too (seed 0: 28.3 ms at the end, 176 um at speed)."""
    streams = case_streams(demo_cell, StreamCase("motoros", "line100", "all_slow"), seed)
    run = _right_delay_no_worse_than_tracking_off(demo_cell, streams)
    assert not run.unsettled.any()  # a configured delay is settled from the start


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_from_an_unknown_delay_every_estimate_is_flagged_until_settled(demo_cell, seed):
    """delay_s = 0 and no delay_se_s: the delay is found from the motion, a step (no slew at
    1 ms/s: 30 s of 1-7 mm errors in the issue), and every estimate before it is settled is
    flagged."""
    streams = case_streams(demo_cell, StreamCase("motoros", "line100", "all_slow"), seed)
    run = run_tracker(demo_cell, streams, 0.0, None)
    at20 = streams.motion_start + 20.0
    harm_m, harm_rad = delay_harm(streams, run, at20)
    good = (harm_m <= 50e-6) and (harm_rad <= 50e-6)
    sel = run.t <= at20
    # either within 50 um / 50 urad 20 s after the motion starts, or every estimate up to then
    # carries the flag (the fits of this slow, receipt-stamped motion scatter by ~1 ms)
    assert good or run.unsettled[sel].all(), (harm_m, harm_rad, run.decisions)
    # the flag never lies: an unflagged estimate's delay is within 50 um at speed
    settled = ~run.unsettled
    if settled.any():
        first = float(run.t[np.argmax(settled)])
        assert delay_harm(streams, run, first + 1.0)[0] <= 50e-6, run.decisions
    # it got near the truth at once, not at 1 ms/s: the delay in use 10 s after the motion
    # starts is within 3 ms (a slew from 0 would still be 20 ms short)
    k = np.searchsorted(run.t, streams.motion_start + 10.0)
    assert abs(run.delay[k] - TRUTH) < 3e-3, run.decisions


@pytest.mark.parametrize("seed", [4, 5])
def test_one_joint_at_constant_speed_cannot_change_a_right_delay(demo_cell, seed):
    """ROS 2 streams, one joint at constant speed, 30 ms configured right: the tool's velocity
    in the tool frame is constant, so a delay looks like a constant tool error. Before the
    separability test three fits biased alike by 3-5 ms were taken (seed 4: 865 um / 435 urad
    worse than tracking off at the end; seed 5: 575 um / 289 urad)."""
    streams = case_streams(demo_cell, StreamCase("ros2", "ros2", "one_joint"), seed)
    _right_delay_no_worse_than_tracking_off(demo_cell, streams)


def test_one_joint_from_an_unknown_delay_stays_flagged(demo_cell):
    """MotoROS / 1 kHz line tracker, one joint at constant speed, from delay_s = 0: the fits
    agree, but the motion cannot separate a delay from a tool error, so the estimate is never
    marked settled (seed 2 was settled and 94 um off 20 s after the motion started)."""
    streams = case_streams(demo_cell, StreamCase("motoros", "line1k", "one_joint"), 2)
    run = run_tracker(demo_cell, streams, 0.0, None)
    at20 = streams.motion_start + 20.0
    harm_m, harm_rad = delay_harm(streams, run, at20)
    assert (harm_m <= 50e-6 and harm_rad <= 50e-6) or run.unsettled[run.t <= at20].all()
    assert run.unsettled.all(), run.decisions


@pytest.mark.parametrize(
    ("encoder", "seed"),
    [("rtde", 1), ("motoros", 0)],
)
def test_all_joints_slow_with_geometry_found_from_zero_within_50_um(demo_cell, encoder, seed):
    """All joints slow with configuration-dependent geometric errors, from delay_s = 0: 20 s
    after the motion starts the delay in use is within 50 um / 50 urad at the tool's speed,
    every estimate until then flagged, and its stated se covers its error. These two runs
    were the worst of the stretches' consensus alone: short stretches' linear error models
    take up most of a slow motion's delay signature and, with geometric errors, are biased
    alike; the pooled fit of the samples since the delay was unknown is not (figures in
    docs/timing-delay.md)."""
    streams = case_streams(demo_cell, StreamCase(encoder, "line100", "all_slow", True), seed)
    run = run_tracker(demo_cell, streams, 0.0, None)
    at20 = streams.motion_start + 20.0
    harm_m, harm_rad = delay_harm(streams, run, at20)
    assert harm_m <= 50e-6, (harm_m, run.decisions)
    assert harm_rad <= 50e-6, (harm_rad, run.decisions)
    upto = run.t <= at20
    last = int(np.flatnonzero(upto)[-1])
    assert abs(run.delay[last] - TRUTH) <= 2.5 * run.delay_se[last], run.decisions
    # the flag never lies: an unflagged estimate's delay is within 50 um at speed
    clear = ~run.unsettled & upto
    err = np.abs(run.delay[clear] - TRUTH) * np.linalg.norm(streams.tool_v[clear], axis=1)
    assert np.max(err, initial=0.0) <= 50e-6


@pytest.mark.parametrize("seed", [0, 1])
def test_one_joint_cannot_separate_flagged_and_covered(demo_cell, seed):
    """MotoROS / 100 Hz, one joint at constant speed, from delay_s = 0: T(q - w t)^-1 T(q) is
    constant, so a delay is a constant tool error to the data after the start's ramp. The
    delay stays unsettled, every estimate flagged, the tracker says the motion does not
    separate a delay, and the standard error it states for the delay in use covers that
    delay's actual error (within 2.5 of it) at every estimate that has one: the verdict is
    "cannot separate", never "met"."""
    from keo_service.sim.delay_study import harm_row, harm_verdict

    streams = case_streams(demo_cell, StreamCase("motoros", "line100", "one_joint"), seed)
    run = run_tracker(demo_cell, streams, 0.0, None)
    assert run.unsettled.all(), run.decisions
    assert run.separable[-1] == 0, run.decisions
    stated = np.isfinite(run.delay_se)
    assert stated[-1]
    z = np.abs(run.delay[stated] - TRUTH) / run.delay_se[stated]
    assert z.max() <= 2.5, (z.max(), run.decisions)
    row = harm_row(demo_cell, StreamCase("motoros", "line100", "one_joint"), seed)
    assert row["verdict"] == "cannot separate", row
    assert not row["ok"]
    # the verdicts themselves: only "met" meets the target
    assert harm_verdict(True, True, True, False, 0.5) == "met"
    assert harm_verdict(False, True, True, True, 0.5) == "covered, missed"
    assert harm_verdict(False, True, True, False, 3.0) == "missed"
    assert harm_verdict(False, False, False, False, 0.5) == "missed"
