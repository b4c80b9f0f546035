"""Two device clocks, end to end with real processes: the RTDE mock controller on its own clock
(+80 ppm, delivery late in bursts) and the line-protocol mock tracker on its own (-40 ppm, late
in bursts too), each adapter killed and restarted three times, the service starting from
`delay_s = 0` with the online delay fit on (the default). keo must find the delay itself.
The adapters keep their clock mappings in `timing.clock_state_dir`, so that a restarted
adapter goes on on the line it had instead of learning its device's drift anew.

The truth is established from the mocks, not from keo: each mock stamps a sample with its own
clock at the instant the sample describes (`offset + scenario time * (1 + drift)`, offsets and
drifts given on the command line), so from a sample's device stamp the test knows the wall
time it describes. The samples on the bus also carry their receipt time (`host_ns`), so the
transport floor of each stream (least receipt - instant) is measured independently of keo's
clock mapping; and each mapped stamp's own error (stamp - instant) is known too. The delay
keo needs is then

    injected delay + (tracker stamp error) - (encoder stamp error)

(a tracker sample stamped t showed the tool at scenario time s - D, whose encoder stamp is off
by the encoder's stamp error); with stamps mapped onto the lower envelope, each stamp error is
that stream's transport floor, so the truth is also D + floor(tracker) - floor(encoder). The
test prints both and judges against the first (what the estimate needs); the estimate is
judged against the injected constant tool error, known from the simulator."""

from __future__ import annotations

import json
import math
import signal
import threading
import time

import msgspec
import numpy as np
import pytest

from keo_service.bench.demo import loopback_config
from keo_service.bench.procs import process_group
from keo_service.io.cell import cell_from_config
from keo_service.io.config import config_to_toml, load_config
from keo_service.live.bus import session_for_client
from keo_service.live.messages import EstimateMessage, JointSample, TrackerSample, decode
from keo_service.sim.simulate import make_scenario, simulate
from tests.conftest import CONFIGS, wait_for_status

pytestmark = pytest.mark.e2e

ROBOT_CLOCK = (1000.0, 80.0)  # controller clock: offset at scenario time 0 (s), drift (ppm)
TRACKER_CLOCK = (2000.0, -40.0)
INJECTED_DELAY_S = 0.0003  # the tracker row stamped s shows the tool at scenario time s - this
SEED = 5
PLAY_S = 62.0
# scenario seconds at which both adapters are killed (and restarted RESTART_GAP_S later):
# each three times, 14 s apart, so that each mapping lives long enough for delay fits
KILLS = [14.0, 28.0, 42.0]
RESTART_GAP_S = 1.0
SETTLE_S = 10.0


def _needed_delays(
    stamps: np.ndarray, k_inst: np.ndarray, k_err: np.ndarray, e_inst: np.ndarray, e_err: np.ndarray
) -> np.ndarray:
    """The delay each estimate (by its tracker stamp) needed, from the mocks' truth (nan where
    its tracker sample is not found)."""
    k_stamp = k_inst + k_err
    order = np.argsort(k_stamp)
    k_stamp, k_inst, k_err = k_stamp[order], k_inst[order], k_err[order]
    i = np.clip(np.searchsorted(k_stamp, stamps), 1, k_stamp.size - 1)
    i = np.where(np.abs(k_stamp[i - 1] - stamps) < np.abs(k_stamp[i] - stamps), i - 1, i)
    e_order = np.argsort(e_inst)
    e_inst, e_err = e_inst[e_order], e_err[e_order]
    lo = np.searchsorted(e_inst, k_inst[i] - 0.25)
    hi = np.searchsorted(e_inst, k_inst[i] + 0.25)
    out = np.full(stamps.size, np.nan)
    for j, (k, s) in enumerate(zip(i, stamps, strict=True)):
        if abs(k_stamp[k] - s) < 1e-6 and hi[j] > lo[j]:
            out[j] = INJECTED_DELAY_S + k_err[k] - np.median(e_err[lo[j] : hi[j]])
    return out


class BusLog:
    """Samples and estimates on the bus, decoded in the subscriber's thread."""

    def __init__(self, config) -> None:
        self.session = session_for_client(config, retry_for=20)
        self.items: list[object] = []
        self._lock = threading.Lock()
        cell = config.cell
        self.subs = [
            self.session.declare_subscriber(f"keo/{cell}/{k}", self._on)
            for k in ("encoder", "tracker", "estimate")
        ]

    def _on(self, sample) -> None:
        try:
            msg = decode(sample.payload.to_bytes())
        except msgspec.DecodeError:
            return
        with self._lock:
            self.items.append(msg)

    def snapshot(self) -> list[object]:
        with self._lock:
            return list(self.items)

    def close(self) -> None:
        for sub in self.subs:
            sub.undeclare()
        self.session.close()


