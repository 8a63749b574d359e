"""`cellctl heat-plan JOB_OR_DIR`: the plan written beside report.json and told one sentence a line,
a job found under the configured data_dir, the [forming] rules from cell.toml or --forming, and the
refusals (exit 2, nothing written)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from analysis.design.plates import FormingError, GaussianBump, plate_spec
from analysis.forming.plan_file import read_heating_plan
from cellctl.cli import main
from cellctl.daemon.heat_plan import HeatPlanAnswer
from tests.support.results_fixture import CELL_LAYOUT, write_synthetic_results

#: a coarse model and few lines: each plan takes about 2 s on the shared machine
FORMING = {"element_mm": 40.0, "max_lines_per_round": 4}
_NO_BUMPS = (GaussianBump(0.0, 0.0, 0.0, 50.0),) * 2


def _results(out: Path, bend_fraction: float) -> Path:
    spec = plate_spec("cylinder", length_mm=600.0, width_mm=400.0)
    error = FormingError(bumps=_NO_BUMPS, bend_fraction=bend_fraction)
    write_synthetic_results(out, spec=spec, error=error, n_points=6000, layout=CELL_LAYOUT)
    return out


@pytest.fixture(scope="module")
def bent(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _results(tmp_path_factory.mktemp("bent"), -0.2)


def test_heat_plan_writes_the_files_and_tells_one_sentence_a_line(bent: Path, tmp_path: Path, capsys) -> None:
    d = Path(shutil.copytree(bent, tmp_path / "r"))
    assert main(["heat-plan", str(d), "--forming", json.dumps(FORMING)]) == 0
    out = capsys.readouterr().out.splitlines()
    plan = read_heating_plan(d)
    assert plan.status == "plan" and 1 <= len(plan.lines) <= FORMING["max_lines_per_round"]
    sentences = [ln.sentence() for ln in plan.lines]
    assert out[: len(sentences)] == sentences
    assert sentences[0].startswith("H1: top face, (")
    assert any(line.startswith("predicted after the round: largest Zmax") for line in out)
    assert out[-2:] == [str(d / "heating-plan.json"), str(d / "heating-plan.dxf")]
    assert (d / "heating-plan.dxf").is_file()


def test_a_job_id_is_found_under_the_data_dir_with_cell_toml_rules(
    bent: Path, tmp_path: Path, capsys
) -> None:
    results = tmp_path / "store" / "jobs" / "job-7" / "results"
    shutil.copytree(bent, results)
    cfg = tmp_path / "cell.toml"
    cfg.write_text(
        f'[cell]\ndata_dir = "{tmp_path / "store"}"\n\n[forming]\nelement_mm = 40.0\nmax_lines_per_round = 2\n'
        "allow_bottom_face = false\n"
    )
    assert main(["heat-plan", "job-7", "--config", str(cfg), "--json"]) == 0
    answer = HeatPlanAnswer.model_validate_json(capsys.readouterr().out.splitlines()[-1])
    assert Path(answer.json_path) == results / "heating-plan.json"
    plan = read_heating_plan(results)
    assert answer.status == plan.status == "plan" and answer.lines == len(plan.lines) <= 2
    assert plan.model is not None and plan.model.rules.allow_bottom_face is False
    assert all(ln.face == "top" for ln in plan.lines)


def test_a_plate_within_the_standard_range_is_told_why_there_is_no_plan(tmp_path: Path, capsys) -> None:
    d = _results(tmp_path / "r", 0.0)
    assert main(["heat-plan", str(d), "--forming", json.dumps(FORMING)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("no heating plan: every line is within the standard range")
    assert read_heating_plan(d).status == "no_plan"
    assert not (d / "heating-plan.dxf").exists()


def test_plans_turned_off_in_cell_toml_write_the_reason(bent: Path, tmp_path: Path, capsys) -> None:
    d = Path(shutil.copytree(bent, tmp_path / "r"))
    assert main(["heat-plan", str(d), "--forming", '{"enabled": false}']) == 0
    assert "[forming] enabled = false" in capsys.readouterr().out
    assert read_heating_plan(d).status == "no_plan"


def test_what_is_not_a_results_directory_is_refused_and_nothing_written(tmp_path: Path, capsys) -> None:
    assert main(["heat-plan", str(tmp_path / "nowhere")]) == 2
    assert "nowhere: no such directory" in capsys.readouterr().err
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["heat-plan", str(empty)]) == 2
    assert "no report.json (is this a results directory?)" in capsys.readouterr().err
    assert list(empty.iterdir()) == []


def test_bad_rules_are_refused_as_cell_toml_refuses_them(bent: Path, tmp_path: Path, capsys) -> None:
    d = Path(shutil.copytree(bent, tmp_path / "r"))
    assert main(["heat-plan", str(d), "--forming", '{"min_spacing_mm": -1}']) == 2
    assert "--forming: forming.min_spacing_mm = -1: Input should be greater than 0" in capsys.readouterr().err
    assert main(["heat-plan", str(d), "--forming", "{not json"]) == 2
    assert "--forming: not JSON" in capsys.readouterr().err
    cfg = tmp_path / "cell.toml"
    cfg.write_text('[forming]\nmaterial = "wood"\n')
    assert main(["heat-plan", str(d), "--config", str(cfg)]) == 2
    assert "forming: material 'wood' is not in the coefficient table" in capsys.readouterr().err
    assert not (d / "heating-plan.json").exists()
