"""Rerun logging, kept at the edge: one function sets up the blueprint, one logs estimates."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from keo_service.messages import EstimateMessage

POS = "keo/error/pos"
ROT = "keo/error/rot"


def blueprint() -> rrb.Blueprint:
    return rrb.Blueprint(
        rrb.Vertical(
            rrb.TimeSeriesView(origin=f"/{POS}", name="position error [mm]"),
            rrb.TimeSeriesView(origin=f"/{ROT}", name="orientation error [mrad]"),
        ),
        rrb.TimePanel(state="collapsed"),
    )


def log_estimates(path: Path, estimates: Sequence[EstimateMessage]) -> None:
    """Measured and estimated error per channel (mm, mrad) on the sample time line."""
    rec = rr.RecordingStream("keo")
    rec.set_sinks(rr.FileSink(str(path)), default_blueprint=blueprint())
    if estimates:
        t = np.array([e.stamp for e in estimates])
        est = np.array([e.estimate for e in estimates]) * 1e3
        meas = (
            np.array(
                [
                    e.measured if e.measured is not None else [np.nan] * len(e.estimate)
                    for e in estimates
                ]
            )
            * 1e3
        )
        times = [rr.TimeColumn("t", duration=t - t[0])]
        channels = estimates[0].channels
        for i, name in enumerate(channels):
            group = POS if name.startswith("p") else ROT
            rec.send_columns(
                f"{group}/{name}/estimate",
                indexes=times,
                columns=rr.Scalars.columns(scalars=est[:, i]),
            )
            rec.send_columns(
                f"{group}/{name}/measured",
                indexes=times,
                columns=rr.Scalars.columns(scalars=meas[:, i]),
            )
    rec.flush(timeout_sec=5.0)
    rec.disconnect()
