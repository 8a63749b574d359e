"""A template table through the trigger: read by `cellctl scan`, carried as rows (not a path) in the
trigger, the job record and the job's settings, validated where each crosses a boundary."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from analysis.contracts.job import AnalysisJob
from analysis.design.template_table import TableTemplate
from cellctl.analysis_job import analysis_job
from cellctl.api.models import AnalysisOptions, TriggerError, parse_trigger
from cellctl.commands.scan_cmd import template_table_rows
from cellctl.config import CellConfig
from cellctl.jobstore.jobs import JobRecord, JobStore

PLACEMENT = {"pos_mm": [1600.0, 100.0, 0.0], "rpy_deg": [0.0, 0.0, 3.0]}


def test_the_table_travels_as_rows_from_the_cli_to_the_workers_settings(tmp_path: Path) -> None:
    (tmp_path / "designs").mkdir()
    (tmp_path / "designs" / "p.ply").write_text("ply\n")
    (tmp_path / "t.csv").write_text("name;from;distance;angle\nFR7;x;120;90\nLK2;0-1;80;95\n")
    rows = template_table_rows(str(tmp_path / "t.csv"))
    payload = json.dumps(
        {"plate_id": "P1", "design": "p.ply", "placement": PLACEMENT, "template_table": rows}
    )
    req, _ = parse_trigger(payload, tmp_path / "designs")
    assert req.template_table == (
        TableTemplate("FR7", "0-3", 120.0, 90.0),
        TableTemplate("LK2", "0-1", 80.0, 95.0),
    )

    store = JobStore(tmp_path / "data")
    store.create(
        JobRecord("j1", "P1", "p.ply", "/d/p.ply", PLACEMENT, analysis=req.analysis_options().record())
    )
    rec = store.load("j1")  # the record on disk keeps the rows: a re-analysis uses the same table
    cfg = CellConfig.model_validate({"cell": {"id": "c1"}, "analysis": {"transverse_count": 3}})
    job = analysis_job(cfg, job_id="j1", plate_id="P1", design="/d/p.ply", placement=rec.placement,
                       out_dir=tmp_path / "o", analysis=AnalysisOptions.model_validate(rec.analysis))  # fmt: skip
    worker_side = AnalysisJob.model_validate_json(job.model_dump_json())
    assert worker_side.settings.layout.templates == req.template_table
    assert worker_side.settings.layout.transverse_count == 3


def test_a_trigger_with_a_bad_row_is_refused_and_the_cli_refuses_a_bad_file(tmp_path: Path) -> None:
    (tmp_path / "p.ply").write_text("ply\n")
    bad = {"plate_id": "P1", "design": "p.ply", "placement": PLACEMENT,
           "template_table": [{"name": "A", "edge": "bow", "distance_mm": 1.0}]}  # fmt: skip
    with pytest.raises(TriggerError, match="template_table"):
        parse_trigger(json.dumps(bad), tmp_path)
    (tmp_path / "t.csv").write_text("name,edge\nA,0-3\n")
    with pytest.raises(ValueError, match=r"t\.csv: line 1: missing column 'distance_mm'"):
        template_table_rows(str(tmp_path / "t.csv"))
    assert template_table_rows(None) == []


def test_the_design_side_and_thickness_travel_from_the_trigger_to_the_settings(tmp_path: Path) -> None:
    (tmp_path / "p.igs").write_text("x\n")
    base = {"plate_id": "P1", "design": "p.igs", "placement": PLACEMENT}
    req, _ = parse_trigger(
        json.dumps({**base, "design_side": "moulded_down", "thickness_mm": 12.5}), tmp_path
    )
    cfg = CellConfig.model_validate({"cell": {"id": "c1"}})
    job = analysis_job(cfg, job_id="j", plate_id="P1", design="/d/p.igs", placement=PLACEMENT,
                       out_dir=tmp_path, analysis=req.analysis_options())  # fmt: skip
    settings = AnalysisJob.model_validate_json(job.model_dump_json()).settings
    assert (settings.design_side, settings.thickness_mm) == ("moulded_down", 12.5)
    plain, _ = parse_trigger(json.dumps(base), tmp_path)
    assert plain.analysis_options() == AnalysisOptions()
    assert plain.analysis_options().record() == {}  # a plain job's record carries no options
    for bad, field in (
        ({"design_side": "moulded_down"}, "needs its thickness"),
        ({"design_side": "sideways", "thickness_mm": 5}, "design_side"),
        ({"design_side": "moulded_down", "thickness_mm": -3}, "thickness_mm"),
    ):
        with pytest.raises(TriggerError, match=field):
            parse_trigger(json.dumps({**base, **bad}), tmp_path)
