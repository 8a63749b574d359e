"""`cellctl design check FILE`: what a design file (IGES, STEP or mesh) gives the inspection.

Exit codes: 0 the design is usable, 2 it is not (one line naming the file and the problem).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from cellctl.config import ConfigError, load_config


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("design", help="check a design file (IGES, STEP, PLY, STL, OBJ) before scanning")
    dsub = p.add_subparsers(dest="design_command", required=True, metavar="check")
    c = dsub.add_parser(
        "check",
        help="units, faces, size, corners, area, smallest radius, detection lines, preview PNG; exit 2 if unusable",
        description=__doc__.split("\n\n")[0],
    )
    c.add_argument("file", help="design: .igs/.iges/.stp/.step (units from the file) or .ply/.stl/.obj (mm)")
    c.add_argument("--thickness", type=float, default=None, metavar="MM",
                   help="plate thickness: also give the other side's corners (offset along the normals)")  # fmt: skip
    c.add_argument("--template-table", default=None, metavar="CSV",
                   help="the yard's template table: also list the lines it places (docs/designs.md)")  # fmt: skip
    c.add_argument("--preview", default=None, metavar="PNG",
                   help="preview image path (default: <file stem>-check.png in the current directory)")  # fmt: skip
    c.add_argument("--no-preview", action="store_true", help="do not draw the preview")
    c.add_argument("--json", action="store_true", help="print the result as one JSON object")
    c.add_argument(
        "--config",
        default=None,
        help="cell.toml for the [analysis] line layout (default: ./cell.toml if present)",
    )
    c.set_defaults(func=run_check)


def _fail(msg: str) -> int:
    print(f"cellctl design check: {msg}", file=sys.stderr)
    return 2


def run_check(args: argparse.Namespace) -> int:
    from analysis.design.template_table import read_template_table
    from analysis.design_check import check_design, preview_png
    from cellctl.analysis_job import inspection_settings
    from cellctl.config import AnalysisSection

    cfg_path = args.config or ("cell.toml" if Path("cell.toml").is_file() else None)
    try:
        section = load_config(cfg_path).analysis if cfg_path else AnalysisSection()
    except ConfigError as err:
        return _fail(f"{err.source}: " + "; ".join(err.problems))
    try:
        table = read_template_table(args.template_table) if args.template_table else ()
        check = check_design(args.file, inspection_settings(section, table).layout, args.thickness)
    except ValueError as exc:  # the readers' errors are one-line ValueErrors naming the file
        return _fail(str(exc))
    if not args.no_preview:
        png = Path(args.preview or f"{Path(args.file).stem}-check.png")
        try:
            check.summary["preview"] = str(preview_png(check, png))
        except OSError as exc:
            return _fail(f"cannot write {png}: {exc.strerror or exc}")
    s = check.summary
    if args.json:
        print(json.dumps(s))
        return 0
    print(f"{s['file']}: {s['format']}, file units {s['file_units']}, {s.get('faces') or 'mesh,'} face(s)")
    print(f"  size {s['size_mm'][0]:.2f} x {s['size_mm'][1]:.2f} mm, area {s['area_mm2'] / 1e6:.4f} m^2")
    if "smallest_radius_mm" in s:
        print(f"  smallest radius of curvature {s['smallest_radius_mm']:.1f} mm")
        t = s["tessellation"]
        print(f"  tessellation {t['triangles']} triangles, chord error {t['chord_error_mm']:.4f} mm")
    for k, c in enumerate(s["corners_mm"]):
        print(f"  corner {k}: ({c[0]:.3f}, {c[1]:.3f}, {c[2]:.3f}) mm, design frame")
    if "other_side" in s:
        o = s["other_side"]
        print(
            f"  other side ({s['thickness_mm']} mm below): {o['size_mm'][0]:.2f} x {o['size_mm'][1]:.2f} mm"
        )
    print(f"  {len(s['lines'])} detection lines:")
    for line in s["lines"]:
        print(
            f"    {line['name']:>4} {line['family']:<12} at {line['position_mm']:8.2f} mm, "
            f"{line['start_plate_mm']} -> {line['end_plate_mm']} (plate frame), {line['length_mm']:.1f} mm"
        )
    if "preview" in s:
        print(f"  preview: {s['preview']}")
    return 0
