"""Analysis accuracy against the truth: template lift and Zmax error at three sensor noise levels.

Synthetic dented plates (the 1200 x 800 mm sail; dents of known depth and width at random places,
nothing else: then the template's true resting pose is exactly where the generator put the design,
see ``analysis.accuracy``) are scanned through ``analysis.synth`` (raster and edge passes, bed,
supports, outliers, dropouts, any placement angle) at each ``--noise-mm`` and inspected with
``analysis.pipeline.inspect_cloud``; both template fits are evaluated (rigid judged, per-line
through ``template_fit_compare``).

Per noise level: ``lift_mean_mm`` / ``lift_max_abs_mm`` (the rested design's height above the true
undented surface, mean and largest over the footprint, worst plate) and the same in sigmas;
``zmax_error_max_mm`` (largest |Zmax - true Zmax| over every line of every plate, rigid fit) and
``zmax_error_max_per_line_fit_mm``; ``penetration_points`` (of the resting surface, summed: 0);
``rest_cell_mm``. Prints one JSON object with ``levels`` and ``target`` (lift < 0.3 sigma, every
Zmax within 0.1 mm).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np
import structlog

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from analysis.accuracy import template_lift, true_line_zmax
from analysis.contracts.placement import Placement
from analysis.design.plates import FormingError, GaussianBump, design_mesh, plate_spec
from analysis.pipeline import InspectionSettings, inspect_cloud
from analysis.register.height_field import height_field_from_mesh
from analysis.synth import ScanSettings, synthesize_scan


def dented(spec, rng: np.random.Generator, count: int) -> FormingError:
    """``count`` dents 0.3-2.5 mm deep, 20-80 mm wide (Gaussian sigma), inside the footprint."""
    bumps = tuple(
        GaussianBump(
            float(rng.uniform(-0.4, 0.4) * spec.length_mm),
            float(rng.uniform(-0.4, 0.4) * spec.width_mm),
            -float(rng.uniform(0.3, 2.5)),
            float(rng.uniform(20.0, 80.0)),
        )
        for _ in range(count)
    )
    return FormingError(bumps=bumps)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--noise-mm", type=float, nargs="+", default=[0.02, 0.05, 0.1])
    ap.add_argument("--plates", type=int, default=2, help="dented plates per noise level")
    ap.add_argument("--dents", type=int, default=4)
    ap.add_argument("--point-pitch-mm", type=float, default=0.5, help="0.1 is HD8's native pitch")
    ap.add_argument("--profile-step-mm", type=float, default=1.0)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    structlog.configure(
        wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING),
        logger_factory=structlog.PrintLoggerFactory(sys.stderr),
    )
    spec = plate_spec("sail")
    design = design_mesh(spec, pitch_mm=2.0)
    field = height_field_from_mesh(design, 1.0)
    settings = InspectionSettings(template_fit_compare=True)
    levels = []
    t0 = time.perf_counter()
    for noise in args.noise_mm:
        lifts, errs, errs_pl, pen, cells, sigmas = [], [], [], 0, [], []
        for k in range(args.plates):
            rng = np.random.default_rng(args.seed * 100 + k)
            error = dented(spec, rng, args.dents)
            st = ScanSettings(
                point_pitch_mm=args.point_pitch_mm,
                points_per_profile=round(50.0 / args.point_pitch_mm),
                profile_step_mm=args.profile_step_mm,
                noise_mm=noise,
            )
            scan = synthesize_scan(spec, error, settings=st, seed=args.seed * 100 + k)
            T = scan.T_bed_design
            nominal = Placement.on_bed(T[0, 3], T[1, 3], float(np.degrees(np.arctan2(T[1, 0], T[0, 0]))))
            ins = inspect_cloud(scan.cloud, design, settings, nominal_placement=nominal)
            lifts.append(template_lift(field, spec, T, ins.T_measured_design))
            truth = [
                true_line_zmax(spec, error, T, c.line.start_mm, c.line.direction, c.s_mm) for c in ins.cuts
            ]
            errs += [abs(ln.zmax_mm - z) for ln, z in zip(ins.report.lines, truth, strict=True)]
            by_name = {ln.name: ln for ln in ins.report.template_fit_compare.lines}
            errs_pl += [
                abs(by_name[ln.name].zmax_mm - z)
                for ln, z in zip(ins.report.lines, truth, strict=True)
                if ln.name in by_name
            ]
            reg = ins.report.registration
            pen += reg.penetration_points
            cells.append(reg.rest_surface.cell_mm)
            sigmas.append(reg.rest_surface.noise_mm)
        worst_mean = max(lifts, key=lambda x: abs(x.mean_mm)).mean_mm
        worst_abs = max(x.max_abs_mm for x in lifts)
        levels.append(
            {
                "noise_mm": noise,
                "noise_estimated_mm": round(float(np.mean(sigmas)), 5),
                "lift_mean_mm": round(worst_mean, 5),
                "lift_max_abs_mm": round(worst_abs, 5),
                "lift_mean_sigma": round(worst_mean / noise, 3),
                "lift_max_abs_sigma": round(worst_abs / noise, 3),
                "zmax_error_max_mm": round(max(errs), 4),
                "zmax_error_max_per_line_fit_mm": round(max(errs_pl), 4),
                "lines": len(errs),
                "penetration_points": pen,
                "rest_cell_mm": round(float(np.mean(cells)), 2),
            }
        )
    print(
        json.dumps(
            {
                "levels": levels,
                "plates": args.plates,
                "dents": args.dents,
                "points_last_scan": len(scan.xyz_mm),
                "wall_s": round(time.perf_counter() - t0, 1),
                "target": {"lift_sigma": 0.3, "zmax_error_mm": 0.1},
            }
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
