"""Old import path of the compensation objects, kept for scripts written against keo 0.1.

New code imports `io.cell.tool_model` (the model's tool poses from a config) and `io.targets`
(the targets CSV); `keo_service.compensate` runs the whole command.
"""

from __future__ import annotations

from keo_service.io.cell import tool_model
from keo_service.io.targets import Targets, read_targets

__all__ = ["Targets", "read_targets", "tool_model"]
