"""Surface extraction: the plate's top and nothing else, from organised and unorganised scans."""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from analysis.cloud_io import ScanCloud
from analysis.contracts.placement import Placement
from analysis.design.plates import FormingError, GaussianBump, formed_height_mm, plate_spec
from analysis.segment import (
    NoPlateError,
    SegmentError,
    SegmentSettings,
    dense_ranks,
    pass_cells,
    segment_plate,
)
from analysis.synth import ScanSettings, synthesize_scan

COARSE = {"point_pitch_mm": 1.0, "points_per_profile": 50, "profile_step_mm": 2.0}


@cache
def _scan(kind: str = "sail", seed: int = 11, noise_mm: float = 0.02, length_mm: float = 1200.0):
    spec = plate_spec(kind, length_mm=length_mm, width_mm=length_mm * 2 / 3)
    return synthesize_scan(spec, settings=ScanSettings(noise_mm=noise_mm, **COARSE), seed=seed)


def _truth_top(scan, tol_mm: float) -> np.ndarray:
    """Points within tol of the formed top surface over the footprint, outliers excluded."""
    T = scan.T_bed_design
    q = (scan.xyz_mm - T[:3, 3]) @ T[:3, :3]
    z = formed_height_mm(scan.spec, scan.error, q[:, 0], q[:, 1])
    # The first hundredths of a millimetre of a thickness face are the top edge itself.
    inside = (np.abs(q[:, 0]) <= scan.spec.length_mm / 2 + 0.05) & (
        np.abs(q[:, 1]) <= scan.spec.width_mm / 2 + 0.05
    )
    return inside & (np.abs(q[:, 2] - z) < tol_mm) & ~scan.is_outlier


def test_grid_segmentation_keeps_the_top_surface_and_drops_bed_supports_faces_and_outliers():
    scan = _scan()
    res = segment_plate(scan.cloud)
    assert res.method == "grid"
    wide = _truth_top(scan, 0.2)
    # Nothing off the top surface: no bed, support, thickness face or outlier point.
    assert not (res.mask & ~wide).any()
    assert not (res.mask & scan.is_outlier).any()
    # Nearly all of the top surface (the rest: 6-sigma tails and a few cells at holes).
    assert res.mask.sum() >= 0.99 * _truth_top(scan, 0.12).sum()
    np.testing.assert_array_equal(res.points_mm, scan.xyz_mm[res.mask])
    assert res.cloud.organised and len(res.cloud) == res.mask.sum()


def test_scan_pitch_is_reported_for_meshing_the_points():
    # COARSE: 1 mm along the line, 2 mm between profiles; the coarser one bounds mesh cells.
    assert segment_plate(_scan().cloud).point_spacing_mm == pytest.approx(2.0, rel=0.05)
    small = _scan("sail", seed=6, length_mm=450.0)
    assert segment_plate(small.xyz_mm).point_spacing_mm == pytest.approx(2.0, rel=0.1)


def test_measured_noise_level_matches_the_sensor_noise():
    res = segment_plate(_scan().cloud)
    assert res.noise_sigma_mm == pytest.approx(0.02, rel=0.15)
    assert res.inlier_tol_mm == pytest.approx(6 * res.noise_sigma_mm)


def test_plate_area_is_the_design_top_area():
    res = segment_plate(_scan().cloud)
    assert res.plate_area_mm2 == pytest.approx(1200 * 800, rel=0.05)


@pytest.mark.parametrize("kind", ["saddle", "twisted", "cylinder"])
def test_other_plate_shapes_segment_without_foreign_points(kind):
    scan = _scan(kind, seed=4, length_mm=450.0)
    res = segment_plate(scan.cloud)
    assert not (res.mask & ~_truth_top(scan, 0.2)).any()
    assert res.mask.sum() >= 0.98 * _truth_top(scan, 0.12).sum()


def test_a_deep_narrow_dent_stays_part_of_the_plate():
    spec = plate_spec("sail", length_mm=600.0, width_mm=400.0)
    err = FormingError(bumps=(GaussianBump(50.0, 20.0, -4.0, 35.0),))
    scan = synthesize_scan(spec, err, settings=ScanSettings(**COARSE), seed=2)
    res = segment_plate(scan.cloud)
    T = scan.T_bed_design
    q = (res.points_mm - T[:3, 3]) @ T[:3, :3]
    in_dent = np.hypot(q[:, 0] - 50.0, q[:, 1] - 20.0) < 30.0
    assert in_dent.sum() > 0.9 * np.pi * 30.0**2 / (1.0 * 2.0)


def test_unorganised_cloud_takes_the_delaunay_route_with_the_same_result_quality():
    scan = _scan("sail", seed=6, length_mm=450.0)
    res = segment_plate(ScanCloud(scan.xyz_mm))
    assert res.method == "delaunay"
    assert not (res.mask & ~_truth_top(scan, 0.2)).any()
    assert res.mask.sum() >= 0.95 * _truth_top(scan, 0.12).sum()
    assert res.noise_sigma_mm == pytest.approx(0.02, rel=0.25)


def test_plain_array_input_is_accepted():
    scan = _scan("sail", seed=6, length_mm=450.0)
    assert segment_plate(scan.xyz_mm).method == "delaunay"


def test_noise_only_cloud_raises_no_plate():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-500, 500, (20_000, 3))
    with pytest.raises(NoPlateError, match="min_plate_area_mm2"):
        segment_plate(pts)


