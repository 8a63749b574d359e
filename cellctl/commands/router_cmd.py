"""`cellctl router`: Zenoh's router for a fleet (cells as peers, workers and tools as clients).

A Zenoh session in router mode, configured from ``[router]`` and ``[zenoh]`` of cell.toml (TLS and
access control as the daemon serves them, the rules covering every cell of ``[router] cells``), or
from a Zenoh JSON5 file (``--zenoh-config``, any setting zenohd takes; its mode is set to router).
It prints one JSON ready line on stdout and routes until SIGTERM or Ctrl-C. A stand-alone ``zenohd``
of the same Zenoh version does the same job (docs/operations.md, "Fleet").
"""

from __future__ import annotations

import argparse
import json
import sys

from cellctl.config import DEFAULT_CONFIG_PATH, ConfigError, load_config


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "router",
        help="run Zenoh's router for a fleet of cells and worker machines",
        description="Route Zenoh between cells (peers), workers and tools (clients) until SIGTERM or Ctrl-C.",
    )
    p.add_argument("--config", default=str(DEFAULT_CONFIG_PATH), help="cell.toml (default: ./cell.toml)")
    p.add_argument(
        "--zenoh-config", default=None, help="a Zenoh JSON5 configuration file instead of cell.toml"
    )
    p.add_argument("--listen", action="append", default=None, help="endpoint to listen on (repeatable)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import asyncio

    import zenoh

    from cellctl.api.session import ZenohSetupError, close_session, open_session, router_config_dict
    from cellctl.config import RouterSection
    from drivers.runtime import stop_on_signals

    try:
        if args.zenoh_config:
            zcfg = zenoh.Config.from_file(args.zenoh_config)
            zcfg.insert_json5("mode", '"router"')
            if args.listen:
                zcfg.insert_json5("listen/endpoints", json.dumps(args.listen))
            listen = args.listen or json.loads(zcfg.get_json("listen/endpoints") or "[]")
        else:
            config = load_config(args.config)
            listen = args.listen or list(config.router.listen)
            RouterSection(listen=listen)  # the same endpoint checks as the file's
            prefixes = list(config.router.cells) or [config.key_prefix]
            zcfg = zenoh.Config()
            for key, value in router_config_dict(config.zenoh, listen, prefixes).items():
                zcfg.insert_json5(key, json.dumps(value))
    except ConfigError as err:
        for problem in err.problems:
            print(f"{err.source}: {problem}", file=sys.stderr)
        return 2
    except (ZenohSetupError, ValueError, zenoh.ZError) as exc:
        where = f"{args.zenoh_config}: " if args.zenoh_config else ""  # zenoh's message names no file
        print(f"cellctl router: {where}{exc}", file=sys.stderr)
        return 2

    async def serve() -> int:
        stop = asyncio.Event()
        release = stop_on_signals(stop)
        session = None
        try:
            try:
                session = await asyncio.to_thread(open_session, zcfg, what="router")
            except ZenohSetupError as exc:
                print(f"cellctl router: {exc}", file=sys.stderr)
                return 2
            print(json.dumps({"ready": True, "zid": str(session.info.zid()), "listen": listen}), flush=True)
            await stop.wait()
            return 0
        finally:
            close_session(session)
            release()

    return asyncio.run(serve())
