"""The `cellctl` command line: one entry point, one sub-command module per command group.

Each module in :mod:`cellctl.commands` exposes ``register(subparsers)``, which adds its parser and
sets ``func(args) -> int`` as the handler. Exit codes: 0 success (or "pass"), 1 "fail" verdicts,
2 errors (bad input, bad configuration), 130 interrupted.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
from collections.abc import Sequence

from cellctl import __version__
from cellctl.commands import COMMAND_MODULES
from cellctl.logging import configure_logging

EXIT_OK = 0
EXIT_FAIL = 1
EXIT_ERROR = 2
EXIT_INTERRUPTED = 130
EXIT_BROKEN_PIPE = 141  # 128 + SIGPIPE, what a shell reports for a tool whose reader went away


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one readable line, exit 2, no usage dump
        self.exit(EXIT_ERROR, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="cellctl",
        description="Robot laser-scanning cell for curved hull plate inspection.",
    )
    parser.add_argument("--version", action="version", version=f"cellctl {__version__}")
    parser.add_argument(
        "--log-format",
        choices=["auto", "json", "console"],
        default="auto",
        help="log line format (default: console lines on a terminal, JSON otherwise)",
    )
    parser.add_argument("--log-level", default="INFO", help="DEBUG, INFO, WARNING or ERROR (default INFO)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for module in COMMAND_MODULES:
        module.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_ERROR
    try:
        configure_logging(args.log_format, args.log_level)
    except ValueError as exc:
        print(f"cellctl: error: {exc}", file=sys.stderr)
        return EXIT_ERROR
    try:
        return int(args.func(args))
    except BrokenPipeError:
        # the reader went away (`cellctl status | head`): stop quietly, as a shell tool does; stdout
        # goes to /dev/null so that the interpreter's final flush does not fail again
        with contextlib.suppress(OSError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_BROKEN_PIPE
    except KeyboardInterrupt:
        print("cellctl: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
