"""Issue 45 as it was found: the whole cell as processes (keo run, both adapters, a MotoROS
controller mock stamped on receipt, 40 Hz sent with jitter, and a line-protocol tracker on its
own clock), all six joints moving, a constant tool error injected, the delay between the
streams injected by the mocks (28 ms, 3 ms jitter).

- With the right delay configured, tracking on never ends worse than tracking off (the issue:
  a wrong fit taken at once, 0.76 mm / 1.29 mrad off after 25 s). "Off" is the same play's
  samples, recorded by `keo record` and run through `keo estimate` with the configured delay:
  two plays differ by more than what is judged (the delay the stamps need moves with the host's
  load by a few hundred microseconds, 12 against 69 um for one configuration in two plays at a
  load of 12 on two cores).
- From an unknown delay (`delay_s = 0`), 20 s after the motion starts the estimate is within
  50 um / 50 urad of the truth, or every estimate until then carried `delay_unsettled`.

What is judged is the estimate against the error the simulator injected, never a number the
service computed."""

from __future__ import annotations

import asyncio
import json
import time

import msgspec
import numpy as np
import pytest

from keo_service.bench.demo import loopback_config
from keo_service.bench.procs import process_group
from keo_service.io.config import config_to_toml
from keo_service.offline.library import estimate
from keo_service.sim.simulate import make_scenario, simulate
from tests.test_live import collect

SCENARIO = "path"
# the issue's outside check: tool 0.1-0.3 m/s, the tracker's poses 10 um / 10 urad noisy, its
# stamps lagging by the delay alone (the scenario's default adds 3 ms of random lag per pose,
# the paper's tracker, which would bury every difference judged here in noise)
SETTINGS = {
    "tool_error_only": "true",
    "duration_s": "40",
    "path_speed": "0.6",
    "delay_jitter_s": "0",
    "position_noise_m": "10e-6",
    "rotation_noise_rad": "10e-6",
}
SPAN_S = 30.0  # seconds of estimates collected from the first one
GAIN = 2.0  # the observer's gain (1/s): noise of a few um / urad per estimate


def _play(demo_config, tmp_path, name: str, record: bool = False, **timing: object) -> list:
    """One play of the cell with these [timing] keys: the estimates over SPAN_S seconds (and,
    with `record`, the samples in <tmp_path>/<name>/recording)."""
    config = loopback_config(demo_config)
    observer = msgspec.structs.replace(config.observer, gain=[GAIN] * 6)
    config = msgspec.structs.replace(
        config, observer=observer, timing=msgspec.structs.replace(config.timing, **timing)
    )
    work = tmp_path / name
    work.mkdir()
    cfg = work / "cell.toml"
    cfg.write_text(config_to_toml(config))
    t0 = time.time() + 5.0
    play = ["--scenario", SCENARIO, "--seed", "3", "--t0", repr(t0), "--duration", "40"]
    for key, value in SETTINGS.items():
        play += ["--set", f"{key}={value}"]
    with process_group(work) as procs:
        procs.start_cell(cfg, play)
        if record:
            out = ["--out", str(work / "recording"), "--duration", "45"]
            procs.start("record", ["record", "--config", str(cfg), *out])
        estimates = asyncio.run(collect(config, t0 + 45.0, span=SPAN_S))
    return [e for e in estimates if e.measured is not None]


def _error(estimates: list, truth: np.ndarray, since: float, until: float) -> tuple[float, float]:
    """RMS over estimates stamped in [since, until] of the estimate's distance from the truth:
    position (m, norm of xyz), orientation (rad, norm of the rotation part)."""
    stamps = np.array([e.stamp for e in estimates])
    values = np.array([e.estimate for e in estimates])
    return _error_of(stamps, values, truth, since, until)


def _error_of(
    stamps: np.ndarray, values: np.ndarray, truth: np.ndarray, since: float, until: float
) -> tuple[float, float]:
    sel = (stamps >= since) & (stamps <= until)
    assert sel.sum() > 20, f"only {sel.sum()} estimates in [{since:.1f}, {until:.1f}]"
    err = values[sel] - truth
    pos = np.sqrt(np.mean(np.sum(err[:, :3] ** 2, axis=1)))
    rot = np.sqrt(np.mean(np.sum(err[:, 3:] ** 2, axis=1)))
    return float(pos), float(rot)


@pytest.mark.e2e
@pytest.mark.slow  # two plays of 35-45 s each
def test_the_issue_cell_a_right_delay_kept_and_an_unknown_one_flagged(
    demo_config, demo_cell, tmp_path
):
    scenario = make_scenario(SCENARIO, SETTINGS)
    truth = simulate(demo_cell, scenario, seed=3).truth
    assert np.ptp(truth, axis=0).max() < 1e-9  # a constant tool error: one truth
    truth = truth[0]
    assert np.linalg.norm(truth[:3]) > 3e-4  # large against what is judged (50 um)

    right = {"delay_s": 0.028, "delay_se_s": 0.0005}
    on = _play(demo_config, tmp_path, "on", record=True, track_delay=True, **right)
    unknown = _play(demo_config, tmp_path, "unknown", track_delay=True, delay_s=0.0)
    # tracking off: the same samples through the service's estimator, the delay fixed
    fixed = msgspec.structs.replace(demo_config.timing, track_delay=False, **right)
    observer = msgspec.structs.replace(demo_config.observer, gain=[GAIN] * 6)
    config_off = msgspec.structs.replace(demo_config, timing=fixed, observer=observer)
    recording = tmp_path / "on" / "recording"
    off = estimate(config_off, recording / "encoder.csv", recording / "tracker.csv", quiet=True)

    last = on[-1].stamp
    end = {
        "on": _error(on, truth, last - 5.0, last),
        "off": _error_of(off.stamp, off.estimate, truth, last - 5.0, last),
    }
    first = unknown[0].stamp
    at20 = _error(unknown, truth, first + 19.0, first + 20.0)
    flagged = all("delay_unsettled" in e.flags for e in unknown if e.stamp <= first + 20.0)
    print(json.dumps({"end_um_urad": end, "unknown_at_20s": at20, "flagged": flagged}))
    print(
        json.dumps({"delay_in_use_at_end": {"on": on[-1].delay_s, "unknown": unknown[-1].delay_s}})
    )
    # a right configured delay: tracking on ends no worse than off (10 um / 10 urad)
    assert end["on"][0] <= end["off"][0] + 10e-6, end
    assert end["on"][1] <= end["off"][1] + 10e-6, end
    # a configured delay is settled from the start: no estimate flagged
    assert not any("delay_unsettled" in e.flags for e in on)
    # from an unknown delay: found, or said not to be
    assert (at20[0] <= 50e-6 and at20[1] <= 50e-6) or flagged, (at20, flagged)
    # once the flag is off the delay is right: 3 s later (six of the observer's time
    # constants, so the estimate has left what the unsettled delay did) within 50 um / 50 urad
    settled = [e for e in unknown if "delay_unsettled" not in e.flags]
    if settled and settled[0].stamp + 5.0 <= unknown[-1].stamp:
        since = settled[0].stamp
        later = _error(unknown, truth, since + 3.0, since + 5.0)
        assert later[0] <= 50e-6, later
        assert later[1] <= 50e-6, later
