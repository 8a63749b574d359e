"""The queue's records and its client side: restart recovery of queued jobs, the state publication's
job lists, and `cellctl scan --wait` following a job from its queue position to its end."""

from __future__ import annotations

import asyncio
import io

from cellctl.api import CellState, CellStatus, JobProgress, JobState, QueuedJob
from cellctl.commands.scan_cmd import StatusFollower, wait_for_job
from cellctl.jobstore.jobs import JobRecord, JobStore


def _record(job_id: str, state: JobState = JobState.QUEUED) -> JobRecord:
    return JobRecord(job_id=job_id, plate_id="p1", design="d.ply", design_path="/d/d.ply",
                     placement={"pos_mm": [1.0, 2.0, 3.0], "rpy_deg": [0.0, 0.0, 3.0]}, state=state.value)  # fmt: skip


def test_restart_cancels_queued_jobs_and_interrupts_started_ones(tmp_path):
    store = JobStore(tmp_path)
    running = store.create(_record("20260101T000000-aaaa0001"))
    store.set_state(running, JobState.SCANNING)
    queued = store.create(_record("20260101T000001-aaaa0002"))
    found = JobStore(tmp_path).recover()
    assert sorted(r.job_id for r in found) == [running.job_id, queued.job_id]
    back_q = store.load(queued.job_id)
    assert back_q.state == "cancelled" and back_q.terminal
    assert "trigger it again" in back_q.history[-1]["message"]
    assert back_q.info.cancelled_in == "queued"
    assert store.load(running.job_id).state == "interrupted"
    assert not store.raw_dir(queued.job_id).exists()  # a queued job never acquired anything
    assert JobStore(tmp_path).recover() == []  # cancelled is final: a second restart changes nothing


def _progress(job_id: str, state: str, fraction: float = 0.0, message: str = "") -> JobProgress:
    return JobProgress(job_id=job_id, plate_id="p", state=JobState(state), fraction=fraction, message=message)


def test_status_jobs_lists_recent_ends_before_live_entries_so_live_ones_win():
    st = CellStatus(
        cell_id="c", state=CellState.SCANNING, t_utc="t",
        job=_progress("b", "scanning", 0.5),
        analyses=[_progress("a", "analysing")],
        recent=[_progress("a", "interrupted"), _progress("x", "cancelled")],
    )  # fmt: skip
    seen = {}
    for jp in st.jobs():
        seen[jp.job_id] = jp.state.value
    assert seen == {"a": "analysing", "x": "cancelled", "b": "scanning"}


class _ScriptedFollower(StatusFollower):
    """The StatusFollower fed from a list of publications, one per ``next()`` (no session)."""

    def __init__(self, statuses: list[CellStatus]) -> None:
        self._init_state()
        self.statuses = list(statuses)

    async def next(self, timeout_s: float) -> None:
        if not self.statuses:
            await asyncio.sleep(0.01)  # stays: the fake follower's wait for a status that never comes
            return
        self.feed(self.statuses.pop(0))


def _status(job=None, queue=(), recent=()) -> CellStatus:
    return CellStatus(cell_id="c", state=CellState.SCANNING, t_utc="t", job=job,
                      queued=len(queue), queue=list(queue), recent=list(recent))  # fmt: skip


def test_wait_for_job_says_the_queue_position_then_follows_the_job_to_its_end():
    q = lambda pos: QueuedJob(job_id="mine", plate_id="p", position=pos)  # noqa: E731
    other = _progress("other", "scanning", 0.4)
    follower = _ScriptedFollower([
        _status(other, [QueuedJob(job_id="first", plate_id="p", position=1), q(2)]),
        _status(other, [q(1)]),
        _status(_progress("mine", "planning")),
        _status(_progress("mine", "scanning", 0.5)),
        # the end is published, then at once overwritten by the next job's progress
        _status(_progress("next", "planning"), recent=[_progress("mine", "failed", message="boom")]),
    ])  # fmt: skip
    out = io.StringIO()
    state, message, report = asyncio.run(wait_for_job(follower, "mine", 5.0, out=out))
    assert (state, message, report) == ("failed", "boom", None)
    lines = out.getvalue().splitlines()
    assert lines[:2] == ["queued at position 2", "queued at position 1"]
    assert [line.split()[0] for line in lines[2:]] == ["planning", "scanning", "failed"]


def test_wait_for_job_ignores_an_end_it_saw_before_it_was_called():
    follower = _ScriptedFollower([
        _status(_progress("mine", "waiting_for_worker")),
        _status(None, recent=[_progress("mine", "interrupted"), _progress("mine", "done", 1.0, "report.json")]),
    ])  # fmt: skip
    follower.jobs["mine"] = _progress("mine", "interrupted")  # what it ended as before the re-analysis
    state, message, _ = asyncio.run(wait_for_job(follower, "mine", 5.0, out=io.StringIO()))
    assert (state, message) == ("done", "report.json")


def test_wait_for_job_reports_a_new_end_equal_to_the_one_it_saw_before_it_was_called():
    failed = _progress("mine", "failed", message="analysis failed: no worker")
    follower = _ScriptedFollower([
        _status(None, recent=[failed]),  # the old end, published again: not this end
        _status(_progress("mine", "waiting_for_worker")),  # the re-analysis runs ...
        _status(None, recent=[failed, failed]),  # ... and fails as the last one did
    ])  # fmt: skip
    follower.feed(_status(None, recent=[failed]))  # what the follower knew at the call
    follower.changed.clear()
    state, message, _ = asyncio.run(wait_for_job(follower, "mine", 3.0, out=io.StringIO()))
    assert (state, message) == ("failed", "analysis failed: no worker")  # timed out before
    assert follower.statuses == []


def test_a_record_whose_analysis_options_do_not_validate_is_quarantined_not_fed_to_a_reanalysis(tmp_path):
    import json

    store = JobStore(tmp_path)
    rec = store.create(_record("20260101T000002-aaaa0003", JobState.DONE))
    path = store.root / rec.job_id / "job.json"
    data = json.loads(path.read_text())
    data["analysis"] = {"template_table": [{"name": "FR7"}], "design_side": "moulded_down"}
    path.write_text(json.dumps(data))
    found = JobStore(tmp_path).recover()
    assert [r.job_id for r in found] == [rec.job_id]
    back = store.load(rec.job_id)
    assert back.state == "interrupted" and back.analysis == {}  # raw data stays re-analysable
    assert "analysis" in back.info.quarantine_reason
    assert (store.root / rec.job_id / "job.json.quarantined").exists()
