"""keo: a real-time Kinematic Error Observer for industrial robots.

The public surface is `__all__`, and this page is its reference:

- the offline work as functions, each taking a config and a recording (paths or arrays) and
  returning a typed result that holds what the matching command prints or writes:
  `estimate` (`keo estimate`), `calibrate_delay` (`keo calibrate-delay`), `analyze`
  (`keo analyze`);
- the client of a running service (`Client`, `SyncClient`) and the wire message types it
  returns (`EstimateMessage`, `ServiceStatus`, ...);
- the estimator itself (`Estimator`, `EstimatorSettings`, `Cell`) for feeding samples by hand;
- config loading (`load_config`, `cell_from_config`, `estimator_settings`) and keo's errors
  (every one derives from `KeoError`).

Units are SI everywhere (s, m, rad); mm and mrad appear only in text meant for people.

    from keo_service import analyze, calibrate_delay, estimate

    found = calibrate_delay("cell.toml", "rec/encoder.csv", "rec/tracker.csv")
    print(found.delay_s, found.delay_se_s)              # s
    result = estimate("cell.toml", "rec/encoder.csv", "rec/tracker.csv", out="est.csv")
    print(result.estimate[-1], result.warnings)         # m, rad
    report = analyze("cell.toml", "rec/encoder.csv", "rec/tracker.csv", "analysis")
    print(report.final["validation"]["pos_rms_mm"], report.model_path)

The names load lazily, so that `import keo_service.core` stays free of asyncio, Zenoh and
msgspec (docs/design.md §8). Where each part lives: ARCHITECTURE.md.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

_EXPORTS = {
    "AdapterStatus": "keo_service.live.messages",
    "DelayState": "keo_service.live.messages",
    "Client": "keo_service.live.client",
    "SyncClient": "keo_service.live.client",
    "ClientError": "keo_service.live.client",
    "Estimator": "keo_service.core.estimator",
    "EstimatorSettings": "keo_service.core.settings",
    "Estimate": "keo_service.core.estimator",
    "Cell": "keo_service.core.kinematics",
    "KeoError": "keo_service.core.errors",
    "ConfigError": "keo_service.core.errors",
    "DataFormatError": "keo_service.core.errors",
    "Config": "keo_service.io.config",
    "load_config": "keo_service.io.config",
    "cell_from_config": "keo_service.io.cell",
    "estimator_settings": "keo_service.io.cell",
    "EstimateMessage": "keo_service.live.messages",
    "ServiceStatus": "keo_service.live.messages",
    "JointSample": "keo_service.live.messages",
    "TrackerSample": "keo_service.live.messages",
    "RobotStatus": "keo_service.live.messages",
    "compensate": "keo_service.offline.compensate",
    "CompensateResult": "keo_service.offline.compensate",
    # the offline work as functions (the commands are a thin layer over them)
    "estimate": "keo_service.offline.library",
    "EstimateResult": "keo_service.offline.library",
    "calibrate_delay": "keo_service.offline.library",
    "DelayResult": "keo_service.offline.library",
    "analyze": "keo_service.offline.library",
    "AnalysisResult": "keo_service.offline.library",
}

__all__ = [
    "AdapterStatus",
    "AnalysisResult",
    "Cell",
    "Client",
    "ClientError",
    "CompensateResult",
    "Config",
    "ConfigError",
    "DataFormatError",
    "DelayResult",
    "DelayState",
    "Estimate",
    "EstimateMessage",
    "EstimateResult",
    "Estimator",
    "EstimatorSettings",
    "JointSample",
    "KeoError",
    "RobotStatus",
    "ServiceStatus",
    "SyncClient",
    "TrackerSample",
    "analyze",
    "calibrate_delay",
    "cell_from_config",
    "compensate",
    "estimate",
    "estimator_settings",
    "load_config",
]

if TYPE_CHECKING:
    from keo_service.core.errors import ConfigError, DataFormatError, KeoError
    from keo_service.core.estimator import Estimate, Estimator
    from keo_service.core.kinematics import Cell
    from keo_service.core.settings import EstimatorSettings
    from keo_service.io.cell import cell_from_config, estimator_settings
    from keo_service.io.config import Config, load_config
    from keo_service.live.client import Client, ClientError, SyncClient
    from keo_service.live.messages import (
        AdapterStatus,
        DelayState,
        EstimateMessage,
        JointSample,
        RobotStatus,
        ServiceStatus,
        TrackerSample,
    )
    from keo_service.offline.compensate import CompensateResult, compensate
    from keo_service.offline.library import (
        AnalysisResult,
        DelayResult,
        EstimateResult,
        analyze,
        calibrate_delay,
        estimate,
    )


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'keo_service' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return [*globals(), *__all__]
