"""The locate run: time and placement error over random placements of the 1200 x 800 sail plate.

``--plate long``: a 6000 x 2000 mm plate (``--length-mm`` / ``--width-mm`` for another) on the long
cell's bed (``docs/examples/cell-track.toml``),
laid within ``--yaw-spread-deg`` (3) of the bed's long axis: a 6 m plate fits a long bed only along
it. The JSON names the config, the plate and the spread.

Mode ``optics`` (what this measures): the locate passes are the real ones of ``cell.toml``
(:func:`cellctl.daemon.locate.next_locate_plans`, the daemon's order: the planner's passes at the
locate height along the ``[locate]`` bed, then passes across planned from the first fit at the
heights of the outline they cross, or the square family across the bed's middle), the sensor is the laser simulator's optics (``drivers.laser.sim.optics``:
ray-cast fan, resampled 500-point line, depth noise ``[sim] depth_noise_mm``, outliers) over the
simulated cell's scene (the formed plate with its forming error, supports, bed) at ``--placements``
random placements on the bed (any yaw within 90 deg of the bed convention, the plate wholly on the
bed). Sensor poses are the passes' waypoints at the profile spacing (speed / rate); robot tracking
and clock errors are not in it (the e2e test, tests/e2e/test_locate_e2e.py, has them). A fit that
stays pinned in one direction only is an error, as the daemon fails the job.

Figures: ``located`` (placements found without error), ``within`` (found within 2 mm and 0.2 deg),
``max_pos_err_mm`` / ``max_angle_err_deg`` (xy of the design origin, yaw; a half-turn-symmetric
plate is compared with the convention's yaw, as the daemon decides it), ``max_z_err_mm``,
``locate_s_max`` / ``locate_s_mean``: the locate run's time = the planned motion of the runs (each
with the sensor settle of ``[daemon] settle_s``) + the fits' time + the time to plan the passes
across (those along are planned once, for every lay); ``fit_s_max`` (wall) / ``fit_cpu_s_max``;
``locate_cpu_s_max``: the same with the fits' and plans' CPU time instead of their wall time (the
figure to compare on a loaded machine); ``across_runs``: placements that needed passes across;
``across_plan_s_max``; per lay (stderr)
``runs`` and ``across_heights_mm`` (the sensor's z on each pass across). One JSON object on stdout.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path

import numpy as np
import structlog

from analysis.cloud_io import ScanCloud
from analysis.contracts.placement import Placement
from analysis.design.plates import design_mesh, plate_spec
from analysis.register.locate import LocateError, locate_plate, placement_offset
from cellctl.config import load_config
from cellctl.daemon.locate import LocatePlan, locate_settings, next_locate_plans
from cellctl.simcell.truth import plate_truth
from drivers.laser.sim.optics import LaserOptics, render_uniform
from drivers.laser.sim.scene import SceneRaycaster

REPO = Path(__file__).resolve().parents[1]


def _lay(
    rng: np.random.Generator, cfg, length_mm: float, width_mm: float, yaw_spread_deg: float | None = None
) -> tuple[float, float, float]:
    """A random lay wholly on the bed: any yaw within 90 deg of the convention, or within
    ``yaw_spread_deg`` of the bed's long axis (a 6 m plate fits a long bed only along it)."""
    lo, hi = np.asarray(cfg.locate.bed_min_xy_mm), np.asarray(cfg.locate.bed_max_xy_mm)
    axis_deg = 0.0 if (hi - lo)[0] >= (hi - lo)[1] else 90.0
    for _ in range(100_000):
        if yaw_spread_deg is None:
            yaw = float(rng.uniform(-89.9, 89.9)) + cfg.locate.convention_yaw_deg
        else:
            yaw = axis_deg + float(rng.uniform(-yaw_spread_deg, yaw_spread_deg))
            # the same outline half a turn round, within 90 deg of the convention (as the daemon reads it)
            yaw = cfg.locate.convention_yaw_deg + (yaw - cfg.locate.convention_yaw_deg + 90.0) % 180.0 - 90.0
        a = np.deg2rad(yaw)
        hx = abs(np.cos(a)) * length_mm / 2 + abs(np.sin(a)) * width_mm / 2
        hy = abs(np.sin(a)) * length_mm / 2 + abs(np.cos(a)) * width_mm / 2
        if 2 * hx < hi[0] - lo[0] and 2 * hy < hi[1] - lo[1]:
            return float(rng.uniform(lo[0] + hx, hi[0] - hx)), float(rng.uniform(lo[1] + hy, hi[1] - hy)), yaw
    raise SystemExit(f"a {length_mm:g} x {width_mm:g} mm plate does not fit the [locate] bed {lo} .. {hi}")


