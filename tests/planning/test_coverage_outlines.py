"""The scan planner on plates that are not rectangles: a 70-degree parallelogram and a bowed trapezoid.

The edge passes follow the design's own outline (the four edges between its corners, a bowed edge's
curve, the sensor tilted outward along the outline's normal), the raster passes reach as far as the
plate does, and the predicted coverage is measured over the plate (cells inside the outline), its
thickness faces included. A rectangle plans exactly as it did when the passes followed its bounds.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from analysis.contracts.placement import placement_transform
from analysis.design.mesh import TriMesh
from analysis.design.plates import (
    design_corners,
    design_height_mm,
    design_mesh,
    footprint_contains,
    outline_edges,
    plate_spec,
)
from cellctl.planning import PlannerSettings, ScanPlan, plan_scan
from cellctl.planning.coverage import (
    build_segments,
    design_surface,
    outline_in_plan,
    predict_edge_face_coverage,
)
from tests.support.plans import SAIL_PLACEMENT

# a gentler sail than the default: the default sail continued over a parallelogram's longer reach
# in x is too steep for the depth range under the placement uncertainty (refused either way)
SHAPE = {"radius_x_mm": 6000.0, "radius_y_mm": 5000.0}
OUTLINES = {
    "parallelogram_70": {"corner_angle_deg": 70.0},
    "trapezoid_bowed": {"corner_angle_deg": 80.0, "top_length_mm": 1000.0, "bow_mm": (0.0, 0.0, 16.0, 0.0)},
}
#: an edge pass's surface point lies this close to its outline edge (the mesh border lies on the
#: analytic curve; the bow is fitted with a quartic)
EDGE_TOL_MM = 0.5
#: the sensor's axis is tilted outward from the surface normal as asked, within this angle (the
#: planner's normal comes from its spline fit of the mesh)
OUTWARD_TOL_DEG = 1.0

SETTINGS = PlannerSettings()


def _mesh(outline: str | None):
    return design_mesh(plate_spec("sail", **SHAPE, **(OUTLINES[outline] if outline else {})), pitch_mm=10.0)


@pytest.fixture(scope="module")
def plans() -> dict[str | None, ScanPlan]:
    return {name: plan_scan(_mesh(name), SAIL_PLACEMENT, SETTINGS) for name in (None, *OUTLINES)}


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _plate_frame(plan: ScanPlan, seg) -> tuple[np.ndarray, np.ndarray]:
    """(positions (n, 3), view axes (n, 3)) of a segment in the plate frame."""
    T = placement_transform(plan.placement)
    return (seg.pos_mm - T[:3, 3]) @ T[:3, :3], seg.R_base_sensor[:, :, 2] @ T[:3, :3]


@pytest.mark.parametrize("outline", list(OUTLINES))
def test_outline_in_plan_starts_at_the_reference_corner_and_runs_counter_clockwise(outline):
    spec = plate_spec("sail", **SHAPE, **OUTLINES[outline])
    xy, corners = outline_in_plan(design_mesh(spec, pitch_mm=10.0))
    np.testing.assert_allclose(xy[corners], design_corners(spec)[:, :2], atol=1e-6)
    assert corners[0] == 0
    assert np.sum(xy[:, 0] * np.roll(xy[:, 1], -1) - np.roll(xy[:, 0], -1) * xy[:, 1]) > 0


@pytest.mark.slow
@pytest.mark.parametrize("outline", list(OUTLINES))
def test_every_edge_pass_follows_its_outline_edge_looking_outward(plans, outline):
    spec = plate_spec("sail", **SHAPE, **OUTLINES[outline])
    plan = plans[outline]
    edges = outline_edges(spec)
    passes = [s for s in plan.segments if s.kind == "edge"]
    assert len(passes) == 4
    run = SETTINGS.placement_uncertainty_mm + SETTINGS.line_width_mm / 2
    matched = []
    for seg in passes:
        pos, view = _plate_frame(plan, seg)
        look = pos + SETTINGS.standoff_mm * view  # the surface point on the line's centre
        # the edge this pass runs along: the one whose curve its points lie nearest to, on average
        offs = []
        for ed in edges:
            s = (look[:, :2] - ed.a) @ ed.e
            offs.append(np.abs((look[:, :2] - ed.a) @ ed.n - ed.bow(s)).mean())
        k = int(np.argmin(offs))
        matched.append(k)
        ed = edges[k]
        s = (look[:, :2] - ed.a) @ ed.e
        on = (s >= 0) & (s <= ed.chord_mm)
        cross = np.abs((look[on, :2] - ed.a) @ ed.n - ed.bow(s[on]))
        assert cross.max() <= EDGE_TOL_MM, f"{seg.label}: {cross.max():.2f} mm off edge {k}"
        # the pass runs past both corners by the uncertainty plus half a line
        assert s.min() <= -run + 1.0 and s.max() >= ed.chord_mm + run - 1.0
        # the sensor looks in from outside: its axis tilted by edge_tilt_deg from the surface normal
        # towards the edge's outward normal (in the plate plane, carried into the tangent plane)
        xy = look[on, :2]
        h = 1e-3
        gx = (
            design_height_mm(spec, xy[:, 0] + h, xy[:, 1]) - design_height_mm(spec, xy[:, 0] - h, xy[:, 1])
        ) / (2 * h)
        gy = (
            design_height_mm(spec, xy[:, 0], xy[:, 1] + h) - design_height_mm(spec, xy[:, 0], xy[:, 1] - h)
        ) / (2 * h)
        n = _unit(np.column_stack([-gx, -gy, np.ones_like(gx)]))
        o = np.column_stack([ed.outward(s[on]), np.zeros(len(xy))])
        o = _unit(o - np.sum(o * n, axis=1, keepdims=True) * n)
        a = np.radians(SETTINGS.edge_tilt_deg)
        want = n * np.cos(a) + o * np.sin(a)
        cosang = np.sum(-view[on] * want, axis=1)
        assert np.degrees(np.arccos(np.clip(cosang.min(), -1, 1))) <= OUTWARD_TOL_DEG
    assert sorted(matched) == [0, 1, 2, 3]


@pytest.mark.slow
@pytest.mark.parametrize("outline", list(OUTLINES))
def test_coverage_is_measured_over_the_plate_and_is_no_less_than_the_rectangles(plans, outline):
    spec = plate_spec("sail", **SHAPE, **OUTLINES[outline])
    plan, rect = plans[outline], plans[None]
    cov = plan.coverage
    # the cells counted are the plate's (centre inside the outline), not the bounding box's
    x0, x1, y0, y1 = plan.footprint_mm
    nx, ny = int(np.ceil((x1 - x0) / cov.cell_mm)), int(np.ceil((y1 - y0) / cov.cell_mm))
    cx = x0 + (np.arange(nx) + 0.5) * (x1 - x0) / nx
    cy = y0 + (np.arange(ny) + 0.5) * (y1 - y0) / ny
    X, Y = np.meshgrid(cx, cy, indexing="ij")
    assert cov.cells_total == int(footprint_contains(spec, X, Y).sum()) < nx * ny * 0.95
    assert cov.fraction >= rect.coverage.fraction
    # under the placement uncertainty a sheared edge's boundary cells hold only a sliver of plate,
    # which the ray lattice (2.5 x 3 mm) can miss: at most one such cell per edge
    assert cov.worst_fraction >= rect.coverage.worst_fraction - 4 / cov.cells_total


@pytest.mark.slow
@pytest.mark.parametrize("outline", list(OUTLINES))
def test_every_thickness_face_is_lit_as_the_rectangles_are(plans, outline):
    spec = plate_spec("sail", **SHAPE, **OUTLINES[outline])
    mesh = _mesh(outline)
    surface = design_surface(mesh)
    plan, rect = plans[outline], plans[None]
    faces = predict_edge_face_coverage(
        plan.segments, mesh, surface, SAIL_PLACEMENT, SETTINGS, spec.thickness_mm
    )
    rect_faces = predict_edge_face_coverage(
        rect.segments, _mesh(None), design_surface(_mesh(None)), SAIL_PLACEMENT, SETTINGS, spec.thickness_mm
    )
    assert min(faces.per_edge) >= min(rect_faces.per_edge) >= 0.99
    assert faces.fraction >= rect_faces.fraction
    # passes along the bounding box instead (the planner without the outline) leave a sheared or
    # tapered side's face dark
    boxed, _ = build_segments(
        dataclasses.replace(surface, outline_xy=None, corner_index=None), SAIL_PLACEMENT, SETTINGS
    )
    dark = predict_edge_face_coverage(boxed, mesh, surface, SAIL_PLACEMENT, SETTINGS, spec.thickness_mm)
    assert min(dark.per_edge) < 0.5


def test_a_rectangle_plans_exactly_as_along_its_bounds():
    mesh = design_mesh(plate_spec("sail"), pitch_mm=10.0)
    surface = design_surface(mesh)
    assert surface.outline_xy is not None
    for sign in (1.0, -1.0):
        got, m_got = build_segments(surface, SAIL_PLACEMENT, SETTINGS, sign=sign)
        boxed = dataclasses.replace(surface, outline_xy=None, corner_index=None)
        want, m_want = build_segments(boxed, SAIL_PLACEMENT, SETTINGS, sign=sign)
        assert m_got == m_want and [s.label for s in got] == [s.label for s in want]
        for a, b in zip(got, want, strict=True):
            assert np.array_equal(a.pos_mm, b.pos_mm) and np.array_equal(a.R_base_sensor, b.R_base_sensor)


def test_a_design_without_a_four_cornered_boundary_falls_back_to_its_bounds():
    mesh = design_mesh(plate_spec("sail", **SHAPE, **OUTLINES["parallelogram_70"]), pitch_mm=20.0)
    # a triangle soup (no shared vertices, as an unwelded STL): every edge is a border, no outline
    soup = TriMesh(
        mesh.triangle_vertices_mm.reshape(-1, 3), np.arange(3 * len(mesh.triangles)).reshape(-1, 3)
    )
    assert outline_in_plan(soup) is None
    surface = design_surface(soup)
    assert surface.outline_xy is None
    segments, _ = build_segments(surface, SAIL_PLACEMENT, SETTINGS)
    T = placement_transform(SAIL_PLACEMENT)
    xs = []
    for seg in (s for s in segments if s.kind == "edge"):
        look = (seg.pos_mm - T[:3, 3]) @ T[:3, :3] + SETTINGS.standoff_mm * (
            seg.R_base_sensor[:, :, 2] @ T[:3, :3]
        )
        xs.append(look[:, :2])
    pts = np.concatenate(xs)
    # every edge pass runs along a side of the footprint's bounds
    on_x = np.minimum(np.abs(pts[:, 0] - surface.x_min_mm), np.abs(pts[:, 0] - surface.x_max_mm))
    on_y = np.minimum(np.abs(pts[:, 1] - surface.y_min_mm), np.abs(pts[:, 1] - surface.y_max_mm))
    assert np.minimum(on_x, on_y).max() < 1e-6


def test_reversed_passes_run_the_serpentine_from_the_far_end_leaning_the_same_way():
    mesh = design_mesh(plate_spec("sail"), pitch_mm=10.0)
    surface = design_surface(mesh)
    settings = dataclasses.replace(SETTINGS, sweep_pitch_deg=15.0)
    fwd, _ = build_segments(surface, SAIL_PLACEMENT, settings)
    rev, _ = build_segments(surface, SAIL_PLACEMENT, dataclasses.replace(settings, passes_reversed=True))
    scans = [[s for s in segs if s.kind == "scan"] for segs in (fwd, rev)]
    assert len(scans[0]) == len(scans[1]) > 1
    for a, b in zip(*scans, strict=True):
        # the same pass, run the other way round, the sensor leaning the same way
        assert np.allclose(a.pos_mm[::-1], b.pos_mm) and np.allclose(a.R_base_sensor[::-1], b.R_base_sensor)
