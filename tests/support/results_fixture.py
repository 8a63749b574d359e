"""A results directory computed from a design and a formed plate whose deviation is known exactly.

No figure here is typed in: the design and formed heights come from :mod:`analysis.design.plates`, the
detection lines from :mod:`analysis.templates`, the six figures and the verdict from
:mod:`analysis.metrics`. The plate is laid in its own design frame (registration is the identity),
so the deviation at every point is ``design - formed = -dz`` of the forming error, exactly.
Used by the report tests and by ``benchmarks/report.py``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from analysis.contracts.job import Report
from analysis.contracts.results import write_report_json
from analysis.design.plates import (
    EdgeSpringback,
    FormingError,
    GaussianBump,
    PlateSpec,
    design_corners,
    design_height_mm,
    formed_height_mm,
    plate_spec,
)
from analysis.metrics import Tolerances, judge, line_metrics
from analysis.report.csv_table import write_csv
from analysis.templates import DetectionLayout, detection_lines

HOLE_CELL_MM = 5.0


@dataclass(frozen=True)
class SyntheticResults:
    """What the fixture wrote and the truth behind it.

    dent_xy_mm / bump_xy_mm: the centres of the dent (plate below the template) and of the bump
    (plate above it), mm from the reference corner; hole_box_mm: (x0, y0, x1, y1) the unscanned patch.
    """

    results_dir: Path
    spec: PlateSpec
    error: FormingError
    report: Report
    dent_xy_mm: tuple[float, float]
    dent_depth_mm: float
    bump_xy_mm: tuple[float, float]
    bump_height_mm: float
    hole_box_mm: tuple[float, float, float, float]


def default_error(spec: PlateSpec, dent_mm: float = 3.6, bump_mm: float = 2.6) -> FormingError:
    """A deep dent at (+L/4, -W/8), a bump at (-L/5, +W/5) (design frame), mild spring-back."""
    L, W = spec.length_mm, spec.width_mm
    return FormingError(
        bumps=(
            GaussianBump(L / 4, -W / 8, -dent_mm, min(L, W) / 14),
            GaussianBump(-L / 5, W / 5, bump_mm, min(L, W) / 12),
        ),
        springback=EdgeSpringback(0.4, 60.0),
    )


#: the cell's detection layout (cell.toml [analysis]): the paper's spacing, the counts scaled to the
#: plate (23 lines on the 1200 x 800 mm sail, 95 on a 6000 x 2000 mm plate)
CELL_LAYOUT = DetectionLayout(transverse_count=None, longitudinal_count=None)


def write_plate_results(
    out_dir: Path,
    length_mm: float,
    width_mm: float,
    *,
    n_points: int = 300_000,
    layout: DetectionLayout = CELL_LAYOUT,
    plate_id: str = "P-LONG",
) -> SyntheticResults:
    """:func:`write_synthetic_results` for a sail-shaped plate of any size, with as many map points
    as the pipeline stores (``analysis.pipeline.MAX_MAP_POINTS``) and the cell's layout by default."""
    spec = plate_spec("sail", length_mm=length_mm, width_mm=width_mm)
    return write_synthetic_results(out_dir, n_points=n_points, spec=spec, layout=layout, plate_id=plate_id)


def _ply(points_mm: np.ndarray, deviation_mm: np.ndarray, path: Path) -> None:
    rec = np.empty(
        len(points_mm), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("scalar_deviation", "<f4")]
    )
    rec["x"], rec["y"], rec["z"] = points_mm.T
    rec["scalar_deviation"] = deviation_mm
    header = (
        f"ply\nformat binary_little_endian 1.0\nelement vertex {len(rec)}\n"
        "property float x\nproperty float y\nproperty float z\nproperty float scalar_deviation\nend_header\n"
    )
    with path.open("wb") as f:
        f.write(header.encode("ascii"))
        f.write(rec.tobytes())