def test_organised_cloud_of_a_too_small_surface_raises_no_plate():
    spec = plate_spec("flat", length_mm=60.0, width_mm=40.0)
    scan = synthesize_scan(
        spec,
        FormingError(),
        settings=ScanSettings(**COARSE, margin_mm=5.0),
        placement=Placement.on_bed(0.0, 0.0, 0.0),
        seed=1,
    )
    with pytest.raises(NoPlateError):
        segment_plate(scan.cloud, SegmentSettings(min_plate_area_mm2=50_000.0))


@pytest.mark.parametrize(
    ("points", "message"),
    [
        (np.zeros((10, 3)), "too few"),
        (np.zeros((500, 2)), r"\(n, 3\)"),
        (np.full((500, 3), np.nan), "non-finite"),
    ],
)
def test_unusable_input_raises_segment_error(points, message):
    with pytest.raises(SegmentError, match=message):
        segment_plate(points)


def test_organisation_too_sparse_to_be_a_scan_grid_falls_back_to_delaunay():
    scan = _scan("sail", seed=6, length_mm=450.0)
    c = scan.cloud
    sparse = ScanCloud(c.xyz_mm, c.pass_id, c.profile_index * 1000, c.point_index)
    res = segment_plate(sparse)
    assert res.method == "delaunay"
    assert res.mask.sum() >= 0.95 * _truth_top(scan, 0.12).sum()


def test_a_transit_pass_that_sees_the_plate_at_both_ends_of_the_scan_keeps_the_scan_grid():
    """The daemon files the transit rows of a whole scan under pass 0 and numbers profiles by frame.
    When rows near both ends see the plate (the scan starts over it, where a stopped scan left the
    arm) that pass spans every frame: its grid was counted as all passes that long, the cloud was
    taken for no scan grid and went the Delaunay way (which mis-sized the demo plate: CI, stop 36).
    The pass's long run of missing frames is numbered short, the same in a streamed pass."""
    scan = _scan("sail", seed=6, length_mm=450.0)
    c = scan.cloud
    pid = c.pass_id.astype(np.int64)
    frames = np.bincount(pid, weights=None, minlength=pid.max() + 1) * 0
    np.maximum.at(frames, pid, c.profile_index.astype(np.int64) + 1)
    frame = c.profile_index + np.concatenate([[0], np.cumsum(frames)[:-1]])[pid]  # over the whole scan
    first, last = pid == 0, pid == pid.max() - 4  # the first and the last raster pass
    mid_first = np.median(c.profile_index[first])
    mid_last = np.median(c.profile_index[last])
    transit = (first & (np.abs(c.profile_index - mid_first) < 3)) | (
        last & (np.abs(c.profile_index - mid_last) < 3)
    )
    assert transit.sum() > 100 and np.ptp(frame[transit]) > 0.5 * np.ptp(frame)
    cloud = ScanCloud(c.xyz_mm, np.where(transit, 0, pid + 1), frame, c.point_index)
    res = segment_plate(cloud)
    assert res.method == "grid"
    assert res.mask.sum() >= 0.99 * _truth_top(scan, 0.12).sum()
    assert not (res.mask & ~_truth_top(scan, 0.2)).any()
    # the transit pass's cells made from its own rows (as a streamed scan makes them): the same
    sel = np.flatnonzero(transit)
    pc = pass_cells(c.xyz_mm[sel], frame[sel], c.point_index[sel], sel)
    assert pc is not None and pc.idx.shape[0] < 300 + 2 * 6  # two runs of 5 profiles, 256 apart
    np.testing.assert_array_equal(segment_plate(cloud, passes={0: pc}).mask, res.mask)


@settings(max_examples=8, deadline=None)
@given(
    kind=st.sampled_from(["sail", "saddle", "twisted", "cylinder", "flat"]),
    yaw=st.floats(0.0, 360.0),
    tilt=st.floats(0.0, 1.0),
    seed=st.integers(0, 1000),
)
def test_any_small_plate_at_any_placement_segments_to_its_top_surface(kind, yaw, tilt, seed):
    spec = plate_spec(kind, length_mm=300.0, width_mm=200.0, radius_x_mm=1500.0, radius_y_mm=1200.0)
    scan = synthesize_scan(
        spec,
        settings=ScanSettings(**COARSE),
        placement=Placement.on_bed(20.0, -10.0, yaw, tilt_deg=tilt, tilt_axis_deg=yaw / 2),
        seed=seed,
    )
    res = segment_plate(scan.cloud)
    assert not (res.mask & ~_truth_top(scan, 0.2)).any()
    assert res.mask.sum() >= 0.97 * _truth_top(scan, 0.12).sum()


def test_dense_unorganised_cloud_fits_cell_planes_on_a_subsample_with_the_same_result():
    scan = _scan("sail", seed=6, length_mm=450.0)
    full = segment_plate(scan.xyz_mm)
    sub = segment_plate(scan.xyz_mm, SegmentSettings(max_cell_sample=40_000))
    assert not (sub.mask & ~_truth_top(scan, 0.2)).any()
    assert sub.mask.sum() >= 0.97 * full.mask.sum()
    assert sub.noise_sigma_mm == pytest.approx(0.02, rel=0.25)


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.integers(min_value=0, max_value=40), min_size=1, max_size=300),
    st.sampled_from([0, 1, 5_000_000, 2**31 - 2]),
)
def test_dense_ranks_are_np_unique_s_inverse_for_dense_and_sparse_ids(ids, spread):
    # spread: ids far sparser than the points take the sorting route, the rest are counted
    a = np.asarray(ids, dtype=np.int64) * max(spread, 1)
    want = np.unique(a, return_inverse=True)[1]
    got = dense_ranks(a)
    assert got.dtype == np.int64
    np.testing.assert_array_equal(got, want)
