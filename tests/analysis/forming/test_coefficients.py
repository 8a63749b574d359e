"""The coefficient table and the inherent deformation law of one heating line."""

from __future__ import annotations

import math

import pytest
from pydantic import ValidationError

from analysis.forming.coefficients import (
    DEFAULT_TABLE,
    Coefficients,
    heat_input_for_bend,
    inherent_deformation,
    load_coefficients,
    peak_bend_heat_input_j_per_mm,
    torch_speed_mm_s,
)


@pytest.fixture(scope="module")
def table() -> Coefficients:
    return load_coefficients()


def test_shipped_table_loads_and_refuses_unknown_keys(table: Coefficients, tmp_path) -> None:
    assert {"mild_steel", "ah36"} <= set(table.material)
    bad = tmp_path / "t.toml"
    bad.write_text(DEFAULT_TABLE.read_text(encoding="utf-8") + "\n[extra]\nx = 1\n", encoding="utf-8")
    with pytest.raises(ValidationError):
        load_coefficients(bad)
    with pytest.raises(KeyError, match="mild_steel"):
        table.for_material("unobtainium")


def test_bend_rises_then_falls_with_heat_input_peaking_at_one_q_over_h_squared(table: Coefficients) -> None:
    """The published shape (angular distortion against Q/h^2 rises to a peak and falls once the whole
    thickness heats); in this law the peak sits at one Q/h^2 for every thickness."""
    m, p = table.for_material("mild_steel"), table.process
    peaks = []
    for h in (8.0, 12.0, 16.0):
        q_peak = peak_bend_heat_input_j_per_mm(h, m, p)
        below = inherent_deformation(0.5 * q_peak, h, m, p).bend_across_rad
        at = inherent_deformation(q_peak, h, m, p).bend_across_rad
        above = inherent_deformation(min(2.0 * q_peak, p.heat_input_max_j_per_mm), h, m, p).bend_across_rad
        assert below < at and above < at
        peaks.append(q_peak / h**2)
    assert max(peaks) / min(peaks) < 1.1, peaks


def test_shrinkage_grows_with_heat_input_and_falls_with_thickness(table: Coefficients) -> None:
    m, p = table.for_material("mild_steel"), table.process
    s = [inherent_deformation(q, 15.0, m, p).shrink_across_mm for q in (300.0, 800.0, 2000.0)]
    assert s[0] < s[1] < s[2]
    assert inherent_deformation(800.0, 25.0, m, p).shrink_across_mm < s[1]


def test_heat_input_for_bend_inverts_the_rising_branch(table: Coefficients) -> None:
    m, p = table.for_material("mild_steel"), table.process
    want = math.radians(0.5)
    q = heat_input_for_bend(want, 15.0, m, p)
    assert q is not None
    assert inherent_deformation(q, 15.0, m, p).bend_across_rad == pytest.approx(want, rel=1e-3)
    assert q < peak_bend_heat_input_j_per_mm(15.0, m, p)
    assert heat_input_for_bend(math.radians(5.0), 15.0, m, p) is None
    assert torch_speed_mm_s(q, p) == pytest.approx(p.torch_efficiency * p.torch_power_w / q)