def write_synthetic_results(
    out_dir: Path,
    *,
    n_points: int = 20_000,
    spec: PlateSpec | None = None,
    error: FormingError | None = None,
    layout: DetectionLayout = DetectionLayout(),
    tolerances: Tolerances = Tolerances(),
    plate_id: str = "P-0001",
    seed: int = 3,
) -> SyntheticResults:
    """Write report.json, report.csv, results.npz and cloud.ply for a formed plate into ``out_dir``."""
    spec = spec or plate_spec("sail")
    error = error if error is not None else default_error(spec)
    out_dir.mkdir(parents=True, exist_ok=True)
    L, W = spec.length_mm, spec.width_mm
    origin = np.array([-L / 2, -W / 2])  # the reference corner in the design frame
    rng = np.random.default_rng(seed)

    # the scan: a dense jittered 2 mm grid with one unscanned patch away from the dent and the bump;
    # the results keep a random subsample of it, as the pipeline does
    hole = (0.45 * L, 0.75 * W, 0.45 * L + 60.0, 0.75 * W + 40.0)
    gx, gy = np.meshgrid(np.arange(1.0, L, 2.0), np.arange(1.0, W, 2.0), indexing="ij")
    scan = np.column_stack([gx.ravel(), gy.ravel()]) + rng.uniform(-0.9, 0.9, size=(gx.size, 2))
    in_hole = (
        (scan[:, 0] >= hole[0]) & (scan[:, 0] < hole[2]) & (scan[:, 1] >= hole[1]) & (scan[:, 1] < hole[3])
    )
    scan = scan[~in_hole]
    xy = scan[rng.choice(len(scan), size=min(n_points, len(scan)), replace=False)]
    xd, yd = (xy + origin).T
    z_design = design_height_mm(spec, xd, yd)
    z_formed = formed_height_mm(spec, error, xd, yd)
    deviation = z_design - z_formed

    # coverage: 5 mm cells of the design with no scan point in them
    nx, ny = int(np.ceil(L / HOLE_CELL_MM)), int(np.ceil(W / HOLE_CELL_MM))
    ij = np.minimum((scan / HOLE_CELL_MM).astype(int), [nx - 1, ny - 1])
    seen = np.zeros((nx, ny), dtype=bool)
    seen[ij[:, 0], ij[:, 1]] = True
    hi, hj = np.nonzero(~seen)
    holes = np.column_stack([(hi + 0.5) * HOLE_CELL_MM, (hj + 0.5) * HOLE_CELL_MM]).astype(np.float32)

    # detection lines, sampled every mm on design and formed surfaces, judged by analysis.metrics
    corners = design_corners(spec)
    lines = detection_lines(corners, layout)
    arrays: dict[str, np.ndarray] = {}
    metrics = []
    records = []
    for k, line in enumerate(lines):
        s = np.arange(0.0, np.floor(line.chord_mm) + 1e-9, 1.0)
        p = line.start_mm[:2] + np.outer(s, line.direction[:2])
        hd = design_height_mm(spec, p[:, 0], p[:, 1])
        hm = formed_height_mm(spec, error, p[:, 0], p[:, 1])
        arrays[f"line{k}_s_mm"] = s
        arrays[f"line{k}_design_z_mm"] = hd
        arrays[f"line{k}_measured_z_mm"] = hm
        arrays[f"line{k}_deviation_mm"] = hd - hm
        metrics.append(line_metrics(s, hd, hm, noise_mm=0.0, family=line.family, index=line.index))
        records.append((line.start_mm[:2] - origin, line.end_mm[:2] - origin))
    verdict = judge(metrics, tolerances)
    report_lines = []
    for m, (a, b) in zip(verdict.lines, records, strict=True):
        rec = m.as_dict()
        rec["name"] = f"{m.family[0].upper()}{m.index}"
        rec["start_plate_mm"] = [float(a[0]), float(a[1])]
        rec["end_plate_mm"] = [float(b[0]), float(b[1])]
        report_lines.append(rec)
    arrays["plate_xy_mm"] = xy.astype(np.float32)
    arrays["plate_deviation_mm"] = deviation.astype(np.float32)
    arrays["plate_size_mm"] = np.array([L, W])
    arrays["coverage_holes_xy_mm"] = holes
    np.savez_compressed(out_dir / "results.npz", **arrays)

    pts = np.column_stack([xd, yd, z_formed])
    _ply(pts, deviation, out_dir / "cloud.ply")
    rms = float(np.sqrt(np.mean(deviation**2)))
    report = Report.model_validate({
        "plate_id": plate_id,
        "job_id": "job-fixture",
        "cell_id": "sim1",
        "created_utc": "2026-01-01T00:00:00Z",
        "verdict": verdict.verdict,
        "standard": tolerances.standard,
        "registration": {
            "coarse_rms_mm": rms,
            "icp_rms_mm": rms,
            "nonpen_rms_mm": rms,
            "penetration_points": int(np.count_nonzero(deviation < 0)),
            "penetration_points_before": int(np.count_nonzero(deviation < 0)),
            "surface_points": len(xy),
            "surface_cell_mm": 2.0,
            "raw_points_below_4sigma": 0,
            "transform": np.eye(4).tolist(),
            "corner_shift": 0,
        },
        "corners_mm": corners.tolist(),
        "plate_size_mm": [L, W],
        "lines": report_lines,
        "tolerances": tolerances.as_dict(),
        "timings_s": {"fixture": 0.0},
        "coverage": {
            "fraction": float(seen.mean()),
            "holes_mm2": float((~seen).sum() * HOLE_CELL_MM**2),
        },
        "surface": {"points": len(xy), "noise_sigma_mm": 0.0, "max_deviation_mm": float(deviation.max())},
        "inputs": {"cloud": "synthetic", "design": f"{spec.kind} {L:g} x {W:g}", "points": len(xy)},
    })  # fmt: skip
    write_report_json(report, out_dir / "report.json")
    write_csv(report, out_dir / "report.csv")
    dent, bump = error.bumps[0], error.bumps[1]
    return SyntheticResults(
        out_dir,
        spec,
        error,
        report,
        (dent.x_mm + L / 2, dent.y_mm + W / 2),
        -dent.amplitude_mm,
        (bump.x_mm + L / 2, bump.y_mm + W / 2),
        bump.amplitude_mm,
        hole,
    )
