"""The offline pipelines (`keo_service.offline`): each file of a recording is read once per
command, and the command's result is what the pipeline computes from those arrays."""

from __future__ import annotations

import msgspec
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


class _AnalyzedError(Exception):
    """Raised in place of the analysis: every file is read before it starts."""


@pytest.fixture
def stop_at_analysis(monkeypatch):
    """keo analyze up to the analysis itself (the reading, pairing and the delay's fit and
    judgement run; the analysis after them reads nothing), plus the interchange readers
    counted wherever they are looked up at call time."""
    from keo_service.offline import analyze

    seen = []

    def stop(robot, data, *args, **kwargs):
        seen.append(data)
        raise _AnalyzedError

    monkeypatch.setattr(analyze, "analyze", stop)
    return seen


def test_keo_analyze_reads_each_file_once(
    demo_config, recorded, reads, stop_at_analysis, monkeypatch, tmp_path
):
    """A motion recording: paired with the config's delay, the delay fitted from the motion
    and the streams paired again with it, all from one read of each file (it was four)."""
    from keo_service.offline.analyze import run_analysis

    # the config says no delay: the simulator's 28 ms is found and the streams re-paired
    config = msgspec.structs.replace(
        demo_config, timing=msgspec.structs.replace(demo_config.timing, delay_s=0.0)
    )
    for name in ("read_encoder", "read_tracker"):  # a reader imported at call time counts too
        monkeypatch.setattr(interchange, name, getattr(recording_module(), name))
    from keo_service.offline import analyze

    delays = []

    def pair_streams(robot, recording, delay, *args, **kwargs):
        delays.append(delay.offset_s)
        return pair(robot, recording, delay, *args, **kwargs)

    pair = analyze.pair_streams
    monkeypatch.setattr(analyze, "pair_streams", pair_streams)
    run, encoder, tracker = recorded
    with pytest.raises(_AnalyzedError):
        run_analysis(config, encoder, tracker, tmp_path / "out", False)
    assert sorted(reads) == ["encoder.csv", "tracker.csv"]
    assert delays[0] == 0.0  # paired twice (the config's delay, the found one), read once
    assert abs(delays[1] - 0.028) < 1e-3
    (data,) = stop_at_analysis
    assert data.velocity is not None
    assert data.n > 0.9 * run.tracker.t.size


def test_keo_analyze_reads_each_file_of_each_session_once(
    demo_config, demo_cell, reads, stop_at_analysis, tmp_path
):
    from keo_service.offline.analyze import run_analysis

    paths = []
    for seed in (1, 2):
        run = simulate(demo_cell, make_scenario("static-poses", {"poses": "60"}), seed=seed)
        folder = tmp_path / f"s{seed}"
        folder.mkdir()
        write_encoder(folder / "encoder.csv", run.encoder)
        write_tracker(folder / "tracker.csv", run.tracker)
        paths.append((folder / "encoder.csv", folder / "tracker.csv"))
    encoders, trackers = [list(p) for p in zip(*paths, strict=True)]
    with pytest.raises(_AnalyzedError):
        run_analysis(demo_config, encoders, trackers, tmp_path / "out", False)
    assert sorted(reads) == ["encoder.csv"] * 2 + ["tracker.csv"] * 2
    (data,) = stop_at_analysis
    assert data.n == 120
    assert set(data.session.tolist()) == {0, 1}


def recording_module():
    from keo_service.offline import recording

    return recording
