"""The worker's Zenoh service (`cellctl worker`): :class:`Worker` serves jobs from one or more cells
over an open session, :func:`run_worker` opens the session and runs it until stopped."""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import os
import shutil
import socket
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import structlog
import zenoh

from analysis.contracts.job import AnalysisJob
from cellctl.api import (
    JobEvent,
    JobSpec,
    Keys,
    ReportEnvelope,
    WorkerAnnouncement,
    default_worker_id,
    now_utc,
)
from cellctl.api.models import StreamChunk, StreamEnd
from cellctl.api.proof import chunk_mac, sign
from cellctl.api.session import (
    ZenohSetupError,
    async_get,
    build_zenoh_config,
    close_session,
    declare_async_queryable,
    open_session,
    subscribe,
)
from cellctl.api.transfer import ResultChunk, ResultManifest, TransferError, pack_results
from cellctl.worker.child import AnalysisLoadError, ChildAnswer
from cellctl.worker.design_cache import cache_design, cached_design
from cellctl.worker.process import AnalysisCrashed, AnalysisProcess
from cellctl.worker.settings import WorkerSettings
from drivers.runtime import RateLimitedLog, stop_on_signals

log = structlog.get_logger(__name__)


@dataclass
class _StreamInbox:
    """The chunks of the streamed job this worker holds, as they arrive (any order, duplicates)."""

    job_id: str
    attempt: int
    chunks: dict[int, tuple[StreamChunk, bytes]] = field(default_factory=dict)
    end: StreamEnd | None = None
    next_seq: int = 0
    points: int = 0
    duplicates: int = 0
    corrupt: int = 0
    # set when the daemon that streams this job is gone (its liveliness token ended) before the end
    daemon_gone: bool = False
    wake: asyncio.Event = field(default_factory=asyncio.Event)


