"""Bytes per point of the analysis' stages (issue 42 item 2, docs/operations.md): a float32 cloud is
held as it came, the segmentation's peak, the design's rasterisation and the resting surface stay within
their bounds, with the same results as before the cuts."""

from __future__ import annotations

import tracemalloc
from functools import cache

import numpy as np
import pytest

from analysis.cloud_io import ScanCloud
from analysis.design.plates import design_mesh, plate_spec
from analysis.register import height_field as hf_module
from analysis.register.height_field import height_field_from_mesh
from analysis.segment import pass_cells, segment_plate
from analysis.synth import ScanSettings, synthesize_scan

#: the segmentation's peak on a float32 cloud, bytes a point of the cloud: 162 before the cuts (int64
#: pass order and grid, every pass's cells and coordinates kept to the end, the selection's parts held
#: twice), 98 after
SEGMENT_PEAK_B_PER_POINT = 125.0
#: what a pass's cells hold per point of the pass (its positions in the cloud and its grid), kept to the
#: end of a streamed scan: 28 with a float32 copy of its coordinates and int64 indices, 8-9 now
PASS_CELLS_B_PER_POINT = 12.0
#: the design rasterisation's peak, bytes a grid node: 400 in one pass over every (triangle, node)
#: pair, about 100 in blocks on the sail's 1 mm grid (the block is a fixed 75 MB)
RASTER_PEAK_B_PER_NODE = 160.0
#: the resting surface's peak past the gap evaluation (whose blocks are bounded apart), bytes a plate
#: point: 260 with three float64 copies of the points, int64 and float64 columns per point and
#: ``_edge_fits``' sorted copies of them all (203 held); about 40 now (the caller's points read a
#: chunk at a time, gap float64 + patch int32 + weight bool held, the edge fits on the edge's points)
REST_SURFACE_PEAK_B_PER_POINT = 90.0


@cache
def _float32_scan() -> tuple[ScanCloud, ScanCloud]:
    """The sail at a coarse pitch (780 k points): as the wire carries it (float32) and as float64."""
    scan = synthesize_scan(
        plate_spec("sail"),
        settings=ScanSettings(noise_mm=0.02, point_pitch_mm=1.0, points_per_profile=50, profile_step_mm=2.0),
        seed=11,
    )
    c = scan.cloud
    xyz32 = c.xyz_mm.astype(np.float32)
    return (
        ScanCloud(xyz32, c.pass_id, c.profile_index, c.point_index),
        ScanCloud(xyz32.astype(np.float64), c.pass_id, c.profile_index, c.point_index),
    )


def _peak_bytes(fn, *args, **kwargs) -> tuple[object, int]:
    """(fn's result, the numpy heap's peak over what was live before, bytes)."""
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        tracemalloc.reset_peak()
        out = fn(*args, **kwargs)
        return out, tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()


def test_a_float32_cloud_is_held_as_given_without_a_float64_copy():
    xyz = np.arange(30, dtype=np.float32).reshape(10, 3)
    org, prof = np.zeros(10, np.int32), np.arange(10, dtype=np.int32)
    cloud = ScanCloud(xyz, org, prof, org)
    assert cloud.xyz_mm.dtype == np.float32 and np.shares_memory(cloud.xyz_mm, xyz)
    assert np.shares_memory(cloud.profile_index, prof)  # int32 indices: no copy either
    assert ScanCloud(xyz.astype(np.float16)).xyz_mm.dtype == np.float64  # other dtypes: float64 as before


def test_segmenting_a_float32_cloud_selects_what_its_float64_copy_selects():
    c32, c64 = _float32_scan()
    r32, r64 = segment_plate(c32), segment_plate(c64)
    np.testing.assert_array_equal(r32.mask, r64.mask)
    assert r32.points_mm.dtype == np.float64  # the later stages' arithmetic stays float64
    np.testing.assert_array_equal(r32.points_mm, r64.points_mm)
    assert r32.noise_sigma_mm == r64.noise_sigma_mm and r32.point_spacing_mm == r64.point_spacing_mm


def test_segmentation_peak_stays_within_its_bytes_per_point():
    c32, _ = _float32_scan()
    res, peak = _peak_bytes(segment_plate, c32)
    per_point = peak / len(c32)
    assert res.mask.sum() > 0.5 * len(c32)
    assert per_point <= SEGMENT_PEAK_B_PER_POINT, f"segment peak {per_point:.0f} B/point"


