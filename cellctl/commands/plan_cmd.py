"""`cellctl plan --design MESH --placement X,Y,ANGLE_DEG`: plan a coverage scan for commissioning.

Prints the passes, the predicted coverage, the scan time and the sweep ratio, or the refusal with
the pass, the point and the limit; ``--out`` writes the whole plan as JSON. Exit 0 when a plan was
made, 2 when it was refused or the input is unusable.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from cellctl.config import DEFAULT_CONFIG_PATH, ConfigError, load_config

EXIT_OK = 0
EXIT_REFUSED = 2


class PlacementArgError(ValueError):
    """A --placement value that is not X,Y,ANGLE_DEG or X,Y,Z,ANGLE_DEG (finite numbers)."""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "plan",
        help="plan a coverage scan of a design at a placement; prints passes, coverage, scan time",
        description=__doc__.split("\n\n")[0],
    )
    p.add_argument(
        "--design",
        required=True,
        help="design: IGES/STEP surface or top-surface mesh (PLY, STL or OBJ, mm, plate frame), "
        "or 'sim' for the plate in [sim.plate]",
    )
    p.add_argument(
        "--placement",
        required=True,
        help="plate frame origin and rotation on the bed, base frame: X,Y,ANGLE_DEG or X,Y,Z,ANGLE_DEG "
        "(mm, deg; Z defaults to [scan] placement_z_mm)",
    )
    p.add_argument("--config", default=str(DEFAULT_CONFIG_PATH), help="cell.toml (default: ./cell.toml)")
    p.add_argument("--out", help="write the plan as JSON to this file")
    p.add_argument(
        "--json", action="store_true", help="print the summary (or the refusal) as one JSON object"
    )
    p.add_argument("--no-coverage", action="store_true", help="skip the ray-cast coverage prediction")
    p.set_defaults(func=run_plan)


def parse_placement(text: str, default_z_mm: float):
    """``"X,Y,ANGLE_DEG"`` or ``"X,Y,Z,ANGLE_DEG"`` -> :class:`~analysis.contracts.placement.Placement`."""
    from pydantic import ValidationError

    from analysis.contracts.placement import Placement

    parts = [p.strip() for p in text.split(",")]
    if len(parts) not in (3, 4):
        raise PlacementArgError(f"--placement {text!r}: expected X,Y,ANGLE_DEG or X,Y,Z,ANGLE_DEG")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise PlacementArgError(f"--placement {text!r}: every value must be a number") from None
    if not all(math.isfinite(v) for v in values):
        raise PlacementArgError(f"--placement {text!r}: values must be finite")
    if len(values) == 3:
        x, y, a = values
        z = default_z_mm
    else:
        x, y, z, a = values
    try:
        return Placement.on_bed(x, y, a, z_mm=z)
    except ValidationError as exc:  # out of range: +-100 m, +-360 deg
        problem = exc.errors(include_url=False)[0]
        raise PlacementArgError(f"--placement {text!r}: {problem['msg']}") from None


def _design(arg: str, cfg):
    from analysis.design.cad import design_mesh_from_file
    from analysis.design.plates import design_mesh, plate_spec

    if arg == "sim" and cfg.sim.plate.kind == "mesh":
        return design_mesh_from_file(cfg.sim.plate.design_file)
    if arg == "sim":
        sp = cfg.sim.plate
        kind = "cylinder" if sp.kind == "cylindrical" else sp.kind
        spec = plate_spec(
            kind,
            length_mm=sp.length_mm,
            width_mm=sp.width_mm,
            thickness_mm=sp.thickness_mm,
            radius_x_mm=sp.radius_x_mm,
            radius_y_mm=sp.radius_y_mm,
        )
        return design_mesh(spec, pitch_mm=10.0)
    return design_mesh_from_file(Path(arg))


def _error(msg: str, as_json: bool) -> int:
    if as_json:
        print(json.dumps({"ok": False, "error": msg}))
    print(f"cellctl plan: error: {msg}", file=sys.stderr)
    return EXIT_REFUSED


def run_plan(args: argparse.Namespace) -> int:
    from analysis.design.mesh import MeshError
    from analysis.design.plates import PlateError
    from cellctl.planning import PlanInputError, PlannerSettings, PlanRefused, plan_scan

    try:
        cfg = load_config(args.config)
    except ConfigError as err:
        for problem in err.problems:
            print(f"{err.source}: {problem}", file=sys.stderr)
        return EXIT_REFUSED
    try:
        placement = parse_placement(args.placement, cfg.scan.placement_z_mm)
        design = _design(args.design, cfg)
        settings = PlannerSettings.from_config(cfg)
    except (PlacementArgError, PlanInputError, MeshError, PlateError) as exc:
        return _error(str(exc), args.json)
    try:
        plan = plan_scan(design, placement, settings, with_coverage=not args.no_coverage)
    except PlanRefused as exc:
        if args.json:
            print(json.dumps({"ok": False, "refusal": exc.to_dict()}))
        print(f"refused: {exc}", file=sys.stderr)
        return EXIT_REFUSED
    except PlanInputError as exc:
        return _error(str(exc), args.json)
    summary = plan.summary()
    if args.out:
        try:
            plan.to_json(args.out)
        except OSError as exc:
            return _error(f"--out {args.out}: {exc.strerror or exc}", args.json)
        summary["out"] = str(args.out)
    if args.json:
        print(json.dumps({"ok": True, **summary}))
        return EXIT_OK
    print(
        f"passes: {summary['passes']} raster + {summary['edge_passes']} edge (margin {summary['margin_mm']} mm)"
    )
    for seg, times in zip(plan.passes, summary["pass_times"], strict=True):
        print(
            f"  {seg.label:>8}: {seg.length_mm:8.1f} mm, {seg.duration_s:7.2f} s from t = {seg.t_start_s:8.2f} s"
            f" (transition before it {times['transition_s']:5.2f} s)"
        )
    print(
        f"coverage: {summary['coverage']:.2%} of the top surface (worst over the placement uncertainty "
        f"{summary['coverage_worst']:.2%})"
    )
    print(
        f"scan time: {summary['scan_time_s']:.1f} s at {summary['scan_speed_mm_s']} mm/s; sweep time "
        f"{summary['sweep_time_s']:.1f} s; ratio {summary['sweep_ratio']:.3f}"
    )
    print(
        f"  = approach {summary['approach_s']:.1f} s + passes {summary['sweep_s']:.1f} s + transitions "
        f"{summary['transitions_s']:.1f} s + retract {summary['retract_s']:.1f} s"
    )
    if args.out:
        print(f"plan written to {args.out}")
    return EXIT_OK
