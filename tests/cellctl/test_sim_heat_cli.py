"""`cellctl sim heat PLAN --mesh IN --out OUT`: the heated mesh and its sidecar (the draw), and the
refusals with a clear error (exit 2, nothing written): a plan with no lines, a plan for another plate
size, a file that is no plan, a mesh that is no file."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from analysis.design.mesh import load_mesh
from analysis.design.plates import plate_spec
from analysis.forming.coefficients import load_coefficients
from analysis.forming.plan_file import HeatingPlanFile, PlanLine, PlanModel, write_heating_plan
from analysis.forming.rules import HeatingRules
from analysis.synth import write_formed_mesh
from cellctl.cli import main


def _plan(path: Path, *, lines: int = 1, length_mm: float = 600.0) -> Path:
    table = load_coefficients()
    model = PlanModel(
        name="test", element_mm=30.0, length_mm=length_mm, width_mm=300.0, thickness_mm=10.0,
        thickness_from="config", coefficients_file="", material="mild_steel",
        material_properties=table.for_material("mild_steel"), process=table.process, rules=HeatingRules(),
    )  # fmt: skip
    plan_lines = [
        PlanLine(
            id=f"H{k + 1}",
            order=k + 1,
            start_plate_mm=[200.0 + 150 * k, 30.0],
            end_plate_mm=[200.0 + 150 * k, 270.0],
            face="top",
            heat_input_j_mm=1200.0,
            torch_speed_mm_s=6.0,
            bend_deg=0.4,
            shrink_mm=0.1,
        )
        for k in range(lines)
    ]
    return write_heating_plan(HeatingPlanFile(status="plan", lines=plan_lines, model=model), path)


@pytest.fixture(scope="module")
def mesh(tmp_path_factory: pytest.TempPathFactory) -> Path:
    spec = plate_spec("cylinder", length_mm=600.0, width_mm=300.0, thickness_mm=10.0)
    return write_formed_mesh(spec, None, tmp_path_factory.mktemp("m") / "plate.ply", pitch_mm=10.0)


def test_sim_heat_writes_the_heated_mesh_and_the_draw(mesh: Path, tmp_path: Path, capsys) -> None:
    plan = _plan(tmp_path / "heating-plan.json", lines=2)
    out = tmp_path / "heated" / "plate-1.ply"
    assert main(["sim", "heat", str(plan), "--mesh", str(mesh), "--out", str(out), "--seed", "4"]) == 0
    told = json.loads(capsys.readouterr().out)
    assert told["out"] == str(out) and told["max_deflection_mm"] > 0
    before, after = load_mesh(mesh), load_mesh(out)
    assert np.array_equal(before.triangles, after.triangles)
    assert np.abs(after.vertices_mm[:, 2] - before.vertices_mm[:, 2]).max() > 0.05
    side = json.loads((tmp_path / "heated" / "plate-1.heat.json").read_text())
    draw = side["draw"]
    assert draw["seed"] == 4 and set(draw["lines"]) == {"H1", "H2"}
    assert 0.75 <= draw["bend_factor"] <= 1.25 and 0.75 <= draw["shrink_factor"] <= 1.25
    assert side["element_mm"] == pytest.approx(21.0)


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda p: _plan(p, lines=0), "no heating lines"),
        (lambda p: _plan(p, length_mm=1200.0), "the plan is for a 1200 x 300 mm plate"),
        (lambda p: p.write_text("{not json"), "heating-plan.json: (top level)"),
        (lambda p: p.write_text('{"status": "plan", "lines": 3}'), "heating-plan.json: lines"),
    ],
    ids=["no_lines", "other_size", "not_json", "not_a_plan"],
)
def test_sim_heat_refuses_with_a_clear_error(mesh: Path, tmp_path: Path, capsys, make, message: str) -> None:
    plan = tmp_path / "heating-plan.json"
    make(plan)
    out = tmp_path / "out.ply"
    assert main(["sim", "heat", str(plan), "--mesh", str(mesh), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("cellctl sim heat: ") and message in err
    assert not out.exists() and not (tmp_path / "out.heat.json").exists()


def test_sim_heat_refuses_a_missing_mesh(tmp_path: Path, capsys) -> None:
    plan = _plan(tmp_path / "heating-plan.json")
    assert (
        main(["sim", "heat", str(plan), "--mesh", str(tmp_path / "no.ply"), "--out", str(tmp_path / "o.ply")])
        == 2
    )
    assert "no.ply: no such file" in capsys.readouterr().err