def test_a_pass_s_cells_hold_no_copy_of_its_coordinates():
    c32, _ = _float32_scan()
    sel = np.flatnonzero(c32.pass_id == np.bincount(c32.pass_id).argmax())
    pc = pass_cells(c32.xyz_mm[sel], c32.profile_index[sel], c32.point_index[sel], sel.astype(np.int64))
    # the arrays that grow with the pass's points (per point or per grid place; not the cells' own)
    arrays = [v for v in vars(pc).values() if isinstance(v, np.ndarray)]
    per_point = sum(v.nbytes for v in arrays if v.shape[:1] == sel.shape or v.shape == pc.idx.shape) / len(
        sel
    )
    assert per_point <= PASS_CELLS_B_PER_POINT, f"a pass's cells hold {per_point:.1f} B/point"


def test_design_rasterisation_in_blocks_is_the_one_pass_field_within_a_bounded_peak(monkeypatch):
    mesh = design_mesh(plate_spec("sail"), pitch_mm=10.0)
    field, peak = _peak_bytes(height_field_from_mesh, mesh, 1.0)
    per_node = peak / field.z_mm.size
    assert per_node <= RASTER_PEAK_B_PER_NODE, f"rasterisation peak {per_node:.0f} B/node"
    # blocks of any size give the field of one pass (a shared node keeps the later triangle's value)
    for pairs in (997, 1 << 30):
        monkeypatch.setattr(hf_module, "_RASTER_BLOCK_PAIRS", pairs)
        other = height_field_from_mesh(mesh, 1.0)
        np.testing.assert_array_equal(other.z_mm, field.z_mm)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_the_registered_cloud_file_stores_the_float64_transform_rounded_once(tmp_path, dtype):
    from analysis.pipeline import _moved_float32
    from analysis.register.transforms import apply_transform, make_transform

    rng = np.random.default_rng(2)
    pts = (rng.normal(0, 3000, (5000, 3))).astype(dtype).astype(np.float64)
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    T = make_transform(R, np.array([1234.5678, -987.654, 12.3]))
    np.testing.assert_array_equal(
        _moved_float32(T, pts, block=777), apply_transform(T, pts).astype(np.float32)
    )


def test_the_resting_surface_s_peak_stays_within_its_bytes_per_point(monkeypatch):
    import analysis.register.rest_surface as rs
    from analysis.register.transforms import apply_transform, make_transform

    # a 600 x 400 mm sail-like plate at 4 points per mm^2 (960 k points), tilted and turned on the bed
    xs, ys = np.linspace(-310.0, 310.0, 125), np.linspace(-210.0, 210.0, 85)
    X, Y = np.meshgrid(xs, ys)
    field = hf_module.HeightField(float(xs[0]), float(ys[0]), 5.0, X**2 / 12000.0 + Y**2 / 8000.0)
    rng = np.random.default_rng(5)
    xy = rng.uniform([-300.0, -200.0], [300.0, 200.0], (960_000, 2))
    z = xy[:, 0] ** 2 / 12000.0 + xy[:, 1] ** 2 / 8000.0 + rng.normal(0.0, 0.02, len(xy))
    a = np.radians(20.0)
    R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    T = make_transform(R, np.array([2500.0, 1200.0, 80.0]))
    P = np.ascontiguousarray(apply_transform(T, np.column_stack([xy, z])))
    # the peak from the end of the first gap evaluation on (its blocks in flight are a fixed amount)
    peaks: list[int] = []
    gaps = rs.deflection_gaps

    def timed_gaps(*args, **kwargs):
        peaks.append(tracemalloc.get_traced_memory()[1])
        out = gaps(*args, **kwargs)
        tracemalloc.reset_peak()
        return out

    monkeypatch.setattr(rs, "deflection_gaps", timed_gaps)
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        rest = rs.rest_surface(field, P, T)
        peaks.append(tracemalloc.get_traced_memory()[1])
    finally:
        tracemalloc.stop()
    per_point = (max(peaks[1:]) - base) / len(P)
    assert rest.edge_patches > 0 and len(rest.counts) > 500
    assert per_point <= REST_SURFACE_PEAK_B_PER_POINT, f"rest_surface peak {per_point:.0f} B/point"
