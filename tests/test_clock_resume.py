"""A device-clock mapping that goes on across a reconnect or a restarted adapter (core.clock
`export` / `resume` / `reconnect`, adapters.clock_state on disk): on synthetic streams whose
truth is known (tests/test_clock.py's), the stamps after a restart stay on the line they were
on, a device that restarted meanwhile (or another device at the address) starts a new
mapping, and a saved mapping too old only lends its drift."""

from __future__ import annotations

import json

import msgspec
import numpy as np
import pytest

from keo_service.adapters.clock_state import load_into, save, state_path
from keo_service.core.clock import RESUME_MAX_AGE_S, ClockMapper, Stamper
from keo_service.io.config import config_to_toml, load_config
from tests.conftest import CONFIGS
from tests.test_clock import FLOOR_S, Stream, connection_start, mapped_errors, stream


def _split(s: Stream, at_s: float, gap_s: float) -> tuple[Stream, Stream]:
    """The stream before `at_s` and the one from `at_s + gap_s` on (an adapter away)."""
    since = s.h - s.h[0]
    first = since < at_s
    before = Stream(s.h[first], s.d[first], s.r[first])
    return before, connection_start(s, at_s + gap_s)


@pytest.mark.parametrize("drift_ppm", [80.0, -40.0])
def test_a_restarted_adapter_goes_on_on_the_saved_line(drift_ppm):
    """Same stream, the adapter killed at 30 s and back 1 s later: from the saved mapping the
    stamps go on where they were; learned anew they are off by the held drift and then by a
    drift fitted from a few seconds of blocks."""
    s = stream(50.0, drift_ppm=drift_ppm, rate_hz=500.0 if drift_ppm > 0 else 100.0, seed=6)
    before, after = _split(s, 30.0, 1.0)
    first = ClockMapper()
    err_before = mapped_errors(first, before)
    saved = json.loads(json.dumps(first.export()))  # as it goes through the file
    resumed = ClockMapper()
    assert resumed.resume(saved)
    err_resumed = mapped_errors(resumed, after)
    fresh_err = mapped_errors(ClockMapper(), after)
    since = after.h - after.h[0]
    ref = float(np.median(err_before[before.h - before.h[0] > 20.0]))
    # the connection's backlog (2 ms decaying over 0.15 s) is in the first second either way
    settled = since > 1.0
    assert np.max(np.abs(err_resumed[settled] - ref)) < 5e-6
    assert resumed.state().steps == 0
    assert not resumed.state().drift_held
    assert resumed.state().continued == 1
    # learned anew: the drift held at zero for 4 s costs drift x hold / 2 and more
    assert np.max(np.abs(fresh_err[settled] - ref)) > 15e-6


def test_a_device_that_restarted_meanwhile_gets_a_new_mapping():
    """The controller restarted while the adapter was away: its clock starts again at 0.
    The saved line is refused (a step) and the drift it had is the new mapping's prior."""
    s = stream(40.0, drift_ppm=80.0, seed=7)
    before, after = _split(s, 20.0, 1.0)
    first = ClockMapper()
    mapped_errors(first, before)
    mapper = ClockMapper()
    assert mapper.resume(first.export())
    restarted = Stream(after.h, after.d - after.d[0], after.r)  # device time from 0
    out = np.array([mapper.map(d, r) for d, r in zip(restarted.d, restarted.r, strict=True)])
    assert mapper.state().steps == 1
    assert mapper.prior_drift == pytest.approx(-80e-6, abs=2e-6)
    since = after.h - after.h[0]
    err = out - (after.h + FLOOR_S)
    assert np.max(np.abs(err[(since > 1.0) & (since < 4.0)])) < 60e-6


def test_a_device_whose_stamps_come_late_against_the_saved_line_gets_a_new_mapping():
    """Another device at the address (or a clock set back by less than it ran): its samples
    arrive 2 s later than the saved line says. Late is normally a stall the mapping removes;
    against a continued line not yet confirmed it is a step."""
    s = stream(40.0, drift_ppm=80.0, seed=8)
    before, after = _split(s, 20.0, 1.0)
    first = ClockMapper()
    mapped_errors(first, before)
    stamper = Stamper("device", epoch=5)
    said = stamper.resume({"domain": "device", "epoch": 3, "mapping": first.export()}, 2.0)
    assert "goes on" in said
    stamper.restart()  # the adapter's new connection
    assert stamper.epoch == 3  # the saved epoch: the time base goes on
    stamps = [stamper.stamp(d - 2.0, r) for d, r in zip(after.d, after.r, strict=True)]
    assert stamper.epoch == 4  # the line did not hold: a new time base
    assert stamper.mapper.state().steps == 1
    since = after.h - after.h[0]
    err = np.array([st.stamp for st in stamps]) - (after.h + FLOOR_S)
    assert np.max(np.abs(err[since > 1.0])) < 100e-6