def _stamp_errors(samples, t0: float, clock: tuple[float, float]):
    """(instant described, mapped stamp - instant, receipt - instant) per sample [wall s]."""
    device = np.array([s.device_stamp for s in samples])
    instant = t0 + (device - clock[0]) / (1.0 + clock[1] * 1e-6)
    mapped = np.array([s.stamp for s in samples]) - instant
    receipt = np.array([s.host_ns for s in samples]) * 1e-9 - instant
    return instant, mapped, receipt


@pytest.mark.slow
def test_delay_found_across_restarts_with_two_device_clocks(tmp_path, capsys):
    base = load_config(CONFIGS / "ur10_demo.toml")
    # joints are not interpolated across a gap of more than 10 of the controller's 500 Hz
    # periods: a loaded machine starves the mock controller, which then skips the instants
    # it slept through (a real controller's stream does not), and joints interpolated
    # linearly across its 40-170 ms stalls put 50-630 urad into the estimates and one fit
    # 770 us off, with the delay right (docs/timing-delay.md, "Under load"); the default
    # 0.2 s is for slow encoders (MotoROS at 40 Hz)
    timing = msgspec.structs.replace(
        base.timing, delay_s=0.0, clock_state_dir=str(tmp_path / "clocks"), max_gap_s=0.02
    )
    config = loopback_config(msgspec.structs.replace(base, timing=timing))
    assert config.timing.track_delay  # on by default
    cfg = tmp_path / "c.toml"
    cfg.write_text(config_to_toml(config))
    sets = {
        "duration_s": repr(PLAY_S),
        "path_speed": "2",
        "tool_error_only": "true",
        "delay_s": repr(INJECTED_DELAY_S),
        "delay_jitter_s": "0",
        "encoder_rate_hz": "500",
        "encoder_rate_std_hz": "0",
        # noise-free poses, as the pyzeros peer's: what is judged here is time (the tracker's
        # 20 um / 50 urad per pose leave the estimate peaks of 12-16 urad by themselves at
        # this observer gain; measured with them, see below)
        "position_noise_m": "0",
        "rotation_noise_rad": "0",
    }
    run = simulate(cell_from_config(config), make_scenario("path", sets), seed=SEED)
    truth = run.truth.mean(axis=0)
    assert np.ptp(run.truth, axis=0).max() < 1e-9  # a constant error
    t0 = time.time() + 6.0
    play = ["--scenario", "path", "--seed", str(SEED), "--t0", repr(t0)]
    for key, value in sets.items():
        play += ["--set", f"{key}={value}"]
    robot = ["mock", "robot", "--config", str(cfg), "--protocol", "rtde", *play]
    robot += ["--clock-offset", repr(ROBOT_CLOCK[0]), "--clock-drift-ppm", repr(ROBOT_CLOCK[1])]
    robot += ["--late-ms", "6", "--burst-every", "1"]
    tracker = ["mock", "tracker", "--config", str(cfg), *play]
    tracker += ["--device-clock", f"{TRACKER_CLOCK[0]}:{TRACKER_CLOCK[1]}"]
    tracker += ["--late-ms", "4", "--burst-every", "2"]
    adapters = {name: ["adapter", name, "--config", str(cfg)] for name in ("encoder", "tracker")}
    restarts: list[float] = []

    def at(seconds: float) -> None:
        time.sleep(max(0.0, t0 + seconds - time.time()))

    with process_group(tmp_path) as procs:
        procs.start("service", ["run", "--config", str(cfg)])
        procs.start("mock-robot", robot)
        procs.start("mock-tracker", tracker)
        for name, args in adapters.items():
            procs.start(name, args)
        wait_for_status(config)
        bus = BusLog(config)
        for when in KILLS:
            at(when)
            for name in adapters:
                procs.procs[name].send_signal(signal.SIGKILL)
                procs.stop(name)
            at(when + RESTART_GAP_S)
            for name, args in adapters.items():
                procs.start(name, args)
            restarts.append(time.time())
        at(PLAY_S - 0.5)
        items = bus.snapshot()
        bus.close()
        code = procs.stop("service")
        service_log = procs.log("service")
    assert code == 0, service_log

    enc = [m for m in items if isinstance(m, JointSample)]
    trk = [m for m in items if isinstance(m, TrackerSample) and m.device_stamp is not None]
    est = [m for m in items if isinstance(m, EstimateMessage)]
    e_inst, e_err, e_rcv = _stamp_errors(enc, t0, ROBOT_CLOCK)
    k_inst, k_err, k_rcv = _stamp_errors(trk, t0, TRACKER_CLOCK)
    stamps = np.array([m.stamp for m in est])
    delays = np.array([m.delay_s for m in est])
    # judged whatever the delay tracker says of itself (delay_unsettled): stricter, not looser
    good = [m for m in est if not set(m.flags) - {"delay_unsettled"}]
    g_stamps = np.array([m.stamp for m in good])
    err = np.array([m.estimate for m in good]) - truth
    # judged: from SETTLE_S after the start and after each restart until the next kill. After
    # the start (delay_s = 0) an estimate the tracker flags as unsettled is not judged: issue
    # 45's rule (flagged until the delay is known, within 50 um 20 s after the motion starts,
    # checked by the delay scenario matrix) replaces issue 31's 10 s there; it failed at load
    # 5-12 when fits under load came with se of 300 us. After each restart the delay is known
    # and every estimate is judged, flagged or not.
    unsettled = np.array(["delay_unsettled" in m.flags for m in good])
    starts = [t0 + SETTLE_S] + [r + SETTLE_S for r in restarts]
    ends = [t0 + k for k in KILLS] + [t0 + PLAY_S]
    judged = np.zeros(g_stamps.size, dtype=bool)
    for a, b in zip(starts, ends, strict=True):
        judged |= (g_stamps > a) & (g_stamps < b)
    judged &= ~(unsettled & (g_stamps < t0 + KILLS[0]))
    # the delay each estimate needed: its tracker sample's stamp error minus that of the
    # encoder's stamps then (their median over half a second), plus the injected delay; the
    # stamps' errors walk with load (by 90 us in the last 10 s of one run), so the delay in use
    # is compared with the delay needed at the same instants
    needed = _needed_delays(stamps, k_inst, k_err, e_inst, e_err)
    last = stamps > t0 + PLAY_S - 3.0
    delay_end = float(np.median(delays[last]))
    truth_end = float(np.nanmedian(needed[last]))
    end = t0 + PLAY_S - 8.0
    floor_end = INJECTED_DELAY_S + np.min(k_rcv[k_inst > end]) - np.min(e_rcv[e_inst > end])
    off_need = np.abs(delays - needed)[np.isin(stamps, g_stamps[judged])]
    se_end = [m.delay_se_s for m in est if m.stamp > t0 + PLAY_S - 3.0]

    def wander(inst: np.ndarray, e: np.ndarray) -> list[float]:
        """Range of the stream's per-second median stamp error within each mapping's life
        from 4 s after its start (us): how much the transport floor moved under load."""
        out = []
        for a, b in zip(
            [t0 - 10.0, *restarts], [*[t0 + k for k in KILLS], t0 + PLAY_S], strict=True
        ):
            w = (inst > a + 4.0) & (inst < b)
            if w.sum() > 100:
                sec = np.floor(inst[w])
                meds = [np.median(e[w][sec == k]) for k in np.unique(sec)]
                out.append(round(float(np.ptp(meds)) * 1e6, 1))
        return out

    def across_restarts(inst: np.ndarray, e: np.ndarray) -> list[float]:
        """How far the stream's per-second median stamp error moved in the 10 s after each
        restart from its median over the 3 s before the kill (us): a mapping learned anew
        swings here, one that goes on does not."""
        out = []
        for kill, back in zip(KILLS, restarts, strict=True):
            before = (inst > t0 + kill - 3.0) & (inst < t0 + kill)
            after = (inst > back) & (inst < back + 10.0)
            sec = np.floor(inst[after] - back)
            meds = np.array([np.median(e[after][sec == k]) for k in np.unique(sec)])
            out.append(round(float(np.max(np.abs(meds - np.median(e[before])))) * 1e6, 1))
        return out

    def phase(a: float, b: float) -> dict[str, float]:
        """The judged estimates' error in one mapping's life [um, urad]."""
        w = judged & (g_stamps > a) & (g_stamps < b)
        if not w.any():  # no estimate judged in this phase: reported, and the asserts fail
            return {
                "max_um": math.inf,
                "p95_um": math.inf,
                "max_urad": math.inf,
                "p95_urad": math.inf,
            }
        pos, rot = np.abs(err[w, :3]).max(axis=1) * 1e6, np.abs(err[w, 3:]).max(axis=1) * 1e6
        return {
            "max_um": round(float(pos.max()), 1),
            "p95_um": round(float(np.percentile(pos, 95)), 1),
            "max_urad": round(float(rot.max()), 1),
            "p95_urad": round(float(np.percentile(rot, 95)), 1),
        }

    report = {
        "delay_needed_end_us": truth_end * 1e6,
        "delay_floors_end_us": floor_end * 1e6,
        "delay_in_use_end_us": delay_end * 1e6,
        "delay_error_end_us": float(np.nanmedian(delays[last] - needed[last])) * 1e6,
        "delay_error_judged_p95_us": float(np.nanpercentile(off_need, 95)) * 1e6,
        "delay_se_end_us": se_end[-1] * 1e6 if se_end and se_end[-1] is not None else None,
        "stamp_wander_us": {"encoder": wander(e_inst, e_err), "tracker": wander(k_inst, k_err)},
        "stamp_change_after_restarts_us": {
            "encoder": across_restarts(e_inst, e_err),
            "tracker": across_restarts(k_inst, k_err),
        },
        "clock_epochs": {
            "encoder": len({m.clock_epoch for m in enc}),
            "tracker": len({m.clock_epoch for m in trk}),
        },
        "judged_by_phase": [phase(a, b) for a, b in zip(starts, ends, strict=True)],
        "judged_max_err_pos_um": float(np.abs(err[judged, :3]).max() * 1e6),
        "judged_max_err_rot_urad": float(np.abs(err[judged, 3:]).max() * 1e6),
        "judged_p95_err_pos_um": float(
            np.percentile(np.abs(err[judged, :3]).max(axis=1), 95) * 1e6
        ),
        "judged_p95_err_rot_urad": float(
            np.percentile(np.abs(err[judged, 3:]).max(axis=1), 95) * 1e6
        ),
        "all_max_err_pos_um": float(np.abs(err[g_stamps > t0 + SETTLE_S, :3]).max() * 1e6),
        "all_max_err_rot_urad": float(np.abs(err[g_stamps > t0 + SETTLE_S, 3:]).max() * 1e6),
        "estimates_judged": int(judged.sum()),
    }
    with capsys.disabled():
        print("\n" + json.dumps(report, indent=1))
    (tmp_path / "report.json").write_text(json.dumps(report))
    np.savez(
        tmp_path / "streams.npz",
        e_inst=e_inst,
        e_err=e_err,
        e_rcv=e_rcv,
        k_inst=k_inst,
        k_err=k_err,
        k_rcv=k_rcv,
        restarts=np.array(restarts),
        t0=t0,
        stamps=stamps,
        delays=delays,
        est=np.array([m.estimate for m in est]) - truth,
        flagged=np.array([bool(m.flags) for m in est]),
    )
    assert judged.sum() > 0.5 * 100 * (PLAY_S - 4 * SETTLE_S)
    # Each adapter restart goes on on the clock mapping the adapter saved
    # (timing.clock_state_dir): one clock epoch per stream over the whole run (learned anew, as
    # before, every restart was a new epoch), and the mapped stamps do not swing after a
    # restart. Measured over 17 runs: within 10 s of a restart the encoder's stamps moved 2-32
    # us and the tracker's 8-130 us from before the kill (the largest when the tracker's
    # transport floor itself moved then); learning the drift anew: 29-57 and 87-323 us.
    assert report["clock_epochs"] == {"encoder": 1, "tracker": 1}, report
    assert max(report["stamp_change_after_restarts_us"]["encoder"]) < 60.0, report
    assert max(report["stamp_change_after_restarts_us"]["tracker"]) < 250.0, report
    # Issue 31 asks for the delay within 10 us and the estimate within 20 um / 20 urad from 10 s
    # after the start and after each restart: asserted as asked. Measured alone on the 2-core
    # machine with this code (the delay fitted under each stream's newest clock line and
    # carried along as the lines move, fit/stamp_lines.py), 5 runs: the delay in use at the end
    # -0.1..+1.3 us from the one needed at the same instants; the largest error per phase
    # (start and three restarts) 0.2-5.2 um / 0.4-7.4 urad, p95 over all judged up to 4.1 um /
    # 4.5 urad. Before it (fits that lagged each line's move by a stretch), 14 runs: 12.9 um /
    # 22.2 urad at worst, p95 up to 8.8 um / 12.5 urad. What is left to follow by fits: each
    # mapping's slope error while its drift converges (a microsecond or a few per second).
    # Under load the transport floor each mapping follows moves by tens of us within a phase
    # (stamp_wander_us), and the delay in use follows it a stretch late: with two busy loops
    # beside the run, one phase's estimates sat 6 um / 11 urad off for its whole length (p95
    # over all judged 6.0 um / 9.9 urad, delay p95 22 us from the one needed), and one CI run
    # gave a p95 of 10.2. The p95 guards against a phase-long offset at 15 um / 15 urad; the
    # largest error is judged at issue 31's 20 um / 20 urad.
    brief = {k: report[k] for k in ("delay_error_end_us", "delay_error_judged_p95_us")}
    brief |= {"phases": report["judged_by_phase"], "wander_us": report["stamp_wander_us"]}
    assert abs(report["delay_error_end_us"]) < 10.0, brief
    assert report["judged_p95_err_pos_um"] < 15.0, brief
    assert report["judged_p95_err_rot_urad"] < 15.0, brief
    assert report["judged_max_err_pos_um"] < 20.0, brief
    assert report["judged_max_err_rot_urad"] < 20.0, brief
