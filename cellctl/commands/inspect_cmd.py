"""`cellctl inspect CLOUD --design MESH --out DIR`: offline analysis of a scan, no robot.

Exit codes: 0 the plate passes, 1 it fails the tolerances, 2 the inputs cannot be inspected.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

from cellctl.commands.scan_cmd import add_design_side_arguments
from cellctl.config import ConfigError, load_config


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "inspect",
        help="analyse a scan cloud against a design surface; exit 0 pass, 1 fail, 2 error",
        description="Segment the plate, find its corners, register the design (coarse, ICP, "
        "non-penetrating), cut the detection lines and judge them against the tolerances.",
    )
    p.add_argument("cloud", help="scan cloud: .ply (organised or not), .pcd, .xyz/.csv/.txt, .npz (mm)")
    p.add_argument(
        "--design",
        required=True,
        help="design surface: IGES/STEP (.igs/.iges/.stp/.step, units from the file) or a top-surface "
        "mesh (.ply/.stl/.obj, mm)",
    )
    p.add_argument("--out", required=True, help="results directory (created)")
    p.add_argument(
        "--placement",
        default=None,
        metavar="X,Y,ANGLE_DEG",
        help="nominal placement of the design on the bed (mm, mm, deg); optional, it decides the "
        "reference corner of a design that is symmetric under a half turn",
    )
    p.add_argument(
        "--template-table",
        default=None,
        metavar="CSV",
        help="the yard's template table (docs/designs.md): one named line per template, added to the layout",
    )
    add_design_side_arguments(p)
    p.add_argument("--plate-id", default="", help="plate id for the report (default: the cloud's file name)")
    p.add_argument(
        "--config", default=None, help="cell.toml for [analysis] settings (default: ./cell.toml if present)"
    )
    p.add_argument("--quiet", action="store_true", help="do not print the table")
    p.set_defaults(func=run)


def _fail(msg: str) -> int:
    print(f"cellctl inspect: {msg}", file=sys.stderr)
    return 2


def run(args: argparse.Namespace) -> int:
    # Heavy imports here, so `cellctl --help` stays fast.
    from analysis.cloud_io import read_cloud
    from analysis.contracts.job import ReportInputs
    from analysis.design.cad import read_design
    from analysis.design.template_table import read_template_table
    from analysis.pipeline import inspect_cloud, write_results
    from analysis.report.write import write_report
    from cellctl.analysis_job import inspection_settings
    from cellctl.commands.plan_cmd import parse_placement
    from cellctl.commands.tables import line_table
    from cellctl.config import AnalysisSection

    try:
        placement = parse_placement(args.placement, 0.0) if args.placement else None
        table = read_template_table(args.template_table) if args.template_table else ()
    except ValueError as exc:
        return _fail(str(exc))
    cfg_path = args.config or ("cell.toml" if Path("cell.toml").is_file() else None)
    try:
        section = load_config(cfg_path).analysis if cfg_path else AnalysisSection()
    except ConfigError as err:
        return _fail(f"{err.source}: " + "; ".join(err.problems))
    try:
        cloud = read_cloud(args.cloud)
        design = read_design(args.design)
        ins = inspect_cloud(
            cloud, design, replace(inspection_settings(section, table), design_side=args.design_side,
                                   thickness_mm=args.thickness),
            plate_id=args.plate_id or Path(args.cloud).stem,
            inputs=ReportInputs(points=0, cloud=str(args.cloud), design=str(args.design)),
            nominal_placement=placement,
        )  # fmt: skip
    except ValueError as exc:  # every analysis error type is a ValueError with a readable message
        return _fail(str(exc))
    except MemoryError:
        return _fail("out of memory: the cloud is too large for this machine")
    try:
        files = write_results(ins, args.out)
        files.update({p.name: p for p in write_report(args.out)})
    except OSError as exc:
        return _fail(f"cannot write {args.out}: {exc.strerror or exc}")
    if not args.quiet:
        print(line_table(ins.report))
        print(f"report: {files.get('report.html', files['report.json'])}")
    return 0 if ins.report.verdict == "pass" else 1
