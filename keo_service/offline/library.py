"""The offline work as library functions: `estimate`, `calibrate_delay` and `analyze`.

Each takes a config (a path or a loaded `Config`) and a recording (paths of the interchange
files or of an MCAP recording, or arrays), and returns a typed result that holds what the
matching `keo` command prints or writes; the commands are a thin layer over these functions,
so a script and the command line give the same numbers. Units are SI throughout (seconds,
metres, radians); millimetres and milliradians appear only in the text meant for people.

A function that is about to give a result that depends on a default the user never chose
says so: `estimate` and `analyze` carry a warning (and print it on stderr from the command)
when `timing.delay_s` is 0 while the recording moves, because then every measured error holds
the tool's speed times the unknown delay.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeAlias

import numpy as np

from keo_service.io.interchange import EncoderData, TrackerData
from keo_service.offline.recording import Recording, read_recording

if TYPE_CHECKING:
    from keo_service.io.config import Config
    from keo_service.offline.delay import DelayCalibration

__all__ = [
    "AnalysisResult",
    "DelayResult",
    "EncoderInput",
    "EstimateResult",
    "TrackerInput",
    "analyze",
    "calibrate_delay",
    "delay_warning",
    "estimate",
]

EncoderInput: TypeAlias = str | Path | tuple[np.ndarray, np.ndarray]
"""An encoder stream: the path of `encoder.csv` (or of an MCAP recording), or the arrays
`(t, q)`: `t` (n,) seconds, `q` (n, nq) radians in the robot model's joint order."""

TrackerInput: TypeAlias = (
    str | Path | tuple[np.ndarray, np.ndarray] | tuple[np.ndarray, np.ndarray, np.ndarray | None]
)
"""A tracker stream: the path of `tracker.csv` (or of an MCAP recording), or the arrays
`(t, p)` / `(t, p, quat)`: `t` (n,) seconds, `p` (n, 3) metres (sensor frame in the tracker
frame), `quat` (n, 4) unit quaternions, scalar first (None or absent: a single reflector)."""

# a recording "moves" for the delay warning when its tool speed exceeds this for at least
# MOVING_FRACTION of the time: 1 mm/s makes each millisecond of delay a micrometre of error
MOVING_SPEED_M_S = 1e-3
MOVING_FRACTION = 0.05
SPEED_ROWS = 4000  # encoder rows (evenly spread) the tool speed is computed from


# ---- inputs ----------------------------------------------------------------------------------


def _config(config: Config | str | Path) -> tuple[Config, str]:
    """The loaded config and how a command line would name it."""
    from keo_service.io.config import Config, load_config

    if isinstance(config, Config):
        return config, "CONFIG"
    return load_config(config), str(config)


def _is_path(value: object) -> bool:
    return isinstance(value, str | os.PathLike)


def _recording(
    config: Config,
    encoder: EncoderInput,
    tracker: TrackerInput,
    while_parsing: Callable[[], object] | None = None,
) -> Recording:
    """Both streams: read from files (each once; `while_parsing` runs while the tracker file
    parses) or taken from arrays."""
    if _is_path(encoder) and _is_path(tracker):
        return read_recording(config, encoder, tracker, while_parsing=while_parsing)  # type: ignore[arg-type]
    from keo_service.io.cell import cell_from_config
    from keo_service.io.interchange import read_encoder, read_tracker

    cell = cell_from_config(config)
    enc = (
        read_encoder(encoder, nq=cell.robot.nq)  # type: ignore[arg-type]
        if _is_path(encoder)
        else _encoder_arrays(encoder, cell.robot.nq)  # type: ignore[arg-type]
    )
    trk = read_tracker(tracker) if _is_path(tracker) else _tracker_arrays(tracker)  # type: ignore[arg-type]
    return Recording(cell, enc, trk)


def _encoder_arrays(value: tuple[np.ndarray, np.ndarray], nq: int) -> EncoderData:
    from keo_service.core.errors import KeoError

    t, q = (np.asarray(v, dtype=float) for v in value)
    if t.ndim != 1 or q.ndim != 2 or q.shape != (t.size, nq):
        raise KeoError(
            f"encoder arrays: t must be (n,) and q (n, {nq}) for this robot; got t "
            f"{t.shape} and q {q.shape}"
        )
    return EncoderData(t, q)


