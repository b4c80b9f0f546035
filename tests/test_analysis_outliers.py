"""The analysis's outlier listing: each listed pose with the joints on which it lies outside
the angles the fit saw, and runs of consecutive listed poses, named in report.md. Nothing is
rejected. The poses placed outside and how far are the test's own construction."""

from __future__ import annotations

import numpy as np

from keo_service.fit.analysis import split
from keo_service.fit.model import Data
from keo_service.io.analysis_report import _outliers_markdown
from keo_service.offline.analyze import OUTLIER_FACTOR, outlier_poses

NAMES = ("j1", "j2", "j3")


def test_a_run_outside_the_fitted_angles_is_named_with_how_far() -> None:
    rng = np.random.default_rng(4)
    n = 4000  # held-out noise enough that the threshold (4x their RMS) lies below the run
    q = rng.uniform(-1.0, 1.0, size=(n, 3))
    train, val = split(n)
    first = int(val[10])  # eleven consecutive held-out poses (one held-out block holds 50)
    run = np.arange(first, first + 11)
    assert np.all(np.isin(run, val))
    beyond = np.linspace(0.04, 0.08, run.size)  # how far below joint 2's fitted range
    q[run, 1] = q[train, 1].min() - beyond
    error = np.abs(rng.normal(0.0, 0.05, n))
    error[run] = 0.5 + beyond  # the model extrapolates: the error grows outside
    lone = int(val[40])  # one large error inside the fitted angles
    error[lone] = 1.0
    data = Data(q, np.zeros((n, 3)), None, np.arange(n, dtype=float))

    out = outlier_poses(error, error[val], data, train, val, NAMES)

    threshold = OUTLIER_FACTOR * float(np.sqrt(np.mean(error[val] ** 2)))
    assert out["threshold_mm"] == threshold
    listed = {r["row"]: r for r in out["held_out"]}
    assert set(run) | {lone} <= set(listed)
    for i, d in zip(run, beyond, strict=True):
        assert np.isclose(listed[int(i)]["outside_fitted_rad"]["j2"], d)
        assert set(listed[int(i)]["outside_fitted_rad"]) == {"j2"}
    assert "outside_fitted_rad" not in listed[lone]
    assert [r["pos_mm"] for r in out["held_out"]] == sorted(
        (r["pos_mm"] for r in out["held_out"]), reverse=True
    )
    assert len(out["runs"]) == 1
    found = out["runs"][0]
    assert (found["set"], found["first_row"], found["last_row"]) == (
        "held_out",
        int(run[0]),
        int(run[-1]),
    )
    assert found["poses"] == found["outside_fitted"] == 11
    assert np.isclose(found["outside_fitted_rad"]["j2"], beyond.max())
    assert out["fitted"] == []

    text = "\n".join(_outliers_markdown({"outliers": out}))
    assert f"rows {run[0]}-{run[-1]}" in text
    assert "j2 by up to 0.080 rad" in text
    assert "not rejected" in text
