"""The pipeline on synthetic scans with known truth (in-process, small plates for speed)."""

from __future__ import annotations

import numpy as np
import pytest

from analysis.contracts.placement import Placement
from analysis.design.plates import (
    NO_FORMING_ERROR,
    FormingError,
    GaussianBump,
    design_corners,
    design_mesh,
    plate_spec,
)
from analysis.pipeline import (
    InspectionSettings,
    design_corners_from_mesh,
    height_grid_mesh,
    inspect_cloud,
    plate_frame,
)
from analysis.synth import ScanSettings, synthesize_scan
from analysis.templates import DetectionLayout

SETTINGS = InspectionSettings(layout=DetectionLayout(5, 100.0, 3, 100.0, True))


def _scan(error: FormingError, seed: int):
    spec = plate_spec("sail", length_mm=600, width_mm=400)
    st = ScanSettings.coarse()
    return spec, synthesize_scan(spec, error, settings=st, seed=seed)


def test_design_corners_from_mesh_match_the_plate_definition() -> None:
    spec = plate_spec("sail", length_mm=600, width_mm=400)
    got = design_corners_from_mesh(design_mesh(spec, pitch_mm=10))
    np.testing.assert_allclose(got, design_corners(spec), atol=1e-6)


def test_plate_frame_puts_the_reference_corner_at_the_origin() -> None:
    c = design_corners(plate_spec("sail", length_mm=600, width_mm=400))
    T = plate_frame(c)
    p = c @ T[:3, :3].T + T[:3, 3]
    np.testing.assert_allclose(p[:, :2], [[0, 0], [600, 0], [600, 400], [0, 400]], atol=1e-9)


def test_height_grid_mesh_averages_points_per_cell() -> None:
    xy = np.stack(np.meshgrid(np.arange(0, 10, 0.1), np.arange(0, 10, 0.1)), -1).reshape(-1, 2) + 0.05
    z = 0.5 * xy[:, 0] + np.random.default_rng(0).normal(0, 0.02, len(xy))
    mesh = height_grid_mesh(np.column_stack([xy, z]), 1.0)
    assert len(mesh.vertices_mm) == 100 and len(mesh.triangles) == 2 * 81
    resid = mesh.vertices_mm[:, 2] - 0.5 * mesh.vertices_mm[:, 0]
    assert np.abs(resid).max() < 0.02  # 100 points per cell: noise down by 10x


@pytest.mark.slow
def test_rigidly_moved_design_without_forming_error_reads_below_0_05_mm() -> None:
    spec, scan = _scan(NO_FORMING_ERROR, seed=4)
    ins = inspect_cloud(scan.cloud, design_mesh(spec, pitch_mm=2.0), SETTINGS)
    zmax = [line.zmax_mm for line in ins.report.lines]
    assert len(zmax) == 10
    assert max(zmax) < 0.05, zmax
    assert ins.report.registration.penetration_points == 0
    assert ins.report.verdict == "pass"


@pytest.mark.slow
def test_known_dent_depth_is_found_on_the_lines_through_it() -> None:
    h = 1.5
    # A dent centred on transverse line 3 (x = 0 in the design frame) and longitudinal line 2 (y = 0).
    error = FormingError(bumps=(GaussianBump(x_mm=0.0, y_mm=0.0, amplitude_mm=-h, sigma_mm=40.0),))
    spec, scan = _scan(error, seed=5)
    ins = inspect_cloud(scan.cloud, design_mesh(spec, pitch_mm=2.0), SETTINGS)
    by_name = {line.name: line for line in ins.report.lines}
    for name in ("T3", "L2"):
        assert abs(by_name[name].zmax_mm - h) < 0.1, (name, by_name[name].zmax_mm)
    assert ins.report.registration.penetration_points == 0


@pytest.mark.slow
def test_the_same_plate_scanned_five_times_repeats_zmax_within_0_05_mm() -> None:
    from analysis.design.plates import default_forming_error

    spec = plate_spec("sail", length_mm=600, width_mm=400)
    error = default_forming_error(spec)
    design = design_mesh(spec, pitch_mm=2.0)
    zmax = []
    for seed in range(5):  # every seed: new noise, outliers and a new random placement on the bed
        st = ScanSettings.coarse(point_pitch_mm=0.5, points_per_profile=100, profile_step_mm=1.0)
        scan = synthesize_scan(spec, error, settings=st, seed=10 + seed)
        T = scan.T_bed_design  # the operator's nominal placement: which end is the reference corner
        nominal = Placement.on_bed(T[0, 3], T[1, 3], float(np.degrees(np.arctan2(T[1, 0], T[0, 0]))))
        report = inspect_cloud(scan.cloud, design, SETTINGS, nominal_placement=nominal).report
        zmax.append([line.zmax_mm for line in report.lines])
    spread = np.ptp(np.array(zmax), axis=0)
    assert spread.max() < 0.05, dict(
        zip([f"line{i}" for i in range(len(spread))], spread.round(3), strict=True)
    )
