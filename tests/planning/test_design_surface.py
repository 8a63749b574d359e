"""The design surface's height field: its own bicubic evaluation against the spline's (FITPACK's)."""

from __future__ import annotations

import numpy as np

from analysis.design.plates import design_mesh, plate_spec
from cellctl.planning.coverage import design_surface


def test_heights_and_gradients_are_fitpacks_inside_on_the_knots_and_beyond_the_footprint():
    mesh = design_mesh(
        plate_spec("sail", length_mm=900.0, width_mm=300.0, radius_x_mm=2000.0, radius_y_mm=1500.0),
        pitch_mm=10.0,
    )
    surface = design_surface(mesh)
    rng = np.random.default_rng(7)
    x = rng.uniform(surface.x_min_mm - 50.0, surface.x_max_mm + 50.0, 4000)
    y = rng.uniform(surface.y_min_mm - 50.0, surface.y_max_mm + 50.0, 4000)
    # the grid's own points, the footprint's corners and the spline's end knots
    x[:40], y[:40] = surface.xs_mm[:40], surface.ys_mm[np.arange(40) % surface.ys_mm.size]
    x[40:44], y[40:44] = (
        [surface.x_min_mm, surface.x_max_mm] * 2,
        [surface.y_min_mm] * 2 + [surface.y_max_mm] * 2,
    )
    h, gx, gy = surface.height_and_gradient(x.reshape(40, 100), y.reshape(40, 100))
    assert h.shape == gx.shape == gy.shape == (40, 100)
    xc = np.clip(x, surface.x_min_mm, surface.x_max_mm)
    yc = np.clip(y, surface.y_min_mm, surface.y_max_mm)
    ref_gx, ref_gy = surface.spline.ev(xc, yc, dx=1), surface.spline.ev(xc, yc, dy=1)
    ref_h = surface.spline.ev(xc, yc) + ref_gx * (x - xc) + ref_gy * (y - yc)
    np.testing.assert_allclose(h.ravel(), ref_h, rtol=0, atol=1e-9)
    np.testing.assert_allclose(gx.ravel(), ref_gx, rtol=0, atol=1e-12)
    np.testing.assert_allclose(gy.ravel(), ref_gy, rtol=0, atol=1e-12)
    assert np.ptp(ref_gx) > 0.1 and np.ptp(ref_gy) > 0.1  # a curved plate: the gradients vary
