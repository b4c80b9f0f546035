"""The estimator's settings: plain data, apart from the estimator so that reading a config
file does not load the kinematics libraries."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from keo_service.core.timing import DelayModel


@dataclass(frozen=True)
class EstimatorSettings:
    """How the estimator aligns the streams and filters the measured error
    (`estimator_settings` reads them from a config's [observer] and [timing] sections, all
    but `start`; docs/config.md says what each key does).

    Attributes:
        gains: the observer's gain per channel, px, py, pz, rx, ry, rz (1/s): the estimate
            follows a step of the error with the time constant 1/gain.
        max_dt_s: a sample after a longer gap updates as if it came this long (s) after the
            previous one.
        delay: offset (s) and drift (s/s) of the tracker's stamps behind the encoder's.
        alignment: "interpolate" (the joints at each pose's time) or "latest" (the reference
            method: the newest joints at `sample_rate_hz`).
        sample_rate_hz: the fixed rate of "latest" alignment (Hz); from a zero start, the
            first step is taken as one period of it.
        buffer_s: encoder samples kept for alignment (s of stream time).
        max_gap_s: two encoder samples further apart (s) are not interpolated between.
        stale_after_s: a pose waits at most this long (s of stream time) for encoder data.
        start: the observer's initial state: "zero" (the reference) or "first" (the first
            measured error).
    """

    gains: tuple[float, ...] = (1.0,) * 6
    max_dt_s: float = 0.25
    delay: DelayModel = field(default_factory=DelayModel)
    alignment: str = "interpolate"
    sample_rate_hz: float = 40.0
    buffer_s: float = 2.0
    max_gap_s: float = 0.2
    stale_after_s: float = 0.5
    start: str = "zero"


def encoder_capacity(settings: EstimatorSettings) -> int:
    """Encoder samples the buffer holds: buffer_s of a stream of up to 2 kHz (64 at least).
    The batch path reproduces the buffer's verdicts from this same number."""
    return max(64, math.ceil(settings.buffer_s * 2000.0))