class Worker:
    """Serves analysis jobs over an open session, for one cell (``keys``) and every cell of ``cells``
    (key prefixes, or key expressions of prefixes such as ``cell/*``: each cell whose daemon is
    alive under it is served from the moment it appears). One job at a time, whichever cell it is
    from; when several cells wait (a cell's job offered while busy), the next free slot goes to
    the cell passed over longest (for ``fair_hold_s``), so no cell is starved by a busier one.
    Use :meth:`serve` until ``stop`` is set."""

    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys | None,
        settings: WorkerSettings,
        runner: AnalysisProcess | None = None,
        cells: list[str] | tuple[str, ...] = (),
    ) -> None:
        self.session = session
        self.keys = keys
        self.cells = tuple(cells)
        self.settings = settings
        self.worker_id = settings.worker_id or default_worker_id()
        self.runner = runner or AnalysisProcess.from_settings(settings)
        self.jobs_done = 0
        self.malformed = RateLimitedLog(log, interval_s=5.0)
        self._current: JobSpec | None = None
        self._current_cell: str | None = None
        self._stream: _StreamInbox | None = None
        self._restarting: asyncio.Task[None] | None = None
        self._served: dict[str, Keys] = {}
        self._entities: list[Any] = []
        # cells whose offer was turned down while busy (prefix -> when first), and since when idle
        self._passed_over: dict[str, float] = {}
        self._idle_since = time.monotonic()
        self._task: asyncio.Task[None] | None = None
        self._started_utc = now_utc()
        self._stopping = False

    def announcement(self) -> WorkerAnnouncement:
        return WorkerAnnouncement(
            worker_id=self.worker_id,
            host=socket.gethostname(),
            pid=os.getpid(),
            analysis=self.settings.analysis,
            started_utc=self._started_utc,
            busy_job=self._current.job_id if self._current else None,
            jobs_done=self.jobs_done,
        )

    def _event(self, keys: Keys, spec: JobSpec, event: str, message: str = "") -> None:
        ev = JobEvent(
            job_id=spec.job_id,
            worker_id=self.worker_id,
            attempt=spec.attempt,
            event=event,  # type: ignore[arg-type]
            message=message,
            t_utc=now_utc(),
            offer_id=spec.offer_id,
        )
        payload = ev.to_json()
        self.session.put(
            keys.job_event(spec.job_id), payload, encoding="application/json", attachment=_mac(spec, payload)
        )

    async def serve(self, stop: asyncio.Event) -> None:
        """Start the analysis child, declare the worker's entities, serve until ``stop``; undeclare all."""
        if not self.runner.running:
            await self.runner.start()
        entities = self._entities
        try:
            if self.keys is not None:
                self._serve_cell(self.keys.prefix)
            for cell in self.cells:
                if "*" in cell:  # a key expression: serve each cell whose daemon is alive under it
                    entities.append(
                        subscribe(self.session, f"{cell}/alive/daemon", self._on_daemon, liveliness=True)
                    )
                else:
                    self._serve_cell(cell)
            log.info("worker_ready", worker_id=self.worker_id, analysis=self.settings.analysis,
                     cells=sorted(self._served), patterns=[c for c in self.cells if "*" in c])  # fmt: skip
            await stop.wait()
        finally:
            self._stopping = True
            if self._task is not None:
                self._task.cancel()
                with contextlib.suppress(BaseException):
                    await self._task
            for ent in reversed(entities):
                with contextlib.suppress(Exception):
                    ent.undeclare()
            self.runner.kill()
            log.info("worker_stopped", worker_id=self.worker_id, jobs_done=self.jobs_done)

    def _serve_cell(self, prefix: str) -> None:
        """Declare this worker's entities in one cell (once)."""
        if prefix in self._served:
            return
        keys = self._served[prefix] = Keys(prefix)
        wid, ents = self.worker_id, self._entities
        ents.append(subscribe(self.session, keys.worker_job(wid), lambda s: self._on_job(keys, s)))
        ents.append(subscribe(self.session, keys.worker_cancel(wid), self._on_cancel))
        ents.append(subscribe(self.session, keys.worker_stream(wid), self._on_stream))
        ents.append(
            declare_async_queryable(self.session, keys.worker_info(wid), lambda q: self._on_info(keys, q))
        )
        ents.append(
            subscribe(
                self.session, keys.daemon_alive, lambda s: self._on_daemon_token(keys, s), liveliness=True
            )
        )
        # The token comes last: once the dispatcher sees it, the job subscriber already exists.
        ents.append(self.session.liveliness().declare_token(keys.worker_alive(wid)))
        log.info("worker_serves_cell", worker_id=wid, prefix=prefix)

    def _on_daemon(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            key = str(sample.key_expr)
            self._serve_cell(key[: -len("/alive/daemon")])

    def _on_daemon_token(self, keys: Keys, sample: zenoh.Sample) -> None:
        """The daemon of a served cell went away (killed, its link down): a stream it was sending to
        this worker can never end, so the attempt is given up now rather than after ``stream_idle_s``
        (a restarted daemon's re-analysis of the same job would find this worker busy with it)."""
        inbox = self._stream
        if sample.kind != zenoh.SampleKind.DELETE or inbox is None or inbox.end is not None:
            return
        if self._current_cell != keys.prefix:
            return
        log.warning("stream_daemon_gone", job_id=inbox.job_id, attempt=inbox.attempt, cell=keys.prefix)
        inbox.daemon_gone = True
        inbox.wake.set()

    async def _on_info(self, keys: Keys, query: zenoh.Query) -> None:
        # Reply on our own key, not the (possibly wildcard) query key: replies on one key are
        # consolidated into one, and every worker must be heard.
        query.reply(
            keys.worker_info(self.worker_id), self.announcement().to_json(), encoding="application/json"
        )

    def _turn_down(self, keys: Keys, spec: JobSpec) -> str | None:
        """Why this offer is turned down (busy, or the slot is held for a cell passed over), or None."""
        now = time.monotonic()
        if self._current is not None:
            if keys.prefix != self._current_cell:
                self._passed_over.setdefault(keys.prefix, now)
            return f"busy with {self._current.job_id}"
        if now - self._idle_since >= self.settings.fair_hold_s:
            return None  # the held cell did not come back in time: first come, first served
        waiting = {p: t for p, t in self._passed_over.items() if p in self._served}
        first = min(waiting, key=waiting.__getitem__) if waiting else keys.prefix
        if first == keys.prefix:
            return None
        self._passed_over.setdefault(keys.prefix, now)
        return f"next slot held for {first}"

    def _on_job(self, keys: Keys, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            if sample.attachment is None:
                raise ValueError("no JobSpec attachment")
            spec = JobSpec.model_validate_json(sample.attachment.to_bytes())
            if spec.job_id != Keys.last_chunk(key):
                raise ValueError(f"attachment job_id {spec.job_id!r} does not match the key")
        except ValueError as exc:
            self.malformed.warning("job_message_malformed", key=key, error=str(exc)[:300])
            return
        cur, task = self._current, self._task
        if cur is not None and (cur.job_id, cur.attempt, cur.offer_id) == (
            spec.job_id,
            spec.attempt,
            spec.offer_id,
        ):
            return  # the same offer again
        # Another offer of the job held: the dispatcher took this streamed job back (a link cut, its
        # cancel lost) and offers it again, or a restarted daemon offers it afresh (the same attempt
        # number, another offer): the old attempt's stream will never end, its daemon is not there
        # to take its report, so it makes way for the new one.
        again = cur is not None and cur.job_id == spec.job_id
        newer = again and (
            (cur.stream and spec.attempt > cur.attempt)
            or (spec.attempt == cur.attempt and spec.offer_id != cur.offer_id)
        )
        if newer and task:
            log.info(
                "job_superseded", job_id=spec.job_id, attempt=cur.attempt, by_attempt=spec.attempt,
                by_offer=spec.offer_id,
            )  # fmt: skip
            task.cancel()

            async def take_over() -> None:
                with contextlib.suppress(BaseException):
                    await task
                self._on_job(keys, sample)

            asyncio.get_running_loop().create_task(take_over())
            return
        why = self._turn_down(keys, spec)
        if why is not None:
            log.info("job_turned_down", job_id=spec.job_id, cell=keys.prefix, reason=why)
            self._event(keys, spec, "rejected", why)
            return
        self._passed_over.pop(keys.prefix, None)
        self._current, self._current_cell = spec, keys.prefix
        # the inbox exists before "accepted" goes out: the dispatcher streams only after it
        self._stream = _StreamInbox(spec.job_id, spec.attempt) if spec.stream else None
        self._event(keys, spec, "accepted")
        self._task = asyncio.get_running_loop().create_task(self._run(keys, spec, sample))

    def _on_stream(self, sample: zenoh.Sample) -> None:
        """A chunk or the end of the streamed job held: kept once, checked against its checksum;
        anything for another job or attempt is ignored."""
        key = str(sample.key_expr)
        job_id, attempt, last = key.rsplit("/", 3)[-3:]
        inbox = self._stream
        if inbox is None or job_id != inbox.job_id or attempt != str(inbox.attempt):
            log.debug("stream_message_ignored", key=key)
            return
        try:
            if last == "end":
                end = StreamEnd.model_validate_json(sample.payload.to_bytes())
                if end.job_id != inbox.job_id or end.attempt != inbox.attempt:
                    raise ValueError("StreamEnd does not match the key")
                inbox.end = end
            else:
                if sample.attachment is None:
                    raise ValueError("no StreamChunk attachment")
                head = StreamChunk.model_validate_json(sample.attachment.to_bytes())
                if (head.job_id, str(head.attempt), str(head.seq)) != (job_id, attempt, last):
                    raise ValueError("StreamChunk attachment does not match the key")
                if head.seq < inbox.next_seq or head.seq in inbox.chunks:
                    inbox.duplicates += 1
                    return
                data = sample.payload.to_bytes()
                if hashlib.sha256(data).hexdigest() != head.sha256:
                    inbox.corrupt += 1
                    log.warning("stream_chunk_corrupt", job_id=job_id, seq=head.seq, bytes=len(data))
                    return
                inbox.chunks[head.seq] = (head, data)
        except ValueError as exc:
            self.malformed.warning("stream_message_malformed", key=key, error=str(exc)[:300])
            return
        inbox.wake.set()

    async def _run_stream(self, keys: Keys, spec: JobSpec, job: AnalysisJob) -> ChildAnswer:
        """A streamed job: the chunks go to the analysis child in ``seq`` order as they arrive; after
        StreamEnd with every chunk the analysis finishes. A chunk still missing ``stream_grace_s``
        after the end (or totals that disagree): the whole cloud from the daemon, analysed whole."""
        inbox = self._stream
        assert inbox is not None
        st = self.settings
        await self.runner.open_stream(job)
        while True:
            inbox.wake.clear()
            while inbox.next_seq in inbox.chunks:
                head, data = inbox.chunks.pop(inbox.next_seq)
                await self.runner.add_chunk(data)
                inbox.next_seq += 1
                inbox.points += head.points
                if head.last_pass and st.analyse_ahead:
                    # the arm retracts: the analysis runs now, the rest of the stream seldom adds a point
                    await self.runner.ahead_stream()
            end = inbox.end
            if end is None and inbox.daemon_gone:
                raise TransferError(
                    f"stream of job {spec.job_id}: the daemon sending it is gone (its liveliness token ended)"
                )
            if end is not None and inbox.next_seq >= end.chunks:
                if inbox.next_seq == end.chunks and inbox.points == end.points:
                    out = await self.runner.finish_stream()
                    return self._stream_outcome(out, inbox, fallback=False)
                why = f"{inbox.next_seq} chunks of {inbox.points} points, the end says {end.chunks} of {end.points}"
                return await self._stream_fallback(keys, spec, job, inbox, why)
            try:
                await asyncio.wait_for(inbox.wake.wait(), st.stream_grace_s if end else st.stream_idle_s)
            except TimeoutError:
                if end is None:
                    raise TransferError(
                        f"stream of job {spec.job_id}: nothing for {st.stream_idle_s} s"
                    ) from None
                why = f"chunk {inbox.next_seq} of {end.chunks} missing {st.stream_grace_s} s after the end"
                return await self._stream_fallback(keys, spec, job, inbox, why)

    async def _stream_fallback(
        self, keys: Keys, spec: JobSpec, job: AnalysisJob, inbox: _StreamInbox, why: str
    ) -> ChildAnswer:
        """The stream is incomplete: the whole cloud from the daemon (``Keys.job_cloud``), analysed whole."""
        log.warning("stream_incomplete", job_id=spec.job_id, reason=why, corrupt=inbox.corrupt)
        await self.runner.drop_stream()
        cloud = await self._get_bytes(
            keys.job_cloud(spec.job_id),
            self.settings.cloud_timeout_s,
            f"stream incomplete ({why}) and the whole cloud unavailable",
        )
        log.info("stream_cloud_fetched", job_id=spec.job_id, bytes=len(cloud))
        out = await self.runner.run(job, cloud)
        return self._stream_outcome(out, inbox, fallback=True)

    @staticmethod
    def _stream_outcome(out: ChildAnswer, inbox: _StreamInbox, *, fallback: bool) -> ChildAnswer:
        extra = {"stream_chunks": float(inbox.next_seq), "stream_duplicates": float(inbox.duplicates),
                 "stream_fallback": float(fallback)}  # fmt: skip
        return out.model_copy(update={"timings_s": {**out.timings_s, **extra}})

    def _on_cancel(self, sample: zenoh.Sample) -> None:
        job_id = Keys.last_chunk(str(sample.key_expr))
        said = sample.payload.to_bytes().decode(errors="replace").strip()
        attempt = int(said) if said.isdigit() else None  # empty: whichever attempt is held
        if attempt is not None and self._current is not None and attempt < self._current.attempt:
            log.info("job_cancel_ignored", job_id=job_id, attempt=attempt, holding=self._current.attempt)
            return
        if self._current is not None and self._current.job_id == job_id and self._task is not None:
            log.info("job_cancelled", job_id=job_id)
            self._task.cancel()

    async def _heartbeat(self, keys: Keys, spec: JobSpec) -> None:
        while True:
            await asyncio.sleep(self.settings.heartbeat_s)
            self._event(keys, spec, "heartbeat")

    async def _run(self, keys: Keys, spec: JobSpec, sample: zenoh.Sample) -> None:
        log.info("job_started", job_id=spec.job_id, attempt=spec.attempt, cell=keys.prefix)
        hb = asyncio.get_running_loop().create_task(self._heartbeat(keys, spec))
        t0 = time.perf_counter()
        out_dir: Path | None = None
        try:
            if self._restarting is not None and not self._restarting.done():
                with contextlib.suppress(Exception):
                    await asyncio.shield(self._restarting)  # the analysis child of the previous job
            cloud = await asyncio.to_thread(sample.payload.to_bytes)
            del sample
            job = spec.job
            if spec.transfer is not None:
                try:
                    job, out_dir = await self._local_job(keys, spec)
                except TransferError as exc:
                    log.warning("design_unavailable", job_id=spec.job_id, error=str(exc))
                    self._event(keys, spec, "failed", str(exc))
                    return
            try:
                if spec.stream:
                    outcome = await self._run_stream(keys, spec, job)
                else:
                    outcome = await self.runner.run(job, cloud)
            except TransferError as exc:
                log.warning("stream_failed", job_id=spec.job_id, error=str(exc))
                self._event(keys, spec, "failed", str(exc))
                await self._restart_runner()  # the child may hold half a stream
                return
            except AnalysisCrashed as exc:
                log.error("analysis_crashed", job_id=spec.job_id, error=str(exc))
                self._event(keys, spec, "failed", str(exc))
                await self._restart_runner()
                return
            del cloud
            manifest = None
            if (
                outcome.ok
                and out_dir is not None
                and spec.transfer is not None
                and spec.transfer.return_results
            ):
                manifest = await self._send_results(keys, spec, out_dir)
            env = ReportEnvelope(
                job_id=spec.job_id,
                plate_id=spec.plate_id,
                worker_id=self.worker_id,
                attempt=spec.attempt,
                ok=outcome.ok,
                report=outcome.report,
                error=outcome.error,
                timings_s={**outcome.timings_s, "worker_total": time.perf_counter() - t0},
                t_utc=now_utc(),
                results=manifest,
                offer_id=spec.offer_id,
            )
            payload = env.to_json()
            # Reports can be large (per-line curves): BLOCK, never silently dropped.
            await asyncio.to_thread(
                self.session.put,
                keys.report(spec.job_id),
                payload,
                encoding="application/json",
                attachment=_mac(spec, payload),
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
            self.jobs_done += 1
            log.info(
                "job_reported", job_id=spec.job_id, ok=outcome.ok, seconds=round(time.perf_counter() - t0, 3)
            )
        except asyncio.CancelledError:
            with contextlib.suppress(Exception):  # the link may be down: the restart below must run
                self._event(
                    keys,
                    spec,
                    "cancelled",
                    "worker stopping" if self._stopping else "cancelled by the dispatcher",
                )
            if not self._stopping:  # the analysis child may be mid-job: start a clean one
                await self._restart_runner()
            raise
        except Exception as exc:
            # Anything else (a put refused, an unreadable result): the job goes elsewhere, we go on.
            log.exception("job_error", job_id=spec.job_id)
            with contextlib.suppress(Exception):
                self._event(keys, spec, "failed", f"{type(exc).__name__}: {exc}")
        finally:
            hb.cancel()
            self._stream = None
            self._current = self._current_cell = None
            self._task = None
            self._idle_since = time.monotonic()
            if out_dir is not None:
                shutil.rmtree(out_dir, ignore_errors=True)

    async def _local_job(self, keys: Keys, spec: JobSpec) -> tuple[AnalysisJob, Path]:
        """The job as this worker runs it: the design from its cache (fetched by hash from the
        daemon when missing), the results into a fresh directory of its own."""
        transfer = spec.transfer
        assert transfer is not None
        update: dict[str, Any] = {}
        if transfer.design is not None:
            update["design"] = str(await self._design(keys, transfer.design))
        out_dir = self.settings.data_dir / "jobs" / f"{spec.job_id}-{spec.attempt}"
        await asyncio.to_thread(shutil.rmtree, out_dir, True)
        out_dir.mkdir(parents=True)
        update["out_dir"] = str(out_dir.resolve())
        return spec.job.model_copy(update=update), out_dir

    async def _get_bytes(self, key: str, timeout_s: float, what: str) -> bytes:
        """The payload of the first good reply to a query on ``key``; none -> TransferError naming
        ``what`` and the first error reply (or "no reply")."""
        replies = await async_get(self.session, key, timeout_s=timeout_s)
        ok = [r.ok for r in replies if r.ok is not None]
        if not ok:
            why = replies[0].err.payload.to_bytes().decode(errors="replace") if replies else "no reply"
            raise TransferError(f"{what}: {why}")
        return await asyncio.to_thread(ok[0].payload.to_bytes)

    async def _design(self, keys: Keys, ref: Any) -> Path:
        cache = self.settings.data_dir / "designs"
        path = await asyncio.to_thread(cached_design, cache, ref)
        if path is not None:
            return path
        data = await self._get_bytes(
            keys.design(ref.sha256), self.settings.design_timeout_s, f"design {ref.name} ({ref.sha256[:12]})"
        )
        path = await asyncio.to_thread(cache_design, cache, ref, data)
        log.info("design_cached", name=ref.name, sha256=ref.sha256[:12], bytes=len(data))
        return path

    async def _send_results(self, keys: Keys, spec: JobSpec, out_dir: Path) -> ResultManifest:
        """Pack the results directory and put its chunks (BLOCK) before the report goes out."""
        transfer = spec.transfer
        assert transfer is not None
        manifest, chunks = await asyncio.to_thread(
            pack_results, out_dir, chunk_bytes=transfer.chunk_bytes, max_bytes=transfer.max_result_bytes
        )

        def put_all() -> None:
            for i, data in enumerate(chunks):
                head = ResultChunk(
                    job_id=spec.job_id, worker_id=self.worker_id, attempt=spec.attempt, index=i,
                    chunks=len(chunks), sha256=(sha := hashlib.sha256(data).hexdigest()),
                    mac=chunk_mac(spec.offer_key, spec.job_id, spec.attempt, i, len(chunks), sha)
                    if spec.offer_key else "",
                )  # fmt: skip
                self.session.put(
                    keys.result_chunk(spec.job_id, spec.attempt, i), data, attachment=head.to_json(),
                    congestion_control=zenoh.CongestionControl.BLOCK,
                )  # fmt: skip

        await asyncio.to_thread(put_all)
        log.info("results_sent", job_id=spec.job_id, chunks=manifest.chunks, bytes=manifest.total_bytes)
        return manifest

    async def _restart_runner(self) -> None:
        # A task of its own, shielded: a second cancellation of the job (its cancel message after
        # a take-over) must not leave a child half started whose hello the next job would read.
        if self._restarting is None or self._restarting.done():
            self._restarting = asyncio.get_running_loop().create_task(self._restart())
        await asyncio.shield(self._restarting)

    async def _restart(self) -> None:
        await asyncio.to_thread(self.runner.kill)  # kill() joins the child: not on the loop
        try:
            await self.runner.start()
        except AnalysisLoadError as exc:
            log.error("analysis_restart_failed", error=str(exc))


def _mac(spec: JobSpec, payload: bytes) -> str | None:
    """The attachment that proves a message comes from the worker holding this offer
    (:mod:`cellctl.api.proof`); None for an offer without a key."""
    return sign(spec.offer_key, payload) if spec.offer_key else None


async def run_worker_async(
    section_zenoh: Any,
    key_prefix: str,
    settings: WorkerSettings,
    stop: asyncio.Event | None = None,
    cells: list[str] | tuple[str, ...] = (),
) -> int:
    """Open a client session (retrying until the daemon or router is reachable), serve, close.

    Returns the process exit code: 0 after a clean stop, 2 for configuration or analysis load errors.
    """
    stop = stop or asyncio.Event()
    release_signals = stop_on_signals(stop)
    try:
        cfg_factory = lambda: build_zenoh_config(section_zenoh, role="connect", key_prefix=key_prefix)  # noqa: E731
        cfg_factory()
    except ZenohSetupError as exc:
        log.error("worker_config_invalid", error=str(exc))
        return 2
    # The analysis callable is loaded first: a wrong dotted path fails now, not after connecting.
    runner = AnalysisProcess.from_settings(settings)
    try:
        await runner.start()
    except AnalysisLoadError as exc:
        log.error("analysis_load_failed", error=str(exc))
        return 2
    session = None
    try:
        while session is None and not stop.is_set():
            try:
                session = await asyncio.to_thread(open_session, cfg_factory(), what="worker session")
            except ZenohSetupError as exc:
                log.warning("worker_connect_failed", error=str(exc), retry_s=settings.connect_retry_s)
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(stop.wait(), settings.connect_retry_s)
        if session is None:
            return 0
        # [worker] cells given: those cells (the configured one only if listed); else this cell
        own = None if cells else Keys(key_prefix)
        await Worker(session, own, settings, runner, cells=cells).serve(stop)
        return 0
    finally:
        runner.kill()
        close_session(session)
        release_signals()


def run_worker(config: Any, settings: WorkerSettings) -> int:
    """Blocking entry point used by `cellctl worker`: one worker for ``config`` (a CellConfig).

    Under access control with roles, the worker's id is its Zenoh identity (the ACL lets the
    identity ``w1`` receive only ``workers/w1/**`` and declare only ``alive/workers/w1``): without
    ``--worker-id`` it is ``[zenoh.access] user`` (under ``auth = "tls"`` give the certificate's
    common name as ``--worker-id``)."""
    access = config.zenoh.access
    if not settings.worker_id and access.enabled and access.roles and access.auth != "tls":
        settings = replace(settings, worker_id=access.user)
    return asyncio.run(run_worker_async(config.zenoh, config.key_prefix, settings, cells=config.worker.cells))
