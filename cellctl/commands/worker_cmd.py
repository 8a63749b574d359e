"""`cellctl worker [--config cell.toml]`: an analysis worker for the cell named in the configuration."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from cellctl.config import DEFAULT_CONFIG_PATH, ConfigError, load_config


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "worker",
        help="run an analysis worker (start one or many, anywhere Zenoh reaches the daemon)",
        description="Serve analysis jobs of the cell over Zenoh until SIGTERM or Ctrl-C.",
    )
    p.add_argument("--config", default=str(DEFAULT_CONFIG_PATH), help="cell.toml (default: ./cell.toml)")
    p.add_argument("--worker-id", default="", help="key-safe id (default: <host>-<pid>)")
    p.add_argument(
        "--analysis",
        default=None,
        help="analysis callable as 'package.module:function' (default: [analysis] callable)",
    )
    p.add_argument(
        "--heartbeat-s",
        type=float,
        default=None,
        help="job heartbeat period (default: [analysis] heartbeat_s)",
    )
    p.add_argument(
        "--data-dir",
        default=None,
        help="the worker's own directory: design cache, results until sent (default: [worker] data_dir)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # Imported here: `cellctl --help` must not pay for Zenoh.
    from cellctl.worker.service import run_worker
    from cellctl.worker.settings import WorkerSettings

    try:
        config = load_config(args.config)
    except ConfigError as err:
        for problem in err.problems:
            print(f"{err.source}: {problem}", file=sys.stderr)
        return 2
    if args.worker_id and not all(c.isalnum() or c in "-_." for c in args.worker_id):
        print(
            f"cellctl worker: --worker-id {args.worker_id!r}: letters, digits, '-', '_', '.' only",
            file=sys.stderr,
        )
        return 2
    if args.heartbeat_s is not None and not args.heartbeat_s > 0:
        print("cellctl worker: --heartbeat-s must be positive", file=sys.stderr)
        return 2
    settings = WorkerSettings.from_config(
        config, worker_id=args.worker_id, analysis=args.analysis, heartbeat_s=args.heartbeat_s,
        data_dir=None if args.data_dir is None else Path(args.data_dir),
    )  # fmt: skip
    return run_worker(config, settings)
