"""Simulated heating (analysis/forming/simulate.py): the plan's plate frame mapped onto the mesh's
(a line planned at x = 300 mm bends the mesh there, also for a mesh in ship coordinates), the
perturbation seeded and bounded, and the refusals."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from analysis.design.mesh import TriMesh
from analysis.design.plates import plate_spec
from analysis.forming.coefficients import Coefficients
from analysis.forming.plan_file import HeatingPlanFile, PlanLine, PlanModel
from analysis.forming.rules import HeatingRules
from analysis.forming.simulate import HeatError, draw_perturbation
from analysis.heat_mesh import heat_mesh
from analysis.synth import formed_plate_mesh

L_MM, W_MM, H_MM = 900.0, 400.0, 12.0


def _plan(table: Coefficients, lines: list[tuple[tuple[float, float], tuple[float, float], str]], *,
          length_mm: float = L_MM, width_mm: float = W_MM) -> HeatingPlanFile:  # fmt: skip
    plan_lines = [
        PlanLine(
            id=f"H{k + 1}",
            order=k + 1,
            start_plate_mm=list(a),
            end_plate_mm=list(b),
            face=face,  # type: ignore[arg-type]
            heat_input_j_mm=1500.0,
            torch_speed_mm_s=5.0,
            bend_deg=0.5,
            shrink_mm=0.1,
        )
        for k, (a, b, face) in enumerate(lines)
    ]
    model = PlanModel(
        name="test", element_mm=20.0, length_mm=length_mm, width_mm=width_mm, thickness_mm=H_MM,
        thickness_from="config", coefficients_file="", material="mild_steel",
        material_properties=table.for_material("mild_steel"), process=table.process, rules=HeatingRules(),
    )  # fmt: skip
    return HeatingPlanFile(status="plan", lines=plan_lines, model=model)


def _ship_pose() -> np.ndarray:
    """Design frame -> ship coordinates: turned 30 degrees about z, tilted 5 degrees, far away."""
    a, b = np.radians(30.0), np.radians(5.0)
    rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    T = np.eye(4)
    T[:3, :3] = rz @ rx
    T[:3, 3] = [12_000.0, -3_000.0, 1_500.0]
    return T


@pytest.mark.parametrize("ship", [False, True], ids=["design_frame", "ship_coordinates"])
def test_a_line_planned_at_x_300_bends_the_mesh_at_x_300(table: Coefficients, ship: bool) -> None:
    spec = plate_spec("flat", length_mm=L_MM, width_mm=W_MM, thickness_mm=H_MM)
    T = _ship_pose() if ship else None
    mesh = formed_plate_mesh(spec, None, pitch_mm=4.0, T_file_design=T)
    plan = _plan(table, [((300.0, 40.0), (300.0, 360.0), "top")])
    heated = heat_mesh(plan, mesh, seed=7)
    back = np.linalg.inv(T) if T is not None else np.eye(4)
    before = mesh.vertices_mm @ back[:3, :3].T + back[:3, 3]
    after = heated.mesh.vertices_mm @ back[:3, :3].T + back[:3, 3]
    # the design frame's origin is the corners' mean: the plate frame's x is design x + L/2
    x_plate, y_plate = before[:, 0] + L_MM / 2, before[:, 1] + W_MM / 2
    mid = np.abs(y_plate - W_MM / 2) < 1e-6
    order = np.argsort(x_plate[mid])
    x, dz = x_plate[mid][order], (after[:, 2] - before[:, 2])[mid][order]
    curvature = dz[:-2] - 2 * dz[1:-1] + dz[2:]
    k = int(np.argmax(curvature))  # top face: the sides turn up, a kink concave upward
    c0, c1, c2 = curvature[k - 1 : k + 2]
    peak_x = x[k + 1] + 0.5 * (c0 - c2) / (c0 - 2 * c1 + c2) * (x[1] - x[0])
    drawn = heated.round.draw.lines["H1"]
    assert abs(peak_x - 300.0) <= 5.0 + 1.0
    assert abs(peak_x - 0.5 * (drawn[0][0] + drawn[1][0])) <= 2.0
    assert curvature[k] > 0 and heated.max_deflection_mm > 0.05


def test_the_bottom_face_bends_the_other_way(table: Coefficients) -> None:
    spec = plate_spec("flat", length_mm=L_MM, width_mm=W_MM, thickness_mm=H_MM)
    mesh = formed_plate_mesh(spec, None, pitch_mm=8.0)
    top = heat_mesh(_plan(table, [((450.0, 40.0), (450.0, 360.0), "top")]), mesh, seed=1)
    bottom = heat_mesh(_plan(table, [((450.0, 40.0), (450.0, 360.0), "bottom")]), mesh, seed=1)
    dz_top = top.mesh.vertices_mm[:, 2] - mesh.vertices_mm[:, 2]
    dz_bottom = bottom.mesh.vertices_mm[:, 2] - mesh.vertices_mm[:, 2]
    np.testing.assert_allclose(dz_bottom, -dz_top, atol=1e-6 + 1e-6 * np.abs(dz_top).max())


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 2**31), spread=st.floats(0.0, 0.5), pos=st.floats(0.0, 20.0))
def test_the_draw_is_seeded_and_bounded(table: Coefficients, seed: int, spread: float, pos: float) -> None:
    plan = _plan(table, [((0.0, 40.0), (0.0, 360.0), "top"), ((300.0, 40.0), (600.0, 360.0), "bottom")])
    a = draw_perturbation(plan, L_MM, W_MM, seed, coefficient_spread=spread, position_spread_mm=pos)
    assert a == draw_perturbation(plan, L_MM, W_MM, seed, coefficient_spread=spread, position_spread_mm=pos)
    assert abs(a.bend_factor - 1) <= spread and abs(a.shrink_factor - 1) <= spread
    for line in plan.lines:
        ends = np.array(a.lines[line.id])
        planned = np.array([line.start_plate_mm, line.end_plate_mm])
        assert np.all(np.abs(ends - planned) <= pos + 1e-9)
        assert np.all(ends >= 0) and np.all(ends <= [L_MM, W_MM])
    other = draw_perturbation(plan, L_MM, W_MM, seed + 1, coefficient_spread=0.25)
    assert other != draw_perturbation(plan, L_MM, W_MM, seed, coefficient_spread=0.25)


def test_refusals(table: Coefficients) -> None:
    mesh = formed_plate_mesh(plate_spec("flat", length_mm=L_MM, width_mm=W_MM), None, pitch_mm=20.0)
    with pytest.raises(HeatError, match="no heating lines"):
        heat_mesh(_plan(table, []), mesh)
    with pytest.raises(HeatError, match="holds no plan: nothing to heat"):
        heat_mesh(HeatingPlanFile(status="no_plan", reason="nothing to heat"), mesh)
    with pytest.raises(HeatError, match=r"1200 x 800 mm plate, the mesh's is 900.0 x 400.0"):
        heat_mesh(_plan(table, [((300.0, 40.0), (300.0, 360.0), "top")], length_mm=1200, width_mm=800), mesh)
    blob = TriMesh(np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]), np.array([[0, 1, 2]]))
    with pytest.raises(HeatError, match="outline"):
        heat_mesh(_plan(table, [((300.0, 40.0), (300.0, 360.0), "top")]), blob)
