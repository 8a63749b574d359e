"""Boundary feature points, edge splines and corners, for any placement angle."""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from analysis.boundary import BoundaryError, find_corners
from analysis.contracts.placement import Placement
from analysis.design.plates import (
    FormingError,
    GaussianBump,
    canonical_corner_order,
    design_corners,
    formed_height_mm,
    plate_spec,
)
from analysis.segment import segment_plate
from analysis.synth import ScanSettings, synthesize_scan

COARSE = ScanSettings(point_pitch_mm=1.0, points_per_profile=50, profile_step_mm=2.0)


def _rot(yaw_deg: float) -> np.ndarray:
    a = np.deg2rad(yaw_deg)
    return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])


def _top_points(spec, err, pitch_mm: float, rng: np.random.Generator) -> np.ndarray:
    """Jittered samples of a formed top surface, design frame, reaching the edges like a scan does."""
    hl, hw = spec.length_mm / 2, spec.width_mm / 2
    x, y = np.meshgrid(np.arange(-hl, hl + 1e-9, pitch_mm), np.arange(-hw, hw + 1e-9, pitch_mm))
    x = np.clip(x.ravel() + rng.uniform(-0.3, 0.3, x.size) * pitch_mm, -hl, hl)
    y = np.clip(y.ravel() + rng.uniform(-0.3, 0.3, y.size) * pitch_mm, -hw, hw)
    z = formed_height_mm(spec, err, x, y) + rng.normal(0, 0.02, x.size)
    return np.column_stack([x, y, z])


@settings(max_examples=8, deadline=None)
@given(yaw=st.floats(0.0, 360.0), seed=st.integers(0, 2**16))
def test_corners_of_a_sampled_top_surface_are_found_at_any_yaw(yaw, seed):
    rng = np.random.default_rng(seed)
    spec = plate_spec("sail", length_mm=360.0, width_mm=240.0, radius_x_mm=1500.0, radius_y_mm=1200.0)
    err = FormingError()
    T = _rot(yaw)
    T_t = np.array([120.0, -40.0, 80.0])
    pts = _top_points(spec, err, 0.5, rng) @ T.T + T_t
    res = find_corners(pts)
    truth = canonical_corner_order(design_corners(spec) @ T.T + T_t)
    err_mm = np.linalg.norm(res.corners_mm - truth, axis=1)
    assert err_mm.max() < 0.6, err_mm
    length, width = res.size_mm
    assert length == pytest.approx(360.0, abs=0.6) and width == pytest.approx(240.0, abs=0.6)


@cache
def _scan_and_corners(yaw: float, kind: str = "sail"):
    spec = plate_spec(kind)
    err = FormingError(bumps=(GaussianBump(300.0, -100.0, -2.0, 60.0),))
    scan = synthesize_scan(
        spec,
        err,
        settings=COARSE,
        placement=Placement.on_bed(40.0, -25.0, yaw, tilt_deg=0.4, tilt_axis_deg=yaw + 33.0),
        seed=int(yaw),
    )
    seg = segment_plate(scan.cloud)
    return scan, find_corners(seg.points_mm)


@pytest.mark.parametrize("yaw", [0.0, 93.0, 227.0, 301.5])
def test_corners_of_a_scanned_plate_match_the_truth_in_the_convention_order(yaw):
    scan, res = _scan_and_corners(yaw)
    truth = scan.corners_bed_mm()
    d = res.corners_mm - truth
    assert np.abs(d[:, :2]).max() < 1.5, d
    assert np.abs(d[:, 2]).max() < 0.5, d
    # Edge 0 is a long edge pointing into the bed's +x half plane; the order is counter-clockwise.
    e0 = res.corners_mm[1, :2] - res.corners_mm[0, :2]
    assert np.linalg.norm(e0) == pytest.approx(1200.0, abs=2.0) and e0[0] > 0
    xy = res.corners_mm[:, :2]
    assert 0.5 * np.sum(xy[:, 0] * np.roll(xy[:, 1], -1) - np.roll(xy[:, 0], -1) * xy[:, 1]) > 0


def test_edges_run_from_corner_to_corner_and_sample_the_edge_curves():
    scan, res = _scan_and_corners(93.0)
    for k, edge in enumerate(res.edges):
        ends = edge.evaluate(np.array([0.0, 1.0]))
        np.testing.assert_allclose(ends[0, :2], res.corners_mm[k, :2], atol=1e-6)
        np.testing.assert_allclose(ends[1, :2], res.corners_mm[(k + 1) % 4, :2], atol=1e-6)
        # The corner height is the mean of two edges' heights: each edge is within a hair of it.
        assert abs(ends[0, 2] - res.corners_mm[k, 2]) < 0.5
        samples = edge.sample_mm(2.0)
        steps = np.linalg.norm(np.diff(samples[:, :2], axis=0), axis=1)
        assert steps.max() < 2.1
        assert edge.rms_mm < 0.5
        assert len(edge.points_mm) > 100
    # The sail's edges are curves: 1204.5 mm and 802.4 mm of arc over the 1200 x 800 footprint.
    x = np.linspace(-600, 600, 12001)
    arc_long = np.linalg.norm(
        np.diff(np.column_stack([x, formed_height_mm(scan.spec, scan.error, x, -400.0)]), axis=0), axis=1
    ).sum()
    y = np.linspace(-400, 400, 8001)
    arc_short = np.linalg.norm(
        np.diff(np.column_stack([y, formed_height_mm(scan.spec, scan.error, 600.0, y)]), axis=0), axis=1
    ).sum()
    lengths = sorted(e.length_mm for e in res.edges)
    assert lengths[3] == pytest.approx(arc_long, abs=2.0) and lengths[0] == pytest.approx(arc_short, abs=2.0)


