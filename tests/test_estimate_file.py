"""The estimate file written in pieces while the rows are computed (`EstimateFile`): the same
bytes as one plain write of the whole table, written while the batch still computes, and a
run that fails midway leaves the path as it was (never a file cut off or mixing two runs)."""

from __future__ import annotations

import csv
import errno
import io
import math
import os
import time
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from keo_service.core import batch
from keo_service.core.errors import KeoError
from keo_service.io.interchange import write_encoder, write_tracker
from keo_service.offline import library
from keo_service.sim.simulate import make_scenario, simulate
from tests.conftest import CONFIGS

DEMO = CONFIGS / "demo.toml"
CHANNELS = ("px", "py", "pz", "rx", "ry", "rz")
SMALL_CHUNK, SMALL_STEP = 256, 1024  # rows per kinematics chunk and per observer step


def _table(rows: int, seed: int) -> tuple[np.ndarray, ...]:
    """Stamps, measured (NaN rows: held), estimates and flags with awkward numbers: tiny,
    huge, negative zero, whole, and values whose shortest text needs an exponent."""
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.0005, 0.0015, rows))
    awkward = np.array([1e-300, -1e-5, 1e5, 1e16, -0.0, 0.0, 1.0, 5e-324, 123456789.125])
    measured = rng.normal(0.0, 1e-3, (rows, 6)) * 10.0 ** rng.integers(-8, 8, (rows, 6))
    measured[rng.random(rows) < 0.02] = np.nan
    measured.flat[rng.integers(0, measured.size, 50)] = rng.choice(awkward, 50)
    estimate = np.asfortranarray(rng.normal(0.0, 1e-4, (rows, 6)))
    flags = rng.choice(
        np.array(["", "encoder_gap", "outside_calibrated_range"], dtype=object), rows
    )
    return t, np.asfortranarray(measured), estimate, flags


def _plain_write(path: Path, t, measured, estimate, flags) -> None:
    """One polars write of the whole table, built here (the columns of the interchange
    format: held rows' measured values and empty flags written as empty cells)."""
    columns = {"t": t}
    columns |= {f"meas_{c}": measured[:, i] for i, c in enumerate(CHANNELS)}
    columns |= {f"est_{c}": estimate[:, i] for i, c in enumerate(CHANNELS)}
    frame = pl.DataFrame(columns).fill_nan(None)
    texts = [f or None for f in flags.tolist()]
    frame.with_columns(pl.Series("flags", texts, dtype=pl.String)).write_csv(path)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_pieces_of_any_size_give_the_bytes_of_one_plain_write(tmp_path, seed):
    from keo_service.io.interchange import EstimateFile

    t, measured, estimate, flags = _table(5000, seed)
    _plain_write(tmp_path / "plain.csv", t, measured, estimate, flags)
    cuts = np.sort(np.random.default_rng(seed).choice(np.arange(1, 5000), 12, replace=False))
    file = EstimateFile(tmp_path / "pieces.csv")
    for lo, hi in zip([0, *cuts.tolist()], [*cuts.tolist(), 5000], strict=True):
        file.add(CHANNELS, t[lo:hi], measured[lo:hi], estimate[lo:hi], flags[lo:hi])
    file.commit()
    written = (tmp_path / "pieces.csv").read_bytes()
    assert written == (tmp_path / "plain.csv").read_bytes()
    # and the text reads back to the same floats, held values and empty flags empty
    rows = list(csv.reader(io.StringIO(written.decode())))
    assert rows[0] == [
        "t",
        *(f"meas_{c}" for c in CHANNELS),
        *(f"est_{c}" for c in CHANNELS),
        "flags",
    ]
    for k in (0, 1, 2499, 4999):
        row = rows[k + 1]
        assert float(row[0]) == t[k]
        for i in range(6):
            want = measured[k, i]
            assert (row[1 + i] == "") if math.isnan(want) else float(row[1 + i]) == want
        assert [float(v) for v in row[7:13]] == estimate[k].tolist()
        assert row[13] == flags[k]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pieces.csv", "plain.csv"]


def test_an_empty_table_is_its_header(tmp_path):
    from keo_service.io.interchange import EstimateFile

    file = EstimateFile(tmp_path / "e.csv")
    file.add((), np.empty(0), np.empty((0, 0)), np.empty((0, 0)), [])
    file.commit()
    assert (tmp_path / "e.csv").read_text() == "t,flags\n"


def test_a_replaced_file_keeps_its_mode_and_a_link_stays_a_link(tmp_path):
    from keo_service.io.interchange import EstimateFile

    t, measured, estimate, flags = _table(10, 4)
    target = tmp_path / "target.csv"
    target.write_text("old\n")
    target.chmod(0o640)
    link = tmp_path / "link.csv"
    link.symlink_to(target)
    file = EstimateFile(link)
    file.add(CHANNELS, t, measured, estimate, flags)
    file.commit()
    assert link.is_symlink()
    assert target.read_text().startswith("t,meas_px")
    assert target.stat().st_mode & 0o777 == 0o640


