"""A job record's ``info`` is a model (JobInfo): records of earlier daemons load, keys this version
does not name are kept through a rewrite, a named key of another type quarantines the record, and
the daemon writes only the keys the model names."""

from __future__ import annotations

import json

import pytest

from analysis.contracts.job import PlacementFinding
from cellctl.api import JobState
from cellctl.api.models import MotionCounters
from cellctl.jobstore.info import JobInfo, PlanCounts, RunInfo
from cellctl.jobstore.jobs import JobRecord, JobStore, read_job_record

JOB_ID = "20261122T101500-0a1b2c3d"

#: job.json as the first daemon (2026-11-22) wrote it for a finished job: no ``analysis`` field, no
#: locate run, no motion counters, the plan's summary of that version
FIRST_DAEMON_RECORD = {
    "job_id": JOB_ID,
    "plate_id": "P-100",
    "design": "sail.ply",
    "design_path": "/var/lib/cellctl/designs/sail.ply",
    "placement": {"pos_mm": [1500.0, 0.0, 0.0], "rpy_deg": [0.0, 0.0, 90.0]},
    "note": "",
    "state": "done",
    "created_utc": "2026-11-22T10:15:00Z",
    "history": [
        {"state": "queued", "t_utc": "2026-11-22T10:15:00Z", "message": "accepted"},
        {"state": "done", "t_utc": "2026-11-22T10:19:02Z", "message": "/var/lib/.../report.json"},
    ],
    "info": {
        "plan": {"passes": 14, "coverage": 0.991, "scan_time_s": 141.2, "toppra_time_s": 3.1},
        "plan_s": 2.31,
        "scan_s": 150.512,
        "profiles": 30102,
        "execution": "finished",
        "max_tracking_error_mm": 0.412,
        "last_profile_utc_s": 1795342720.5,
        "acquisition": {"sensor_clock": None, "robot_clock": {"rms_us": 40.0}, "latency_ms": 1.5},
        "points": 4_200_000,
        "cloud_bytes": 117_600_120,
        "assemble_s": 4.1,
        "worker_id": "w-1",
        "verdict": "pass",
        "report": "/var/lib/cellctl/jobs/x/report.json",
        "analysis_timings_s": {"segment": 1.2, "register": 8.5},
        "report_utc_s": 1795342740.0,
        "encoding": "application/x-cellctl-cloud",  # a key no later daemon writes
    },
}


def _plant(tmp_path, record: dict) -> JobStore:
    store = JobStore(tmp_path)
    d = store.job_dir(record["job_id"])
    d.mkdir()
    (d / "job.json").write_text(json.dumps(record))
    return store


def test_a_record_of_the_first_daemon_loads_with_its_info_typed(tmp_path):
    store = _plant(tmp_path, FIRST_DAEMON_RECORD)
    rec = store.load(JOB_ID)
    info = rec.info
    assert isinstance(info, JobInfo)
    assert info.plan is not None and (info.plan.passes, info.plan.edge_passes) == (14, None)
    assert info.verdict == "pass" and info.report == "/var/lib/cellctl/jobs/x/report.json"
    assert info.profiles == 30102 and info.scan_s == pytest.approx(150.512)
    assert info.placement_found is None and info.motion is None and info.html_s is None
    assert rec.analysis == {}


def test_keys_this_version_does_not_name_survive_a_rewrite_of_the_record(tmp_path):
    store = _plant(tmp_path, FIRST_DAEMON_RECORD)
    rec = store.load(JOB_ID)
    assert rec.info.model_extra == {"encoding": "application/x-cellctl-cloud"}
    store.set_state(rec, JobState.DONE, "again", html_s=1.5)
    written = json.loads((store.job_dir(JOB_ID) / "job.json").read_text())["info"]
    assert written["encoding"] == "application/x-cellctl-cloud" and written["html_s"] == 1.5
    # the plan summary's other figures are kept as written too
    assert written["plan"] == FIRST_DAEMON_RECORD["info"]["plan"]
    assert read_job_record(store.job_dir(JOB_ID)).info == rec.info


def test_the_daemon_writes_only_the_keys_the_model_names(tmp_path):
    store = _plant(tmp_path, FIRST_DAEMON_RECORD)
    rec = store.load(JOB_ID)
    with pytest.raises(ValueError, match="verdikt"):
        store.set_state(rec, JobState.DONE, "typo", verdikt="pass")
    with pytest.raises(ValueError, match=r"info\.verdict"):
        rec.info.updated(verdict="maybe")


def test_locate_runs_are_kept_by_name_and_validated_as_runs():
    info = JobInfo.read({"locate_along": {"scan_s": 12.5, "profiles": 800, "execution": "finished"}})
    info = info.updated(locate_across_2={"scan_s": 3.0, "motion": MotionCounters(cycles=10)})
    runs = info.locate_runs()
    assert set(runs) == {"locate_along", "locate_across_2"}
    assert runs["locate_along"] == RunInfo(scan_s=12.5, profiles=800, execution="finished")
    assert runs["locate_across_2"].motion == MotionCounters(cycles=10)
    with pytest.raises(ValueError, match="locate_along"):
        JobInfo.read({"locate_along": {"scan_s": "long"}})


def test_a_placement_finding_is_read_back_as_the_model():
    given = {"pos_mm": [10.0, 20.0, 0.0], "rpy_deg": [0.0, 0.0, 180.0]}
    info = JobInfo.read({"placement_found": {"source": "checked", "given": given, "rms_mm": 0.8}})
    assert isinstance(info.placement_found, PlacementFinding)
    assert info.placement_found.source == "checked" and info.placement_found.given.yaw_deg == 180.0


@pytest.mark.parametrize(
    ("info", "where"),
    [
        ({"plan": {"passes": -3}}, "info.plan.passes"),
        ({"plan": [14]}, "info.plan"),
        ({"placement_found": {"source": "guessed"}}, "info.placement_found.source"),
        ({"raw_files": "profiles.craw"}, "info.raw_files"),
        ({"report_utc_s": "yesterday"}, "info.report_utc_s"),
        ({"motion": {"cycles": 3, "jitter": 1}}, "info.motion.jitter"),
        ({"verdict": "unknown"}, "info.verdict"),
    ],
)
def test_a_named_key_of_another_type_quarantines_the_record(tmp_path, info, where):
    store = _plant(tmp_path, {**FIRST_DAEMON_RECORD, "state": "scanning", "info": info})
    found = store.recover()
    assert [r.job_id for r in found] == [JOB_ID]
    back = store.load(JOB_ID)
    assert back.state == "interrupted" and where in (back.info.quarantine_reason or "")
    assert (store.job_dir(JOB_ID) / "job.json.quarantined").exists()


def test_a_record_made_in_code_validates_its_info():
    rec = JobRecord(JOB_ID, "P", "d.ply", "/d.ply", None, info={"plan": {"passes": 3, "edge_passes": 4}})
    assert rec.info.plan == PlanCounts(passes=3, edge_passes=4)
    with pytest.raises(ValueError):
        JobRecord(JOB_ID, "P", "d.ply", "/d.ply", None, info={"profiles": -1})
