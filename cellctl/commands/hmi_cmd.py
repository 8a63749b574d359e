"""`cellctl hmi`: the operator's screen (a web server speaking to the cell over Zenoh);
`cellctl hmi adduser`: add a user to its secrets file; `cellctl history [PLATE]`: the plate history."""

from __future__ import annotations

import argparse
import getpass
import os
import sys
from pathlib import Path

from cellctl.commands.scan_cmd import _config  # the configuration, or its problems printed
from cellctl.config import DEFAULT_CONFIG_PATH

DEFAULT_LISTEN = "127.0.0.1:8088"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "hmi",
        help="the operator's screen: serve the HMI over HTTP (pages, websocket) on the cell's Zenoh API",
        description=__doc__.split("\n\n")[0],
    )
    p.add_argument("--config", default=str(DEFAULT_CONFIG_PATH), help="cell.toml (default: ./cell.toml)")
    p.add_argument(
        "--listen", default=DEFAULT_LISTEN, help=f"host:port to serve on (default {DEFAULT_LISTEN})"
    )
    p.add_argument("--users", help="the HMI users' secrets file (name:role:hash per line, chmod 600)")
    p.add_argument(
        "--secure-cookie", action="store_true", help="mark the session cookie Secure (behind HTTPS)"
    )
    p.add_argument(
        "--default-placement",
        metavar="X,Y,Z,YAW",
        help="the Start page's placement to begin with (mm, mm, mm, deg)",
    )
    p.set_defaults(func=run)
    hsub = p.add_subparsers(dest="hmi_command", metavar="SUBCOMMAND")
    a = hsub.add_parser(
        "adduser", help="add or replace a user in the users file (password from stdin or prompt)"
    )
    a.add_argument("--users", required=True, help="the users file (created with mode 600)")
    a.add_argument("name")
    a.add_argument("role", choices=["viewer", "operator", "engineer"])
    a.add_argument("--password-env", help="read the password from this environment variable")
    a.set_defaults(func=adduser)

    h = sub.add_parser("history", help="the plate history: jobs, or one plate's rounds with Zmax per line")
    h.add_argument("plate", nargs="?", help="a plate id: its rounds side by side")
    h.add_argument("--config", default=str(DEFAULT_CONFIG_PATH), help="cell.toml (default: ./cell.toml)")
    h.set_defaults(func=history)


def adduser(args: argparse.Namespace) -> int:
    from cellctl.hmi.auth import AuthError, add_user

    if args.password_env:
        password = os.environ.get(args.password_env, "")
    elif sys.stdin.isatty():
        password = getpass.getpass(f"password for {args.name}: ")
    else:
        password = sys.stdin.readline().rstrip("\n")
    try:
        add_user(args.users, args.name, args.role, password)
    except AuthError as exc:
        print(f"cellctl hmi adduser: error: {exc}", file=sys.stderr)
        return 2
    print(f"{args.name} ({args.role}) written to {args.users}")
    return 0


def history(args: argparse.Namespace) -> int:
    from cellctl.jobstore.history import History, format_history

    cfg = _config(args.config)
    if cfg is None:
        return 2
    jobs_dir = Path(cfg.cell.data_dir) / "jobs"
    if not jobs_dir.is_dir():
        print(
            f"cellctl history: {jobs_dir}: no job directory here (is [cell] data_dir right?)", file=sys.stderr
        )
        return 2
    # an index in memory, rebuilt from the job directories (the record): reading the history needs no
    # write access to the daemon's data directory and never touches its history.sqlite
    hist = History(cfg.cell.data_dir, db_path=":memory:")
    try:
        hist.rebuild()
        print(format_history(hist, args.plate))
    finally:
        hist.close()
    return 0


def run(args: argparse.Namespace) -> int:
    import asyncio

    from cellctl.hmi.auth import Authenticator, AuthError, load_users
    from cellctl.hmi.server import serve
    from drivers.runtime import stop_on_signals

    cfg = _config(args.config)
    if cfg is None:
        return 2
    if not args.users:
        print(
            "cellctl hmi: error: --users FILE is required (create it with `cellctl hmi adduser`)",
            file=sys.stderr,
        )
        return 2
    try:
        users = load_users(args.users)
    except (AuthError, OSError) as exc:
        print(f"cellctl hmi: error: {exc}", file=sys.stderr)
        return 2
    host, _, port = args.listen.rpartition(":")
    if not host or not port.isdigit():
        print(f"cellctl hmi: error: --listen {args.listen!r}: expected host:port", file=sys.stderr)
        return 2

    placement = None
    if args.default_placement:
        try:
            x, y, z, yaw = (float(v) for v in args.default_placement.split(","))
        except ValueError:
            print("cellctl hmi: error: --default-placement: expected X,Y,Z,YAW", file=sys.stderr)
            return 2
        placement = {"pos_mm": [x, y, z], "rpy_deg": [0.0, 0.0, yaw]}

    async def main() -> int:
        stop = asyncio.Event()
        release = stop_on_signals(stop)
        try:
            return await serve(
                cfg, Authenticator(users), host, int(port), stop,
                secure_cookie=args.secure_cookie, default_placement=placement,
            )  # fmt: skip
        finally:
            release()

    return asyncio.run(main())
