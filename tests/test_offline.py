"""The offline pipelines (`keo_service.offline`): each file of a recording is read once per
command, and the command's result is what the pipeline computes from those arrays."""

from __future__ import annotations

import numpy as np
import pytest

from keo_service.io import interchange
from keo_service.io.interchange import write_encoder, write_tracker
from keo_service.sim.simulate import make_scenario, simulate


@pytest.fixture
def recorded(demo_cell, tmp_path):
    run = simulate(demo_cell, make_scenario("path"), seed=7)
    encoder, tracker = tmp_path / "encoder.csv", tmp_path / "tracker.csv"
    write_encoder(encoder, run.encoder)
    write_tracker(tracker, run.tracker)
    return run, encoder, tracker


@pytest.fixture
def reads(monkeypatch):
    """Every call of the interchange readers, by file name."""
    from keo_service.offline import recording

    calls: list[str] = []

    def counted(reader):
        def read(path, *args, **kwargs):
            calls.append(str(path).rsplit("/", 1)[-1])
            return reader(path, *args, **kwargs)

        return read

    monkeypatch.setattr(recording, "read_encoder", counted(interchange.read_encoder))
    monkeypatch.setattr(recording, "read_tracker", counted(interchange.read_tracker))
    return calls


def test_keo_estimate_reads_each_file_once(demo_config, recorded, reads):
    from keo_service.offline.estimate import estimate_files

    run, encoder, tracker = recorded
    result = estimate_files(demo_config, encoder, tracker)
    assert sorted(reads) == ["encoder.csv", "tracker.csv"]
    assert result.path == "batch"
    assert result.table.stamp.size == run.tracker.t.size


def test_keo_calibrate_delay_reads_each_file_once(demo_config, recorded, reads):
    from keo_service.offline.delay import calibrate_delay

    _run, encoder, tracker = recorded
    result = calibrate_delay(demo_config, encoder, tracker)
    assert sorted(reads) == ["encoder.csv", "tracker.csv"]
    # the simulator's delay (the demo config's 28 ms) is found within a few standard errors
    assert result.explained
    assert abs(result.fit.delay_s - 0.028) < 5 * result.fit.delay_se_s + 1e-4
    assert result.lines()[0].startswith("delay: ")
    assert np.isclose(result.document()["delay_s"], result.fit.delay_s)
