"""A running re-analysis can be aborted with control/abort and its job id (issue 43, item 6): the
worker holding it is told to stop, the job ends ``aborted`` with its raw data, and it can be
re-analysed again. The daemon's real control handler and hand-over; the dispatcher is a stand-in
that holds the job as a worker would (no cell, no Zenoh)."""

from __future__ import annotations

import asyncio
import json

from cellctl.api import ControlRequest, JobState
from cellctl.config import CellConfig, CellSection
from cellctl.daemon.dispatch import JobFailed
from cellctl.daemon.handover import Handover
from cellctl.daemon.service import CellDaemon
from cellctl.jobstore.jobs import JobRecord


class _Dispatcher:
    """Holds each submitted job until it is abandoned (the worker analysing it, for ever)."""

    def __init__(self) -> None:
        self.futures: dict[str, asyncio.Future] = {}
        self.abandoned: list[tuple[str, str]] = []
        self.submitted = asyncio.Event()

    @property
    def pending(self) -> list[str]:
        return [j for j, f in self.futures.items() if not f.done()]

    def submit(self, params, payload, **kw) -> asyncio.Future:
        fut = self.futures[params.job_id] = asyncio.get_running_loop().create_future()
        self.submitted.set()
        return fut

    def abandon(self, job_id: str, reason: str) -> None:
        self.abandoned.append((job_id, reason))
        self.futures[job_id].set_exception(JobFailed(job_id, reason))


def test_a_running_reanalysis_is_aborted_by_its_job_id_and_can_be_reanalysed_again(tmp_path):
    designs = tmp_path / "designs"
    designs.mkdir()
    (designs / "d.ply").write_text("ply")
    d = CellDaemon(CellConfig(cell=CellSection(data_dir=tmp_path / "data", designs_dir=designs)))
    job_id = "20260101T000000-aaaa0042"
    rec = JobRecord(job_id, "P1", "d.ply", str(designs / "d.ply"), None, state="interrupted")
    d.store.raw_dir(job_id).mkdir(parents=True)
    (d.store.raw_dir(job_id) / "profiles.craw").write_bytes(b"")
    (d.store.job_dir(job_id) / "job.json").write_text(json.dumps(rec.as_json()))

    async def main():
        disp = _Dispatcher()
        d.dispatcher = disp  # type: ignore[assignment]
        d.handover = Handover(d.cfg, d.store, disp, d._job_state)  # type: ignore[arg-type]

        async def publish_whole(job):  # the cloud rebuilt from the raw files, submitted
            return disp.submit(d.handover._params(job), b""), b""

        d.handover._publish_whole = publish_whole  # type: ignore[method-assign]
        first = await d._control("reanalyse", ControlRequest(job_id=job_id))
        await asyncio.wait_for(disp.submitted.wait(), 10)
        task = d._analysis_tasks[job_id]
        reply = await d._control("abort", ControlRequest(job_id=job_id))  # refused before: "not scanning"
        await asyncio.gather(task, return_exceptions=True)
        again = await d._control("reanalyse", ControlRequest(job_id=job_id))
        d._analysis_tasks[job_id].cancel()
        return first, reply, disp.abandoned, again

    first, reply, abandoned, again = asyncio.run(main())
    assert first.job_state == "waiting_for_worker"
    assert (reply.action, reply.job_id, reply.job_state) == ("abort", job_id, "aborted")
    assert abandoned == [(job_id, "aborted by the operator")]  # the worker is told to stop
    record = d.store.load(job_id)
    aborted = [h for h in record.history if h["state"] == JobState.ABORTED.value]
    assert aborted and aborted[0]["message"] == "analysis aborted by the operator; raw data kept"
    assert again.job_state == "waiting_for_worker"  # an aborted re-analysis can be run again
