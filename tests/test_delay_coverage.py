"""Issue 45, item 2: the standard error each online delay fit reports covers the injected
delay. In-process streams stamped as the adapters stamp them (sim/delay_study.py), run
through the online tracker with the right delay configured; z = |fit - injected| / the se
the fit reports (the one the log, `keo status` and the gate use). The whole matrix, 200 fits
per scenario, is `python docs/delay_coverage.py` (docs/timing-delay.md has its table)."""

from __future__ import annotations

import numpy as np
import pytest

from keo_service.fit.delay_online import DelayRefused, OnlineDelayTracker
from keo_service.sim.delay_study import StreamCase, case_streams, coverage

# a receipt-stamped encoder with all joints slow and geometric errors that the stretches'
# linear error model does not hold (the cell; its fits the roughest), a device clock
# stopping and going, and a wrist turning about a still tool point with geometric errors
REPRESENTATIVE = [
    (StreamCase("motoros", "line100", "all_slow", geometry=True), 900.0, 900.0),
    (StreamCase("rtde", "line100", "stop_go"), 120.0, 360.0),  # its moves last 121 s
    (StreamCase("rtde", "line100", "wrist", geometry=True), 300.0, 300.0),
]


@pytest.mark.slow
def test_the_fits_standard_errors_cover_the_injected_delay(demo_cell):
    pooled: list[float] = []
    for case, seconds, total in REPRESENTATIVE:
        cov = coverage(demo_cell, case, min_fits=10_000, seconds=seconds, max_seconds=total)
        assert cov.n >= 60, (case.label, cov.row())
        # 95 % within 2.5 se is the target; one scenario's 50-100 fits may miss it by a fit
        assert cov.within(2.5) >= 0.93, (case.label, cov.row())
        pooled += cov.z
    assert np.mean(np.asarray(pooled) <= 2.5) >= 0.95
    assert len(pooled) >= 200


@pytest.mark.slow
@pytest.mark.parametrize(
    ("encoder", "tracker"), [("rtde", "line100"), ("ros2", "line100"), ("rtde", "line1k")]
)
def test_all_joints_slow_with_geometric_errors_the_fits_scatter_is_counted(
    demo_cell, encoder, tracker
):
    """The rows that missed the target (issue 45; 86.7-87.6 % of fits within 2.5 se at 100
    Hz, then 93.2-93.6 % at 1 kHz): all joints slow on a device or shared clock, geometric
    errors the stretches' linear error model does not hold. Their fits scatter by hundreds
    of us beyond their own se from one stretch to the next; the scatter (tau) is estimated
    over the segment's recent fits beyond their own se with their unequal precision weighed
    (Paule-Mandel), and counted in every fit's se unless its two error models disagree by
    more. Deterministic (simulated streams, fits in line): the same figures at any load."""
    case = StreamCase(encoder, tracker, "all_slow", geometry=True)
    cov = coverage(demo_cell, case, min_fits=200, max_seconds=2100.0)
    assert cov.n >= 200, cov.row()
    # measured 97.7-98.6 % of 218-219 fits: the target holds with 5 fits to spare
    assert cov.within(2.5) >= 0.95, cov.row()


def test_one_joint_at_constant_speed_is_not_identifiable_and_says_why(demo_cell):
    """The tool's velocity in the tool frame is constant: a delay looks like a tool error.
    The stretch says so instead of giving a number (the fits gave 45-69 % of their values
    within 2.5 of their own se there)."""
    streams = case_streams(demo_cell, StreamCase("rtde", "line100", "one_joint"), 1)
    tracker = OnlineDelayTracker(demo_cell, prior_s=0.030, prior_se_s=0.0005)
    sel = (streams.trk_t > 10.0) & (streams.trk_t < 15.0)
    enc = (streams.enc_t > 9.0) & (streams.enc_t < 16.0)
    window = (
        streams.enc_t[enc],
        streams.enc_q[enc],
        streams.trk_t[sel],
        streams.trk_p[sel],
        streams.trk_quat[sel],
    )
    found = tracker.measure(window, 0.030)
    assert isinstance(found, DelayRefused), found
    assert found.counter == "fits_not_identifiable"
    assert "cannot separate a delay from a tool error" in found.reason
