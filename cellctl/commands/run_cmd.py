"""`cellctl run [--config cell.toml]`: the cell daemon (see :mod:`cellctl.daemon.service`)."""

from __future__ import annotations

import argparse
import sys

from cellctl.config import DEFAULT_CONFIG_PATH, ConfigError, load_config


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "run",
        help="run the cell daemon: robot, sensor, jobs and the Zenoh API",
        description="Serve scan triggers over Zenoh until SIGTERM or Ctrl-C (a scan in progress stops smoothly).",
    )
    p.add_argument("--config", default=str(DEFAULT_CONFIG_PATH), help="cell.toml (default: ./cell.toml)")
    p.add_argument("--no-html", action="store_true", help="store report.json only (no HTML / PDF rendering)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import asyncio

    from cellctl.daemon.service import run_daemon
    from drivers.runtime import precise_event_loop

    try:
        cfg = load_config(args.config)
    except ConfigError as err:
        for problem in err.problems:
            print(f"{err.source}: {problem}", file=sys.stderr)
        return 2
    if args.no_html:
        cfg = cfg.model_copy(update={"daemon": cfg.daemon.model_copy(update={"write_html_report": False})})
    with asyncio.Runner(loop_factory=precise_event_loop) as runner:
        return runner.run(run_daemon(cfg))