def _render(plan, speed_mm_s: float, rate_hz: float, rc, optics, rng) -> ScanCloud:
    """The plan's passes sampled at the profile spacing, rendered, in the cloud vocabulary."""
    step = speed_mm_s / rate_hz
    xs, ps, prs, pts = [], [], [], []
    prof0 = 0
    for k, seg in enumerate(plan.passes, start=1):
        p = seg.pos_mm
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
        u = np.arange(0.0, s[-1], step)
        pos = np.column_stack([np.interp(u, s, p[:, i]) for i in range(3)])
        T = np.tile(np.eye(4), (len(u), 1, 1))
        T[:, :3, :3] = seg.R_base_sensor[0]
        T[:, :3, 3] = pos
        r = render_uniform(rc, T, optics, rng)
        i, j = np.nonzero(r.valid)
        local = np.column_stack([r.x_mm[i, j], np.zeros(len(i)), r.z_mm[i, j]]).astype(np.float64)
        xs.append(np.einsum("nab,nb->na", T[i, :3, :3], local) + T[i, :3, 3])
        ps.append(np.full(len(i), k))
        prs.append(i + prof0)
        pts.append(j)
        prof0 += len(u)
    return ScanCloud(
        np.concatenate(xs),
        np.concatenate(ps).astype(np.int32),
        np.concatenate(prs).astype(np.int32),
        np.concatenate(pts).astype(np.int32),
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--placements", type=int, default=20)
    ap.add_argument("--seed", type=int, default=20)
    ap.add_argument("--config", default=None, help="default cell.toml; --plate long: the long cell's example")
    ap.add_argument("--plate", choices=["sail", "long"], default="sail",
                    help="long: a 6000 x 2000 mm plate (--length-mm/--width-mm) on the long cell's bed")  # fmt: skip
    ap.add_argument("--length-mm", type=float, default=None)
    ap.add_argument("--width-mm", type=float, default=None)
    ap.add_argument("--yaw-spread-deg", type=float, default=None,
                    help="lays within this of the bed's long axis (default: any yaw; --plate long: 3)")  # fmt: skip
    args = ap.parse_args(argv)
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))
    long_plate = args.plate == "long"
    if args.config is None:
        long_cell = REPO / "docs" / "examples" / "cell-track.toml"
        fallback = REPO / "examples" / "cell-track-6000x1200.toml"
        args.config = (
            str(REPO / "cell.toml") if not long_plate else str(long_cell if long_cell.exists() else fallback)
        )
    cfg = load_config(args.config)
    if long_plate or args.length_mm or args.width_mm:
        plate = cfg.sim.plate.model_copy(
            update={"length_mm": args.length_mm or (6000.0 if long_plate else cfg.sim.plate.length_mm),
                    "width_mm": args.width_mm or (2000.0 if long_plate else cfg.sim.plate.width_mm)}
        )  # fmt: skip
        cfg = cfg.model_copy(update={"sim": cfg.sim.model_copy(update={"plate": plate})})
    spread = args.yaw_spread_deg if args.yaw_spread_deg is not None else (3.0 if long_plate else None)
    sp = cfg.sim.plate
    spec = plate_spec(sp.kind, length_mm=sp.length_mm, width_mm=sp.width_mm, thickness_mm=sp.thickness_mm,
                      radius_x_mm=sp.radius_x_mm, radius_y_mm=sp.radius_y_mm)  # fmt: skip
    design = design_mesh(spec, pitch_mm=5.0)
    t0 = time.perf_counter()
    first = next_locate_plans(cfg, design, [], None)  # the family along the bed: every lay's
    plan_s = time.perf_counter() - t0
    optics = LaserOptics(
        width=cfg.laser.points_per_profile,
        x_pitch_mm=cfg.laser.line_width_mm / cfg.laser.points_per_profile,
        z_min_mm=cfg.laser.depth_min_mm,
        z_max_mm=cfg.laser.depth_max_mm,
        noise_sigma_mm=cfg.sim.depth_noise_mm,
        outlier_probability=cfg.sim.outlier_fraction,
    )
    rng = np.random.default_rng(args.seed)
    rows = []
    for _ in range(args.placements):
        x, y, yaw = _lay(rng, cfg, sp.length_mm, sp.width_mm, spread)
        truth_pl = Placement.on_bed(x, y, yaw, z_mm=cfg.sim.placement.pos_mm[2])
        truth = plate_truth(sp.kind, pos_mm=(x, y, truth_pl.z_mm), angle_deg=yaw, forming_error=True,
                            length_mm=sp.length_mm, width_mm=sp.width_mm, thickness_mm=sp.thickness_mm,
                            radius_x_mm=sp.radius_x_mm, radius_y_mm=sp.radius_y_mm)  # fmt: skip
        rc = SceneRaycaster(truth.scene())
        st = locate_settings(cfg, design, None)
        clouds: list[ScanCloud] = []
        run: list[LocatePlan] = []
        motion_s = fit_s = fit_cpu_s = across_plan_s = across_plan_cpu_s = 0.0
        found, error = None, ""
        while True:
            t, c = time.perf_counter(), time.process_time()
            plans = first if not run else next_locate_plans(cfg, design, run, found)
            if run:
                across_plan_s += time.perf_counter() - t
                across_plan_cpu_s += time.process_time() - c
            if not plans:
                break
            for lp in plans:
                clouds.append(_render(lp.plan, lp.plan.scan_speed_mm_s, cfg.laser.rate_hz, rc, optics, rng))
                motion_s += lp.plan.scan_time_s + cfg.daemon.settle_s
                run.append(lp)
            t, c = time.perf_counter(), time.process_time()
            try:
                found = locate_plate(clouds, design, st, [lp.range_z_mm for lp in run])
                error = ""
            except LocateError as exc:
                found, error = None, str(exc)
            fit_s += time.perf_counter() - t
            fit_cpu_s += time.process_time() - c
        if found is not None and not found.constrained:
            found, error = None, f"pinned in one direction only ({found.constraint_points:.0f} points across)"
        row = {"truth": [round(x, 2), round(y, 2), round(yaw, 3)], "runs": [lp.name for lp in run],
               "motion_s": round(motion_s, 2), "locate_s": round(motion_s + fit_s + across_plan_s, 2),
               "fit_s": round(fit_s, 3), "fit_cpu_s": round(fit_cpu_s, 3),
               "across_plan_s": round(across_plan_s, 3), "across_plan_cpu_s": round(across_plan_cpu_s, 3),
               "locate_cpu_s": round(motion_s + fit_cpu_s + across_plan_cpu_s, 2),
               "across_heights_mm": [round(float(lp.plan.passes[0].pos_mm[0, 2]), 1)
                                     for lp in run if lp.across]}  # fmt: skip
        if found is not None:
            d_mm, d_deg = placement_offset(found.placement, truth_pl)
            row.update(pos_err_mm=round(d_mm, 3), angle_err_deg=round(d_deg, 4),
                       z_err_mm=round(abs(found.placement.z_mm - truth_pl.z_mm), 3),
                       rms_mm=round(found.rms_mm, 3), coverage=round(found.coverage, 3))  # fmt: skip
        else:
            row["error"] = error
        rows.append(row)
        print(json.dumps(row), file=sys.stderr, flush=True)
    ok = [r for r in rows if "pos_err_mm" in r]
    out = {
        "benchmark": "locate",
        "mode": "optics",
        "mode_note": "real locate passes of cell.toml, laser simulator optics over the simulated scene; "
        "no robot tracking or clock error (the e2e test has those)",
        "plate": f"{sp.kind} {sp.length_mm:g} x {sp.width_mm:g} mm",
        "config": args.config,
        "yaw_spread_deg": spread,
        "track": cfg.robot.track is not None,
        "bed_mm": [cfg.locate.bed_min_xy_mm, cfg.locate.bed_max_xy_mm],
        "pass_spacing_mm": cfg.locate.pass_spacing_mm,
        "along_passes": first[0].plan.summary()["passes"],
        "along_motion_s": round(first[0].plan.scan_time_s + cfg.daemon.settle_s, 2),
        "plan_s": round(plan_s, 3),
        "placements": len(rows),
        "located": len(ok),
        "within": sum(1 for r in ok if r["pos_err_mm"] < 2.0 and r["angle_err_deg"] < 0.2),
        "max_pos_err_mm": max((r["pos_err_mm"] for r in ok), default=None),
        "max_angle_err_deg": max((r["angle_err_deg"] for r in ok), default=None),
        "max_z_err_mm": max((r["z_err_mm"] for r in ok), default=None),
        "max_rms_mm": max((r["rms_mm"] for r in ok), default=None),
        "locate_s_max": max(r["locate_s"] for r in rows),
        "locate_cpu_s_max": max(r["locate_cpu_s"] for r in rows),
        "locate_s_mean": round(float(np.mean([r["locate_s"] for r in rows])), 2),
        "fit_s_max": max(r["fit_s"] for r in rows),
        "fit_cpu_s_max": max(r["fit_cpu_s"] for r in rows),
        "load_1min": round(os.getloadavg()[0], 1),
        "across_runs": sum(1 for r in rows if len(r["runs"]) > 1),
        "across_plan_s_max": max(r["across_plan_s"] for r in rows),
        "errors": [r["error"] for r in rows if "error" in r],
    }
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
