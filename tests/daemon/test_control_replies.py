"""The control replies of the daemon (issue 43): a pause answers the state the job goes to, a resume
or pause of a job being aborted is refused with its reason (no cell: the daemon's control handler
with a stand-in executor)."""

from __future__ import annotations

import asyncio

import pytest

from cellctl.api import CellState, ControlError, ControlRequest, JobState
from cellctl.config import CellConfig, CellSection
from cellctl.daemon.jobs import ActiveJob, JobRecord
from cellctl.daemon.service import CellDaemon


class _Executor:
    def __init__(self) -> None:
        self.requests: list[str] = []

    def pause(self) -> None:
        self.requests.append("pause")

    def resume(self) -> None:
        self.requests.append("resume")

    def abort(self) -> None:
        self.requests.append("abort")


def _scanning_daemon(tmp_path) -> tuple[CellDaemon, ActiveJob]:
    d = CellDaemon(CellConfig(cell=CellSection(data_dir=tmp_path / "data", designs_dir=tmp_path)))
    for state in (CellState.IDLE, CellState.PLANNING, CellState.SCANNING):
        d.sm.to(state)
    rec = JobRecord("20260101T000000-aaaa0001", "p", "d.ply", str(tmp_path / "d.ply"), None)
    d.store.create(rec)
    d.store.set_state(rec, JobState.SCANNING)
    job = ActiveJob(rec)
    job.executor = _Executor()  # type: ignore[assignment]
    d._scan_job = d._current = job
    return d, job


def test_pause_answers_paused_not_the_state_it_found(tmp_path):
    d, job = _scanning_daemon(tmp_path)
    reply = asyncio.run(d._control("pause", ControlRequest()))
    assert (reply.state, reply.job_state) == ("paused", "paused")  # was "scanning", "scanning"
    assert job.executor.requests == ["pause"]
    reply = asyncio.run(d._control("resume", ControlRequest(job_id=job.record.job_id)))
    assert (reply.state, reply.job_state) == ("scanning", "scanning")


@pytest.mark.parametrize("action", ["resume", "pause"])
def test_resume_or_pause_after_abort_is_refused_with_its_reason(tmp_path, action):
    d, job = _scanning_daemon(tmp_path)
    asyncio.run(d._control("abort", ControlRequest()))
    with pytest.raises(ControlError) as err:  # answered OK before, and did nothing
        asyncio.run(d._control(action, ControlRequest()))
    assert err.value.code == "not_allowed" and "being aborted" in err.value.message
    assert job.executor.requests == ["abort"]
    again = asyncio.run(d._control("abort", ControlRequest()))  # a second abort is harmless
    assert again.job_id == job.record.job_id
