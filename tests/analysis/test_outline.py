"""Plates that are not rectangles: parallelograms, trapezoids, bowed edges, corner angles 60-120 deg.

The design's corners and own frame from a mesh in any pose (analysis.design.outline), the synthetic
plate's outline (analysis.design.plates), and the measured boundary's corners (analysis.boundary).
"""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from analysis.boundary import find_corners
from analysis.contracts.placement import Placement
from analysis.design.mesh import TriMesh
from analysis.design.outline import (
    design_corners_from_mesh,
    frame_design_mesh,
    mesh_boundary_loops,
    mesh_free_edges,
)
from analysis.design.plates import (
    FormingError,
    GaussianBump,
    PlateError,
    design_corners,
    design_height_mm,
    design_mesh,
    footprint_contains,
    outline_edges,
    plate_spec,
)
from analysis.segment import segment_plate
from analysis.synth import ScanSettings, synthesize_scan
from tests.support.surfaces import grid_mesh, sail, ship_pose

COARSE = ScanSettings(point_pitch_mm=1.0, points_per_profile=50, profile_step_mm=2.0)

OUTLINES = {
    "parallelogram_70": {"corner_angle_deg": 70.0},
    "parallelogram_118": {"corner_angle_deg": 118.0},
    "trapezoid_bowed": {"corner_angle_deg": 80.0, "top_length_mm": 1000.0, "bow_mm": (0.0, 0.0, 16.0, 0.0)},
    "bowed_in_and_out": {"corner_angle_deg": 98.0, "bow_mm": (-12.0, 8.0, 24.0, -8.0)},
}


def _angle_deg(u: np.ndarray, v: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(u @ v / np.linalg.norm(u) / np.linalg.norm(v), -1, 1))))


def test_outline_of_a_sheared_plate_has_the_corner_angles_and_edge_lengths_asked_for() -> None:
    spec = plate_spec("sail", corner_angle_deg=70.0, top_length_mm=1000.0)
    c = design_corners(spec)[:, :2]
    assert _angle_deg(c[1] - c[0], c[3] - c[0]) == pytest.approx(70.0, abs=1e-9)
    assert np.linalg.norm(c[1] - c[0]) == pytest.approx(1200.0) and np.linalg.norm(
        c[2] - c[3]
    ) == pytest.approx(1000.0)
    assert c[3, 1] - c[0, 1] == pytest.approx(800.0)
    np.testing.assert_allclose(c.mean(axis=0), 0.0, atol=1e-9)


def test_a_bowed_edge_bows_by_its_sagitta_and_the_mesh_border_lies_on_the_outline() -> None:
    spec = plate_spec("sail", **OUTLINES["bowed_in_and_out"])
    for ed, bow in zip(outline_edges(spec), spec.bow_mm, strict=True):
        mid = ed.point(0.5 * ed.chord_mm)[0]
        assert (mid - (ed.a + 0.5 * ed.chord_mm * ed.e)) @ ed.n == pytest.approx(bow)
    mesh = design_mesh(spec, pitch_mm=10.0)
    border = mesh.vertices_mm[mesh_boundary_loops(mesh)[0]]
    # every border vertex lies on one of the edge curves (cross offset equals the bow there)
    off = []
    for ed in outline_edges(spec):
        s = (border[:, :2] - ed.a) @ ed.e
        off.append(np.abs((border[:, :2] - ed.a) @ ed.n - ed.bow(s)))
    assert np.min(off, axis=0).max() < 1e-9
    inside = mesh.vertices_mm[:, :2] * (1 - 1e-9)
    assert footprint_contains(spec, inside[:, 0], inside[:, 1]).all()


