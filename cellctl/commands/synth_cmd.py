"""`cellctl synth`: a synthetic scan of a formed plate with its design and truth.

The command line of :mod:`analysis.synth`: the options (:func:`build_parser`), the ``--deform``
items (:func:`parse_deform`) and ``--bow-mm`` (:func:`parse_bows`) parsed, the outline checked
against what the analysis handles (:func:`check_outline_range`), then
:func:`analysis.synth.synthesize_scan` and :func:`analysis.synth.write_synth`.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from analysis.cloud_io import CloudError
from analysis.design.cad_write import write_design
from analysis.design.plates import (
    PLATE_KINDS,
    EdgeSpringback,
    FormingError,
    GaussianBump,
    PlateError,
    PlateSpec,
    default_forming_error,
    outline_corners_xy,
    plate_spec,
)
from analysis.synth import (
    ScanSettings,
    SynthError,
    random_placement,
    synthesize_scan,
    write_formed_mesh,
    write_synth,
)


def register(sub: argparse._SubParsersAction) -> None:
    # The options are build_parser()'s own; it prints them for `cellctl synth --help`.
    p = sub.add_parser(
        "synth",
        help=build_parser().description,
        add_help=False,
        prefix_chars="\0",
    )
    p.add_argument("args", nargs=argparse.REMAINDER)
    p.set_defaults(func=lambda a: synth_main(a.args))


def _kv(text: str, what: str) -> dict[str, float]:
    out: dict[str, float] = {}
    for part in text.split(","):
        if not part.strip():
            continue
        if "=" not in part:
            raise PlateError(f"--deform {what}: expected key=value, got {part!r}")
        k, v = part.split("=", 1)
        try:
            out[k.strip().lower()] = float(v)
        except ValueError:
            raise PlateError(f"--deform {what}: {k.strip()} is not a number: {v!r}") from None
    return out


def parse_deform(items: list[str] | None, spec: PlateSpec) -> FormingError:
    """Parse ``--deform`` items into a :class:`FormingError`.

    Items (repeatable): ``none``; ``default``; ``dent:x=200,y=-100,depth=2.5,sigma=60`` (down);
    ``bump:x=..,y=..,height=1.5,sigma=..`` (up); ``springback:amp=1,decay=80``; ``bend:0.01``
    (fraction); or a path to a JSON file holding :meth:`FormingError.to_dict`. No items: default.
    """
    if not items:
        return default_forming_error(spec)
    bumps: list[GaussianBump] = []
    springback: EdgeSpringback | None = None
    bend = 0.0
    for item in items:
        head, _, rest = item.partition(":")
        head = head.strip().lower()
        if head == "none":
            continue
        if head == "default":
            d = default_forming_error(spec)
            bumps.extend(d.bumps)
            springback = d.springback
            bend += d.bend_fraction
        elif head in ("dent", "bump"):
            kv = _kv(rest, head)
            amp_key = "depth" if head == "dent" else "height"
            missing = {"x", "y", amp_key, "sigma"} - set(kv)
            if missing:
                raise PlateError(f"--deform {head}: missing {', '.join(sorted(missing))}")
            amp = -abs(kv[amp_key]) if head == "dent" else abs(kv[amp_key])
            bumps.append(GaussianBump(kv["x"], kv["y"], amp, kv["sigma"]))
        elif head == "springback":
            kv = _kv(rest, head)
            if "amp" not in kv:
                raise PlateError("--deform springback: missing amp")
            springback = EdgeSpringback(kv["amp"], kv.get("decay", 80.0))
        elif head == "bend":
            try:
                bend += float(rest)
            except ValueError:
                raise PlateError(f"--deform bend: not a number: {rest!r}") from None
        elif Path(item).suffix.lower() == ".json":
            try:
                return FormingError.from_dict(json.loads(Path(item).read_text()))
            except (OSError, ValueError, TypeError) as exc:
                raise PlateError(f"--deform {item}: unreadable forming-error JSON ({exc})") from exc
        else:
            raise PlateError(
                f"--deform: unknown item {item!r} (none, default, dent:, bump:, springback:, bend:, FILE.json)"
            )
    return FormingError(bumps=tuple(bumps), springback=springback, bend_fraction=bend)


MAX_BOW_FRACTION = 0.02  # the largest bow (sagitta / edge length) the analysis is tested for


def parse_bows(text: str) -> tuple[float, float, float, float]:
    """``--bow-mm B0,B1,B2,B3``: four finite numbers (mm), one per edge; PlateError otherwise."""
    try:
        bows = tuple(float(v) for v in text.split(","))
    except ValueError:
        bows = ()
    if len(bows) != 4 or not np.isfinite(bows).all():
        raise PlateError(f"--bow-mm: four comma-separated bows in mm (edges 0-3) expected, got {text!r}")
    return bows  # type: ignore[return-value]


def check_outline_range(spec: PlateSpec) -> None:
    """Refuse an outline outside what the analysis handles (issue 18): every corner 60-120 degrees,
    edges 0 and 2 the long pair, each edge's bow at most 2 % of its length. Raises PlateError with
    the command-line option to blame; a spec in range passes silently.
    """
    # corner_angle_deg itself (60-120) and top_length_mm > 0 are PlateSpec's own checks.
    c = outline_corners_xy(spec)
    top = spec.length_mm if spec.top_length_mm is None else spec.top_length_mm
    lengths = [float(np.linalg.norm(c[(k + 1) % 4] - c[k])) for k in range(4)]
    for k in range(4):
        a, b = c[(k - 1) % 4] - c[k], c[(k + 1) % 4] - c[k]
        angle = float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))
        if not 60.0 - 1e-9 <= angle <= 120.0 + 1e-9:
            raise PlateError(
                f"--top-length-mm {top:g}: the corner at corner {k} would be {angle:.1f} degrees, "
                f"outside 60-120 (edge 2 from {_top_range(spec)} mm for this plate)"
            )
    if lengths[0] + lengths[2] < lengths[1] + lengths[3]:
        raise PlateError(
            f"outline: edges 0 and 2 ({lengths[0]:.1f}, {lengths[2]:.1f} mm) must be the long pair, edges 1 "
            f"and 3 are {lengths[1]:.1f}, {lengths[3]:.1f} mm (lengthen --top-length-mm or narrow --width-mm)"
        )
    for k, (bow, chord) in enumerate(zip(spec.bow_mm, lengths, strict=True)):
        if abs(bow) > MAX_BOW_FRACTION * chord + 1e-9:
            raise PlateError(
                f"--bow-mm: edge {k}'s bow {bow:g} mm exceeds 2 % of its {chord:.1f} mm length "
                f"({MAX_BOW_FRACTION * chord:.1f} mm)"
            )


def _top_range(spec: PlateSpec) -> str:
    """'lo-hi': the edge-2 lengths that keep corners 1 and 2 within 60-120 degrees."""
    shear = spec.width_mm / np.tan(np.radians(spec.corner_angle_deg))
    # c2 - c1 = (shear + top - length, width): the angle at corner 1 is 180 - atan2(width, that x).
    lo = spec.length_mm - shear - spec.width_mm / np.tan(np.radians(60.0))
    hi = spec.length_mm - shear + spec.width_mm / np.tan(np.radians(60.0))
    return f"{max(lo, 0.0):.1f}-{hi:.1f}"


def build_parser() -> argparse.ArgumentParser:
    """The ``cellctl synth`` argument parser."""
    p = argparse.ArgumentParser(
        prog="cellctl synth",
        description="Make a synthetic scan of a formed plate lying on the bed, with its design and truth.",
        epilog="example: cellctl synth --plate sail --deform dent:x=300,y=-100,depth=2.5,sigma=50 "
        "--out scan.ply  (a quick test scan: add --point-pitch-mm 1 --points-per-profile 50 "
        "--profile-step-mm 2)",
    )
    p.add_argument("--plate", choices=PLATE_KINDS, default="sail", help="design shape (default: sail)")
    p.add_argument("--length-mm", type=float, default=1200.0, help="footprint length along x (default 1200)")
    p.add_argument("--width-mm", type=float, default=800.0, help="footprint width along y (default 800)")
    p.add_argument("--thickness-mm", type=float, default=15.0, help="plate thickness (default 15)")
    o = p.add_argument_group(
        "outline",
        "A four-sided outline other than the rectangle. Corners count counter-clockwise seen from "
        "above, corner 0 first; edge k runs from corner k to corner k+1: edge 0 (0-1) along +x, "
        "--length-mm long; edge 2 (3-2) parallel to it, --width-mm away; edges 1 and 3 the sides.",
    )
    o.add_argument(
        "--corner-angle-deg",
        metavar="DEG",
        type=float,
        default=90.0,
        help="angle at corner 0 between edges 0 and 3, 60-120 (default 90; else a parallelogram)",
    )
    o.add_argument(
        "--top-length-mm",
        metavar="MM",
        type=float,
        default=None,
        help="length of edge 2 (default --length-mm; else a trapezoid); the corners at 1 and 2 must "
        "also be 60-120 degrees and edges 0 and 2 the long pair",
    )
    o.add_argument(
        "--bow-mm",
        metavar="B0,B1,B2,B3",
        default="0,0,0,0",
        help="per edge 0-3: sagitta of a parabolic bow in plan, positive outward, each at most 2%% of "
        "its edge's length (default 0,0,0,0)",
    )
    p.add_argument("--deform", action="append", metavar="ITEM",
                   help="none | default | dent:x=,y=,depth=,sigma= | bump:x=,y=,height=,sigma= | "
                   "springback:amp=,decay= | bend:FRACTION | FILE.json (repeatable; default: default)")  # fmt: skip
    p.add_argument(
        "--out", required=True, help="scan PLY path; writes <stem>-design.ply and <stem>-truth.json beside it"
    )
    p.add_argument(
        "--seed", type=int, default=0, help="seeds placement, noise, dropouts, outliers (default 0)"
    )
    p.add_argument(
        "--yaw-deg", type=float, default=None, help="placement yaw (default: random from the seed)"
    )
    p.add_argument(
        "--point-pitch-mm", type=float, default=0.1, help="spacing along the laser line (HD8: 0.1)"
    )
    p.add_argument("--points-per-profile", type=int, default=500, help="points per laser line (HD8: 500)")
    p.add_argument("--profile-step-mm", type=float, default=0.5, help="travel between profiles (default 0.5)")
    p.add_argument("--noise-mm", type=float, default=0.02, help="range noise sigma (default 0.02)")
    p.add_argument("--no-edge-passes", action="store_true", help="raster passes only (no thickness faces)")
    p.add_argument(
        "--cad",
        action="store_true",
        help="also write the design as exact NURBS: <stem>-design.igs and <stem>-design.step (mm)",
    )
    p.add_argument(
        "--formed-mesh",
        action="store_true",
        help="also write the formed plate's top surface (design + forming error, 4 mm grid, design "
        'frame): <stem>-formed.ply, the mesh_file of [sim.plate] kind = "mesh"',
    )
    return p


def synth_main(argv: list[str] | None = None) -> int:
    """``cellctl synth``: returns 0 on success, 2 on bad arguments or an unwritable output."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse already printed the message
        return 0 if exc.code == 0 else 2
    try:
        if not 60.0 <= args.corner_angle_deg <= 120.0:  # also refuses nan
            raise PlateError(f"--corner-angle-deg {args.corner_angle_deg:g}: outside 60-120 degrees")
        if args.top_length_mm is not None and not (
            np.isfinite(args.top_length_mm) and args.top_length_mm > 0
        ):
            raise PlateError(f"--top-length-mm {args.top_length_mm:g}: must be a positive length")
        spec = plate_spec(
            args.plate,
            length_mm=args.length_mm,
            width_mm=args.width_mm,
            thickness_mm=args.thickness_mm,
            corner_angle_deg=args.corner_angle_deg,
            top_length_mm=args.top_length_mm,
            bow_mm=parse_bows(args.bow_mm),
        )
        check_outline_range(spec)
        error = parse_deform(args.deform, spec)
        settings = ScanSettings(
            point_pitch_mm=args.point_pitch_mm,
            points_per_profile=args.points_per_profile,
            profile_step_mm=args.profile_step_mm,
            noise_mm=args.noise_mm,
            edge_passes=not args.no_edge_passes,
        )
        placement = None
        if args.yaw_deg is not None:
            rng = np.random.default_rng(args.seed)
            placement = random_placement(rng, yaw_deg=args.yaw_deg)
        scan = synthesize_scan(spec, error, settings=settings, placement=placement, seed=args.seed)
        paths = write_synth(scan, args.out)
        if args.cad:
            stem = paths[1].with_suffix("")
            paths = (*paths, write_design(spec, f"{stem}.igs"), write_design(spec, f"{stem}.step"))
        if args.formed_mesh:
            paths = (
                *paths,
                write_formed_mesh(spec, error, paths[0].with_name(f"{paths[0].stem}-formed.ply")),
            )
    except (PlateError, SynthError, CloudError) as exc:
        print(f"cellctl synth: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"cellctl synth: cannot write {args.out}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    print(f"wrote {paths[0]} ({len(scan.xyz_mm)} points), " + ", ".join(str(p) for p in paths[1:]))
    return 0