def _tracker_arrays(value: Sequence[np.ndarray | None]) -> TrackerData:
    from keo_service.core.errors import KeoError

    if len(value) not in (2, 3):
        raise KeoError("tracker arrays: give (t, p) or (t, p, quat)")
    t = np.asarray(value[0], dtype=float)
    p = np.asarray(value[1], dtype=float)
    raw = value[2] if len(value) == 3 else None
    quat = None if raw is None else np.asarray(raw, dtype=float)
    if t.ndim != 1 or p.shape != (t.size, 3):
        raise KeoError(f"tracker arrays: t must be (n,) and p (n, 3); got {t.shape}, {p.shape}")
    if quat is not None and quat.shape != (t.size, 4):
        raise KeoError(f"tracker arrays: quat must be (n, 4), scalar first; got {quat.shape}")
    return TrackerData(t, p, quat)


# ---- the delay warning ----------------------------------------------------------------------


def delay_warning(
    config: Config,
    recording: Recording,
    config_name: str = "CONFIG",
    encoder_name: str = "ENCODER",
    tracker_name: str = "TRACKER",
) -> str | None:
    """Why a result may hold the tool's speed times an unknown delay, or None.

    The measured error of a moving tool holds `v * t_d` (docs/design.md §3): with
    `timing.delay_s = 0` (the default) and a recording that moves, every number that
    `estimate` and `analyze` give depends on a delay nobody measured. Stop-and-measure data
    (an encoder row at every tracker row's time) need none.

    Args:
        config: the config the result is computed with.
        recording: both streams, as read.
        config_name: how the message names the config (a path on the command line).
        encoder_name: how the message names the encoder file.
        tracker_name: how the message names the tracker file.

    Returns:
        One sentence naming the tool speed, what 10 ms of delay would add, and the command
        that finds the delay (`keo calibrate-delay`); None when the config has a delay or the
        recording does not move.
    """
    if config.timing.delay_s != 0.0:
        return None
    enc, trk = recording.encoder, recording.tracker
    finite = np.isfinite(trk.t)
    if finite.any() and np.all(np.isin(trk.t[finite], enc.t)):
        return None  # stop-and-measure: each pose is measured at rest
    speed = tool_speeds(recording)
    if speed.size == 0:
        return None
    moving = float(np.mean(speed > MOVING_SPEED_M_S))
    if moving < MOVING_FRACTION:
        return None
    fast = float(np.percentile(speed, 95))
    return (
        f"timing.delay_s is 0 in {config_name} while the tool moves (faster than "
        f"{MOVING_SPEED_M_S * 1e3:g} mm/s {100 * moving:.0f} % of the time, 95th percentile "
        f"{fast * 1e3:.0f} mm/s): every 10 ms of delay between the streams adds up to "
        f"{fast * 10:.2f} mm to the measured error. Find the delay with: keo calibrate-delay "
        f"--config {config_name} --encoder {encoder_name} --tracker {tracker_name} (and write "
        "the delay_s it prints into the config's [timing])"
    )


def tool_speeds(recording: Recording) -> np.ndarray:
    """The flange's speed (m/s) between evenly spread encoder rows (at most SPEED_ROWS)."""
    from keo_service.core.chain import Chain

    t, q = recording.encoder.t, recording.encoder.q
    ok = np.isfinite(t) & np.all(np.isfinite(q), axis=1)
    t, q = t[ok], q[ok]
    if t.size < 2:
        return np.zeros(0)
    order = np.argsort(t, kind="stable")
    pick = np.unique(np.linspace(0, t.size - 1, min(SPEED_ROWS, t.size)).astype(int))
    t, q = t[order][pick], q[order][pick]
    p = Chain(recording.cell.robot).flange_poses(q)[:, :3, 3]
    dt = np.diff(t)
    good = dt > 0
    speed: np.ndarray = np.linalg.norm(np.diff(p, axis=0), axis=1)[good] / dt[good]
    return speed


def _say(message: str | None, quiet: bool) -> None:
    if message is not None and not quiet:
        print(f"warning: {message}", file=sys.stderr, flush=True)


# ---- estimate --------------------------------------------------------------------------------


