"""The report's previous round found from job directories (cellctl.jobstore.history.previous_round_for)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pytest

from analysis.templates import DetectionLayout
from cellctl.commands import report_cmd
from cellctl.jobstore.history import History, previous_round_for
from tests.support.reports import report_json
from tests.support.results_fixture import write_synthetic_results


def _job(
    data: Path, job_id: str, plate: str, created: str, lines: list[tuple[str, float]] | None, state="done"
) -> Path:
    d = data / "jobs" / job_id
    (d / "results").mkdir(parents=True)
    rec = {"job_id": job_id, "plate_id": plate, "design": "p.ply", "design_path": "/x/p.ply",
           "placement": {"pos_mm": [1500.0, 0.0, 0.0], "rpy_deg": [0.0, 0.0, 0.0]},
           "state": state, "created_utc": created, "history": [{"state": state, "t_utc": created, "message": "m"}],
           "info": {}}  # fmt: skip
    (d / "job.json").write_text(json.dumps(rec))
    if lines is not None:
        rep = [
            {
                "family": "transverse",
                "index": k + 1,
                "name": n,
                "zmax_mm": z,
                "sz_avg_mm": z / 2,
                "pass": z <= 3,
            }
            for k, (n, z) in enumerate(lines)
        ]
        (d / "report.json").write_text(report_json(rep, "pass" if all(z <= 3 for _, z in lines) else "fail"))
    return d


@pytest.fixture
def data(tmp_path: Path) -> Path:
    _job(tmp_path, "j1", "P1", "2026-11-01T10:00:00Z", [("T1", 5.0), ("T2", 4.0)])  # round 1
    _job(tmp_path, "j2", "P2", "2026-11-01T12:00:00Z", [("T1", 9.0)])  # another plate
    _job(tmp_path, "j3", "P1", "2026-11-02T10:00:00Z", [("T1", 3.5), ("T2", 2.0)])  # round 2
    _job(tmp_path, "j4", "P1", "2026-11-02T11:00:00Z", None, state="failed")  # no report: no round
    _job(tmp_path, "j5", "P2", "2026-11-02T12:00:00Z", [("T1", 8.0)])  # another plate, later
    _job(tmp_path, "j6", "P1", "2026-11-03T10:00:00Z", [("T1", 2.0)])  # the job being reported
    return tmp_path


def test_the_latest_earlier_round_of_the_same_plate_is_found(data: Path) -> None:
    prev = previous_round_for(data / "jobs" / "j6" / "results")
    assert prev is not None
    assert (prev.round, prev.job_id, prev.verdict) == (2, "j3", "fail")
    assert [(ln.name, ln.zmax_mm, ln.sz_avg_mm, ln.passed) for ln in prev.lines] == [
        ("T1", 3.5, 1.75, False),
        ("T2", 2.0, 1.0, True),
    ]
    # the same answer from the job directory, and the same job as the HMI's index gives
    assert previous_round_for(data / "jobs" / "j6") == prev
    hist = History(data, db_path=data / "h.sqlite")
    try:
        hist.rebuild()
        assert hist.previous_round("j6")["job_id"] == "j3"
    finally:
        hist.close()


def test_a_first_round_and_a_directory_outside_the_jobs_have_none(data: Path, tmp_path_factory) -> None:
    assert previous_round_for(data / "jobs" / "j1" / "results") is None
    assert previous_round_for(data / "jobs" / "j2" / "results") is None  # P2's first round
    assert previous_round_for(data / "jobs" / "j5" / "results").job_id == "j2"
    assert previous_round_for(tmp_path_factory.mktemp("loose")) is None
    assert not (data / "history.sqlite").exists()  # the lookup leaves the data directory as it is


def test_cellctl_report_of_a_job_shows_its_previous_round(data: Path) -> None:
    results = data / "jobs" / "j6" / "results"
    layout = DetectionLayout(
        transverse_offsets_mm=(300.0, 900.0), longitudinal_offsets_mm=(), diagonals=False
    )
    write_synthetic_results(results, n_points=2000, layout=layout, plate_id="P1")
    args = argparse.Namespace(target=str(results), open=False, json=False, config="/nonexistent/cell.toml")
    assert report_cmd.run(args) == 0
    html = (results / "report.html").read_text(encoding="utf-8")
    section = html.split('<section id="previous-round"', 1)[1].split("</section>", 1)[0]
    assert 'data-round="3"' in section and "job j3" in section
    assert "<td>3.50</td><td>1.75</td>" in section.split('data-line="T1"', 1)[1].split("</tr>", 1)[0]
