"""keo: a real-time Kinematic Error Observer for industrial robots.

The public surface is `__all__`: the client of a running service, the estimator and its
settings, config loading, and the wire message types. The names load lazily, so that
`import keo_service.core` stays free of asyncio, Zenoh and msgspec (docs/design.md §8).
Where each part lives: ARCHITECTURE.md.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

_EXPORTS = {
    "AdapterStatus": "keo_service.live.messages",
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
}

__all__ = [
    "AdapterStatus",
    "Cell",
    "Client",
    "ClientError",
    "CompensateResult",
    "Config",
    "ConfigError",
    "DataFormatError",
    "Estimate",
    "EstimateMessage",
    "Estimator",
    "EstimatorSettings",
    "JointSample",
    "KeoError",
    "RobotStatus",
    "ServiceStatus",
    "SyncClient",
    "TrackerSample",
    "cell_from_config",
    "compensate",
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
        EstimateMessage,
        JointSample,
        RobotStatus,
        ServiceStatus,
        TrackerSample,
    )
    from keo_service.offline.compensate import CompensateResult, compensate


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'keo_service' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return [*globals(), *__all__]
