"""The hand-over of a scanned job to the analysis: cloud encoded, published, report stored.

:class:`Handover` takes a scanned (or re-analysed) job: the live cloud of the scan, or the cloud
rebuilt from the raw files, is thinned and encoded off the loop, submitted to the
:class:`~cellctl.daemon.dispatch.Dispatcher` with the job parameters, kept with the job as ``cloud.bin``,
and the worker's report stored as ``report.json``. The job's states are told to the daemon through
``set_state``; any failure fails the job, it never leaves it hanging. The HTML / PDF render of the
stored report is :mod:`cellctl.daemon.render`, the line-heating plan after it :mod:`cellctl.daemon.heat_plan`.

A live scan streams its cloud instead (:meth:`Handover.open_stream`, :mod:`cellctl.daemon.stream`):
the job goes to a worker when the scan starts and the cloud follows pass by pass; after the last
profile only the last chunk is left to send. ``cloud.bin`` is then the chunks' concatenation.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from pathlib import Path
from typing import Any, Protocol

import structlog

from cellctl.acquisition.publish import PublishSettings, budget_steps, column_steps, encode_scan
from cellctl.acquisition.reassemble import reassemble
from cellctl.acquisition.spill import release
from cellctl.analysis_job import analysis_job
from cellctl.api import JobState, now_utc
from cellctl.api.cloud_codec import CloudMeta, write_concatenated
from cellctl.api.models import AnalysisOptions, ReportEnvelope
from cellctl.api.transfer import TransferError, TransferSpec
from cellctl.config import CellConfig
from cellctl.daemon.active import ActiveJob
from cellctl.daemon.dispatch import Dispatcher, JobFailed
from cellctl.daemon.heat_plan import make_heating_plan
from cellctl.daemon.render import render_report
from cellctl.daemon.result_collector import store_results
from cellctl.daemon.stream import ScanStream
from cellctl.jobstore.jobs import JobStore, JobStoreError
from cellctl.logging import bind_context

__all__ = ["Handover", "SetJobState", "render_html"]

log = structlog.get_logger(__name__)


class SetJobState(Protocol):
    """The daemon's job-state setter (store, publication, final-state bookkeeping)."""

    def __call__(self, job: ActiveJob, state: JobState, message: str = "", **info: Any) -> None: ...


