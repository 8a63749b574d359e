"""The daemon's state machine and job store, without processes."""

from __future__ import annotations

import json

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cellctl.api import CellState, JobState
from cellctl.daemon.states import ALLOWED, CellStateMachine, StateError
from cellctl.jobstore.jobs import JobRecord, JobStore, JobStoreError


def test_state_machine_publishes_each_transition_once_and_in_order():
    seen = []
    sm = CellStateMachine(seen.append)
    sm.to(CellState.IDLE, "ready")
    sm.to(CellState.IDLE, "again")  # no-op: nothing published
    sm.to(CellState.PLANNING, "job 1")
    sm.to(CellState.SCANNING, "job 1")
    assert [(t.old, t.new) for t in seen] == [
        (CellState.STARTING, CellState.IDLE),
        (CellState.IDLE, CellState.PLANNING),
        (CellState.PLANNING, CellState.SCANNING),
    ]
    assert sm.busy and sm.message == "job 1"


def test_state_machine_refuses_a_scan_straight_from_idle():
    sm = CellStateMachine()
    sm.to(CellState.IDLE)
    with pytest.raises(StateError, match="idle -> scanning"):
        sm.to(CellState.SCANNING)
    assert sm.state == CellState.IDLE


def test_a_failing_publisher_does_not_stop_the_transition():
    def boom(_):
        raise RuntimeError("session closed")

    sm = CellStateMachine(boom)
    sm.to(CellState.IDLE)
    assert sm.state == CellState.IDLE


@settings(max_examples=60, deadline=None)
@given(st.lists(st.sampled_from(list(CellState)), max_size=30))
def test_state_machine_only_ever_takes_allowed_steps(targets):
    sm = CellStateMachine()
    for t in targets:
        before = sm.state
        allowed = sm.can(t)
        if allowed:
            sm.to(t)
            assert sm.state == t
        else:
            with pytest.raises(StateError):
                sm.to(t)
            assert sm.state == before
    for tr in sm.history:
        assert tr.new in ALLOWED[tr.old] or tr.new in (CellState.STOPPING, CellState.EMERGENCY_STOPPED)


def test_state_history_keeps_the_newest_transitions_only():
    """The daemon runs for months: its transition history is bounded (it grew by ~10 per job)."""
    from cellctl.daemon.states import HISTORY_MAX

    sm = CellStateMachine()
    sm.to(CellState.IDLE)
    for k in range(HISTORY_MAX):
        sm.to(CellState.PLANNING, f"job {k}")
        sm.to(CellState.IDLE, f"job {k} done")
    assert len(sm.history) == HISTORY_MAX
    assert sm.history[-1].reason == f"job {HISTORY_MAX - 1} done"


def _record(job_id="20260101T000000-aaaa0001", state=JobState.QUEUED):
    return JobRecord(job_id=job_id, plate_id="p1", design="d.ply", design_path="/d/d.ply",
                     placement={"pos_mm": [1.0, 2.0, 3.0], "rpy_deg": [0.0, 0.0, 3.0]}, state=state.value)  # fmt: skip


def test_job_store_keeps_the_state_history_on_disk(tmp_path):
    store = JobStore(tmp_path)
    rec = store.create(_record())
    store.set_state(rec, JobState.PLANNING, "planning")
    store.set_state(rec, JobState.SCANNING, "", profiles=12)
    back = store.load(rec.job_id)
    assert [h["state"] for h in back.history] == ["queued", "planning", "scanning"]
    assert back.info.profiles == 12
    assert not list((tmp_path / "jobs" / rec.job_id).glob("*.tmp"))


def test_recover_marks_unfinished_jobs_interrupted_and_leaves_raw_files_alone(tmp_path):
    store = JobStore(tmp_path)
    done = store.create(_record("20260101T000000-aaaa0001"))
    store.set_state(done, JobState.DONE, "report")
    running = store.create(_record("20260101T000001-aaaa0002"))
    store.set_state(running, JobState.SCANNING)
    raw = store.raw_dir(running.job_id)
    raw.mkdir()
    (raw / "profiles.craw").write_bytes(b"\x01" * 100)
    found = JobStore(tmp_path).recover()
    assert [r.job_id for r in found] == [running.job_id]
    back = store.load(running.job_id)
    assert back.state == "interrupted" and back.info.interrupted_in == "scanning"
    assert back.info.raw_files == ["profiles.craw"]
    assert (raw / "profiles.craw").read_bytes() == b"\x01" * 100
    assert store.load(done.job_id).state == "done"
    assert JobStore(tmp_path).recover() == []  # idempotent


def test_an_unreadable_job_record_is_named_and_skipped(tmp_path):
    store = JobStore(tmp_path)
    bad = tmp_path / "jobs" / "broken"
    bad.mkdir(parents=True)
    (bad / "job.json").write_text("{not json")
    with pytest.raises(JobStoreError, match="broken"):
        store.load("broken")
    assert store.list() == []
    good = store.create(_record())
    assert [r.job_id for r in store.list()] == [good.job_id]
    assert json.loads((tmp_path / "jobs" / good.job_id / "job.json").read_text())["plate_id"] == "p1"
