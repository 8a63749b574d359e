"""The daemon-side job dispatcher: each cloud to exactly one live analysis worker, retried on loss.

Protocol (keys in :class:`cellctl.api.Keys`, payloads in docs/api.md):

1. Workers announce themselves with a liveliness token (``Keys.worker_alive``). The dispatcher
   follows them with a liveliness subscriber (history on, so workers already running count).
2. A job goes to one idle worker: the cloud is put on ``Keys.worker_job(worker, job)`` with
   ``CongestionControl.BLOCK`` and the JobSpec as attachment. A worker holds one job at a time.
3. The worker answers with JobEvents (``accepted``, then ``heartbeat`` every second) and finally
   publishes the ReportEnvelope on ``Keys.report(job)``.
4. The job is re-queued (attempt + 1, another worker preferred) when its worker's token goes
   away (crash, SIGTERM, lost link), when no ``accepted`` arrives within ``ack_timeout_s``, when
   heartbeats stop for ``heartbeat_timeout_s``, when the attempt exceeds ``job_timeout_s``, or
   when the worker reports that its analysis process died. A worker that is busy ``rejected``
   the job: re-queued without counting an attempt. After ``max_attempts`` the job fails.
5. A report resolves its job only when it comes from the worker the job is assigned to, for its
   current offer; any other report (another worker's id, an attempt taken back, a job the
   sender does not hold) is refused, logged and counted (``refused_reports``). "Comes from" is
   proven, not claimed: every offer has a secret key (JobSpec ``offer_key``, sent only to the
   assigned worker) and the worker's events, report and result chunks carry its HMAC
   (:mod:`cellctl.api.proof`); one that does not verify is refused (``refused_events``,
   ``refused_reports``, ``refused_chunks``) and the attempt goes on. A verified report is then
   checked by what it says: its plate, job, design and placement must be the job's, and a job
   that asked for its results back needs the report's result bundle; a verified report that
   fails this is refused and the attempt retried (the worker is broken, not an impostor).

6. A job submitted with a :class:`~cellctl.api.transfer.TransferSpec` shares nothing but the link:
   the design is served by hash (``Keys.design``), and the report's ResultManifest must match the
   chunks received on ``Keys.result_chunk`` (waiting ``results_grace_s`` for late ones); a result
   incomplete or corrupt is refused (``refused_results``) and the job retried, like a lost attempt.
   The verified files wait in :meth:`Dispatcher.take_results` for the daemon to store.

7. A streamed job (:meth:`Dispatcher.submit_stream`, the cloud pass by pass while the plate is
   scanned) goes to a worker at once with an empty job message (JobSpec ``stream``); once the
   attempt is ``accepted``, every chunk stored so far and then each new one is put on
   ``Keys.worker_stream`` (StreamChunk attachment, in ``seq`` order, BLOCK), and StreamEnd when the
   daemon ends the stream. The chunks are kept here until the job resolves: a retry (the worker
   gone, a heartbeat missed) replays them to the next worker from ``seq`` 0. ``Keys.job_cloud``
   serves the whole cloud (the chunks concatenated) to a worker that missed a chunk.

8. Versions: when a worker's token appears its announcement (``Keys.worker_info``) is read; it gets
   jobs only when it speaks this daemon's API_VERSION and STREAM_FORMAT. A worker of another
   version stays out (``incompatible``, with the reason, in the status), so a fleet half
   upgraded keeps every job on the workers that can do it.

No worker at all: jobs wait in the queue and go out when a worker appears. The dispatcher persists
nothing; :class:`DispatchHooks` lets the daemon record every transition.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import hmac
import json
import secrets
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import PurePath
from typing import TYPE_CHECKING, Any

import structlog
import zenoh
from pydantic import ValidationError

from analysis.contracts.job import AnalysisJob
from cellctl.acquisition.spill import release
from cellctl.api.cloud_codec import ENCODING as CLOUD_ENCODING
from cellctl.api.cloud_codec import concat_encoded
from cellctl.api.keys import Keys
from cellctl.api.models import (
    API_VERSION,
    STREAM_FORMAT,
    JobEvent,
    JobSpec,
    ReportEnvelope,
    StreamChunk,
    StreamEnd,
)
from cellctl.api.proof import chunk_mac, new_offer_key, verify
from cellctl.api.session import async_get, declare_async_queryable, subscribe
from cellctl.api.transfer import MAX_RESULT_BYTES, ResultChunk, ResultRefused, TransferSpec
from cellctl.daemon.design_server import DesignServer
from cellctl.daemon.result_collector import ResultCollector

if TYPE_CHECKING:
    from cellctl.config import CellConfig

log = structlog.get_logger(__name__)


class JobFailed(Exception):
    """A job that no worker could complete within ``max_attempts``; the reason of the last attempt."""

    def __init__(self, job_id: str, reason: str) -> None:
        self.job_id = job_id
        self.reason = reason
        super().__init__(f"job {job_id}: {reason}")


@dataclass(frozen=True)
class DispatchSettings:
    """Timeouts and retries of the dispatcher (seconds)."""

    ack_timeout_s: float = 10.0
    heartbeat_timeout_s: float = 10.0
    job_timeout_s: float | None = 900.0
    max_attempts: int = 3
    busy_backoff_s: float = 2.0
    watchdog_period_s: float = 0.2
    # > 0: clouds go through an explicit Zenoh shared-memory pool of this size (same host only;
    # Zenoh copies for remote workers). Cuts the daemon's put from ~1.2 s to ~0.1 s for 280 MB.
    shm_pool_mb: int = 0
    # how long a report waits for result chunks still in flight before its result is refused
    results_grace_s: float = 3.0
    # a worker that just appeared is offered work this much later: through a router its job
    # subscriber may become known here after its liveliness token, and a put before that is lost
    worker_settle_s: float = 0.5
    max_result_bytes: int = MAX_RESULT_BYTES
    # a worker's announcement (its versions) is asked for this long; no answer: asked again after
    # announce_retry_s, doubling up to 10 s, while its token lives (it gets no job meanwhile)
    announce_timeout_s: float = 5.0
    announce_retry_s: float = 0.5

    @classmethod
    def from_config(cls, config: CellConfig) -> DispatchSettings:
        """From ``[analysis]`` and ``[zenoh] shm_pool_mb`` of a CellConfig."""
        a = config.analysis
        return cls(
            ack_timeout_s=a.ack_timeout_s,
            heartbeat_timeout_s=a.heartbeat_timeout_s,
            job_timeout_s=a.job_timeout_s,
            max_attempts=a.max_attempts,
            shm_pool_mb=config.zenoh.shm_pool_mb,
        )


@dataclass
class DispatchHooks:
    """Callbacks for the daemon (all optional, all run on the event loop, must not block)."""

    on_queued: Callable[[str], None] | None = None  # job_id
    on_assigned: Callable[[str, str, int], None] | None = None  # job_id, worker_id, attempt
    on_retry: Callable[[str, str, str], None] | None = None  # job_id, worker_id, reason
    on_report: Callable[[ReportEnvelope], None] | None = None
    on_failed: Callable[[str, str], None] | None = None  # job_id, reason
    on_workers: Callable[[list[str]], None] | None = None  # live worker ids, after every change


@dataclass
class _Worker:
    worker_id: str
    job_id: str | None = None
    available_at: float = 0.0
    last_assigned: float = 0.0
    #: None: its announcement not read yet; True: it speaks our versions; False: it does not
    compatible: bool | None = None
    why: str = ""


@dataclass
class _Stream:
    """A streamed job's chunks (pass index, points, sha256, payload, last pass) as the daemon gave them."""

    chunks: list[tuple[int, int, str, bytes | bytearray | memoryview, bool]] = field(default_factory=list)
    ended: bool = False
    ended_at: float = 0.0
    wake: asyncio.Event = field(default_factory=asyncio.Event)
    pump: asyncio.Task[None] | None = None
    whole: bytearray | None = None

    @property
    def points(self) -> int:
        return sum(c[1] for c in self.chunks)