class Handover:
    """Publishes scanned jobs to the analysis workers and stores their reports."""

    def __init__(
        self,
        cfg: CellConfig,
        store: JobStore,
        dispatcher: Dispatcher,
        set_state: SetJobState,
    ) -> None:
        self.cfg = cfg
        self.store = store
        self.dispatcher = dispatcher
        self._job_state = set_state
        self._streams: dict[str, ScanStream] = {}
        # results the disk refused: job id -> (job, envelope, files, report path), written later
        self._unstored: dict[str, tuple[ActiveJob, ReportEnvelope, dict[str, bytes], Path]] = {}
        self._unstored_task: asyncio.Task[None] | None = None
        self.results_retry_s = 2.0

    @property
    def unstored(self) -> list[str]:
        """Jobs whose results wait for disk space."""
        return list(self._unstored)

    def _keep_results(self, job: ActiveJob, env: ReportEnvelope, files: dict[str, bytes], path: Path) -> None:
        self._unstored[job.record.job_id] = (job, env, files, path)
        if self._unstored_task is None or self._unstored_task.done():
            self._unstored_task = asyncio.get_running_loop().create_task(
                self._store_later(), name="results-retry"
            )

    def try_now(self) -> None:
        """One last attempt for results the disk refused (shutdown); what still fails is logged
        (the job's raw data is kept: a re-analysis makes them again)."""
        for job_id, (job, env, files, report_path) in list(self._unstored.items()):
            try:
                _store_outputs(files, self.store.results_dir(job_id), report_path, env)
            except OSError as exc:
                log.error("results_not_stored", job_id=job_id, error=str(exc))
                continue
            del self._unstored[job_id]
            job.record.info = job.record.info.updated(report=str(report_path), results_pending=False)
            with contextlib.suppress(JobStoreError):  # else the daemon's record retry writes it
                self.store.save(job.record)
        if self._unstored_task is not None:
            self._unstored_task.cancel()

    async def _store_later(self) -> None:
        """Write the kept results every ``results_retry_s`` until the disk takes them; the job's
        record then names its report (``results_pending`` false)."""
        while self._unstored:
            await asyncio.sleep(self.results_retry_s)
            for job_id, (job, env, files, report_path) in list(self._unstored.items()):
                try:
                    await asyncio.to_thread(
                        _store_outputs, files, self.store.results_dir(job_id), report_path, env
                    )
                except OSError as exc:
                    log.warning("results_write_retry_failed", job_id=job_id, error=str(exc))
                    continue
                del self._unstored[job_id]
                rec = job.record
                rec.info = rec.info.updated(
                    report=str(report_path), results_pending=False, results_stored_utc_s=time.time()
                )
                rec.history.append({"state": rec.state, "t_utc": now_utc(),
                                    "message": f"results stored once the disk had room: {report_path}"})  # fmt: skip
                try:
                    self.store.save(rec)
                except JobStoreError as exc:  # the results are on disk; the record's retry is the daemon's
                    log.warning("job_record_write_failed", job_id=job_id, error=str(exc))
                log.info("results_stored_late", job_id=job_id, bytes=sum(map(len, files.values())))
                with contextlib.suppress(Exception):
                    await self._after_report(job)

    def _params(self, job: ActiveJob) -> Any:
        rec = job.record
        return analysis_job(
            self.cfg, job_id=rec.job_id, plate_id=rec.plate_id, design=rec.design_path,
            placement=rec.placement, out_dir=self.store.results_dir(rec.job_id).resolve(),
            analysis=AnalysisOptions.model_validate(rec.analysis),
            placement_found=rec.info.placement_found,
        )  # fmt: skip

    def _meta(self, job: ActiveJob) -> CloudMeta:
        return CloudMeta(cell_id=self.cfg.cell.id, placement=job.record.placement)

    @staticmethod
    def _first_edge(job: ActiveJob) -> int | None:
        # The plan puts the raster passes first and the edge passes after them (pass ids index
        # plan.passes), so the plan's raster count is the first edge pass.
        plan = job.record.info.plan
        return None if plan is None else plan.passes

    @staticmethod
    def _last_pass(job: ActiveJob) -> int | None:
        # the edge passes follow the raster passes: the last pass id is their count less one
        plan = job.record.info.plan
        if plan is None or plan.passes is None:
            return None
        return plan.passes + (plan.edge_passes or 0) - 1

    async def open_stream(self, job: ActiveJob) -> ScanStream:
        """A streamed analysis for the scan about to start (planned: the plan is in the record): the
        job goes to a worker now, :class:`ScanStream` sends the cloud pass by pass."""
        rec = job.record
        transfer = TransferSpec(
            design=await asyncio.to_thread(self.dispatcher.designs.register, Path(rec.design_path))
        )
        fut = self.dispatcher.submit_stream(self._params(job), transfer=transfer)
        stream = ScanStream(
            self.dispatcher, fut, job_id=rec.job_id, plate_id=rec.plate_id,
            settings=PublishSettings.from_config(self.cfg), first_edge_pass=self._first_edge(job),
            meta=self._meta(job), last_pass=self._last_pass(job),
            on_abandon=lambda: self._streams.pop(rec.job_id, None),
        )  # fmt: skip
        self._streams[rec.job_id] = stream
        return stream

    async def _publish_whole(self, job: ActiveJob) -> tuple[Any, bytearray]:
        """The whole cloud thinned, encoded and submitted (a re-analysis, a scan not streamed)."""
        rec = job.record
        t0 = time.perf_counter()
        scan_cloud = job.cloud
        job.cloud = None
        if scan_cloud is None:  # re-analysis: whole-scan clock fits from the raw files
            scan_cloud = (await asyncio.to_thread(reassemble, self.store.raw_dir(rec.job_id))).cloud
        steps = column_steps(scan_cloud.pass_id, self._first_edge(job), PublishSettings.from_config(self.cfg))
        steps = budget_steps(steps, scan_cloud.valid_per_profile(), self.cfg.scan.publish_max_points)
        # thinned and encoded in one pass off the loop: the only copy of the points is the payload
        payload, job.points = await asyncio.to_thread(
            encode_scan, scan_cloud, job_id=rec.job_id, plate_id=rec.plate_id, column_step=steps,
            meta=self._meta(job),
        )  # fmt: skip
        del scan_cloud, steps
        assemble_s = time.perf_counter() - t0
        # waiting for a worker until the dispatcher assigns the job (the daemon's on_assigned
        # hook then says analysing): with no worker present the job says so (docs/operations.md)
        self._job_state(
            job, JobState.WAITING_FOR_WORKER, "cloud published", points=job.points,
            cloud_bytes=len(payload), assemble_s=round(assemble_s, 3), published_utc_s=time.time(),
        )  # fmt: skip
        # nothing shared but Zenoh: the design goes by hash, the results come back as bytes
        transfer = TransferSpec(
            design=await asyncio.to_thread(self.dispatcher.designs.register, Path(rec.design_path))
        )
        return self.dispatcher.submit(self._params(job), payload, transfer=transfer), payload

    async def analyse(self, job: ActiveJob) -> None:
        """Publish the cloud to the workers and store the report; any failure fails the job (logged),
        it never leaves the job hanging."""
        try:
            await self._analyse_inner(job)
        except asyncio.CancelledError:
            raise
        except Exception as exc:
            log.exception("job_analysis_failed", job_id=job.record.job_id)
            self._job_state(job, JobState.FAILED, f"{type(exc).__name__}: {exc}")

    async def _analyse_inner(self, job: ActiveJob) -> None:
        rec = job.record
        bind_context(job_id=rec.job_id)
        job.fraction = 0.0
        stream = self._streams.pop(rec.job_id, None)
        if stream is not None and not stream.finished:  # the scan did not end the stream: whole cloud
            await stream.abandon("the scan did not complete the stream")
            stream = None
        if stream is None:
            self._job_state(job, JobState.WAITING_FOR_WORKER, "cloud being assembled")
        try:
            if stream is not None:
                job.cloud = None
                job.points = stream.points
                payloads, stream.payloads = stream.payloads, []
                worker_id = _streamed_worker(self.dispatcher, rec.job_id, stream.future)
                job.worker_id = worker_id
                self._job_state(
                    job, JobState.ANALYSING if worker_id else JobState.WAITING_FOR_WORKER,
                    f"cloud streamed in {stream.chunks} chunks" + (f", analysing on {worker_id}" if worker_id else ""),
                    points=stream.points, cloud_bytes=stream.bytes, stream_chunks=stream.chunks,
                    assemble_s=round(stream.encode_s, 3), published_utc_s=time.time(),
                )  # fmt: skip
                fut = stream.future
                payload: Any = None
            else:
                fut, payload = await self._publish_whole(job)
                payloads = None
            # the published bytes, kept with the job (cellctl.api.cloud_codec layout); written while the
            # worker analyses, and on disk before the job is done
            cloud_path = self.store.job_dir(rec.job_id) / "cloud.bin"
            written = asyncio.ensure_future(asyncio.to_thread(_write_cloud, cloud_path, payload, payloads))
            del payload, payloads
            try:
                env = await fut
            finally:
                await asyncio.shield(written)
        except asyncio.CancelledError:
            if job.stop_reason == "abort":  # control/abort with its job id (service._abort_analysis)
                self._job_state(job, JobState.ABORTED, "analysis aborted by the operator; raw data kept")
            else:
                self._job_state(
                    job, JobState.INTERRUPTED, "the daemon stopped during the analysis; raw data kept"
                )
            raise
        except JobFailed as exc:
            if job.stop_reason == "abort":
                self._job_state(job, JobState.ABORTED, "analysis aborted by the operator; raw data kept")
                return
            self._job_state(job, JobState.FAILED, f"analysis failed: {exc.reason}")
            return
        except TransferError as exc:
            self._job_state(job, JobState.FAILED, f"design cannot be served: {exc}; raw data kept")
            return
        except Exception as exc:
            log.exception("job_analysis_failed")
            self._job_state(job, JobState.FAILED, f"{type(exc).__name__}: {exc}")
            return
        job.worker_id = env.worker_id
        jd = self.store.job_dir(rec.job_id)
        if not env.ok or env.report is None:
            self._job_state(job, JobState.FAILED, f"analysis error: {env.error}", worker_id=env.worker_id)
            return
        files = self.dispatcher.take_results(rec.job_id)
        report_path = (jd / "report.json").resolve()
        job.fraction = 1.0
        nbytes = sum(map(len, files.values()))
        try:  # the worker's results directory, verified, and report.json: on disk before the job is done
            await asyncio.to_thread(
                _store_outputs, files, self.store.results_dir(rec.job_id), report_path, env
            )
        except OSError as exc:
            # A full (or read-only) disk: the worker's verdict and results are kept here and written
            # once the disk takes them (as a job record is, RecordRetry); the job is done meanwhile.
            log.error("results_write_failed", job_id=rec.job_id, bytes=nbytes, error=str(exc))
            self._job_state(
                job, JobState.DONE, f"verdict {env.report.verdict}; results ({nbytes} bytes) wait for disk "
                f"space: {exc.strerror or exc}", verdict=env.report.verdict, report=None, results_pending=True,
                worker_id=env.worker_id, analysis_timings_s=env.timings_s, report_utc_s=time.time(),
                results_bytes=nbytes,
            )  # fmt: skip
            self._keep_results(job, env, files, report_path)
            return
        # The JSON report (per-line verdicts) completes the job; the HTML / PDF render and the
        # heating plan follow.
        self._job_state(
            job, JobState.DONE, str(report_path), verdict=env.report.verdict,
            report=str(report_path), worker_id=env.worker_id, analysis_timings_s=env.timings_s,
            report_utc_s=time.time(), results_bytes=nbytes,
        )  # fmt: skip
        await self._after_report(job)

    async def _after_report(self, job: ActiveJob) -> None:
        """What follows a done job's report.json, each in a child process: the HTML / PDF render
        (``[daemon] write_html_report``), then the line-heating plan (:mod:`.heat_plan`; the plan
        never delays the report nor the HTML, and a failed one is only its file's reason)."""
        if not (self.store.results_dir(job.record.job_id) / "report.json").exists():
            return
        if self.cfg.daemon.write_html_report:
            await render_html(self.store, job)
        planned = await make_heating_plan(self.cfg, self.store, job)
        if planned and self.cfg.daemon.write_html_report:
            # report.html / .pdf again, now with the plan drawn over the deviation map (the first
            # render's time after the last profile stays the report's figure)
            await render_html(self.store, job, with_plan=True)


