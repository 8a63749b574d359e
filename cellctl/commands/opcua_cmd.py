"""`cellctl opcua`: the cell's OPC UA server (OPC 40210 GMS) for a plant's systems, a process of its
own that follows the cell through its Zenoh API (docs/opcua.md)."""

from __future__ import annotations

import argparse
import sys

from cellctl.commands.scan_cmd import _config  # the configuration, or its problems printed
from cellctl.config import DEFAULT_CONFIG_PATH


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "opcua",
        help="serve the cell over OPC UA (OPC 40210 GMS: state, latest result) on its Zenoh API",
        description=__doc__.split("\n\n")[0],
    )
    p.add_argument("--config", default=str(DEFAULT_CONFIG_PATH), help="cell.toml (default: ./cell.toml)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import asyncio

    from cellctl.api.session import ZenohSetupError
    from cellctl.opcua.server import OpcuaConfigError, serve
    from drivers.runtime import stop_on_signals

    cfg = _config(args.config)
    if cfg is None:
        return 2
    if not cfg.opcua.enabled:
        print("cellctl opcua: error: [opcua] enabled = false in the configuration", file=sys.stderr)
        return 2

    async def main() -> int:
        stop = asyncio.Event()
        release = stop_on_signals(stop)
        try:
            return await serve(cfg, stop)
        finally:
            release()

    try:
        return asyncio.run(main())
    except (OpcuaConfigError, ZenohSetupError) as exc:
        print(f"cellctl opcua: error: {exc}", file=sys.stderr)
        return 2
