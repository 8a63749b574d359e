"""`cellctl config check [FILE]`: validate a cell.toml with readable errors."""

from __future__ import annotations

import argparse
import sys

from cellctl.config import DEFAULT_CONFIG_PATH, ConfigError, load_config, secret_file_problems


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("config", help="configuration tools")
    csub = p.add_subparsers(dest="config_command", metavar="ACTION", required=True)
    check = csub.add_parser("check", help="validate a cell.toml; prints ok or every error, exit 2 on error")
    check.add_argument("file", nargs="?", default=str(DEFAULT_CONFIG_PATH), help="default: ./cell.toml")
    check.set_defaults(func=run_check)


def run_check(args: argparse.Namespace) -> int:
    try:
        cfg = load_config(args.file)
    except ConfigError as err:
        for problem in err.problems:
            print(f"{err.source}: {problem}", file=sys.stderr)
        return 2
    # what the cell would refuse when it runs, said now: a secrets file others may read
    problems = secret_file_problems(cfg)
    for problem in problems:
        print(f"{args.file}: {problem}", file=sys.stderr)
    if problems:
        return 2
    print("ok")
    return 0