def test_free_edges_are_every_edge_of_one_triangle_with_that_triangles_third_vertex() -> None:
    full = grid_mesh(sail, step_mm=100.0)  # 12 x 8 squares of 100 mm: the border's 40 edges
    centre = full.triangle_vertices_mm.mean(axis=1)[:, :2]
    plate = full.triangles[np.abs(centre).max(axis=1) > 100.0]  # a 2 x 2 hole in the middle: 8 more
    piece = grid_mesh(sail, step_mm=400.0)  # 3 x 2 squares, a separate piece 2 m along x: 10 more
    n = len(full.vertices_mm)
    mesh = TriMesh(
        np.vstack([full.vertices_mm, piece.vertices_mm + np.array([2000.0, 0.0, 0.0])]),
        np.vstack([plate, piece.triangles + n]),
    )
    edges, opposite = mesh_free_edges(mesh)
    assert edges.shape == (40 + 8 + 10, 2) and opposite.shape == (58,)
    tri = [set(t) for t in mesh.triangles.tolist()]
    for (a, b), o in zip(edges.tolist(), opposite.tolist(), strict=True):
        assert {a, b, o} in tri  # the edge's own triangle, in its direction
        assert sum({a, b} <= t for t in tri) == 1
    # the loops chain exactly these edges: the outer border, the hole, the piece; longest first
    loops = mesh_boundary_loops(mesh)
    assert [len(lp) for lp in loops] == [40, 10, 8]
    chained = {(int(a), int(b)) for lp in loops for a, b in zip(lp, np.roll(lp, -1), strict=True)}
    assert chained == {tuple(e) for e in edges.tolist()}
    # a closed surface (two triangles back to back) has none
    closed = TriMesh(np.eye(3) * 10.0, np.array([[0, 1, 2], [0, 2, 1]]))
    e0, o0 = mesh_free_edges(closed)
    assert e0.shape == (0, 2) and o0.shape == (0,) and mesh_boundary_loops(closed) == []


def test_outlines_outside_60_to_120_degrees_are_refused() -> None:
    with pytest.raises(PlateError, match="corner_angle_deg"):
        plate_spec("sail", corner_angle_deg=55.0)


@pytest.mark.parametrize("outline", sorted(OUTLINES))
def test_design_corners_of_a_non_rectangular_mesh_are_its_outline_corners(outline: str) -> None:
    spec = plate_spec("sail", **OUTLINES[outline])
    got = design_corners_from_mesh(design_mesh(spec, pitch_mm=10.0))
    np.testing.assert_allclose(got, design_corners(spec), atol=1e-6)


@pytest.mark.parametrize("outline", sorted(OUTLINES))
def test_a_mesh_in_ship_coordinates_is_framed_from_its_own_surface(outline: str) -> None:
    spec = plate_spec("sail", **OUTLINES[outline])
    mesh = design_mesh(spec, pitch_mm=10.0)
    framed = frame_design_mesh(mesh.transformed(ship_pose()))
    # the frame found equals the design's own up to the tilt of a lopsided outline's base plane
    T = framed.T_design_file @ ship_pose()  # design -> found frame
    z_err = _angle_deg(T[:3, 2], np.array([0.0, 0.0, 1.0]))
    assert z_err < 1.0, z_err
    c = framed.corners_mm
    truth = design_corners(spec)
    # the same corners, the same sides and angles (a rigid move), corner 0 still the reference
    np.testing.assert_allclose(
        np.linalg.norm(c[:, None] - c[None], axis=2),
        np.linalg.norm(truth[:, None] - truth[None], axis=2),
        atol=1e-6,
    )
    np.testing.assert_allclose(c, truth @ T[:3, :3].T + T[:3, 3], atol=1e-6)
    if outline.startswith("parallelogram"):  # centrally symmetric: the base plane is the design's own
        np.testing.assert_allclose(T[:3, :3], np.eye(3), atol=1e-9)
        # the origin on the mesh over the corners' centre: the linear mesh's height there
        np.testing.assert_allclose(T[:3, 3], 0.0, atol=0.01)
    # the framed mesh is the design moved by T, its origin on the surface
    np.testing.assert_allclose(framed.mesh.vertices_mm, mesh.vertices_mm @ T[:3, :3].T + T[:3, 3], atol=1e-6)