@dataclass
class EstimateResult:
    """What `keo estimate` writes and prints: one row per estimate.

    Held steps (no encoder data at the tracker sample's time, a gap) have NaN in `measured`
    and say why in `flags`; the observer keeps its state over them.
    """

    stamp: np.ndarray
    """(n,) tracker sample times, s."""
    measured: np.ndarray
    """(n, C) the measured error e_m per channel (m for px py pz, rad for rx ry rz); NaN
    where held."""
    estimate: np.ndarray
    """(n, C) the observer's estimate, same units."""
    flags: list[str]
    """Per row: "" or the flags joined by "|" (e.g. "encoder_gap")."""
    channels: tuple[str, ...]
    """The channel names: px py pz rx ry rz, or px py pz for a single reflector."""
    path: str
    """"batch", or "streaming (<why>)" when the per-sample estimator ran."""
    counters: dict[str, int]
    """The estimator's counters (samples, rejects by reason, held steps by reason)."""
    messages: list[str]
    """The estimator's messages (why a row was refused), newest last."""
    warnings: list[str] = field(default_factory=list)
    """What may make these numbers wrong (e.g. `timing.delay_s` = 0 on a moving recording)."""
    out: Path | None = None
    """Where the estimate file was written, if it was."""

    @property
    def held(self) -> int:
        """Rows whose step was held (`measured` is NaN)."""
        if not self.measured.size:
            return 0
        return int(np.isnan(self.measured).any(axis=1).sum())

    def write(self, path: str | Path) -> Path:
        """Write the estimate file (header `t,meas_px,...,est_rz`; m, rad).

        Args:
            path: the CSV file to write.

        Returns:
            The path written.

        Raises:
            KeoError: the file cannot be written there (a directory, a path under a file, no
                permission, a full disk); the message names the path and the reason.
        """
        from keo_service.core.errors import KeoError
        from keo_service.io.interchange import write_estimate_table

        try:
            write_estimate_table(
                path, self.stamp, self.measured, self.estimate, self.flags, self.channels
            )
        except OSError as exc:  # the user's path, not an internal failure: say which and why
            reason = exc.strerror or str(exc)
            raise KeoError(f"cannot write the estimate file {str(path)!r}: {reason}") from exc
        self.out = Path(path)
        return self.out

    def summary(self) -> dict[str, Any]:
        """What `keo estimate --json` prints: out, path, estimates, held, channels,
        counters, the newest 10 messages and the warnings."""
        return {
            "out": None if self.out is None else str(self.out),
            "path": self.path,
            "estimates": int(self.stamp.size),
            "held": self.held,
            "channels": list(self.channels),
            "counters": dict(self.counters),
            "messages": self.messages[-10:],
            "warnings": list(self.warnings),
        }


def estimate(
    config: Config | str | Path,
    encoder: EncoderInput,
    tracker: TrackerInput,
    out: str | Path | None = None,
    *,
    streaming: bool = False,
    quiet: bool = False,
) -> EstimateResult:
    """The service's alignment and observer over a recording (`keo estimate`).

    The same samples give the same estimates as the live service would publish: the
    config's delay, alignment and gains, every tracker sample evaluated at the joints of its
    time minus the delay.

    Args:
        config: a keo config file (TOML) or a loaded `Config`.
        encoder: `encoder.csv` (or an MCAP recording), or arrays `(t, q)` in s and rad.
        tracker: `tracker.csv` (or an MCAP recording), or arrays `(t, p[, quat])` in s, m
            and unit quaternions (scalar first).
        out: if given, the estimate file is written there (CSV, m and rad).
        streaming: run the per-sample live estimator instead of the array path (the same
            output, much slower: a cross-check; docs/performance.md has the times).
        quiet: do not print the warnings on stderr (they stay in `warnings`).

    Returns:
        An `EstimateResult`: per estimate its stamp (s), measured and estimated error (m,
        rad) and flags, with the counters and any warning.

    Raises:
        ConfigError: the config is wrong (the message names the key).
        DataFormatError: a file is not in the interchange format (file, line, column).
        KeoError: arrays of the wrong shape.
    """
    from keo_service.offline.estimate import estimate_recording, load_estimators

    cfg, name = _config(config)
    # the estimators' and Pinocchio's imports run while the tracker file parses
    recording = _recording(cfg, encoder, tracker, while_parsing=load_estimators)
    from keo_service.io.cell import estimator_settings

    warning = delay_warning(cfg, recording, name, _name(encoder), _name(tracker))
    _say(warning, quiet)
    done = estimate_recording(recording, estimator_settings(cfg), streaming)
    t = done.table
    result = EstimateResult(
        stamp=t.stamp,
        measured=t.measured,
        estimate=t.estimate,
        flags=list(t.flags),
        channels=tuple(t.channels),
        path=done.path,
        counters=dict(t.counters),
        messages=list(t.messages),
        warnings=[warning] if warning else [],
    )
    if out is not None:
        result.write(out)
    return result


