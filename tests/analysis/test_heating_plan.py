"""heating-plan.json and heating-plan.dxf from a job's results directory: an under-bent cylinder
planned back (the face, the direction, the predicted Zmax per line and its verdict), the DXF read
back with ezdxf, and the plans that cannot be made (their reason, never a lost report)."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import ezdxf
import pytest

from analysis.contracts.results import read_report
from analysis.design.plates import FormingError, GaussianBump, plate_spec
from analysis.forming.coefficients import DEFAULT_TABLE
from analysis.forming.dxf import FACE_LAYERS
from analysis.forming.plan_file import HEATING_PLAN_FILE, HeatingPlanFile, read_heating_plan
from analysis.forming.rules import PlanSettings
from analysis.heating_plan import HEATING_PLAN_DXF, JobPlan, write_job_plan
from tests.support.results_fixture import CELL_LAYOUT, write_synthetic_results

L_MM, W_MM = 600.0, 400.0
#: a coarse model and few lines: the plan takes about 2 s on the shared machine
SETTINGS = PlanSettings(element_mm=40.0, max_lines_per_round=6)
_NO_BUMPS = (GaussianBump(0.0, 0.0, 0.0, 50.0),) * 2


def _results(out: Path, error: FormingError) -> Path:
    spec = plate_spec("cylinder", length_mm=L_MM, width_mm=W_MM)
    write_synthetic_results(out, spec=spec, error=error, n_points=8000, layout=CELL_LAYOUT)
    return out


@pytest.fixture(scope="module")
def under_bent(tmp_path_factory: pytest.TempPathFactory) -> JobPlan:
    """A 600 x 400 cylinder (R 2500 mm, edges up as it lies) bent 20 % too little: 3.6 mm at its ends."""
    d = _results(tmp_path_factory.mktemp("under_bent"), FormingError(bumps=_NO_BUMPS, bend_fraction=-0.2))
    return write_job_plan(d, SETTINGS)


def test_an_under_bent_cylinder_is_heated_on_its_top_face_across_its_length(under_bent: JobPlan) -> None:
    plan = under_bent.plan
    assert plan.status == "plan" and plan.reason is None
    top = [ln for ln in plan.lines if ln.face == "top"]
    # the sides must turn up (toward the top face), about lines across the bend (x constant)
    assert len(top) >= 3
    assert all(ln.start_plate_mm[0] == ln.end_plate_mm[0] for ln in top)
    assert sum(ln.bend_deg for ln in top) > 2 * sum(ln.bend_deg for ln in plan.lines if ln.face == "bottom")
    assert plan.predicted is not None
    assert plan.predicted.rms_after_mm < 0.2 * plan.predicted.rms_before_mm


def test_the_predicted_zmax_of_every_line_falls_into_the_standard_range(under_bent: JobPlan) -> None:
    report = read_report(under_bent.json_path.parent)
    predicted = under_bent.plan.predicted
    assert predicted is not None
    assert list(predicted.zmax_mm) == [ln.name for ln in report.lines]
    assert report.verdict == "fail" and max(ln.zmax_mm for ln in report.lines) > 3.0
    after = [z for z in predicted.zmax_mm.values() if z is not None]
    assert len(after) == len(report.lines)
    assert max(after) < report.tolerances.deviation_standard_mm
    assert predicted.verdict == "pass"


def test_the_file_holds_the_schema_the_lines_and_what_the_plan_was_made_with(under_bent: JobPlan) -> None:
    text = under_bent.json_path.read_text()
    assert under_bent.json_path.name == HEATING_PLAN_FILE
    again = read_heating_plan(under_bent.json_path.parent)
    assert again == under_bent.plan
    plan = HeatingPlanFile.model_validate_json(text)
    assert [ln.order for ln in plan.lines] == list(range(1, len(plan.lines) + 1))
    assert [ln.id for ln in plan.lines] == [f"H{i}" for i in range(1, len(plan.lines) + 1)]
    for ln in plan.lines:
        for x, y in (ln.start_plate_mm, ln.end_plate_mm):
            assert SETTINGS.edge_margin_mm - 1e-6 <= x <= L_MM - SETTINGS.edge_margin_mm + 1e-6
            assert SETTINGS.edge_margin_mm - 1e-6 <= y <= W_MM - SETTINGS.edge_margin_mm + 1e-6
        assert ln.bend_deg > 0 and ln.shrink_mm > 0
        # the torch speed is the table's: efficiency * power / heat input
        p = plan.model.process
        assert ln.torch_speed_mm_s == pytest.approx(
            p.torch_efficiency * p.torch_power_w / ln.heat_input_j_mm, rel=2e-3
        )
        assert re.fullmatch(
            rf"{ln.id}: (top|bottom) face, \(\d+, \d+\) to \(\d+, \d+\), \d+ mm/s", ln.sentence()
        )
    m = plan.model
    assert (m.length_mm, m.width_mm, m.element_mm) == (L_MM, W_MM, 40.0)
    assert (m.thickness_mm, m.thickness_from) == (SETTINGS.thickness_mm, "config")
    assert m.rules == SETTINGS.rules() and m.material == "mild_steel"
    assert plan.planning_s is not None and plan.planning_s > 0


def test_the_dxf_reads_back_with_the_lines_on_their_face_layers(under_bent: JobPlan) -> None:
    assert under_bent.dxf_path is not None and under_bent.dxf_path.name == HEATING_PLAN_DXF
    doc = ezdxf.readfile(under_bent.dxf_path)
    assert doc.header["$INSUNITS"] == 4  # millimetres
    msp = doc.modelspace()
    (outline,) = msp.query("LWPOLYLINE[layer=='PLATE']")
    assert outline.closed
    assert sorted((round(x), round(y)) for x, y in outline.get_points("xy")) == [
        (0, 0), (0, 400), (600, 0), (600, 400)
    ]  # fmt: skip
    assert msp.query("CIRCLE[layer=='REFERENCE']")
    drawn = sorted(
        (
            e.dxf.layer,
            round(e.dxf.start.x, 1),
            round(e.dxf.start.y, 1),
            round(e.dxf.end.x, 1),
            round(e.dxf.end.y, 1),
        )
        for e in msp.query("LINE")
        if e.dxf.layer.startswith("HEAT_")
    )
    planned = sorted(
        (FACE_LAYERS[ln.face], *ln.start_plate_mm, *ln.end_plate_mm) for ln in under_bent.plan.lines
    )
    assert drawn == planned
    labels = sorted(t.dxf.text for t in msp.query("TEXT[layer=='HEAT_LABELS']"))
    assert labels == sorted(f"{ln.id} #{ln.order} {ln.face}" for ln in under_bent.plan.lines)


def test_a_plate_within_the_standard_range_gets_no_plan_and_says_why(tmp_path: Path) -> None:
    d = _results(tmp_path / "r", FormingError(bumps=_NO_BUMPS))
    (d / HEATING_PLAN_DXF).write_text("an earlier plan's drawing")
    out = write_job_plan(d, SETTINGS)
    assert out.plan.status == "no_plan" and out.plan.lines == []
    assert "within the standard range" in (out.plan.reason or "")
    assert out.dxf_path is None and not (d / HEATING_PLAN_DXF).exists()  # never marked from a stale drawing
    assert read_heating_plan(d).reason == out.plan.reason
    assert out.plan.job_id == "job-fixture" and out.plan.plate_id == "P-0001"


@pytest.fixture(scope="module")
def bent_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _results(tmp_path_factory.mktemp("bent"), FormingError(bumps=_NO_BUMPS, bend_fraction=-0.2))


def test_plans_turned_off_leave_the_reason(bent_dir: Path, tmp_path: Path) -> None:
    d = Path(shutil.copytree(bent_dir, tmp_path / "r"))
    out = write_job_plan(d, SETTINGS, enabled=False)
    assert out.plan.status == "no_plan"
    assert "[forming] enabled = false" in (out.plan.reason or "")


def test_results_without_their_arrays_cost_the_plan_never_the_report(bent_dir: Path, tmp_path: Path) -> None:
    d = Path(shutil.copytree(bent_dir, tmp_path / "r"))
    (d / "results.npz").unlink()
    before = (d / "report.json").read_bytes()
    out = write_job_plan(d, SETTINGS)
    assert out.plan.status == "no_plan" and "results.npz" in (out.plan.reason or "")
    assert (d / "report.json").read_bytes() == before


def test_a_coefficient_table_gone_since_the_configuration_was_read_is_the_reason(
    bent_dir: Path, tmp_path: Path
) -> None:
    table = tmp_path / "yard.toml"
    shutil.copy(DEFAULT_TABLE, table)
    settings = PlanSettings(coefficients_file=table, element_mm=40.0)
    table.unlink()
    d = Path(shutil.copytree(bent_dir, tmp_path / "r"))
    out = write_job_plan(d, settings)
    assert out.plan.status == "no_plan"
    assert "coefficient table" in (out.plan.reason or "") and "yard.toml" in (out.plan.reason or "")


def test_a_thickness_in_the_report_wins_over_the_configured_one(bent_dir: Path, tmp_path: Path) -> None:
    d = Path(shutil.copytree(bent_dir, tmp_path / "r"))
    report = read_report(d)
    moulded = report.model_copy(update={"design": report.design.model_copy(update={"thickness_mm": 10.0})})
    (d / "report.json").write_text(moulded.model_dump_json())
    plan = write_job_plan(d, SETTINGS.model_copy(update={"max_lines_per_round": 1})).plan
    assert plan.model is not None and (plan.model.thickness_mm, plan.model.thickness_from) == (10.0, "report")


def test_no_results_directory_is_an_error(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="not a results directory"):
        write_job_plan(tmp_path / "nowhere", SETTINGS)


def test_a_file_that_is_not_a_plan_is_refused_naming_the_field(tmp_path: Path) -> None:
    (tmp_path / HEATING_PLAN_FILE).write_text('{"status": "maybe"}')
    with pytest.raises(ValueError, match="status"):
        read_heating_plan(tmp_path)
