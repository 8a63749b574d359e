"""A disk full while a job's results are stored (issue 43, item 3): the worker's verdict and
results are kept and written once the disk has room, as a job record is. Before, the job went
``failed`` (the verdict the worker sent was dropped) and ``results/.cloud.ply.tmp`` stayed behind.

Simulated on a real file system: a small tmpfs mounted on the job's directory, filled but for a
few kilobytes when the report arrives, emptied of its filler to make room (skipped, saying so,
where mounting is not allowed). The daemon's real re-analysis path and hand-over; a stand-in
dispatcher delivers the worker's report and its verified result files."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import subprocess

import pytest

from cellctl.api import ControlRequest, ReportEnvelope
from cellctl.config import CellConfig, CellSection, DaemonSection
from cellctl.daemon.handover import Handover
from cellctl.daemon.service import CellDaemon
from cellctl.jobstore.jobs import JobRecord
from tests.support.waits import wait_until
from tests.support.zworker_fns import minimal_report

JOB = "20260101T000000-aaaa0043"


@contextlib.contextmanager
def tmpfs(directory, size: str):
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size},mode=0700", "tmpfs", str(directory)],
                       capture_output=True, text=True, timeout=30)  # fmt: skip
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here (needs root / CAP_SYS_ADMIN): {r.stderr.strip()}")
    try:
        yield directory
    finally:
        if subprocess.run(["umount", str(directory)], capture_output=True, timeout=30).returncode != 0:
            subprocess.run(["umount", "-l", str(directory)], capture_output=True, timeout=30)


def fill(path) -> None:
    """Write zeros to ``path`` until the file system refuses."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT, 0o600)
    try:
        while True:
            os.write(fd, b"\0" * 4096)
    except OSError:
        pass
    finally:
        os.close(fd)


class _Dispatcher:
    def __init__(self, files: dict[str, bytes]) -> None:
        self.files = files
        self.future: asyncio.Future | None = None
        self.submitted = asyncio.Event()
        self.pending: list[str] = []

    def submit(self, params, payload, **kw) -> asyncio.Future:
        self.future = asyncio.get_running_loop().create_future()
        self.submitted.set()
        return self.future

    def take_results(self, job_id: str) -> dict[str, bytes]:
        return self.files


@pytest.mark.process  # mounts a tmpfs with mount(8)
def test_a_disk_full_while_results_are_stored_keeps_the_verdict_and_writes_them_once_there_is_room(tmp_path):
    designs = tmp_path / "designs"
    designs.mkdir()
    (designs / "d.ply").write_text("ply")
    cell = CellSection(data_dir=tmp_path / "data", designs_dir=designs)
    d = CellDaemon(CellConfig(cell=cell, daemon=DaemonSection(write_html_report=False)))  # no render child
    d._unsaved.period_s = 0.2
    jd = d.store.job_dir(JOB)
    jd.mkdir(parents=True)
    files = {"results.npz": bytes(range(256)) * 800, "report.json": b"{}"}  # 200 kB: more than is left
    with tmpfs(jd, "1m"):
        rec = JobRecord(JOB, "P1", "d.ply", str(designs / "d.ply"), None, state="interrupted")
        (jd / "job.json").write_text(json.dumps(rec.as_json()))
        d.store.raw_dir(JOB).mkdir()
        (d.store.raw_dir(JOB) / "profiles.craw").write_bytes(b"")

        async def main():
            disp = _Dispatcher(files)
            d.dispatcher = disp  # type: ignore[assignment]
            d.handover = Handover(d.cfg, d.store, disp, d._job_state)  # type: ignore[arg-type]
            d.handover.results_retry_s = 0.2

            async def publish_whole(job):
                return disp.submit(None, b""), b""

            d.handover._publish_whole = publish_whole  # type: ignore[method-assign]
            await d._control("reanalyse", ControlRequest(job_id=JOB))
            await asyncio.wait_for(disp.submitted.wait(), 10)
            filler = jd / "filler"
            fill(filler)  # the disk fills up, but for a few kilobytes
            job = minimal_report(d.handover._params(d._analysing[JOB]), 10).model_copy(
                update={"verdict": "pass"}
            )
            disp.future.set_result(
                ReportEnvelope(job_id=JOB, plate_id="P1", worker_id="w1", attempt=1, ok=True, report=job)
            )
            await asyncio.gather(*d._analyses, return_exceptions=True)
            during = (sorted(p.name for p in (jd / "results").glob("*")) if (jd / "results").exists() else [],
                      d.handover.unstored, d._current.record.state, d._current.record.info)  # fmt: skip
            filler.unlink()  # room again
            await wait_until(
                lambda: not d.handover.unstored and not len(d._unsaved), 2.0, "every result stored"
            )
            return during

        during = asyncio.run(main())
        names, unstored, state, info = during
        assert names == [] and unstored == [JOB]  # nothing half-written (no .results.npz.tmp)
        assert state == "done" and info.verdict == "pass" and info.results_pending is True
        record = d.store.load(JOB)
        assert record.state == "done" and record.info.verdict == "pass"
        assert record.info.results_pending is False and record.info.report == str(
            (jd / "report.json").resolve()
        )
        assert (jd / "results" / "results.npz").read_bytes() == files["results.npz"]
        assert json.loads((jd / "report.json").read_text())["verdict"] == "pass"
        assert "results stored once the disk had room" in record.history[-1]["message"]
