"""`cellctl sim [--config cell.toml]`: the simulated cell (controller, sensor, formed plate) on loopback.

`cellctl sim fault [--config cell.toml] [--json JSON] [section.knob=value ...]` sends one request to a
running simulator's fault-control channel (docs/simulator.md) and prints the knobs now in force.

`cellctl sim heat PLAN --mesh IN --out OUT [--seed N]` applies a heating plan (heating-plan.json, or
the results directory holding it) to a formed plate's mesh with a forming model that is not the
planner's (:mod:`analysis.forming.simulate`) and writes the heated plate's mesh, with the draw in
``OUT``'s sidecar ``<stem>.heat.json``.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
from pathlib import Path
from typing import Any

from cellctl.config import DEFAULT_CONFIG_PATH, CellConfig, ConfigError, load_config

FAULT_EPILOG = """examples:
  cellctl sim fault egm.loss_fraction=0.05 egm.burst_ms=50
  cellctl sim fault controller.action=emergency_stop
  cellctl sim fault rws.error_status=503          (rws.error_status=0 clears it)
  cellctl sim fault laser.disconnect_after_frames=40 laser.clock_jump_ms=250
  cellctl sim fault --json '{"laser": {"corrupt": {"groups": 3, "mode": "framing"}}}'
  cellctl sim fault clear=true                    (every knob off)
  cellctl sim fault                               (only print the knobs in force)
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "sim",
        help="run the simulated cell of [sim]: ABB controller (EGM + RWS) and HD8 sensor over a formed plate",
        description="Runs until SIGTERM or Ctrl-C; prints one JSON line with its addresses when ready. "
        "`cellctl sim fault ...` changes a running simulator's fault knobs.",
    )
    p.add_argument("--config", default=str(DEFAULT_CONFIG_PATH), help="cell.toml (default: ./cell.toml)")
    p.set_defaults(func=run)
    actions = p.add_subparsers(dest="sim_action", metavar="{fault,heat}")
    f = actions.add_parser(
        "fault",
        help="send fault knobs to a running `cellctl sim` (its [sim] fault_listen endpoint)",
        description="Sends one request to <prefix>/sim/faults and prints the knobs now in force (JSON).",
        epilog=FAULT_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    # SUPPRESS: `cellctl sim --config X fault` keeps X
    f.add_argument("--config", default=argparse.SUPPRESS, help="cell.toml (default: ./cell.toml)")
    f.add_argument("--json", dest="payload", default=None, help="the whole request as a JSON object")
    f.add_argument(
        "--timeout", type=float, default=10.0, help="seconds to wait for the simulator (default 10)"
    )
    f.add_argument("knobs", nargs="*", metavar="section.knob=value", help="knobs, merged over --json")
    f.set_defaults(func=run_fault)
    h = actions.add_parser(
        "heat",
        help="apply a heating plan to a formed plate's mesh (simulated heating, a mismatched model)",
        description="Heats the plate of --mesh (PLY/STL/OBJ, design frame or ship coordinates) along the "
        "plan's lines with a forming model that is not the planner's: another mesh, coefficients off by "
        "up to +-25 %%, line ends off by up to +-5 mm (seeded). Writes --out and <stem>.heat.json "
        "beside it (the draw).",
    )
    h.add_argument("plan", help="heating-plan.json, or the results directory holding it")
    h.add_argument("--mesh", required=True, help="the formed plate's top surface (.ply/.stl/.obj)")
    h.add_argument("--out", required=True, help="the heated plate's mesh (.ply/.stl/.obj)")
    h.add_argument("--seed", type=int, default=0, help="the perturbation's seed (default 0)")
    h.add_argument(
        "--coefficient-spread", type=float, default=0.25, help="coefficients off by up to this (0.25)"
    )
    h.add_argument("--position-spread-mm", type=float, default=5.0, help="line ends off by up to this (5 mm)")
    h.set_defaults(func=run_heat)


def _load(path: str) -> CellConfig | None:
    try:
        return load_config(path)
    except ConfigError as err:
        for problem in err.problems:
            print(f"{err.source}: {problem}", file=sys.stderr)
        return None


def run(args: argparse.Namespace) -> int:
    from cellctl.simcell.service import main_sync

    cfg = _load(args.config)
    if cfg is None:
        return 2
    return main_sync(cfg)


def _merge(base: dict[str, Any], extra: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in extra.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def run_fault(args: argparse.Namespace) -> int:
    from cellctl.simcell.faults import FaultChannelError, FaultRequestError, parse_assignments

    cfg = _load(args.config)
    if cfg is None:
        return 2
    try:
        request: dict[str, Any] = {}
        if args.payload is not None:
            try:
                request = json.loads(args.payload)
            except json.JSONDecodeError as exc:
                raise FaultRequestError("malformed", "--json", f"not JSON: {exc}") from None
            if not isinstance(request, dict):
                raise FaultRequestError("malformed", "--json", "expected a JSON object")
        request = _merge(request, parse_assignments(args.knobs))
    except FaultRequestError as err:
        print(f"cellctl sim fault: {err}", file=sys.stderr)
        return 2
    try:
        state = asyncio.run(_send(cfg, request, args.timeout))
    except FaultChannelError as exc:
        print(f"cellctl sim fault: {exc}", file=sys.stderr)
        return 1
    print(json.dumps(state, indent=2))
    return 0


async def _send(cfg: CellConfig, request: dict[str, Any], timeout_s: float) -> dict[str, Any]:
    from cellctl.api.session import ZenohSetupError, close_session
    from cellctl.simcell.faults import FaultChannelError, open_fault_session, send_faults

    try:
        session = await asyncio.to_thread(open_fault_session, cfg, role="connect")
    except ZenohSetupError as exc:
        raise FaultChannelError(f"{exc} (is `cellctl sim` running?)") from None
    try:
        state = await send_faults(session, cfg.key_prefix, request, timeout_s=timeout_s)
        return state.model_dump(mode="json")
    finally:
        await asyncio.to_thread(close_session, session)


def heat_sidecar_path(out: Path) -> Path:
    """The sidecar JSON of a heated mesh ``out``: ``<stem>.heat.json`` beside it."""
    return out.with_name(out.stem + ".heat.json")


def run_heat(args: argparse.Namespace) -> int:
    from analysis.design.mesh import load_mesh, save_mesh
    from analysis.forming.plan_file import read_heating_plan
    from analysis.heat_mesh import heat_mesh

    out = Path(args.out)
    if out.suffix.lower() not in {".ply", ".stl", ".obj"}:
        print(f"cellctl sim heat: --out: write .ply, .stl or .obj, got {out.name!r}", file=sys.stderr)
        return 2
    try:
        plan = read_heating_plan(args.plan)
        mesh = load_mesh(args.mesh)
        heated = heat_mesh(
            plan, mesh, args.seed,
            coefficient_spread=args.coefficient_spread, position_spread_mm=args.position_spread_mm,
        )  # fmt: skip
    except ValueError as exc:  # HeatError, MeshError, the plan file (each message names the problem)
        print(f"cellctl sim heat: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"cellctl sim heat: {args.mesh}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    out.parent.mkdir(parents=True, exist_ok=True)
    save_mesh(heated.mesh, out)
    sidecar = heat_sidecar_path(out)
    sidecar.write_text(
        json.dumps({"plan": str(args.plan), "mesh": str(args.mesh), **heated.sidecar()}, indent=2)
    )
    print(
        json.dumps(
            {
                "out": str(out),
                "sidecar": str(sidecar),
                "max_deflection_mm": round(heated.max_deflection_mm, 3),
            }
        )
    )
    return 0
