"""The simulated forming loop (benchmarks/forming_loop.py): one offline round on a small under-bent
cylinder -- scan, inspect, plan, heat with the mismatched model, scan again -- reduces the worst
line's Zmax; and the sampled height field that carries a round's heating (``FormingError.grid``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from analysis.design.plates import FormingError, HeightGrid, forming_dz_mm, plate_spec
from benchmarks.forming_loop import run_plate


def test_a_sampled_twist_is_the_twist_with_its_gradient() -> None:
    spec = plate_spec("flat", length_mm=600.0, width_mm=400.0)
    k = 5e-5
    grid = HeightGrid.sample(lambda x, y: k * x * y, (-340.0, 340.0), (-240.0, 240.0), 10.0)
    err = FormingError(grid=grid)
    x, y = np.array([-290.0, 13.0, 250.0]), np.array([180.0, -7.5, -199.0])
    dz, gx, gy = forming_dz_mm(spec, err, x, y, with_gradient=True)
    np.testing.assert_allclose(dz, k * x * y, atol=1e-9)
    np.testing.assert_allclose(gx, k * y, atol=1e-9)
    np.testing.assert_allclose(gy, k * x, atol=1e-9)
    back = FormingError.from_dict(err.to_dict())
    np.testing.assert_array_equal(back.grid.values_mm, grid.values_mm)
    assert not err.is_zero and FormingError(grid=grid.plus(-grid.values_mm.ravel())).is_zero


@pytest.mark.slow
def test_one_offline_round_reduces_the_worst_zmax(tmp_path: Path) -> None:
    spec = plate_spec("cylinder", length_mm=500.0, width_mm=300.0, thickness_mm=10.0)
    out = run_plate("cyl", spec, FormingError(bend_fraction=-0.25), 1, tmp_path, seed=2)
    first, second = out["rounds"][0], out["rounds"][1]
    assert first["verdict"] == "fail" and first["lines"] >= 1
    assert second["zmax_worst_mm"] < 0.6 * first["zmax_worst_mm"]