@pytest.fixture(scope="module")
def recording(demo_cell, tmp_path_factory) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("recording")
    run = simulate(
        demo_cell,
        make_scenario(
            "path", {"duration_s": "6", "tracker_rate_hz": "1000", "encoder_rate_hz": "250"}
        ),
        seed=5,
    )
    write_encoder(folder / "encoder.csv", run.encoder)
    write_tracker(folder / "tracker.csv", run.tracker)
    return folder / "encoder.csv", folder / "tracker.csv"


def _bytes_in(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.iterdir())


@pytest.fixture
def small_steps(monkeypatch):
    """Several kinematics chunks and observer steps on a short recording."""
    monkeypatch.setattr(batch, "CHUNK", SMALL_CHUNK)
    monkeypatch.setattr(batch, "OBSERVER_ROWS", SMALL_STEP)


def test_rows_are_written_while_the_batch_still_computes(
    recording, tmp_path, small_steps, monkeypatch
):
    encoder, tracker = recording
    out = tmp_path / "estimates.csv"
    steps: list[int] = []
    on_disk_during_batch: list[int] = []
    run_to = batch._Observer.run_to

    def observed(self, hi, measured, estimate):
        run_to(self, hi, measured, estimate)
        steps.append(hi)
        if len(steps) == 3:  # the batch is not done: two more steps at least
            # the writer thread writes the first steps' rows meanwhile: wait for them (the
            # code before wrote nothing until the batch had returned)
            deadline = time.monotonic() + 10.0
            while _bytes_in(tmp_path) == 0 and time.monotonic() < deadline:
                time.sleep(0.01)
            on_disk_during_batch.append(_bytes_in(tmp_path))

    monkeypatch.setattr(batch._Observer, "run_to", observed)
    result = library.estimate(DEMO, encoder, tracker, out)
    assert result.path == "batch"
    assert len(steps) >= 5
    assert on_disk_during_batch == [on_disk_during_batch[0]]
    assert on_disk_during_batch[0] > 0, "nothing written before the batch ended"
    plain = tmp_path / "plain.csv"
    _plain_write(
        plain, result.stamp, result.measured, result.estimate, np.array(result.flags, dtype=object)
    )
    assert out.read_bytes() == plain.read_bytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["estimates.csv", "plain.csv"]


def test_a_write_that_fails_midway_leaves_the_old_file_whole(
    recording, tmp_path, small_steps, monkeypatch
):
    # a full disk after part of the rows: the old file stays as it was, not cut off
    encoder, tracker = recording
    out = tmp_path / "estimates.csv"
    out.write_text("the previous run's file\n")
    write_csv = pl.DataFrame.write_csv
    rows_written = [0]

    def disk_full_midway(self, file=None, **kwargs):
        # the disk fills up once 3000 rows (about half the recording) are in the file
        rows_written[0] += self.height
        if rows_written[0] <= 3000:
            return write_csv(self, file, **kwargs)
        text = write_csv(self, None, **kwargs)
        if isinstance(file, str | os.PathLike):
            with open(file, "w") as f:
                f.write(text[: len(text) // 2])
        else:
            file.write(text[: len(text) // 2].encode())
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(pl.DataFrame, "write_csv", disk_full_midway)
    with pytest.raises(KeoError, match=r"cannot write the estimate file .*No space left"):
        library.estimate(DEMO, encoder, tracker, out)
    assert out.read_text() == "the previous run's file\n"
    assert [p.name for p in tmp_path.iterdir()] == ["estimates.csv"]  # no partial file left


def test_a_batch_that_gives_up_after_writing_rows_is_written_whole_by_the_streaming_path(
    recording, tmp_path, small_steps, monkeypatch
):
    encoder, tracker = recording
    out = tmp_path / "estimates.csv"
    finish = batch._finish_chunk
    chunks = []

    def gives_up_late(rows, *args):
        chunks.append(rows)
        if len(chunks) == 12:  # after several steps were handed to the writer
            raise batch.BatchUnsupportedError("given up for the test")
        return finish(rows, *args)

    monkeypatch.setattr(batch, "_finish_chunk", gives_up_late)
    result = library.estimate(DEMO, encoder, tracker, out)
    assert result.path == "streaming (given up for the test)"
    plain = tmp_path / "plain.csv"
    _plain_write(
        plain, result.stamp, result.measured, result.estimate, np.array(result.flags, dtype=object)
    )
    assert out.read_bytes() == plain.read_bytes()


def test_an_unwritable_path_fails_before_the_work(recording, tmp_path, monkeypatch):
    # the estimate file is opened first: a wrong --out costs no computing
    from keo_service.offline import estimate as offline_estimate

    encoder, tracker = recording
    out = tmp_path / "a folder"
    out.mkdir()
    computed = []
    monkeypatch.setattr(
        offline_estimate, "estimate_recording", lambda *args, **kwargs: computed.append(1)
    )
    with pytest.raises(KeoError, match=r"cannot write the estimate file .*a folder"):
        library.estimate(DEMO, encoder, tracker, out)
    assert computed == []
    assert [p.name for p in tmp_path.iterdir()] == ["a folder"]
