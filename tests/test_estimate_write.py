"""How the estimate file is opened: once, by keo, and handed to polars as an open file. Given
the path, polars opens it twice, truncating each time, and on ext4 the second truncation (of
the then empty file) makes close() start writing the whole file back (docs/performance.md,
Round 12c)."""

from __future__ import annotations

import os

import numpy as np
import polars as pl

from keo_service.io.interchange import read_estimates, write_estimate_table


def test_polars_gets_an_open_file_not_a_path(tmp_path, monkeypatch):
    write_csv = pl.DataFrame.write_csv
    targets: list[object] = []

    def recording_target(self, file=None, **kwargs):
        targets.append(file)
        return write_csv(self, file, **kwargs)

    monkeypatch.setattr(pl.DataFrame, "write_csv", recording_target)
    t = np.array([0.5, 1.0, 1.5])
    measured = np.array([[1e-3, -2e-3, 3e-3], [np.nan, np.nan, np.nan], [4e-3, 5e-3, -6e-3]])
    estimate = np.array([[1e-4, 2e-4, 3e-4], [1e-4, 2e-4, 3e-4], [5e-4, -6e-4, 7e-4]])
    out = tmp_path / "folder" / "estimates.csv"
    write_estimate_table(out, t, measured, estimate, ["", "encoder_gap", ""], ("px", "py", "pz"))
    assert len(targets) == 1
    assert not isinstance(targets[0], str | os.PathLike)
    assert targets[0].closed  # type: ignore[attr-defined]
    back = read_estimates(out)
    assert back.channels == ["px", "py", "pz"]
    assert back.t.tolist() == t.tolist()
    np.testing.assert_array_equal(back.measured, measured)  # NaN where held
    assert back.estimate.tolist() == estimate.tolist()
    assert back.flags == ["", "encoder_gap", ""]