def test_a_reconnect_in_the_same_process_goes_on_and_keeps_the_epoch():
    s = stream(40.0, drift_ppm=-40.0, rate_hz=100.0, seed=9)
    before, after = _split(s, 20.0, 0.5)
    stamper = Stamper("device", epoch=10)
    stamper.restart()
    for d, r in zip(before.d, before.r, strict=True):
        stamper.stamp(d, r)
    stamper.restart()
    assert stamper.epoch == 11
    flags = [stamper.stamp(d, r).flags for d, r in zip(after.d, after.r, strict=True)]
    assert stamper.epoch == 11
    # until its first block confirms the line, samples say the mapping is not sure yet
    assert flags[0] == ("clock_relearning",)
    assert flags[-1] == ()
    assert stamper.state()["continued"] == 1


def test_a_saved_mapping_too_old_lends_only_its_drift():
    s = stream(30.0, drift_ppm=80.0, seed=10)
    first = ClockMapper()
    mapped_errors(first, s)
    saved = {"domain": "device", "epoch": 3, "mapping": first.export()}
    stamper = Stamper("device", epoch=5)
    said = stamper.resume(saved, RESUME_MAX_AGE_S + 1.0)
    assert "prior" in said
    assert stamper.epoch == 5
    assert stamper.mapper.state().blocks == 0
    assert stamper.mapper.prior_drift == pytest.approx(-80e-6, abs=2e-6)
    # not a device clock, or nonsense: nothing changes
    assert "nothing" in Stamper("receipt").resume(saved, 1.0)
    bad = Stamper("device", epoch=5)
    assert "learning anew" in bad.resume({"domain": "device", "mapping": {"blocks": "x"}}, 1.0)
    assert bad.epoch == 5
    assert bad.mapper.state().blocks == 0
    assert not ClockMapper().resume({"blocks": [[1.0, 0.1], [0.5, 0.1]], "drift": 0.0})


def test_the_mapping_file_round_trips_and_a_bad_one_is_learned_anew(tmp_path):
    s = stream(20.0, drift_ppm=80.0, seed=11)
    stamper = Stamper("device", epoch=7)
    stamper.restart()
    for d, r in zip(s.d, s.r, strict=True):
        stamper.stamp(d, r)
    state = stamper.export()
    assert state is not None
    path = state_path(str(tmp_path / "clocks"), "cell/1", "encoder", "rtde://10.0.0.2:30004")
    assert path.parent == tmp_path / "clocks"
    assert "/" not in path.name
    save(state, path, "rtde://10.0.0.2:30004")
    again = Stamper("device", epoch=99)
    assert "goes on" in load_into(again, path, "rtde://10.0.0.2:30004")
    again.restart()
    assert again.epoch == 8
    other = Stamper("device", epoch=99)
    assert "not this device" in load_into(other, path, "rtde://10.0.0.3:30004")
    assert "too old" in load_into(Stamper("device"), path, "rtde://10.0.0.2:30004", now=1e12)
    path.write_text("{not json")
    assert "unreadable" in load_into(Stamper("device"), path, "rtde://10.0.0.2:30004")
    assert "no saved" in load_into(Stamper("device"), tmp_path / "none.json", "x")


def test_a_relative_clock_state_dir_is_relative_to_the_config_file(tmp_path):
    base = load_config(CONFIGS / "ur10_demo.toml")
    assert base.timing.clock_state_dir == ""  # not kept unless asked for
    timing = msgspec.structs.replace(base.timing, clock_state_dir="clocks")
    path = tmp_path / "c.toml"
    path.write_text(config_to_toml(msgspec.structs.replace(base, timing=timing)))
    assert load_config(path).timing.clock_state_dir == str(tmp_path / "clocks")
