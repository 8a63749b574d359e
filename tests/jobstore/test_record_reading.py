"""Job records read safely (issue 43): a record too large or nested too deep, or whose ``job_id`` is
not its directory's name, is quarantined at start-up instead of crash-looping the daemon; recovery
writes only inside the record's own directory; the plate history skips such a record with a log line."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from structlog.testing import capture_logs

from analysis.contracts.placement import Placement
from cellctl.api import JobState
from cellctl.jobstore.history import History, format_history, previous_round_for
from cellctl.jobstore.jobs import JobRecord, JobStore, JobStoreError
from cellctl.jobstore.records import MAX_RECORD_BYTES, RecordError, read_json_file
from tests.support.reports import report_json

DONE_ID = "20260101T000000-aaaa0001"
OTHER_ID = "20260101T000001-aaaa0002"


def _record(job_id: str, state: JobState) -> JobRecord:
    return JobRecord(job_id=job_id, plate_id="p1", design="d.ply", design_path="/d/d.ply",
                     placement={"pos_mm": [1.0, 2.0, 3.0], "rpy_deg": [0.0, 0.0, 3.0]}, state=state.value)  # fmt: skip


def _plant(store: JobStore, dir_name: str, text: str) -> Path:
    d = store.root / dir_name
    d.mkdir()
    (d / "job.json").write_text(text)
    return d


def _files(root: Path) -> set[Path]:
    return {p for p in root.rglob("*") if p.is_file()}


def test_a_record_of_a_thousand_brackets_is_quarantined_not_a_crash(tmp_path):
    store = JobStore(tmp_path)
    d = _plant(store, OTHER_ID, "[" * 1000 + "]" * 1000)
    found = JobStore(tmp_path).recover()  # RecursionError before: the daemon exited 1 on every start
    assert [r.job_id for r in found] == [OTHER_ID]
    back = store.load(OTHER_ID)
    assert back.state == "interrupted" and "nested deeper" in back.info.quarantine_reason
    assert (d / "job.json.quarantined").read_text().startswith("[[[")
    assert JobStore(tmp_path).recover() == []  # the fresh record is readable: no loop


def test_a_record_nested_below_the_recursion_limit_but_too_deep_is_refused(tmp_path):
    deep = '{"a": ' * 200 + "1" + "}" * 200
    with pytest.raises(RecordError, match="nested deeper"):
        read_json_file(_plant(JobStore(tmp_path), OTHER_ID, deep) / "job.json")


def test_a_record_larger_than_the_cap_is_not_read(tmp_path):
    store = JobStore(tmp_path)
    d = store.root / OTHER_ID
    d.mkdir()
    with open(d / "job.json", "wb") as f:  # sparse: its size is past the cap, nothing is read
        f.truncate(MAX_RECORD_BYTES + 1)
    with pytest.raises(JobStoreError, match="more than the"):
        store.load(OTHER_ID)
    found = store.recover()
    assert [r.job_id for r in found] == [OTHER_ID]
    assert "bytes" in store.load(OTHER_ID).info.quarantine_reason


def test_a_record_naming_a_path_never_makes_recovery_write_outside_its_directory(tmp_path):
    data = tmp_path / "a" / "b" / "data"
    store = JobStore(data)
    rec = _record(OTHER_ID, JobState.SCANNING)
    text = json.dumps({**rec.as_json(), "job_id": "../../../escape"})
    d = _plant(store, OTHER_ID, text)
    outside = tmp_path / "a" / "escape"  # where the record points: data_dir/jobs/../../../escape
    outside.mkdir()
    before = _files(tmp_path)
    found = JobStore(data).recover()
    assert [r.job_id for r in found] == [OTHER_ID]
    new = _files(tmp_path) - before
    assert new and all(p.parent == d for p in new), new  # only the fresh record beside the quarantined one
    assert list(outside.iterdir()) == []
    assert "not a job id" in store.load(OTHER_ID).info.quarantine_reason
    assert json.loads((d / "job.json.quarantined").read_text())["job_id"] == "../../../escape"


def test_a_record_naming_another_jobs_id_never_overwrites_that_jobs_record(tmp_path):
    store = JobStore(tmp_path)
    done = store.create(_record(DONE_ID, JobState.DONE))
    store.set_state(done, JobState.DONE, "report.json", verdict="pass")
    kept = (store.job_dir(DONE_ID) / "job.json").read_bytes()
    _plant(store, OTHER_ID, json.dumps({**_record(DONE_ID, JobState.SCANNING).as_json()}))
    for _ in range(2):  # on every restart
        found = JobStore(tmp_path).recover()
        assert DONE_ID not in [r.job_id for r in found]
    assert (store.job_dir(DONE_ID) / "job.json").read_bytes() == kept
    assert store.load(DONE_ID).info.verdict == "pass"
    other = store.load(OTHER_ID)
    assert other.job_id == OTHER_ID and "not its directory" in other.info.quarantine_reason


def test_a_directory_whose_name_is_not_a_job_id_is_left_alone(tmp_path):
    store = JobStore(tmp_path)
    d = _plant(store, "not a job", json.dumps(_record(OTHER_ID, JobState.SCANNING).as_json()))
    with capture_logs() as logs:
        assert JobStore(tmp_path).recover() == []
    assert sorted(p.name for p in d.iterdir()) == ["job.json"]
    assert any(e["event"] == "job_dir_not_a_job_id" for e in logs)
    with pytest.raises(JobStoreError, match="not a job id"):
        store.job_dir("../escape")


def test_a_record_whose_plan_info_has_the_wrong_type_is_quarantined(tmp_path):
    store = JobStore(tmp_path)
    rec = _record(OTHER_ID, JobState.SCANNING)
    store.create(rec)
    path = store.job_dir(OTHER_ID) / "job.json"  # read back by a re-analysis: AttributeError there before
    path.write_text(json.dumps({**rec.as_json(), "info": {"plan": "15 passes"}}))
    found = JobStore(tmp_path).recover()
    assert [r.job_id for r in found] == [OTHER_ID]
    back = store.load(OTHER_ID)
    assert "info.plan" in back.info.quarantine_reason and back.info.plan is None


def test_a_records_placement_is_a_placement_and_one_of_another_shape_is_quarantined(tmp_path):
    store = JobStore(tmp_path)
    rec = store.create(_record(DONE_ID, JobState.DONE))  # done: recovery leaves it alone
    back = store.load(DONE_ID)
    assert isinstance(back.placement, Placement) and back.placement == rec.placement
    assert back.placement == Placement(pos_mm=[1.0, 2.0, 3.0], rpy_deg=[0.0, 0.0, 3.0])
    assert json.loads((store.job_dir(DONE_ID) / "job.json").read_text())["placement"] == {
        "pos_mm": [1.0, 2.0, 3.0], "rpy_deg": [0.0, 0.0, 3.0]
    }  # fmt: skip
    # a field the placement does not know (a record of another version): quarantined, placement dropped
    planted = {**_record(OTHER_ID, JobState.SCANNING).as_json(), "placement": {"pos_mm": [1, 2, 3], "yaw": 3}}
    _plant(store, OTHER_ID, json.dumps(planted))
    with pytest.raises(JobStoreError, match="placement"):
        store.load(OTHER_ID)
    assert [r.job_id for r in JobStore(tmp_path).recover()] == [OTHER_ID]
    again = store.load(OTHER_ID)
    assert again.placement is None and "placement" in again.info.quarantine_reason


def _history_job(data: Path, dir_name: str, text: str, report: str | None = None) -> None:
    d = data / "jobs" / dir_name
    d.mkdir(parents=True)
    (d / "job.json").write_text(text)
    if report is not None:
        (d / "report.json").write_text(report)


def _good(job_id: str, created: str) -> str:
    return json.dumps({"job_id": job_id, "plate_id": "P1", "state": "done", "created_utc": created, "design": "d",
                       "design_path": "/x/d", "placement": None,
                       "history": [{"state": "done", "t_utc": created, "message": "m"}]})  # fmt: skip


REPORT = report_json([{"family": "transverse", "index": 1, "name": "T1", "zmax_mm": 1.0, "sz_avg_mm": 0.5,
                       "pass": True}], "pass")  # fmt: skip


def test_the_history_skips_bad_records_with_a_log_line_instead_of_dying(tmp_path):
    _history_job(tmp_path, "j1", _good("j1", "2026-11-01T10:00:00Z"), REPORT)
    _history_job(tmp_path, "j2", _good("j2", "2026-11-02T10:00:00Z"), REPORT)
    _history_job(tmp_path, "deep", "[" * 1000 + "]" * 1000)
    _history_job(tmp_path, "list", "[]")
    _history_job(tmp_path, "wrongid", _good("j1", "2026-11-03T10:00:00Z"))  # j1's id in another directory
    _history_job(tmp_path, "esc", _good("../../x", "2026-11-03T10:00:00Z"))
    _history_job(tmp_path, "nokeys", json.dumps({"job_id": "nokeys"}))
    _history_job(tmp_path, "badreport", _good("badreport", "2026-11-04T10:00:00Z"), "[" * 1000)
    _history_job(tmp_path, "oddreport", _good("oddreport", "2026-11-05T10:00:00Z"),
                 json.dumps({"verdict": "pass", "lines": [{"family": 3}]}))  # fmt: skip
    # a field the report's schema does not know: not a report this cell wrote
    _history_job(tmp_path, "extrareport", _good("extrareport", "2026-11-06T10:00:00Z"),
                 json.dumps({**json.loads(REPORT), "verdikt": "pass"}))  # fmt: skip
    h = History(tmp_path, db_path=":memory:")
    try:
        with capture_logs() as logs:
            assert h.rebuild() == 5
        skipped = {Path(e["path"]).parent.name for e in logs if e["event"] == "history_record_skipped"}
        assert skipped == {"deep", "list", "wrongid", "esc", "nokeys"}
        bad_reports = {Path(e["path"]).parent.name for e in logs if e["event"] == "history_report_unreadable"}
        assert bad_reports == {"badreport", "oddreport", "extrareport"}
        assert [r["job_id"] for r in h.jobs()] == ["extrareport", "oddreport", "badreport", "j2", "j1"]
        assert h.jobs(plate_id="P1")[0]["verdict"] is None  # an unreadable report leaves no verdict
        assert "2 round(s)" in format_history(h, "P1") and "j1" in format_history(h, None)
    finally:
        h.close()
    # the report's previous round reads the same way
    assert previous_round_for(tmp_path / "jobs" / "j2").job_id == "j1"
    assert previous_round_for(tmp_path / "jobs" / "deep") is None


def test_cellctl_history_prints_the_good_jobs_and_logs_the_bad_record(tmp_path, monkeypatch, capsys):
    import argparse

    from cellctl.commands.hmi_cmd import history

    data = tmp_path / "data"
    _history_job(data, "j1", _good("j1", "2026-11-01T10:00:00Z"), REPORT)
    _history_job(data, "deep", "[" * 1000 + "]" * 1000)  # RecursionError: the command died before
    monkeypatch.setenv("CELL_CELL__DATA_DIR", str(data))
    repo = Path(__file__).resolve().parents[2]
    with capture_logs() as logs:
        assert history(argparse.Namespace(config=str(repo / "cell.toml"), plate=None)) == 0
    out = capsys.readouterr().out
    assert "j1" in out and "deep" not in out
    assert [Path(e["path"]).parent.name for e in logs if e["event"] == "history_record_skipped"] == ["deep"]
