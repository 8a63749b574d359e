"""The control replies of the daemon (issue 43): a pause answers the state the job goes to, a resume
or pause of a job being aborted is refused with its reason (no cell: the daemon's control handler
with a stand-in executor)."""

from __future__ import annotations

import asyncio
import json

import pytest

from cellctl.api import CellState, ControlError, ControlRequest, JobState
from cellctl.config import CellConfig, CellSection
from cellctl.daemon.active import ActiveJob
from cellctl.daemon.service import CellDaemon
from cellctl.jobstore.jobs import JobRecord


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


def _daemon_with_raw_job(tmp_path, job_json: str) -> tuple[CellDaemon, str]:
    (tmp_path / "designs").mkdir()
    d = CellDaemon(CellConfig(cell=CellSection(data_dir=tmp_path / "data", designs_dir=tmp_path / "designs")))
    job_id = "20260101T000000-aaaa0009"
    raw = d.store.raw_dir(job_id)
    raw.mkdir(parents=True)
    (raw / "profiles.craw").write_bytes(b"")
    (d.store.job_dir(job_id) / "job.json").write_text(job_json)
    return d, job_id


def test_reanalysis_of_a_quarantined_record_without_a_design_is_refused_with_the_reason(tmp_path):
    d, job_id = _daemon_with_raw_job(tmp_path, "{broken")
    with pytest.raises(ControlError) as err:  # accepted before; the worker then failed on "design ."
        asyncio.run(d._control("reanalyse", ControlRequest(job_id=job_id)))
    assert err.value.code == "not_allowed"
    assert "names no design" in err.value.message and "quarantined" in err.value.message
    assert "cellctl reassemble" in err.value.message
    assert (d.store.job_dir(job_id) / "job.json.quarantined").read_text() == "{broken"


def test_reanalysis_of_a_record_whose_design_is_outside_designs_dir_is_refused(tmp_path):
    rec = JobRecord("20260101T000000-aaaa0009", "p", "x.ply", "/etc/passwd", None, state="interrupted")
    d, job_id = _daemon_with_raw_job(tmp_path, json.dumps(rec.as_json()))
    with pytest.raises(ControlError, match="not in designs_dir"):
        asyncio.run(d._control("reanalyse", ControlRequest(job_id=job_id)))
