"""`cellctl sim [--config cell.toml]`: the simulated cell (controller, sensor, formed plate) on loopback."""

from __future__ import annotations

import argparse
import sys

from cellctl.config import DEFAULT_CONFIG_PATH, ConfigError, load_config


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "sim",
        help="run the simulated cell of [sim]: ABB controller (EGM + RWS) and HD8 sensor over a formed plate",
        description="Runs until SIGTERM or Ctrl-C; prints one JSON line with its addresses when ready.",
    )
    p.add_argument("--config", default=str(DEFAULT_CONFIG_PATH), help="cell.toml (default: ./cell.toml)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from cellctl.simcell_service import main_sync

    try:
        cfg = load_config(args.config)
    except ConfigError as err:
        for problem in err.problems:
            print(f"{err.source}: {problem}", file=sys.stderr)
        return 2
    return main_sync(cfg)
