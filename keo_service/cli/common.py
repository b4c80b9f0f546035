"""What every command group shares: exit codes, JSON output, config loading, KEY=VALUE
options and the signature of the function that adds a sub-command."""

from __future__ import annotations

import argparse
import functools
import gc
import json
import math
import sys
from collections.abc import Callable, Sequence
from typing import Any, Protocol

from keo_service.core.errors import ConfigError

EXIT_OK, EXIT_FAILURE, EXIT_USAGE = 0, 1, 2
EXIT_BROKEN_PIPE = 128 + 13  # 128 + SIGPIPE: the reader of stdout closed the pipe

Command = Callable[[argparse.Namespace], int]


def finite_or_none(doc: Any) -> Any:
    """JSON has no NaN: absent numbers become null."""
    if isinstance(doc, float):
        return doc if math.isfinite(doc) else None
    if isinstance(doc, dict):
        return {k: finite_or_none(v) for k, v in doc.items()}
    if isinstance(doc, list | tuple):
        return [finite_or_none(v) for v in doc]
    return doc


def print_json(doc: Any) -> None:
    sys.stdout.write(
        json.dumps(finite_or_none(doc), indent=2, allow_nan=False, default=float) + "\n"
    )


def collector_paused(command: Command) -> Command:
    """A command that runs once over its files and returns, run with the cyclic garbage
    collector off: loading numpy, polars and Pinocchio allocates tens of thousands of objects,
    and the collections that triggers are a noticeable part of a short `keo estimate`
    (docs/performance.md); the command's arrays are freed by reference counting either way."""

    @functools.wraps(command)
    def paused(args: argparse.Namespace) -> int:
        was_enabled = gc.isenabled()
        gc.disable()
        try:
            return command(args)
        finally:
            if was_enabled:
                gc.enable()

    return paused


def load(path: str) -> Any:
    from keo_service.io.config import load_config

    return load_config(path)


def parse_sets(values: Sequence[str] | None) -> dict[str, str]:
    out = {}
    for item in values or ():
        if "=" not in item:
            raise ConfigError("--set", item, "expected KEY=VALUE")
        key, value = item.split("=", 1)
        out[key.strip()] = value.strip()
    return out


class AddCommand(Protocol):
    """Adds a sub-command running `func`; with `config`, a required --config option."""

    def __call__(
        self,
        name: str,
        func: Callable[[argparse.Namespace], int],
        help_text: str,
        config: bool = True,
    ) -> argparse.ArgumentParser: ...
