"""Actions carry their person (issue 43, item 5): the daemon's trigger and control handlers record
``requested_by`` in the job's history and append every action, taken or refused, to the audit log
``<data_dir>/audit.jsonl``. The daemon's real handlers, a query object standing in for Zenoh's (no
cell), the job held by a stand-in executor."""

from __future__ import annotations

import asyncio
import json

from cellctl.api import CellState, JobState, TriggerRequest
from cellctl.config import CellConfig, CellSection
from cellctl.daemon.active import ActiveJob
from cellctl.daemon.service import CellDaemon
from cellctl.jobstore.jobs import JobRecord


class _Payload:
    def __init__(self, data: bytes) -> None:
        self.data = data

    def __len__(self) -> int:
        return len(self.data)

    def to_bytes(self) -> bytes:
        return self.data


class _Query:
    """What the control handler uses of a zenoh.Query."""

    key_expr = "cell/t/control/x"

    def __init__(self, body: dict) -> None:
        self.payload = _Payload(json.dumps(body).encode())
        self.replies: list[bytes] = []
        self.errors: list[bytes] = []

    def reply(self, key, data, **kw) -> None:
        self.replies.append(data)

    def reply_err(self, data, **kw) -> None:
        self.errors.append(data)


class _Executor:
    def pause(self) -> None: ...

    def resume(self) -> None: ...

    def abort(self) -> None: ...


def _daemon(tmp_path) -> tuple[CellDaemon, ActiveJob]:
    (tmp_path / "designs").mkdir()
    (tmp_path / "designs" / "d.ply").write_text("ply")
    d = CellDaemon(CellConfig(cell=CellSection(data_dir=tmp_path / "data", designs_dir=tmp_path / "designs")))
    for state in (CellState.IDLE, CellState.PLANNING, CellState.SCANNING):
        d.sm.to(state)
    rec = JobRecord("20260101T000000-aaaa0005", "P1", "d.ply", str(tmp_path / "designs" / "d.ply"), None)
    d.store.create(rec)
    d.store.set_state(rec, JobState.SCANNING)
    job = ActiveJob(rec)
    job.executor = _Executor()  # type: ignore[assignment]
    d._scan_job = d._current = job
    return d, job


def _audit(d: CellDaemon) -> list[dict]:
    return [json.loads(ln) for ln in (d.cfg.cell.data_dir / "audit.jsonl").read_text().splitlines()]


def test_a_control_names_its_person_in_the_job_history_and_the_audit_log_refusals_too(tmp_path):
    d, job = _daemon(tmp_path)
    job_id = job.record.job_id

    async def main():
        pause = _Query({"job_id": job_id, "requested_by": "olga"})
        await d._control_handler("pause")(pause)
        abort = _Query({"requested_by": "erin"})
        await d._control_handler("abort")(abort)
        late = _Query({"requested_by": "olga"})
        await d._control_handler("resume")(late)  # refused: the job is being aborted
        return pause, abort, late

    pause, abort, late = asyncio.run(main())
    assert pause.replies and abort.replies and late.errors
    history = d.store.load(job_id).history
    assert [(h["message"], h["by"]) for h in history if "by" in h] == [
        ("pause by olga", "olga"),
        ("abort by erin", "erin"),
    ]
    lines = _audit(d)
    assert [(e["user"], e["action"], e["job_id"], e["outcome"]) for e in lines] == [
        ("olga", "pause", job_id, "paused"),
        ("erin", "abort", job_id, "scanning"),
        ("olga", "resume", None, "refused: not_allowed"),
    ]
    assert all(e["zenoh_identity"] is None and e["t_utc"] for e in lines)
    assert (d.cfg.cell.data_dir / "audit.jsonl").stat().st_mode & 0o077 == 0


def test_a_trigger_names_its_person_in_the_new_job_and_the_audit_log(tmp_path):
    d, _ = _daemon(tmp_path)  # a scan holds the robot: the trigger is queued

    async def main():
        req = TriggerRequest(plate_id="P2", design="d.ply", requested_by="olga")
        return await d._accept(req, tmp_path / "designs" / "d.ply")

    accepted = asyncio.run(main())
    assert accepted.state == "queued"
    first = d.store.load(accepted.job_id).history[0]
    assert (first["message"], first["by"]) == ("triggered by olga", "olga")
    assert [(e["user"], e["action"], e["job_id"], e["outcome"]) for e in _audit(d)] == [
        ("olga", "trigger", accepted.job_id, "queued")
    ]
