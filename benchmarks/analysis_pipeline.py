"""The whole inspection pipeline on a full 1200 x 800 mm scan at HD8 density; prints one JSON object.

A synthetic scan of the formed sail plate (``analysis.synth``: 0.1 mm point pitch, 500 points per
profile, a profile every ``--profile-step-mm``, raster and edge passes, bed, supports, noise,
outliers, a random placement) goes through ``analysis.pipeline.inspect_cloud`` with the default
detection lines (14 transverse, 7 longitudinal, 2 diagonals). Synthesis and file I/O are not
timed. Then the same for a plate of twice the area (sides x sqrt 2, lines scaled to fit) for the
cost's growth.

``--publish-pitch-mm 0.5`` thins each profile as the cell publishes it (cell.toml ``[scan]
publish_pitch_mm``). Keys: points (points analysed of the 1200 x 800 scan), stages_s (per pipeline
stage), total_s (wall), cpu_s (process CPU time of that run), scaling (total_s of the 2x-area scan / total_s),
points_2x, total_2x_s, load_avg_1min (above 2 the wall times on this 2-core machine are
inflated by other processes), zmax_mm (per line, for a sanity look), verdict.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import structlog

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from analysis.cloud_io import ScanCloud, read_cloud, write_cloud_npz
from analysis.design.plates import default_forming_error, design_mesh, plate_spec
from analysis.pipeline import InspectionSettings, inspect_cloud
from analysis.synth import ScanSettings, synthesize_scan
from analysis.templates import DetectionLayout


def _scan(length_mm: float, width_mm: float, step_mm: float, seed: int, cache: Path | None):
    spec = plate_spec("sail", length_mm=length_mm, width_mm=width_mm)
    if cache and cache.is_file():
        return spec, read_cloud(cache)
    scan = synthesize_scan(
        spec, default_forming_error(spec), settings=ScanSettings(profile_step_mm=step_mm), seed=seed
    )
    cloud = scan.cloud
    if cache:
        write_cloud_npz(cloud, cache)
    return spec, cloud


def _thin(cloud: ScanCloud, pitch_mm: float, native_mm: float = 0.1) -> ScanCloud:
    """Every k-th point of each profile, renumbered densely: what the cell publishes at ``[scan]
    publish_pitch_mm`` (cellctl.acquisition.publish)."""
    k = max(1, round(pitch_mm / native_mm))
    if k == 1:
        return cloud
    keep = cloud.point_index % k == 0
    return ScanCloud(
        cloud.xyz_mm[keep], cloud.pass_id[keep], cloud.profile_index[keep], cloud.point_index[keep] // k
    )


def _run(spec, cloud: ScanCloud, layout: DetectionLayout) -> tuple[dict, float, float]:
    design = design_mesh(spec, pitch_mm=2.0)
    c0 = time.process_time()
    t0 = time.perf_counter()
    ins = inspect_cloud(cloud, design, InspectionSettings(layout=layout))
    return ins.report, time.perf_counter() - t0, time.process_time() - c0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--profile-step-mm", type=float, default=1.0, help="1.0 gives about 10^7 raw points")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument(
        "--publish-pitch-mm", type=float, default=0.0,
        help="thin each profile to this pitch as the cell publishes it (cell.toml: 0.5); 0: all points",
    )  # fmt: skip
    parser.add_argument("--no-scaling", action="store_true", help="skip the 2x-area run")
    parser.add_argument(
        "--cache-dir", type=Path, default=None, help="keep the synthetic scans here between runs"
    )
    args = parser.parse_args()
    structlog.configure(
        logger_factory=structlog.PrintLoggerFactory(sys.stderr),
        wrapper_class=structlog.make_filtering_bound_logger(30),
    )
    cache = (lambda name: args.cache_dir / name) if args.cache_dir else (lambda name: None)
    if args.cache_dir:
        args.cache_dir.mkdir(parents=True, exist_ok=True)

    spec, cloud = _scan(
        1200.0, 800.0, args.profile_step_mm, args.seed, cache(f"scan1x-{args.profile_step_mm}.npz")
    )
    cloud = _thin(cloud, args.publish_pitch_mm)
    report, total_s, cpu_s = _run(spec, cloud, DetectionLayout())
    out = {
        "points": len(cloud),
        "stages_s": {k: v for k, v in report.timings_s.items() if k != "total"},
        "total_s": round(total_s, 3),
        "cpu_s": round(cpu_s, 3),
        "verdict": report.verdict,
        "zmax_mm": {line.name: round(line.zmax_mm, 3) for line in report.lines},
    }
    del cloud
    if not args.no_scaling:
        k = math.sqrt(2.0)
        spec2, cloud2 = _scan(1200.0 * k, 800.0 * k, args.profile_step_mm, args.seed,
                              cache(f"scan2x-{args.profile_step_mm}.npz"))  # fmt: skip
        layout2 = DetectionLayout(14, 80.0 * k, 7, 100.0 * k, True)
        cloud2 = _thin(cloud2, args.publish_pitch_mm)
        _, total2_s, _ = _run(spec2, cloud2, layout2)
        out.update(points_2x=len(cloud2), total_2x_s=round(total2_s, 3),
                   scaling=round(total2_s / total_s, 3))  # fmt: skip
    out["load_avg_1min"] = round(os.getloadavg()[0], 2)
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
