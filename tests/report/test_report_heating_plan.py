"""report.html with the heating plan of its results directory: the lines over the top view and one
sentence each in the crew's order, a plan-less job's reason, and a heating-plan.json that does not
read never costing the report."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from analysis.design.plates import FormingError, GaussianBump, plate_spec
from analysis.forming.plan_file import HEATING_PLAN_FILE, read_heating_plan
from analysis.forming.rules import PlanSettings
from analysis.heating_plan import write_job_plan
from analysis.report.html_page import _heating_html
from analysis.report.load import load_results
from analysis.report.write import write_report
from analysis.templates import DetectionLayout
from tests.support.results_fixture import write_synthetic_results

#: three lines: the report's render is a plot a line
FEW_LINES = DetectionLayout(
    transverse_offsets_mm=(150.0, 450.0), longitudinal_offsets_mm=(200.0,), diagonals=False
)


@pytest.fixture(scope="module")
def planned(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("planned")
    spec = plate_spec("cylinder", length_mm=600.0, width_mm=400.0)
    error = FormingError(bumps=(GaussianBump(0.0, 0.0, 0.0, 50.0),) * 2, bend_fraction=-0.2)
    write_synthetic_results(out, spec=spec, error=error, n_points=6000, layout=FEW_LINES)
    write_job_plan(out, PlanSettings(element_mm=40.0, max_lines_per_round=4))
    return out


@pytest.mark.slow  # the report's HTML and PDF: seconds of matplotlib
def test_the_report_shows_the_plan_one_sentence_a_line_and_links_the_dxf(
    planned: Path, tmp_path: Path
) -> None:
    d = Path(shutil.copytree(planned, tmp_path / "r"))
    plan = read_heating_plan(d)
    write_report(d)
    html = (d / "report.html").read_text()
    section = html[html.index('<section id="heating">') :]
    section = section[: section.index("</section>")]
    for line in plan.lines:
        assert f'data-heat="{line.id}">{line.sentence()}' in section.replace("&#x27;", "'")
    assert f"verdict {plan.predicted.verdict.upper()}" in section
    assert "numbered solid lines are the heating plan" in html
    assert '<a href="heating-plan.dxf">' in html and '<a href="heating-plan.json">' in html
    # drawn over the top view: one solid line a heating line in the face's colour (the SVG's paths)
    assert html.count("stroke: #ff7f0e") + html.count("stroke: #17becf") >= len(plan.lines)


def test_a_plan_that_does_not_read_costs_nothing_and_a_reason_is_shown(planned: Path, tmp_path: Path) -> None:
    d = Path(shutil.copytree(planned, tmp_path / "r"))
    (d / HEATING_PLAN_FILE).write_text("{ not json")
    assert load_results(d).heating_plan is None
    assert _heating_html(load_results(d)) == ""  # no section, and the report is made
    write_job_plan(d, PlanSettings(element_mm=40.0), enabled=False)
    section = _heating_html(load_results(d))
    assert "No heating plan: line-heating plans are off" in section and "<ol>" not in section
