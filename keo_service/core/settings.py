"""The estimator's settings: plain data, apart from the estimator so that reading a config
file does not load the kinematics libraries."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from keo_service.core.timing import DelayModel


@dataclass(frozen=True)
class EstimatorSettings:
    gains: tuple[float, ...] = (1.0,) * 6
    max_dt_s: float = 0.25
    delay: DelayModel = field(default_factory=DelayModel)
    alignment: str = "interpolate"
    sample_rate_hz: float = 40.0
    buffer_s: float = 2.0
    max_gap_s: float = 0.2
    stale_after_s: float = 0.5
    start: str = "zero"  # observer's initial state: "zero" (the reference) or "first"


def encoder_capacity(settings: EstimatorSettings) -> int:
    """Encoder samples the buffer holds: buffer_s of a stream of up to 2 kHz (64 at least).
    The batch path reproduces the buffer's verdicts from this same number."""
    return max(64, math.ceil(settings.buffer_s * 2000.0))