def _name(source: object) -> str:
    return str(source) if _is_path(source) and str(source) != "(arrays)" else "FILE"


# ---- calibrate_delay -------------------------------------------------------------------------


@dataclass(frozen=True)
class DelayResult:
    """What `keo calibrate-delay` prints: the delay between the streams with its standard
    error, the clock drift where the data show it, and the reference method's numbers."""

    delay_s: float
    """The sensor stream lags the encoder stream by this much (s), at `t_ref_s`."""
    delay_se_s: float
    """Its standard error (s, 1 sigma)."""
    drift_ppm: float | None
    """The clocks' relative drift (ppm) where shown significant, else None."""
    drift_se_ppm: float
    """The drift's standard error (ppm)."""
    t_ref_s: float
    """The stream time (s) at which `delay_s` holds when there is a drift."""
    explained: bool
    """False when the fit does not explain the data (the notes say why): do not use it."""
    notes: list[str]
    """What the fit noticed."""
    calibration: DelayCalibration
    """The full calibration (fit, reference-method segments, clock domains)."""

    def document(self) -> dict[str, Any]:
        """What `keo calibrate-delay --json` prints."""
        return self.calibration.document()

    def lines(self) -> list[str]:
        """What `keo calibrate-delay` prints, line by line."""
        return self.calibration.lines()


def calibrate_delay(
    config: Config | str | Path,
    encoder: EncoderInput,
    tracker: TrackerInput,
    *,
    drift: bool = True,
) -> DelayResult:
    """The delay (and clock drift) between the two streams of a recording of any motion
    (`keo calibrate-delay`).

    Args:
        config: a keo config file (TOML) or a loaded `Config`; its `timing.delay_s` is the
            starting point of the fit.
        encoder: `encoder.csv`, or arrays `(t, q)` in s and rad.
        tracker: `tracker.csv`, or arrays `(t, p[, quat])` in s, m and unit quaternions.
        drift: also fit a linear drift of the delay (ppm); False: a constant delay.

    Returns:
        A `DelayResult`: `delay_s` and `delay_se_s` in seconds, `drift_ppm` where
        significant; write `delay_s` into the config's `[timing]`.

    Raises:
        DelayNotIdentifiableError: a `KeoError`: the motion cannot determine the delay (the
            message says why; e.g. the tool never moves).
        ConfigError: the config is wrong (the message names the key).
        DataFormatError: a file is not in the interchange format.
    """
    from keo_service.offline import delay as offline_delay

    cfg = _config(config)[0]
    if _is_path(encoder) and _is_path(tracker):
        calibration = offline_delay.calibrate_delay(cfg, encoder, tracker, with_drift=drift)  # type: ignore[arg-type]
    else:
        recording = _recording(cfg, encoder, tracker)
        calibration = offline_delay.calibrate_recording(recording, cfg.timing.delay_s, drift)
    fit = calibration.fit
    return DelayResult(
        delay_s=float(fit.delay_s),
        delay_se_s=float(fit.delay_se_s),
        drift_ppm=float(fit.drift * 1e6) if fit.drift_significant else None,
        drift_se_ppm=float(fit.drift_se * 1e6),
        t_ref_s=float(fit.t_ref),
        explained=bool(fit.explained),
        notes=list(fit.notes),
        calibration=calibration,
    )


# ---- analyze ---------------------------------------------------------------------------------


@dataclass
class AnalysisResult:
    """What `keo analyze` writes: `report.json` as a dict, and where the files are."""

    report: dict[str, Any]
    """report.json: baseline, effects (each with its held-out statistics), final,
    unexplained, rejected, registration, ... (docs/design.md §6). Lengths in the statistics
    are mm, angles mrad (the report is for people)."""
    out: Path
    """The folder with report.json, report.md, the plots and model.toml."""
    warnings: list[str] = field(default_factory=list)
    """What may make these numbers wrong (also in report.json under "warnings")."""

    @property
    def model_path(self) -> Path:
        """model.toml: the config with every kept effect, usable by `keo run` and
        `keo compensate`."""
        return self.out / "model.toml"

    @property
    def report_path(self) -> Path:
        """report.md, the readable report."""
        return self.out / "report.md"

    @property
    def baseline(self) -> dict[str, Any]:
        """The nominal model (registration fitted): {"train": STATS, "validation": STATS},
        STATS = {"n", "pos_rms_mm", "pos_max_mm", "rot_rms_mrad"}."""
        baseline: dict[str, Any] = self.report["baseline"]
        return baseline

    @property
    def final(self) -> dict[str, Any]:
        """The model with every kept effect, in the same form as `baseline`."""
        final: dict[str, Any] = self.report["final"]
        return final

    @property
    def effects(self) -> list[dict[str, Any]]:
        """The kept effects, in the order added: name, parameters, held-out statistics."""
        effects: list[dict[str, Any]] = self.report["effects"]
        return effects


