"""Digital templates: detection lines located from the corners, section cuts, 1 mm sampling."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from analysis import templates as tp
from analysis.design.mesh import TriMesh
from analysis.register.transforms import apply_transform, make_transform, rotation_from_vector
from tests.support.surfaces import corners, grid_mesh, sail


def test_default_layout_gives_the_papers_23_lines_on_the_sail_plate():
    lines = tp.detection_lines(corners())
    fam = [ln.family for ln in lines]
    assert fam.count("transverse") == 14 and fam.count("longitudinal") == 7 and fam.count("diagonal") == 2
    t = [ln for ln in lines if ln.family == "transverse"]
    assert np.allclose([ln.position_mm for ln in t], 80.0 * np.arange(1, 15))
    assert np.allclose([ln.start_mm[0] for ln in t], -600.0 + 80.0 * np.arange(1, 15))
    assert all(abs(ln.chord_mm - 800.0) < 1e-9 for ln in t)
    lo = [ln for ln in lines if ln.family == "longitudinal"]
    assert np.allclose([ln.position_mm for ln in lo], 100.0 * np.arange(1, 8))
    d = [ln for ln in lines if ln.family == "diagonal"]
    assert np.allclose([ln.chord_mm for ln in d], np.hypot(1200.0, 800.0))
    assert [ln.index for ln in t] == list(range(1, 15))
    for ln in lines:
        assert abs(ln.normal @ ln.direction) < 1e-12 and abs(ln.normal @ ln.up) < 1e-12


@settings(max_examples=25, deadline=None)
@given(
    yaw=st.floats(-180.0, 180.0),
    tx=st.floats(-3000.0, 3000.0),
    ty=st.floats(-3000.0, 3000.0),
    tz=st.floats(0.0, 1000.0),
)
def test_lines_follow_the_plate_not_the_bed(yaw, tx, ty, tz):
    T = make_transform(rotation_from_vector(np.radians([0.0, 0.0, yaw])), np.array([tx, ty, tz]))
    ref = tp.detection_lines(corners())
    moved = tp.detection_lines(apply_transform(T, corners()))
    for a, b in zip(ref, moved, strict=True):
        assert (a.family, a.index) == (b.family, b.index)
        assert abs(a.position_mm - b.position_mm) < 1e-6
        assert abs(a.chord_mm - b.chord_mm) < 1e-6
        assert np.allclose(apply_transform(T, a.start_mm[None])[0], b.start_mm, atol=1e-6)
        assert np.allclose(T[:3, :3] @ a.direction, b.direction, atol=1e-9)


def test_transverse_lines_join_equal_distances_on_a_trapezoidal_plate():
    c = corners()
    c[2, 0] += 100.0  # the far length edge is 100 mm longer
    lines = tp.detection_lines(c, tp.DetectionLayout(transverse_count=3, transverse_spacing_mm=300.0))
    t = [ln for ln in lines if ln.family == "transverse"]
    assert np.allclose([ln.start_mm[0] for ln in t], [-300.0, 0.0, 300.0], atol=1e-9)
    # on the longer edge the same distances from the reference corner's side
    assert np.allclose([ln.end_mm[0] for ln in t], [-300.0, 0.0, 300.0], atol=1e-9)


def test_cut_of_a_grid_mesh_follows_the_surface_and_is_ordered():
    mesh = grid_mesh(sail, step_mm=10.0)
    line = tp.detection_lines(corners())[3]  # transverse at x = -280
    sec = tp.cut_mesh(mesh, line)
    assert np.all(np.diff(sec.s_mm) > 0)
    assert np.allclose(sec.points_mm[:, 0], -280.0, atol=1e-9)
    # vertices of the cut lie on mesh edges: exact at nodes, chordal error between
    assert np.abs(sec.h_mm - sail(sec.points_mm[:, 0], sec.points_mm[:, 1])).max() < 10.0**2 / 8 / 2000 + 1e-9
    assert sec.s_mm[0] == pytest.approx(0.0, abs=1e-9) and sec.s_mm[-1] == pytest.approx(800.0, abs=1e-9)


def test_sampling_is_every_millimetre_on_a_grid_shared_by_design_and_measurement():
    design = grid_mesh(sail, step_mm=10.0)
    measured = grid_mesh(lambda x, y: sail(x, y) - 0.7, step_mm=7.0)
    lines = tp.detection_lines(corners())
    cuts = tp.cut_templates(design, measured, lines)
    assert len(cuts) == 23
    for c in cuts:
        assert np.allclose(np.diff(c.s_mm), 1.0)
        assert np.allclose(c.s_mm, np.round(c.s_mm))
        assert np.nanmax(np.abs(c.design_h_mm - c.measured_h_mm - 0.7)) < 0.01
    diag = next(c for c in cuts if c.line.family == "diagonal")
    assert len(diag.s_mm) == pytest.approx(np.hypot(1200, 800), abs=2)


def test_a_hole_in_the_scan_is_not_bridged():
    m = grid_mesh(sail, step_mm=4.0)
    cen = m.triangle_vertices_mm.mean(axis=1)
    keep = ~((np.abs(cen[:, 1]) < 30.0) & (np.abs(cen[:, 0] + 280.0) < 30.0))
    holed = TriMesh(m.vertices_mm, m.triangles[keep])
    line = tp.detection_lines(corners())[3]  # x = -280 crosses the hole at |y| < 30
    samp = tp.sample_section(tp.cut_mesh(holed, line), step_mm=1.0, max_gap_mm=5.0)
    y = samp.s_mm - 400.0
    assert np.isnan(samp.h_mm[np.abs(y) < 25]).all()
    assert np.isfinite(samp.h_mm[np.abs(y) > 40]).all()


def test_bad_inputs_raise_template_errors_naming_the_problem():
    with pytest.raises(tp.TemplateError, match="counter-clockwise"):
        tp.detection_lines(corners()[::-1])
    with pytest.raises(tp.TemplateError, match=r"corners_mm must be a finite \(4, 3\)"):
        tp.detection_lines(np.zeros((3, 3)))
    with pytest.raises(tp.TemplateError, match="transverse offsets"):
        tp.detection_lines(corners(), tp.DetectionLayout(transverse_offsets_mm=(50.0, 1300.0)))
    far = tp.detection_lines(apply_transform(make_transform(np.eye(3), np.array([5000.0, 0, 0])), corners()))
    with pytest.raises(tp.TemplateError, match="does not cut the mesh"):
        tp.cut_mesh(grid_mesh(sail, 20.0), far[0])
