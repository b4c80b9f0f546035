"""`keo calibrate-delay`: the delay (and clock drift) between the streams of a recording,
with the reference method's number beside it, as a document and as lines to print."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from keo_service.offline.recording import Recording, read_recording

if TYPE_CHECKING:
    from keo_service.fit.delay import DelayFit, ReferenceSegment
    from keo_service.io.config import Config


@dataclass(frozen=True)
class DelayCalibration:
    fit: DelayFit
    segments: list[ReferenceSegment]  # the reference method on each constant-velocity stretch
    # the clock domains the delay holds under (the config's [robot] / [tracker] clock): samples
    # stamped under other domains make `keo run` warn
    clocks: dict[str, str] = field(default_factory=dict)

    @property
    def explained(self) -> bool:
        return bool(self.fit.explained)

    def document(self) -> dict[str, Any]:
        """What `--json` prints."""
        fit = self.fit
        drift = {"drift_ppm": fit.drift * 1e6} if fit.drift_significant else {}
        config: dict[str, Any] = {
            "timing.delay_s": fit.delay_s,
            "timing.delay_se_s": fit.delay_se_s,
        }
        if fit.drift_significant:  # only a drift shown beyond the windows' scatter
            config["timing.drift_ppm"] = fit.drift * 1e6
            config["timing.drift_ref_s"] = fit.t_ref
        return {
            "verdict": "ok" if fit.explained else "unexplained",
            "delay_s": fit.delay_s,
            "delay_se_s": fit.delay_se_s,
            **drift,
            "drift_se_ppm": fit.drift_se * 1e6 if math.isfinite(fit.drift_se) else None,
            "drift_significant": fit.drift_significant,
            "t_ref_s": fit.t_ref,
            "samples": fit.samples,
            "moving_fraction": fit.moving_fraction,
            "residual_rms_moving_m": fit.residual_rms_moving,
            "residual_rms_rest_m": fit.residual_rms_rest,
            "window_delays_s": fit.window_delays_s,
            "notes": fit.notes,
            "reference_method": [s.__dict__ for s in self.segments],
            "clocks": dict(self.clocks),
            "config": config,
        }

    def lines(self) -> list[str]:
        """What the command prints without `--json`."""
        fit = self.fit
        out = [
            f"delay: {fit.delay_s * 1e3:.3f} ms +/- {fit.delay_se_s * 1e3:.3f} ms (1 sigma), "
            f"from {fit.samples} tracker samples, moving {100 * fit.moving_fraction:.0f} % of "
            "the time"
        ]
        if fit.drift_significant:
            out.append(
                f"clock drift: {fit.drift * 1e6:.1f} +/- {fit.drift_se * 1e6:.1f} ppm; the delay "
                f"above holds at t = {fit.t_ref:.3f} s"
            )
        out.extend(f"note: {note}" for note in fit.notes)
        out.extend(
            f"reference method (offset / speed) on the constant-velocity stretch "
            f"{s.start:.2f}-{s.end:.2f} s at {s.speed * 1e3:.0f} mm/s: "
            f"{s.delay_s * 1e3:.2f} ms"
            for s in self.segments
        )
        if self.clocks:
            out.append(
                "clock domains: "
                + ", ".join(f"{key} = {value}" for key, value in self.clocks.items())
                + " (the delay holds for stamps under these domains)"
            )
        out.append("config:")
        out.append(f"  [timing] delay_s = {fit.delay_s:.6f}")
        out.append(f"           delay_se_s = {fit.delay_se_s:.6f}")
        if fit.drift_significant:
            out.append(f"           drift_ppm = {fit.drift * 1e6:.3f}")
            out.append(f"           drift_ref_s = {fit.t_ref!r}")
        return out


def calibrate_delay(
    config: Config, encoder_path: str | Path, tracker_path: str | Path, with_drift: bool = True
) -> DelayCalibration:
    """Read the recording once (interchange CSV files) and fit the delay from the config's
    value; raises `DelayNotIdentifiableError` when the motion cannot determine it."""
    recording = read_recording(config, encoder_path, tracker_path, mcap=False)
    result = calibrate_recording(recording, config.timing.delay_s, with_drift)
    clocks = {"robot.clock": str(config.robot.clock), "tracker.clock": str(config.tracker.clock)}
    return replace(result, clocks=clocks)


def calibrate_recording(
    recording: Recording, initial_delay_s: float, with_drift: bool = True
) -> DelayCalibration:
    from keo_service.fit.delay import fit_delay, reference_method

    enc, trk, cell = recording.encoder, recording.tracker, recording.cell
    fit = fit_delay(cell, *recording.streams(), initial=initial_delay_s, with_drift=with_drift)
    segments = reference_method(cell, enc.t, enc.q, trk.t, trk.p)
    return DelayCalibration(fit, segments)
