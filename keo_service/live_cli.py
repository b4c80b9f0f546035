"""Sub-commands of the live system: run, adapter, mock, echo, router."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import Any


def add_live_commands(sub: Any, add: Callable[..., argparse.ArgumentParser]) -> None:
    """Registered by the live modules once they exist."""