@settings(max_examples=8, deadline=None)
@given(outline=st.sampled_from(sorted(OUTLINES)), yaw=st.floats(0.0, 360.0), seed=st.integers(0, 2**16))
def test_corners_of_a_sampled_non_rectangular_top_surface_are_found_at_any_yaw(outline, yaw, seed) -> None:
    rng = np.random.default_rng(seed)
    spec = plate_spec("sail", radius_x_mm=3000.0, radius_y_mm=2500.0, **OUTLINES[outline])
    # a dense sampling that reaches the outline: the Coons grid of the footprint, jittered inward
    mesh = design_mesh(spec, pitch_mm=0.5)
    P = mesh.vertices_mm
    jitter = rng.uniform(-0.15, 0.15, (len(P), 2))
    xy = P[:, :2] + jitter
    on = footprint_contains(spec, xy[:, 0], xy[:, 1])
    xy[~on] = P[~on, :2]
    z = design_height_mm(spec, xy[:, 0], xy[:, 1]) + rng.normal(0, 0.02, len(P))
    a = np.radians(yaw)
    R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    t = np.array([120.0, -40.0, 80.0])
    pts = np.column_stack([xy, z]) @ R.T + t
    res = find_corners(pts)
    truth = design_corners(spec) @ R.T + t
    err = min(np.abs(np.roll(res.corners_mm, k, axis=0) - truth)[:, :2].max() for k in (0, 2))
    assert err < 0.6, err


@cache
def _scanned(outline: str, yaw: float):
    spec = plate_spec("sail", **OUTLINES[outline])
    err = FormingError(bumps=(GaussianBump(300.0, -100.0, -2.0, 60.0),))
    placement = Placement.on_bed(40.0, -25.0, yaw, tilt_deg=0.4, tilt_axis_deg=yaw + 33.0)
    scan = synthesize_scan(spec, err, settings=COARSE, placement=placement, seed=int(yaw))
    return scan, find_corners(segment_plate(scan.cloud).points_mm)


@pytest.mark.slow
@pytest.mark.parametrize("outline", sorted(OUTLINES))
@pytest.mark.parametrize("yaw", [0.0, 137.0, 251.5])
def test_corners_of_a_scanned_non_rectangular_plate_are_found_as_a_rectangles_are(
    outline: str, yaw: float
) -> None:
    scan, res = _scanned(outline, yaw)
    truth = scan.corners_bed_mm()
    d = res.corners_mm - truth
    # the rectangle's tolerances (tests/analysis/test_boundary.py)
    assert np.abs(d[:, :2]).max() < 1.5, d
    assert np.abs(d[:, 2]).max() < 0.5, d
    # the edges run from corner to corner and fit their feature points to the scan's noise
    for k, edge in enumerate(res.edges):
        ends = edge.evaluate(np.array([0.0, 1.0]))
        np.testing.assert_allclose(ends[0, :2], res.corners_mm[k, :2], atol=1e-6)
        np.testing.assert_allclose(ends[1, :2], res.corners_mm[(k + 1) % 4, :2], atol=1e-6)
        assert edge.rms_mm < 0.35, (k, edge.rms_mm)


def test_a_long_strip_keeps_both_corners_of_its_short_edges() -> None:
    """A 6000 x 400 mm sheared strip: the corners of a short edge lie 0.03 of the perimeter apart."""
    spec = plate_spec("flat", length_mm=6000.0, width_mm=400.0, corner_angle_deg=75.0)
    np.testing.assert_allclose(
        design_corners_from_mesh(design_mesh(spec, pitch_mm=20.0)), design_corners(spec), atol=1e-6
    )


def test_the_plane_of_a_mesh_of_one_or_two_triangles_is_their_normal_not_an_index_error():
    """Found by tests/fuzz/test_fuzz_files.py: two triangles gave a 2 x 3 SVD and `vt[2]` raised."""
    from analysis.design.outline import _surface_up

    v = np.array([[0.0, 0.0, 0.0], [100.0, 0.0, 0.0], [0.0, 100.0, 0.0], [100.0, 100.0, 5.0]])
    z2, _ = _surface_up(v, np.array([[0, 1, 2], [1, 3, 2]]))
    z1, _ = _surface_up(v, np.array([[0, 1, 2]]))
    z0, _ = _surface_up(v, np.array([[0, 1, 1]]))  # degenerate: no area at all
    assert np.allclose(z1, [0.0, 0.0, 1.0])
    assert z2[2] > 0.99 and np.isclose(np.linalg.norm(z2), 1.0)
    assert np.allclose(z0, [0.0, 0.0, 1.0])
