"""The `keo` command line (docs/design.md §6): one argparse tree, one module per command
group (`offline`, `live`, `tools`). The CLI only parses and calls; each command imports what
it runs lazily so that `keo gain` starts fast.

Exit codes: 0 success, 2 bad usage or bad config (the message names the key or argument),
1 other failures, 141 (128 + SIGPIPE) when the reader of stdout closed the pipe. `--json`
prints one JSON document on stdout.
"""

from __future__ import annotations

import argparse
import gc
import os
import signal
import sys
from collections.abc import Callable, Sequence

from keo_service.cli import common, live, offline, tools
from keo_service.core.errors import ConfigError, DataFormatError, KeoError

__all__ = ["build_parser", "console", "main"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="keo", description="Kinematic Error Observer")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def add(
        name: str, func: Callable[[argparse.Namespace], int], help_text: str, config: bool = True
    ) -> argparse.ArgumentParser:
        p: argparse.ArgumentParser = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(func=func)
        if config:
            p.add_argument("--config", required=True, help="keo config (TOML)")
        return p

    tools.register(add)
    offline.register(add)
    live.register(add)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args))
    except (ConfigError, DataFormatError) as exc:
        print(f"keo {args.command}: error: {exc}", file=sys.stderr)
        return common.EXIT_USAGE
    except KeoError as exc:
        print(f"keo {args.command}: error: {exc}", file=sys.stderr)
        return common.EXIT_FAILURE
    except KeyboardInterrupt:
        return common.EXIT_OK


def console() -> int:
    """The `keo` executable: `main`, then an exit without the interpreter's final garbage
    collections over every loaded module's objects: with polars loaded they are a noticeable
    part of a short command (docs/performance.md), and the memory goes back to the system
    whole either way."""
    # SIGTERM asks what SIGINT asks: stop. Until a command installs its own handlers (a
    # running loop stops gracefully), both raise KeyboardInterrupt, which `main` turns into
    # exit 0 instead of the signal's default death (seen: `keo mock` stopped while it still
    # computed its scenario)
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        code = main()
        sys.stdout.flush()  # here, so that a reader gone by now is caught below
    except KeyboardInterrupt:  # before `main` could catch it (parsing the arguments)
        code = common.EXIT_OK
    except BrokenPipeError:
        code = _reader_gone()
    gc.freeze()
    return code


def _reader_gone() -> int:
    """The end of a command whose reader closed the pipe (`keo gain ... | head`): no
    traceback, as for any Unix filter.

    Python ignores SIGPIPE and raises BrokenPipeError instead; the interpreter would raise it
    once more when it flushes stdout at exit, so stdout is pointed at /dev/null first.

    Returns:
        128 + SIGPIPE, the code a shell reports for a filter that SIGPIPE ended, so that
        `set -o pipefail` still sees that the output was cut short.
    """
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    os.close(devnull)
    return common.EXIT_BROKEN_PIPE
