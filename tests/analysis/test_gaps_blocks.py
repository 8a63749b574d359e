"""Per-point gaps computed in bounded blocks (a 6 m plate's 39 M points): the same gaps as in one go."""

from __future__ import annotations

import numpy as np
import pytest

import analysis.register.onesided as reg
from analysis.design.plates import design_mesh, plate_spec
from analysis.register.height_field import height_field_from_mesh
from analysis.register.onesided import deflection_gaps


@pytest.mark.parametrize("geometry", [False, True])
def test_blocks_give_the_same_gaps(monkeypatch: pytest.MonkeyPatch, geometry: bool) -> None:
    design = design_mesh(plate_spec("sail", length_mm=600.0, width_mm=400.0), pitch_mm=10.0)
    surface = height_field_from_mesh(design, 5.0)
    rng = np.random.default_rng(3)
    pts = np.column_stack(
        [rng.uniform(-280, 280, 250_000), rng.uniform(-180, 180, 250_000), rng.normal(0, 5, 250_000)]
    )
    T = np.eye(4)
    T[:3, 3] = [0.5, -0.3, 1.0]
    monkeypatch.setattr(reg, "_PARALLEL_MIN_POINTS", 10**9)  # serial: the reference
    ref = deflection_gaps(surface, pts, T, geometry=geometry)
    monkeypatch.setattr(reg, "_PARALLEL_MIN_POINTS", 1000)
    monkeypatch.setattr(reg, "_GAP_BLOCK_POINTS", 7_777)  # 33 blocks, uneven
    got = deflection_gaps(surface, pts, T, geometry=geometry)
    np.testing.assert_array_equal(got[3], ref[3])
    np.testing.assert_array_equal(got[0], ref[0])
    if geometry:
        np.testing.assert_array_equal(got[1], ref[1])
        np.testing.assert_array_equal(got[2], ref[2])