def analyze(
    config: Config | str | Path,
    encoder: EncoderInput | Sequence[str | Path],
    tracker: TrackerInput | Sequence[str | Path],
    out: str | Path,
    *,
    registration_only: bool = False,
    quiet: bool = False,
) -> AnalysisResult:
    """What the robot model still gets wrong, effects added and judged on held-out poses
    (`keo analyze`).

    Args:
        config: a keo config file (TOML) or a loaded `Config`.
        encoder: `encoder.csv`, a list of them (several sessions of one robot, each with its
            own tracker registration), or arrays `(t, q)` in s and rad.
        tracker: `tracker.csv` (or a list, paired with `encoder`), or arrays
            `(t, p[, quat])` in s, m and unit quaternions.
        out: the folder for report.json, report.md, the plots and model.toml (created).
        registration_only: keep the effects in `config`; re-identify only the tracker and
            tool registration (one recording).
        quiet: no progress or warnings on stderr.

    Returns:
        An `AnalysisResult` holding report.json as a dict and the output folder.

    Raises:
        KeoError: the data cannot be analyzed (the message says why), or `encoder` and
            `tracker` do not pair up.
        ConfigError: the config is wrong (the message names the key).
        DataFormatError: a file is not in the interchange format.
    """
    import contextlib
    import io

    from keo_service.offline.analyze import _read_all, run_analysis

    cfg, name = _config(config)
    out_dir = Path(out)
    encoders, trackers = _as_lists(encoder), _as_lists(tracker)
    if encoders is None or trackers is None:  # arrays: one recording
        recordings = [_recording(cfg, encoder, tracker)]  # type: ignore[arg-type]
        encoders, trackers = [Path("(arrays)")], [Path("(arrays)")]
    else:  # each file read once, here; the analysis gets the arrays
        recordings = _read_all(cfg, encoders, trackers, registration_only)
    warnings = [
        w
        for r, e, t in zip(recordings, encoders, trackers, strict=True)
        if (w := delay_warning(cfg, r, name, _name(e), _name(t))) is not None
    ]
    for w in warnings:
        _say(w, quiet)
    sink = io.StringIO()
    with contextlib.redirect_stderr(sink) if quiet else contextlib.nullcontext():
        report = run_analysis(
            cfg, encoders, trackers, out_dir, registration_only, recordings=recordings
        )
    found = next((e for e in report.get("effects", []) if e.get("name") == "time_delay"), None)
    if warnings and found is not None:
        delay = found.get("parameters", {}).get("delay_s")
        size = f" ({delay * 1e3:.2f} ms)" if isinstance(delay, float) else ""
        warnings = [
            f"{w}; keo analyze found a delay{size} from the motion itself and kept it as the "
            "effect time_delay (model.toml carries it)"
            for w in warnings
        ]
    if warnings:
        report["warnings"] = warnings
        _add_warnings(out_dir, warnings)
    return AnalysisResult(report, out_dir, warnings)


def _as_lists(value: object) -> list[Path] | None:
    """Paths as a list; None for arrays."""
    if _is_path(value):
        return [Path(value)]  # type: ignore[arg-type]
    if isinstance(value, list) and all(_is_path(v) for v in value):
        return [Path(v) for v in value]
    return None


def _add_warnings(out: Path, warnings: list[str]) -> None:
    """The warnings into report.json (under "warnings") and at the top of report.md."""
    import json

    path = out / "report.json"
    if path.exists():
        doc = json.loads(path.read_text(encoding="utf-8"))
        doc["warnings"] = warnings
        path.write_text(json.dumps(doc, indent=2, allow_nan=False), encoding="utf-8")
    md = out / "report.md"
    if md.exists():
        text = md.read_text(encoding="utf-8")
        head, _, rest = text.partition("\n")
        notes = "\n".join(f"> **Warning**: {w}" for w in warnings)
        md.write_text(f"{head}\n\n{notes}\n{rest}", encoding="utf-8")