def _streamed_worker(dispatcher: Dispatcher, job_id: str, fut: asyncio.Future[ReportEnvelope]) -> str | None:
    """The worker analysing a streamed job: the dispatcher's holder while the job is pending, the
    reporting worker once it has reported (a fast analysis can end before the handover looks)."""
    if job_id in dispatcher.pending:
        return dispatcher.assignment(job_id)[0]
    if fut.done() and not fut.cancelled() and fut.exception() is None:
        return fut.result().worker_id
    return None


def _store_outputs(
    files: dict[str, bytes], results_dir: Path, report_path: Path, env: ReportEnvelope
) -> None:
    """The verified result bundle into the results directory, then ``report.json`` beside it
    (written atomically: a failure leaves no partial file); OSError when the disk refuses."""
    if files:
        store_results(files, results_dir)
        log.info("results_stored", results=str(results_dir), files=sorted(files),
                 bytes=sum(map(len, files.values())))  # fmt: skip
    assert env.report is not None
    tmp = report_path.with_name(f".{report_path.name}.tmp")
    try:
        tmp.write_text(env.report.model_dump_json(indent=2), encoding="utf-8")
        tmp.replace(report_path)
    except OSError:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def _write_cloud(
    path: Path, payload: bytes | bytearray | None, chunks: list[bytes | bytearray | memoryview] | None
) -> None:
    """cloud.bin: the published bytes, or a streamed job's chunks as one cloud (written from the
    chunks, not built in memory first: it runs beside the analysis)."""
    if payload is not None:
        path.write_bytes(payload)
    else:
        write_concatenated(path, chunks or [], read=release)  # spilled chunks: their pages released


async def render_html(store: JobStore, job: ActiveJob, *, with_plan: bool = False) -> None:
    """Render report.html / .pdf of a done job in a child process (:mod:`.render`); record where
    and when in the job. ``with_plan``: the render again once the heating plan is beside the report
    (its time as ``html_with_plan_s``; the first render's times stay the report's)."""
    rec = job.record
    results = store.results_dir(rec.job_id).resolve()
    out = await render_report(results)
    info: dict[str, Any] = {"html_with_plan_s" if with_plan else "html_s": round(out.elapsed_s, 3)}
    if out.html is not None:
        info["report_html"] = str(results / Path(out.html).name)
        last = rec.info.last_profile_utc_s
        if last is not None and not with_plan:
            info["html_after_last_profile_s"] = round(time.time() - last, 3)
    rec.info = rec.info.updated(**info)
    try:
        store.save(rec)
    except JobStoreError as exc:  # the job is done with its report.json; only the render's note is lost
        log.warning("job_record_write_failed", job_id=rec.job_id, error=str(exc))
    log.info("html_report_written", job_id=rec.job_id, **info)
    if out.stopped:
        raise asyncio.CancelledError
