"""Design surfaces, forming-error fields and the corner convention."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from analysis.design.mesh import MeshError, save_mesh
from analysis.design.plates import (
    PLATE_KINDS,
    EdgeSpringback,
    FormingError,
    GaussianBump,
    PlateError,
    canonical_corner_order,
    default_forming_error,
    design_corners,
    design_height_mm,
    design_mesh,
    formed_corners,
    formed_height_mm,
    forming_dz_mm,
    load_design,
    plate_spec,
    surface_gradient,
)


def test_design_corners_start_at_minus_minus_and_run_counter_clockwise_from_above():
    spec = plate_spec("sail")
    c = design_corners(spec)
    np.testing.assert_allclose(c[:, :2], [[-600, -400], [600, -400], [600, 400], [-600, 400]])
    xy = c[:, :2]
    signed_area = 0.5 * np.sum(xy[:, 0] * np.roll(xy[:, 1], -1) - np.roll(xy[:, 0], -1) * xy[:, 1])
    assert signed_area == pytest.approx(1200 * 800)
    np.testing.assert_allclose(c[:, 2], design_height_mm(spec, c[:, 0], c[:, 1]))


def test_sail_is_a_dish_and_saddle_is_anticlastic_around_a_zero_centre():
    sail, saddle = plate_spec("sail"), plate_spec("saddle")
    for spec in (sail, saddle):
        assert design_height_mm(spec, 0.0, 0.0) == 0.0
    assert design_height_mm(sail, 300.0, 0.0) > 0 and design_height_mm(sail, 0.0, 300.0) > 0
    assert design_height_mm(saddle, 300.0, 0.0) > 0 > design_height_mm(saddle, 0.0, 300.0)
    # Sail defaults: Rx 4000, Ry 3000 -> 45 mm + 26.67 mm at the corner.
    assert design_height_mm(sail, 600.0, 400.0) == pytest.approx(45.0 + 160000 / 6000)


@pytest.mark.parametrize("kind", PLATE_KINDS)
def test_design_mesh_vertices_lie_on_the_surface_and_normals_point_up(kind):
    spec = plate_spec(kind)
    mesh = design_mesh(spec, pitch_mm=20.0)
    v = mesh.vertices_mm
    np.testing.assert_allclose(v[:, 2], design_height_mm(spec, v[:, 0], v[:, 1]), atol=1e-12)
    assert (mesh.triangle_normals()[:, 2] > 0.9).all()
    assert v[:, 0].min() == -600 and v[:, 0].max() == 600 and v[:, 1].min() == -400 and v[:, 1].max() == 400
    assert mesh.triangle_areas_mm2().sum() >= 1200 * 800


@settings(max_examples=40, deadline=None)
@given(
    kind=st.sampled_from(PLATE_KINDS),
    x=st.floats(-600, 600),
    y=st.floats(-400, 400),
    amp=st.floats(-5, 5),
    spring=st.floats(-2, 2),
    bend=st.floats(-0.05, 0.05),
)
def test_surface_gradient_matches_finite_differences(kind, x, y, amp, spring, bend):
    spec = plate_spec(kind)
    err = FormingError(
        bumps=(GaussianBump(100.0, -50.0, amp, 70.0),),
        springback=EdgeSpringback(spring, 60.0),
        bend_fraction=bend,
    )
    z, gx, gy = surface_gradient(spec, err, np.array([x]), np.array([y]))
    h = 1e-4
    fx = (formed_height_mm(spec, err, x + h, y) - formed_height_mm(spec, err, x - h, y)) / (2 * h)
    fy = (formed_height_mm(spec, err, x, y + h) - formed_height_mm(spec, err, x, y - h)) / (2 * h)
    assert z[0] == pytest.approx(float(formed_height_mm(spec, err, x, y)), abs=1e-12)
    assert gx[0] == pytest.approx(float(fx), abs=1e-6)
    assert gy[0] == pytest.approx(float(fy), abs=1e-6)


def test_dent_of_depth_h_lowers_its_centre_by_h():
    spec = plate_spec("sail")
    err = FormingError(bumps=(GaussianBump(200.0, -100.0, -2.5, 60.0),))
    assert forming_dz_mm(spec, err, 200.0, -100.0) == pytest.approx(-2.5)
    assert abs(float(forming_dz_mm(spec, err, -400.0, 300.0))) < 1e-10


def test_springback_lifts_edges_and_corners_most_and_leaves_the_centre():
    spec = plate_spec("sail")
    err = FormingError(springback=EdgeSpringback(1.0, 50.0))
    centre, edge, corner = (float(forming_dz_mm(spec, err, x, y)) for x, y in ((0, 0), (0, -400), (600, 400)))
    assert centre < 1e-3
    assert edge == pytest.approx(1.0, abs=1e-3)
    assert corner == pytest.approx(2.0, abs=1e-3)


def test_no_forming_error_is_zero_everywhere_and_default_is_not():
    spec = plate_spec("saddle")
    x, y = np.meshgrid(np.linspace(-600, 600, 13), np.linspace(-400, 400, 9))
    assert FormingError().is_zero
    assert np.all(forming_dz_mm(spec, FormingError(), x, y) == 0)
    d = default_forming_error(spec)
    assert not d.is_zero and np.abs(forming_dz_mm(spec, d, x, y)).max() > 0.5


def test_forming_error_dict_round_trips():
    err = default_forming_error(plate_spec())
    again = FormingError.from_dict(err.to_dict())
    assert again == err


def test_formed_corners_add_the_forming_error_to_the_design_corners():
    spec = plate_spec()
    err = FormingError(springback=EdgeSpringback(1.5, 40.0))
    diff = formed_corners(spec, err) - design_corners(spec)
    np.testing.assert_allclose(diff[:, :2], 0)
    np.testing.assert_allclose(diff[:, 2], 3.0, atol=1e-3)


@pytest.mark.parametrize(
    ("overrides", "field"),
    [
        ({"width_mm": 1300.0}, "width_mm"),
        ({"thickness_mm": -1.0}, "thickness_mm"),
        ({"length_mm": float("nan")}, "length_mm"),
        ({"kind": "banana"}, "kind"),
    ],
)
def test_impossible_plate_specs_raise_naming_the_field(overrides, field):
    with pytest.raises(PlateError, match=field):
        plate_spec(**overrides)


def test_bump_with_zero_sigma_is_refused():
    with pytest.raises(PlateError, match="sigma_mm"):
        GaussianBump(0, 0, 1, 0)


@settings(max_examples=50, deadline=None)
@given(yaw=st.floats(-720, 720), shift=st.integers(0, 3), reverse=st.booleans())
def test_canonical_corner_order_undoes_any_cyclic_shift_or_reversal(yaw, shift, reverse):
    """Design corners turned by any yaw and listed from any corner in either sense order the same way."""
    c = design_corners(plate_spec())
    a = np.deg2rad(yaw)
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    turned = c @ R.T
    shuffled = np.roll(turned, shift, axis=0)
    if reverse:
        shuffled = shuffled[::-1]
    out = canonical_corner_order(shuffled)
    ref = canonical_corner_order(turned)
    np.testing.assert_allclose(out, ref, atol=1e-9)
    d = out[1, :2] - out[0, :2]
    assert np.linalg.norm(d) == pytest.approx(1200.0)
    assert d[0] >= -1e-9  # the long edge 0 points into the +x half plane
    # It is the turned design order, up to the half-turn symmetry.
    assert min(np.abs(out - turned).max(), np.abs(out - np.roll(turned, 2, axis=0)).max()) < 1e-9


@pytest.mark.parametrize("suffix", [".ply", ".stl", ".obj"])
def test_design_mesh_saved_and_loaded_keeps_its_geometry(tmp_path, suffix):
    mesh = design_mesh(plate_spec("twisted"), pitch_mm=50.0)
    path = save_mesh(mesh, tmp_path / f"design{suffix}")
    loaded = load_design(path)
    assert len(loaded.triangles) == len(mesh.triangles)
    # STL stores float32 and unshares vertices; compare the triangles' corner sets.
    np.testing.assert_allclose(
        np.sort(loaded.triangle_vertices_mm.reshape(-1, 3), axis=0),
        np.sort(mesh.triangle_vertices_mm.reshape(-1, 3), axis=0),
        atol=1e-3,
    )


def test_loading_a_missing_design_raises_a_mesh_error(tmp_path):
    with pytest.raises(MeshError, match="no such file"):
        load_design(tmp_path / "nope.ply")