def test_boundary_feature_points_lie_on_the_plate_edges():
    scan, res = _scan_and_corners(227.0)
    T = scan.T_bed_design
    q = (res.boundary_points_mm - T[:3, 3]) @ T[:3, :3]
    inside_by = np.minimum(600.0 - np.abs(q[:, 0]), 400.0 - np.abs(q[:, 1]))
    assert np.quantile(inside_by, 0.99) < 1.5
    assert inside_by.min() > -0.2


def test_plate_frame_has_x_along_the_long_edges_and_z_up():
    scan, res = _scan_and_corners(301.5)
    T = res.plate_frame()
    R = T[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-9)
    assert R[2, 2] > 0.99
    design_x_in_bed = scan.T_bed_design[:3, 0]
    assert abs(R[:, 0] @ design_x_in_bed) > 0.9999
    np.testing.assert_allclose(T[:3, 3], res.corners_mm.mean(axis=0))


def test_stray_points_beyond_an_edge_are_removed_as_curvature_outliers():
    rng = np.random.default_rng(3)
    spec = plate_spec("sail", length_mm=360.0, width_mm=240.0, radius_x_mm=1500.0, radius_y_mm=1200.0)
    pts = _top_points(spec, FormingError(), 0.5, rng)
    clean = find_corners(pts)
    # A few isolated spikes 1-3 mm beyond the long edge y = -120 (spray, a burr).
    x = np.array([-100.0, -20.0, 40.0, 90.0, 130.0])
    y = -120.0 - np.array([1.0, 2.0, 3.0, 1.5, 2.5])
    stray = np.column_stack([x, y, formed_height_mm(spec, FormingError(), x, y)])
    res = find_corners(np.concatenate([pts, stray]))
    assert np.abs(res.corners_mm - clean.corners_mm).max() < 0.3
    assert sum(e.n_outliers for e in res.edges) >= 3


@pytest.mark.parametrize(
    ("points", "message"),
    [(np.zeros((10, 3)), "too few"), (np.zeros((500, 2)), r"\(n, 3\)")],
)
def test_unusable_points_raise_boundary_error(points, message):
    with pytest.raises(BoundaryError, match=message):
        find_corners(points)


def test_a_thin_line_of_points_has_no_four_edges():
    x = np.linspace(0, 1000, 5000)
    pts = np.column_stack([x, 0.001 * np.sin(x), np.zeros_like(x)])
    with pytest.raises(BoundaryError):
        find_corners(pts)


@settings(max_examples=6, deadline=None)
@given(
    kind=st.sampled_from(["sail", "saddle", "twisted", "cylinder", "flat"]),
    yaw=st.floats(0.0, 360.0),
    tilt=st.floats(0.0, 1.0),
    seed=st.integers(0, 1000),
)
def test_corners_of_any_small_scanned_plate_are_within_a_scan_pitch_of_the_truth(kind, yaw, tilt, seed):
    spec = plate_spec(kind, length_mm=300.0, width_mm=200.0, radius_x_mm=1500.0, radius_y_mm=1200.0)
    scan = synthesize_scan(
        spec,
        settings=COARSE,
        placement=Placement.on_bed(20.0, -10.0, yaw, tilt_deg=tilt, tilt_axis_deg=yaw / 2),
        seed=seed,
    )
    res = find_corners(segment_plate(scan.cloud).points_mm)
    truth = scan.corners_bed_mm()
    # Corner order is defined up to the half turn only when edge 0 points almost along +-y.
    d = min(np.abs(res.corners_mm - truth).max(), np.abs(np.roll(res.corners_mm, 2, axis=0) - truth).max())
    assert d < 2.0


def test_corners_of_a_ship_sized_plate_are_found_without_a_giant_raster():
    rng = np.random.default_rng(8)
    spec = plate_spec("saddle", length_mm=9000.0, width_mm=3000.0, radius_x_mm=40000.0, radius_y_mm=25000.0)
    pitch_mm = 4.0  # a coarse sampling of 27 m^2: the raster follows the points' spacing
    pts = _top_points(spec, FormingError(), pitch_mm, rng) @ _rot(21.0).T
    res = find_corners(pts)
    truth = canonical_corner_order(design_corners(spec) @ _rot(21.0).T)
    assert np.linalg.norm(res.corners_mm - truth, axis=1).max() < 1.5 * pitch_mm
