"""The simulator and the offline pipeline, checked against the truth they inject."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from keo_service.core.estimator import Estimator, run_offline
from keo_service.core.observer import noise_gain
from keo_service.core.settings import EstimatorSettings
from keo_service.fit.evaluate import as_series, truth_at
from keo_service.io.cell import estimator_settings
from keo_service.io.interchange import read_encoder, read_estimates, read_tracker, read_truth
from keo_service.sim.simulate import make_scenario, simulate
from tests.conftest import DEMO, keo


@pytest.fixture(scope="module")
def vertical_files(tmp_path_factory):
    out = tmp_path_factory.mktemp("vertical")
    result = keo(
        "simulate",
        "--config",
        str(DEMO),
        "--scenario",
        "paper-vertical",
        "--out",
        str(out),
        "--seed",
        "3",
    )
    assert result.returncode == 0, result.stderr
    return out


def test_streams_have_the_requested_rates_jitter_and_noise(vertical_files, tmp_path):
    enc = read_encoder(vertical_files / "encoder.csv")
    trk = read_tracker(vertical_files / "tracker.csv")
    enc_rate = 1 / np.diff(enc.t)
    trk_rate = 1 / np.diff(trk.t)
    # drops (0.5 %) and the spread of 1/period bias these a little; the periods tell better
    assert 1 / np.median(np.diff(enc.t)) == pytest.approx(39.5, rel=0.05)
    assert 1 / np.median(np.diff(trk.t)) == pytest.approx(99.6, rel=0.08)
    assert np.std(np.diff(enc.t)) == pytest.approx(6.0 / 39.5**2, rel=0.25)
    assert np.median(enc_rate) > 35
    assert np.median(trk_rate) > 85
    assert np.all(np.diff(enc.t) > 0)
    assert np.all(np.diff(trk.t) > 0)
    assert np.allclose(np.linalg.norm(trk.quat, axis=1), 1.0, atol=1e-12)
    # position noise: from a static scenario, the spread of the measured position
    out = tmp_path / "step"
    assert (
        keo(
            "simulate",
            "--config",
            str(DEMO),
            "--scenario",
            "paper-step",
            "--out",
            str(out),
            "--set",
            "position_noise_m=25e-6",
        ).returncode
        == 0
    )
    static = read_tracker(out / "tracker.csv")
    assert np.std(static.p, axis=0) == pytest.approx([25e-6] * 3, rel=0.1)


def test_delay_in_the_files_is_what_was_asked(demo_config, demo_cell):
    """With the true delay the motion offset vanishes; with none it is speed x delay."""
    run = simulate(demo_cell, make_scenario("paper-vertical", {"position_noise_m": "0"}), seed=2)
    lags = run.tracker.t - run.physical_t
    assert np.mean(lags) == pytest.approx(0.028, abs=0.5e-3)
    assert np.std(lags) == pytest.approx(0.003, rel=0.15)
    for delay, expected in ((0.028, 0.0), (0.0, -0.1 * 0.028)):
        settings = estimator_settings(demo_config)
        settings = EstimatorSettings(
            **{**settings.__dict__, "delay": type(settings.delay)(offset_s=delay)}
        )
        series = as_series(
            run_offline(
                Estimator(demo_cell, settings),
                run.encoder.t,
                run.encoder.q,
                run.tracker.t,
                run.tracker.p,
                run.tracker.quat,
            )
        )
        moving = np.interp(series.stamp, run.truth_t, run.moving.astype(float)) > 0.5
        dev = series.measured[moving] - truth_at(series.stamp[moving], run.truth_t, run.truth)
        # motion is along the tool's z axis (flange down, moving vertically)
        assert np.nanmean(dev[:, 2]) == pytest.approx(expected, abs=0.1e-3)


def test_zero_noise_zero_delay_recovers_the_injected_error(tmp_path):
    out = tmp_path / "clean"
    sets = ["position_noise_m=0", "rotation_noise_rad=0", "delay_s=0", "delay_jitter_s=0"]
    args = ["simulate", "--config", str(DEMO), "--scenario", "paper-step", "--out", str(out)]
    for s in sets:
        args += ["--set", s]
    assert keo(*args).returncode == 0
    res = keo(
        "estimate",
        "--config",
        str(DEMO),
        "--encoder",
        str(out / "encoder.csv"),
        "--tracker",
        str(out / "tracker.csv"),
        "--out",
        str(out / "est.csv"),
        "--json",
    )
    assert res.returncode == 0, res.stderr
    est = read_estimates(out / "est.csv")
    t_true, truth, channels = read_truth(out / "truth.csv")
    assert channels == ["px", "py", "pz", "rx", "ry", "rz"]
    ok = ~np.isnan(est.measured[:, 0])
    expected = truth_at(est.t[ok], t_true, truth)
    assert np.max(np.abs(est.measured[ok] - expected)) < 1e-9
    late = est.t > est.t[0] + 10.0  # gain 2 in the demo: 10 s is 20 time constants
    assert np.max(np.abs(est.estimate[late] - truth_at(est.t[late], t_true, truth))) < 1e-9
    assert np.max(np.abs(truth[:, :3])) > 1e-4  # the injected error is real, not zero


def test_zero_noise_in_motion_limited_by_interpolation(demo_config, demo_cell):
    scen = make_scenario(
        "path",
        {
            "position_noise_m": "0",
            "rotation_noise_rad": "0",
            "delay_s": "0",
            "delay_jitter_s": "0",
            "encoder_rate_hz": "1000",
            "encoder_rate_std_hz": "0",
            "duration_s": "10",
        },
    )
    run = simulate(demo_cell, scen, seed=4)
    settings = EstimatorSettings(gains=tuple(demo_config.observer.gain))  # delay 0, as simulated
    series = as_series(
        run_offline(
            Estimator(demo_cell, settings),
            run.encoder.t,
            run.encoder.q,
            run.tracker.t,
            run.tracker.p,
            run.tracker.quat,
        )
    )
    ok = np.all(np.isfinite(series.measured), axis=1)
    dev = series.measured[ok] - truth_at(series.stamp[ok], run.truth_t, run.truth)
    assert np.max(np.abs(dev[:, :3])) < 1e-6  # linear interpolation over 1 ms of joint motion


def test_realistic_noise_stays_in_the_predicted_band(demo_config, demo_cell):
    run = simulate(demo_cell, make_scenario("paper-step", {"duration_s": "60"}), seed=5)
    series = as_series(
        run_offline(
            Estimator(demo_cell, estimator_settings(demo_config)),
            run.encoder.t,
            run.encoder.q,
            run.tracker.t,
            run.tracker.p,
            run.tracker.quat,
        )
    )
    late = series.stamp > series.stamp[0] + 5.0
    err = series.estimate[late] - truth_at(series.stamp[late], run.truth_t, run.truth)
    period = float(np.mean(np.diff(run.tracker.t)))
    band = noise_gain(demo_config.observer.gain[0], period)
    for k, sigma in ((0, 20e-6), (1, 20e-6), (2, 20e-6), (3, 50e-6), (4, 50e-6), (5, 50e-6)):
        assert np.std(err[:, k]) == pytest.approx(band * sigma, rel=0.3)
        assert np.max(np.abs(err[:, k])) < 5 * band * sigma


def test_estimate_skips_bad_rows_and_counts_them(tmp_path, vertical_files):
    lines = (vertical_files / "tracker.csv").read_text().splitlines()
    header, rows = lines[0], lines[1:]
    bad = [
        rows[0],
        rows[2],
        rows[1],
        rows[2],
        rows[3].replace(rows[3].split(",")[1], "nan", 1),
        *rows[4:],
    ]
    (tmp_path / "tracker.csv").write_text("\n".join([header, *bad]) + "\n")
    res = keo(
        "estimate",
        "--config",
        str(DEMO),
        "--encoder",
        str(vertical_files / "encoder.csv"),
        "--tracker",
        str(tmp_path / "tracker.csv"),
        "--out",
        str(tmp_path / "e.csv"),
        "--json",
    )
    assert res.returncode == 0, res.stderr
    counters = json.loads(res.stdout)["counters"]
    assert counters["tracker_out_of_order"] == 1
    assert counters["tracker_duplicate"] == 1
    assert counters["tracker_non_finite"] == 1


@pytest.mark.parametrize(
    ("content", "where"),
    [
        ("t,x,y\n0,1,2\n", "columns must start with"),
        (
            "t,x,y,z,qw,qx,qy,qz\n0,1,2,3,1,0,0,0\n0.1,1,2,abc,1,0,0,0\n",
            ":3: column 'z': 'abc' is not a number",
        ),
        ("t,x,y,z,qw,qx,qy,qz\n0,1,2,3,1,0,0\n", ":2: column '-': 7 fields, expected 8"),
    ],
)
def test_bad_file_names_file_line_and_column(tmp_path, vertical_files, content, where):
    (tmp_path / "tracker.csv").write_text(content)
    res = keo(
        "estimate",
        "--config",
        str(DEMO),
        "--encoder",
        str(vertical_files / "encoder.csv"),
        "--tracker",
        str(tmp_path / "tracker.csv"),
        "--out",
        str(tmp_path / "e.csv"),
    )
    assert res.returncode == 2
    assert "tracker.csv" in res.stderr
    assert where in res.stderr


def test_encoder_with_wrong_joint_count_is_refused(tmp_path, vertical_files):
    (tmp_path / "encoder.csv").write_text("t,q1,q2\n0,0,0\n")
    res = keo(
        "estimate",
        "--config",
        str(DEMO),
        "--encoder",
        str(tmp_path / "encoder.csv"),
        "--tracker",
        str(vertical_files / "tracker.csv"),
        "--out",
        str(tmp_path / "e.csv"),
    )
    assert res.returncode == 2
    assert "the robot model has 6" in res.stderr


def test_paper_command_reproduces_the_reference():
    res = keo("paper", "--json", timeout=300)
    assert res.returncode == 0, res.stderr
    report = json.loads(res.stdout)
    for row in report["settling"]:
        assert row["simulated_s"] == pytest.approx(math.log(50) / row["gain"], rel=0.12)
        assert row["simulated_s"] >= row["theory_s"]  # sampling only delays settling
    v = report["vertical"]
    assert v["found_delay_ms"] == pytest.approx(28.0, abs=2.0)
    for w in v["windows"]:
        assert w["offset_before_mm"] == pytest.approx(-2.8, abs=0.3)
        assert w["offset_reduction_pct"] > 90.0
        assert w["noise_rejected_pct"] > 75.0
    for a in report["alignment"]:
        assert a["ratio_motion_pos"] > 2.0  # interpolation beats the reference in motion


def test_position_only_gives_the_same_positions_as_6dof(tmp_path):
    """A 6-DoF file and the same data stripped of orientation: identical position estimates."""
    full = tmp_path / "full"
    assert (
        keo(
            "simulate",
            "--config",
            str(DEMO),
            "--scenario",
            "paper-vertical",
            "--out",
            str(full),
            "--seed",
            "4",
            "--set",
            "duration_s=12",
        ).returncode
        == 0
    )
    stripped = tmp_path / "stripped"
    stripped.mkdir()
    lines = (full / "tracker.csv").read_text().splitlines()
    (stripped / "tracker.csv").write_text(
        "\n".join(",".join(line.split(",")[:4]) for line in lines) + "\n"
    )
    results = {}
    for name, trk in (("full", full / "tracker.csv"), ("stripped", stripped / "tracker.csv")):
        out = tmp_path / f"{name}.csv"
        res = keo(
            "estimate",
            "--config",
            str(DEMO),
            "--encoder",
            str(full / "encoder.csv"),
            "--tracker",
            str(trk),
            "--out",
            str(out),
        )
        assert res.returncode == 0, res.stderr
        results[name] = read_estimates(out)
    a, b = results["full"], results["stripped"]
    assert b.channels == ["px", "py", "pz"]
    assert a.channels == ["px", "py", "pz", "rx", "ry", "rz"]
    assert np.array_equal(a.t, b.t)
    assert np.max(np.abs(a.estimate[:, :3] - b.estimate)) < 1e-12
    ok = ~np.isnan(b.measured[:, 0])
    assert np.max(np.abs(a.measured[ok, :3] - b.measured[ok])) < 1e-12
    header = (tmp_path / "stripped.csv").read_text().splitlines()[0]
    assert "rx" not in header  # orientation is absent, not zero-filled


def test_position_only_scenario_files(tmp_path):
    out = tmp_path / "po"
    assert (
        keo(
            "simulate",
            "--config",
            str(DEMO),
            "--scenario",
            "path",
            "--out",
            str(out),
            "--position-only",
            "--set",
            "duration_s=5",
        ).returncode
        == 0
    )
    assert (out / "tracker.csv").read_text().splitlines()[0] == "t,x,y,z"
    _t, truth, channels = read_truth(out / "truth.csv")
    assert channels == ["px", "py", "pz"]
    assert truth.shape[1] == 3