@dataclass
class _Job:
    job_id: str
    plate_id: str
    cloud: bytes | bytearray
    params: AnalysisJob
    future: asyncio.Future[ReportEnvelope]
    attempt: int = 0
    worker_id: str | None = None
    assigned_at: float = 0.0
    sending: bool = False
    accepted: bool = False
    last_seen: float = 0.0
    tried: set[str] = field(default_factory=set)
    last_reason: str = ""
    transfer: TransferSpec | None = None
    stream: _Stream | None = None
    offer_id: str = ""
    offer_key: str = ""

    def answers(self, worker_id: str, attempt: int, offer_id: str) -> bool:
        """Whether a worker's event or report is about this job's current offer (a restarted daemon
        offers the same job and attempt number again: the old offer's messages are not its own)."""
        return self.worker_id == worker_id and self.attempt == attempt and offer_id == self.offer_id


class Dispatcher:
    """Hands jobs to workers over an open session. ``await start()``, ``submit(...)``, ``await close()``."""

    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        settings: DispatchSettings | None = None,
        hooks: DispatchHooks | None = None,
    ) -> None:
        self.session = session
        self.keys = keys
        self.settings = settings or DispatchSettings()
        self.hooks = hooks or DispatchHooks()
        self._workers: dict[str, _Worker] = {}
        self._jobs: dict[str, _Job] = {}
        self._queue: deque[str] = deque()
        self._entities: list[Any] = []
        self._watchdog: asyncio.Task[None] | None = None
        self._sends: set[asyncio.Task[None]] = set()
        self._shm: Any = None
        self.malformed = 0
        self.refused_reports = 0
        self.refused_results = 0
        self.refused_events = 0
        self.refused_chunks = 0
        self._announcing: set[asyncio.Task[None]] = set()
        self.designs = DesignServer()
        self.collector = ResultCollector(max_bytes=self.settings.max_result_bytes)
        self._results: dict[str, dict[str, bytes]] = {}

    # ------------------------------------------------------------------------------------- public

    @property
    def workers(self) -> list[str]:
        """Live workers that speak this daemon's versions (they get jobs), sorted."""
        return sorted(w.worker_id for w in self._workers.values() if w.compatible)

    @property
    def incompatible(self) -> dict[str, str]:
        """Live workers that get no job, and why (another version, or no announcement read)."""
        return {w.worker_id: w.why for w in sorted(self._workers.values(), key=lambda w: w.worker_id)
                if w.compatible is False}  # fmt: skip

    @property
    def pending(self) -> list[str]:
        """Jobs not yet resolved (queued or being analysed)."""
        return list(self._jobs)

    def assignment(self, job_id: str) -> tuple[str | None, int]:
        """(worker holding the job or None, attempt number) of a pending job."""
        job = self._jobs[job_id]
        return job.worker_id, job.attempt

    async def start(self) -> None:
        """Declare the liveliness, event and report subscribers and start the watchdog."""
        self._entities.append(
            subscribe(self.session, self.keys.worker_alive("*"), self._on_liveliness, liveliness=True)
        )
        self._entities.append(subscribe(self.session, self.keys.job_event("*"), self._on_event))
        self._entities.append(subscribe(self.session, self.keys.report("*"), self._on_report))
        self._entities.append(subscribe(self.session, f"{self.keys.prefix}/results/**", self._on_chunk))
        self._entities.append(declare_async_queryable(self.session, self.keys.design("*"), self._on_design))
        self._entities.append(
            declare_async_queryable(self.session, self.keys.job_cloud("*"), self._on_job_cloud)
        )
        self._watchdog = asyncio.get_running_loop().create_task(self._watch())
        if self.settings.shm_pool_mb > 0:
            try:
                self._shm = zenoh.shm.ShmProvider.default_backend(self.settings.shm_pool_mb * 2**20)
            except Exception as exc:  # the shm API is marked unstable: fall back to the copy path
                log.warning("shm_unavailable", error=str(exc))

    def submit_stream(
        self, params: AnalysisJob, *, transfer: TransferSpec | None = None
    ) -> asyncio.Future[ReportEnvelope]:
        """Queue a job whose cloud follows in chunks (:meth:`stream_chunk`, then :meth:`end_stream`);
        the future as :meth:`submit`'s. The job goes to a worker now, so that it analyses the chunks
        as they come."""
        return self.submit(params, b"", transfer=transfer, stream=True)

    def stream_chunk(
        self,
        job_id: str,
        pass_index: int,
        payload: bytes | bytearray | memoryview,
        points: int,
        *,
        last_pass: bool = False,
    ) -> int:
        """The next chunk of a streamed job's cloud (an encoded cloud of the rows since the previous
        chunk); its ``seq``. Sent on to the worker holding the job once it accepted. ``last_pass``:
        it completes the plan's last pass (StreamChunk.last_pass)."""
        st = self._stream(job_id)
        if st.ended:
            raise ValueError(f"job {job_id!r}: the stream has ended")
        st.chunks.append((pass_index, points, hashlib.sha256(payload).hexdigest(), payload, last_pass))
        st.wake.set()
        return len(st.chunks) - 1

    def end_stream(self, job_id: str) -> None:
        """No more chunks: the worker gets StreamEnd (with the totals) after the last one."""
        st = self._stream(job_id)
        st.ended, st.ended_at = True, time.monotonic()
        st.wake.set()
        log.info("stream_ended", job_id=job_id, chunks=len(st.chunks), points=st.points)

    def stream_payloads(self, job_id: str) -> list[bytes | bytearray | memoryview]:
        """The chunks of a pending streamed job so far, in order."""
        return [c[3] for c in self._stream(job_id).chunks]

    def abandon(self, job_id: str, reason: str) -> None:
        """Give up a pending job (its scan ended early): the worker holding it is told to stop, the
        future fails with JobFailed."""
        job = self._jobs.get(job_id)
        if job is None:
            return
        if job.worker_id is not None:
            self._cancel_on(job.worker_id, job_id, job.attempt)
        self._release(job)
        self._jobs.pop(job_id, None)
        self.collector.forget(job_id)
        with contextlib.suppress(ValueError):
            self._queue.remove(job_id)
        log.info("job_abandoned", job_id=job_id, reason=reason)
        if not job.future.done():
            job.future.set_exception(JobFailed(job_id, reason))
        self._pump()

    def _stream(self, job_id: str) -> _Stream:
        job = self._jobs.get(job_id)
        if job is None or job.stream is None:
            raise ValueError(f"job {job_id!r} is not a pending streamed job")
        return job.stream

    def submit(
        self,
        params: AnalysisJob,
        cloud: bytes | bytearray,
        *,
        transfer: TransferSpec | None = None,
        stream: bool = False,
    ) -> asyncio.Future[ReportEnvelope]:
        """Queue a cloud (encoded by :func:`cellctl.api.cloud_codec.encode_cloud`) for analysis with
        the job's parameters (``params.job_id`` names the job). With ``transfer`` the design must have
        been registered (``self.designs.register``) and the results come back over Zenoh
        (:meth:`take_results`).

        The future resolves with the first ReportEnvelope (``ok`` False when the analysis itself
        raised), or fails with JobFailed after ``max_attempts`` lost attempts.
        """
        job_id, plate_id = params.job_id, params.plate_id
        if not job_id:
            raise ValueError("the job parameters name no job_id")
        if job_id in self._jobs:
            raise ValueError(f"job {job_id!r} is already pending")
        fut: asyncio.Future[ReportEnvelope] = asyncio.get_running_loop().create_future()
        self._jobs[job_id] = _Job(
            job_id, plate_id, cloud, params, fut, transfer=transfer, stream=_Stream() if stream else None
        )
        self._queue.append(job_id)
        log.info("job_queued", job_id=job_id, plate_id=plate_id, bytes=len(cloud), workers=len(self._workers))
        self._call(self.hooks.on_queued, job_id)
        self._pump()
        return fut

    async def close(self) -> None:
        """Undeclare everything; pending futures are cancelled."""
        if self._watchdog is not None:
            self._watchdog.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._watchdog
        for task in list(self._sends):
            with contextlib.suppress(Exception):
                await task
        for task in list(self._announcing):
            task.cancel()
            with contextlib.suppress(BaseException):
                await task
        for ent in self._entities:
            with contextlib.suppress(Exception):
                ent.undeclare()
        self._entities.clear()
        for job in self._jobs.values():
            if not job.future.done():
                job.future.cancel()

    # ------------------------------------------------------------------------------------ internals

    def _call(self, hook: Callable[..., None] | None, *args: Any) -> None:
        if hook is None:
            return
        try:
            hook(*args)
        except Exception:
            log.exception("dispatch_hook_failed", hook=getattr(hook, "__name__", str(hook)))

    def _pick_worker(self, job: _Job, now: float) -> _Worker | None:
        idle = [
            w for w in self._workers.values() if w.compatible and w.job_id is None and w.available_at <= now
        ]
        if not idle:
            return None
        fresh = [w for w in idle if w.worker_id not in job.tried] or idle
        return min(fresh, key=lambda w: w.last_assigned)

    def _pump(self) -> None:
        now = time.monotonic()
        while self._queue:
            job = self._jobs[self._queue[0]]
            worker = self._pick_worker(job, now)
            if worker is None:
                return
            self._queue.popleft()
            self._assign(job, worker, now)

    def _assign(self, job: _Job, worker: _Worker, now: float) -> None:
        job.attempt += 1
        job.worker_id = worker.worker_id
        job.assigned_at = job.last_seen = now
        job.accepted = False
        job.sending = True
        job.tried.add(worker.worker_id)
        worker.job_id = job.job_id
        worker.last_assigned = now
        job.offer_id = secrets.token_hex(8)
        job.offer_key = new_offer_key()
        spec = JobSpec(
            attempt=job.attempt, job=job.params, transfer=job.transfer, stream=job.stream is not None,
            offer_id=job.offer_id, offer_key=job.offer_key,
        )  # fmt: skip
        log.info("job_assigned", job_id=job.job_id, worker_id=worker.worker_id, attempt=job.attempt)
        self._call(self.hooks.on_assigned, job.job_id, worker.worker_id, job.attempt)
        task = asyncio.get_running_loop().create_task(self._send(job, worker.worker_id, spec))
        self._sends.add(task)
        task.add_done_callback(self._sends.discard)

    def _payload(self, cloud: bytes | bytearray | memoryview) -> Any:
        if isinstance(cloud, memoryview):  # a spilled chunk (cellctl.acquisition.spill): Zenoh takes bytes
            cloud = bytes(cloud)
        if self._shm is None or len(cloud) > self.settings.shm_pool_mb * 2**20:
            return cloud
        try:
            buf = self._shm.alloc(len(cloud), zenoh.shm.BlockOn(zenoh.shm.GarbageCollect()))
            buf[0 : len(cloud)] = cloud
            return buf
        except Exception as exc:
            log.warning("shm_alloc_failed", bytes=len(cloud), error=str(exc))
            return cloud

    async def _send(self, job: _Job, worker_id: str, spec: JobSpec) -> None:
        # put() blocks for about the transfer time of a large cloud: keep it off the loop.
        def put() -> None:
            self.session.put(
                self.keys.worker_job(worker_id, job.job_id),
                self._payload(job.cloud),
                encoding=CLOUD_ENCODING,
                attachment=spec.to_json(),
                congestion_control=zenoh.CongestionControl.BLOCK,
            )

        try:
            await asyncio.to_thread(put)
            if job.worker_id == worker_id and job.attempt == spec.attempt:
                # The acknowledgement clock starts once the cloud is out, not while it is sent.
                job.sending = False
                job.last_seen = time.monotonic()
        except Exception as exc:
            log.warning("job_send_failed", job_id=job.job_id, worker_id=worker_id, error=str(exc))
            if job.worker_id == worker_id and job.attempt == spec.attempt:
                self._requeue(job, f"send failed: {exc}", count=True)

    def _release(self, job: _Job, backoff_s: float = 0.0) -> None:
        if job.stream is not None and job.stream.pump is not None:
            job.stream.pump.cancel()  # a retry replays the chunks from seq 0
            job.stream.pump = None
        worker = self._workers.get(job.worker_id or "")
        if worker is not None and worker.job_id == job.job_id:
            worker.job_id = None
            worker.available_at = time.monotonic() + backoff_s
        job.worker_id = None

    def _requeue(self, job: _Job, reason: str, *, count: bool = True, backoff_s: float = 0.0) -> None:
        """Take a job back from its worker and queue it again (first in line)."""
        worker_id = job.worker_id or ""
        self._release(job, backoff_s)
        job.last_reason = reason
        if not count:
            job.attempt -= 1
        if job.attempt >= self.settings.max_attempts:
            self._fail(job, f"{job.attempt} attempts; last: {reason}")
            return
        log.warning("job_retry", job_id=job.job_id, worker_id=worker_id, reason=reason, attempt=job.attempt)
        self._call(self.hooks.on_retry, job.job_id, worker_id, reason)
        self._queue.appendleft(job.job_id)
        self._pump()

    def _fail(self, job: _Job, reason: str) -> None:
        self._jobs.pop(job.job_id, None)
        self.collector.forget(job.job_id)
        with contextlib.suppress(ValueError):
            self._queue.remove(job.job_id)
        log.error("job_failed", job_id=job.job_id, reason=reason)
        self._call(self.hooks.on_failed, job.job_id, reason)
        if not job.future.done():
            job.future.set_exception(JobFailed(job.job_id, reason))

    def _cancel_on(self, worker_id: str, job_id: str, attempt: int | None = None) -> None:
        # the payload names the attempt taken back: a late cancel must not stop a newer attempt
        with contextlib.suppress(Exception):
            self.session.put(
                self.keys.worker_cancel(worker_id, job_id), b"" if attempt is None else str(attempt)
            )

    def _on_liveliness(self, sample: zenoh.Sample) -> None:
        worker_id = Keys.last_chunk(str(sample.key_expr))
        if sample.kind == zenoh.SampleKind.PUT:
            if worker_id not in self._workers:
                worker = self._workers[worker_id] = _Worker(
                    worker_id, available_at=time.monotonic() + self.settings.worker_settle_s
                )
                log.info("worker_appeared", worker_id=worker_id, workers=len(self._workers))
                task = asyncio.get_running_loop().create_task(self._read_announcement(worker))
                self._announcing.add(task)
                task.add_done_callback(self._announcing.discard)
            self._pump()
            return
        worker = self._workers.pop(worker_id, None)
        if worker is None:
            return
        log.warning("worker_gone", worker_id=worker_id, job_id=worker.job_id, workers=len(self._workers))
        self._call(self.hooks.on_workers, self.workers)
        job = self._jobs.get(worker.job_id or "")
        if job is not None and job.worker_id == worker_id:
            self._requeue(job, f"worker {worker_id} disappeared")

    async def _read_announcement(self, worker: _Worker) -> None:
        """Ask a new worker what it speaks (its WorkerAnnouncement); only a worker of this daemon's
        API_VERSION and STREAM_FORMAT gets jobs. Read leniently: an older or newer announcement may
        not fit this version's model, its version fields are what count. Asked again (backing off)
        for as long as its token lives and no announcement came."""
        s = self.settings
        tries = 0
        while self._workers.get(worker.worker_id) is worker:
            tries += 1
            why = "no announcement"
            try:
                replies = await async_get(
                    self.session, self.keys.worker_info(worker.worker_id), timeout_s=s.announce_timeout_s
                )
            except Exception as exc:
                replies, why = [], f"announcement unreadable: {exc}"
            verdicts = [_version_verdict(r.ok.payload.to_bytes()) for r in replies if r.ok is not None]
            verdict = next((v for v in verdicts if v is not None), None)
            if self._workers.get(worker.worker_id) is not worker:
                return  # gone meanwhile
            if verdict is not None:
                worker.compatible, worker.why = verdict
                if worker.compatible:
                    log.info("worker_compatible", worker_id=worker.worker_id, versions=worker.why)
                else:
                    log.warning("worker_incompatible", worker_id=worker.worker_id, reason=worker.why)
                self._call(self.hooks.on_workers, self.workers)
                self._pump()
                return
            if worker.compatible is None or tries % 10 == 0:
                log.warning("worker_unannounced", worker_id=worker.worker_id, reason=why, tries=tries)
            if worker.compatible is None:
                worker.compatible, worker.why = False, f"{why} yet"
                self._call(self.hooks.on_workers, self.workers)
            await asyncio.sleep(min(s.announce_retry_s * 2 ** min(tries - 1, 6), 10.0))

    def _proven(self, job: _Job, ok: bool, what: str, key: str) -> bool:
        """``ok``: a message of the job's current offer carries that offer's MAC; refused, counted
        and logged (rate limited) otherwise."""
        if ok:
            return True
        counter = f"refused_{what}s"
        setattr(self, counter, getattr(self, counter) + 1)
        n = getattr(self, counter)
        if n <= 10 or n % 100 == 0:
            log.warning(
                f"{what}_refused", job_id=job.job_id, key=key, reason="not signed with the offer's key",
                assigned_to=job.worker_id, attempt=job.attempt, count=n,
            )  # fmt: skip
        return False

    def _on_event(self, sample: zenoh.Sample) -> None:
        try:
            payload = sample.payload.to_bytes()
            ev = JobEvent.model_validate_json(payload)
        except ValidationError as exc:
            self._malformed("job_event_malformed", str(sample.key_expr), exc)
            return
        job = self._jobs.get(ev.job_id)
        if job is None or not job.answers(ev.worker_id, ev.attempt, ev.offer_id):
            return  # an event of an attempt that was already taken back or resolved, or another offer
        mac = sample.attachment.to_bytes() if sample.attachment is not None else None
        if not self._proven(job, verify(job.offer_key, payload, mac), "event", str(sample.key_expr)):
            return
        job.last_seen = time.monotonic()
        if ev.event in ("accepted", "heartbeat"):
            job.accepted = True
            if job.stream is not None and job.stream.pump is None and ev.worker_id is not None:
                job.stream.pump = asyncio.get_running_loop().create_task(
                    self._pump_stream(job, ev.worker_id, ev.attempt), name=f"stream-{job.job_id}"
                )
        elif ev.event == "rejected":
            self._requeue(job, f"rejected: {ev.message}", count=False, backoff_s=self.settings.busy_backoff_s)
        elif ev.event in ("failed", "cancelled"):
            # Not straight back to the same worker (it may be stopping, or its analysis restarting):
            # another one first, this one after the busy back-off.
            self._requeue(
                job,
                f"worker {ev.worker_id}: {ev.event}: {ev.message}",
                backoff_s=self.settings.busy_backoff_s,
            )

    def _on_report(self, sample: zenoh.Sample) -> None:
        try:
            payload = sample.payload.to_bytes()
            env = ReportEnvelope.model_validate_json(payload)
        except ValidationError as exc:
            self._malformed("report_malformed", str(sample.key_expr), exc)
            return
        job = self._jobs.get(env.job_id)
        if job is None:
            log.info("report_ignored", job_id=env.job_id, worker_id=env.worker_id, reason="not pending")
            return
        if not job.answers(env.worker_id, env.attempt, env.offer_id):
            # Only the worker the job is assigned to, for its current attempt, reports it: anything
            # else (a peer on an open link naming another worker, a worker for a job it does not
            # hold, a late report of an attempt taken back, the report of a previous daemon's offer)
            # is refused and the analysis goes on.
            self.refused_reports += 1
            log.warning(
                "report_refused", job_id=env.job_id, worker_id=env.worker_id, attempt=env.attempt,
                assigned_to=job.worker_id, current_attempt=job.attempt, key=str(sample.key_expr),
            )  # fmt: skip
            return
        mac = sample.attachment.to_bytes() if sample.attachment is not None else None
        if not self._proven(job, verify(job.offer_key, payload, mac), "report", str(sample.key_expr)):
            return  # copied ids, no key: not the worker's; its own report is still to come
        problem = _content_problem(job, env)
        if problem is not None:
            # signed by the worker holding the offer: the worker is broken, the attempt is lost
            self.refused_reports += 1
            log.warning("report_refused", job_id=env.job_id, worker_id=env.worker_id, reason=problem)
            self._cancel_on(env.worker_id, job.job_id, job.attempt)
            self._requeue(job, f"report refused: {problem}", backoff_s=self.settings.busy_backoff_s)
            return
        if env.results is not None and job.transfer is not None:
            self._resolve_with_results(job, env, waited=0.0)
            return
        self._resolve(job, env)

    def _resolve_with_results(self, job: _Job, env: ReportEnvelope, *, waited: float) -> None:
        """Keep the report only with its verified result bundle; refuse it (a retry) otherwise."""
        if self._jobs.get(job.job_id) is not job or not job.answers(env.worker_id, env.attempt, env.offer_id):
            return  # taken back (worker gone, timeout) while its chunks were awaited
        manifest = env.results
        assert manifest is not None
        if (
            self.collector.missing(job.job_id, env.attempt, manifest)
            and waited < self.settings.results_grace_s
        ):
            # chunks still in flight (they may take another path through a router): look again soon
            asyncio.get_running_loop().call_later(
                0.05, lambda: self._resolve_with_results(job, env, waited=waited + 0.05)
            )
            return
        if waited:
            log.info("results_waited", job_id=job.job_id, waited_s=round(waited, 2))
        try:
            files = self.collector.take(job.job_id, env.attempt, env.worker_id, manifest)
        except ResultRefused as exc:
            self.refused_results += 1
            log.warning("result_refused", job_id=job.job_id, worker_id=env.worker_id, reason=exc.reason)
            self._requeue(job, f"result refused: {exc.reason}")
            return
        self._results[job.job_id] = files
        self._resolve(job, env)

    def take_results(self, job_id: str) -> dict[str, bytes]:
        """The verified result files of a resolved job (name -> bytes), handed over once."""
        return self._results.pop(job_id, {})

    def _resolve(self, job: _Job, env: ReportEnvelope) -> None:
        del self._jobs[env.job_id]
        self.collector.forget(job.job_id)
        self._release(job)
        with contextlib.suppress(ValueError):
            self._queue.remove(job.job_id)
        worker = self._workers.get(env.worker_id)
        if worker is not None and worker.job_id == env.job_id:
            worker.job_id = None
        log.info("job_reported", job_id=env.job_id, worker_id=env.worker_id, attempt=env.attempt, ok=env.ok)
        self._call(self.hooks.on_report, env)
        if not job.future.done():
            job.future.set_result(env)
        self._pump()

    def _on_chunk(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            if sample.attachment is None:
                raise ValueError("no ResultChunk attachment")
            head = ResultChunk.model_validate_json(sample.attachment.to_bytes())
        except ValueError as exc:
            self._malformed("result_chunk_malformed", key, exc)
            return
        if key != self.keys.result_chunk(head.job_id, head.attempt, head.index):
            self._malformed("result_chunk_malformed", key, ValueError("attachment does not match the key"))
            return
        job = self._jobs.get(head.job_id)
        if job is None or job.worker_id != head.worker_id or job.attempt != head.attempt:
            return  # not the current attempt's holder: never kept
        mac = chunk_mac(job.offer_key, head.job_id, head.attempt, head.index, head.chunks, head.sha256)
        if not self._proven(job, bool(head.mac) and hmac.compare_digest(mac, head.mac), "chunk", key):
            return
        job.last_seen = time.monotonic()  # a large bundle is progress, like a heartbeat
        self.collector.add(head, sample.payload.to_bytes())

    async def _pump_stream(self, job: _Job, worker_id: str, attempt: int) -> None:
        """Put a streamed job's chunks, in order, to the worker holding this attempt; StreamEnd last."""
        st = job.stream
        assert st is not None
        sent = 0

        def put(key: str, data: bytes | bytearray, attachment: str | None = None) -> None:
            self.session.put(
                key, data, attachment=attachment, congestion_control=zenoh.CongestionControl.BLOCK
            )

        try:
            while job.worker_id == worker_id and job.attempt == attempt:
                st.wake.clear()
                while sent < len(st.chunks):
                    pass_index, points, sha, data, last_pass = st.chunks[sent]
                    head = StreamChunk(job_id=job.job_id, attempt=attempt, seq=sent, pass_index=pass_index,
                                       points=points, sha256=sha, last_pass=last_pass)  # fmt: skip
                    key = self.keys.worker_stream(worker_id, job.job_id, attempt, sent)
                    await asyncio.to_thread(put, key, self._payload(data), head.to_json())
                    release(data)  # a spilled chunk's pages out of memory again once sent
                    sent += 1
                if st.ended:
                    end = StreamEnd(
                        job_id=job.job_id, attempt=attempt, chunks=len(st.chunks), points=st.points
                    )
                    await asyncio.to_thread(
                        put,
                        self.keys.worker_stream_end(worker_id, job.job_id, attempt),
                        end.to_json(),
                    )
                    log.info(
                        "stream_sent", job_id=job.job_id, worker_id=worker_id, attempt=attempt, chunks=sent
                    )
                    return
                await st.wake.wait()
        except asyncio.CancelledError:
            raise
        except Exception as exc:
            log.warning("stream_send_failed", job_id=job.job_id, worker_id=worker_id, error=str(exc))
            if job.worker_id == worker_id and job.attempt == attempt:
                st.pump = None
                self._cancel_on(worker_id, job.job_id, attempt)  # it holds the attempt: free it for the retry
                self._requeue(
                    job, f"stream send failed: {exc}", count=True, backoff_s=self.settings.busy_backoff_s
                )

    async def _on_job_cloud(self, query: zenoh.Query) -> None:
        job_id = str(query.key_expr).rsplit("/", 2)[-2]
        job = self._jobs.get(job_id)
        st = job.stream if job is not None else None
        if st is None or not st.ended:
            query.reply_err(f"no complete streamed cloud for job {job_id[:64]} here".encode())
            return
        if st.whole is None:
            st.whole = await asyncio.to_thread(concat_encoded, [c[3] for c in st.chunks])
        log.info("stream_cloud_served", job_id=job_id, bytes=len(st.whole))
        query.reply(query.key_expr, bytes(st.whole))

    async def _on_design(self, query: zenoh.Query) -> None:
        sha = Keys.last_chunk(str(query.key_expr))
        data = await asyncio.to_thread(self.designs.read, sha)
        if data is None:
            query.reply_err(f"no design with sha256 {sha[:64]} here".encode())
            return
        query.reply(query.key_expr, data)

    def _malformed(self, event: str, key: str, exc: Exception) -> None:
        self.malformed += 1
        if self.malformed <= 10 or self.malformed % 100 == 0:  # rate limited
            log.warning(event, key=key, count=self.malformed, error=str(exc)[:300])

    @staticmethod
    def _attempt_start(job: _Job) -> float:
        # a streamed job's attempt is timed from the stream's end (the scan may take long)
        if job.stream is None:
            return job.assigned_at
        return max(job.assigned_at, job.stream.ended_at) if job.stream.ended else time.monotonic()

    async def _watch(self) -> None:
        s = self.settings
        while True:
            await asyncio.sleep(s.watchdog_period_s)
            now = time.monotonic()
            for job in list(self._jobs.values()):
                if job.worker_id is None or job.sending:
                    continue
                reason = ""
                if not job.accepted and now - job.last_seen > s.ack_timeout_s:
                    reason = f"no acknowledgement within {s.ack_timeout_s} s"
                elif job.accepted and now - job.last_seen > s.heartbeat_timeout_s:
                    reason = f"no heartbeat for {s.heartbeat_timeout_s} s"
                elif s.job_timeout_s is not None and now - self._attempt_start(job) > s.job_timeout_s:
                    reason = f"attempt took longer than {s.job_timeout_s} s"
                if reason:
                    self._cancel_on(job.worker_id, job.job_id, job.attempt)
                    # The worker is suspect: give it time to recover before it gets work again.
                    self._requeue(job, reason, backoff_s=max(s.ack_timeout_s, s.heartbeat_timeout_s))
            self._pump()


def _version_verdict(raw: bytes) -> tuple[bool, str] | None:
    """(whether a worker announcing ``raw`` gets jobs here, the versions or why not); None when
    ``raw`` is no announcement. An announcement without ``stream_format`` predates it (0)."""
    try:
        ann = json.loads(raw)
        api = int(ann["api_version"])
        stream = int(ann.get("stream_format", 0))
    except (ValueError, TypeError, KeyError):
        return None
    if api != API_VERSION:
        return False, f"api_version {api}, this daemon speaks {API_VERSION}"
    if stream != STREAM_FORMAT:
        return False, f"stream_format {stream}, this daemon sends {STREAM_FORMAT}"
    return True, f"api_version {api}, stream_format {stream}"


def _content_problem(job: _Job, env: ReportEnvelope) -> str | None:
    """What in a report is not the job's (its plate, job, design, placement), or a result bundle
    missing that the job asked for; None when it is the job's report."""
    p = job.params
    if env.plate_id != p.plate_id:
        return f"plate {env.plate_id!r}, the job's is {p.plate_id!r}"
    if env.ok and env.report is None:
        return "ok without a report"
    rep = env.report
    if rep is not None:
        if rep.job_id != p.job_id or rep.plate_id != p.plate_id:
            return f"report of job {rep.job_id!r} plate {rep.plate_id!r}, not the job's"
        ref = job.transfer.design if job.transfer is not None else None
        design = PurePath(rep.inputs.design)
        if (
            (design.parts[-2:] != (ref.sha256, ref.name))
            if ref is not None
            else rep.inputs.design != p.design
        ):
            return f"design {rep.inputs.design!r} is not the job's"
        if rep.inputs.placement != p.placement:
            return "placement is not the job's"
    if env.ok and env.results is None and job.transfer is not None and job.transfer.return_results:
        return "no result bundle"
    return None
