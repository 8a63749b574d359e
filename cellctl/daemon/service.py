"""`cellctl run`: the cell daemon, one asyncio service owning the EGM endpoint, RWS and the sensor.

A job (one remote trigger): validate -> plan (in a thread) -> motors on and the EGM program started
through RWS -> execute the plan over EGM while the HD8 client streams profiles into the acquisition
(raw files first) -> EGM program ended -> the whole-scan cloud rebuilt from the raw files ->
published to the analysis workers through the :class:`~cellctl.daemon.dispatch.Dispatcher` -> the report
stored with the job. One scan at a time: a trigger while a scan holds the robot waits in a bounded
queue (``[daemon] queue_max``; full -> ``queue_full``; 0 -> refused with ``busy``) and starts when
the robot is free; the analysis of a finished scan runs while the next one scans. A fault or an
emergency stop cancels the queue, and so does a restart: the robot never starts moving on its own.
An emergency stop holds the cell in ``emergency_stopped`` until ``control/reset`` finds the
controller released and reset.

State (:class:`~cellctl.api.CellStatus`) is published on every change and every
``status_period_s``; the daemon holds a liveliness token. SIGTERM / SIGINT: a scan in progress is
stopped smoothly along its path, the raw files are flushed and the job is marked interrupted, then
everything is closed and the process exits 0.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import os
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any

import structlog
import zenoh

from cellctl.api import (
    CONTROL_LOG,
    FINAL_JOB_STATES,
    JSON,
    CellState,
    CellStatus,
    ControlError,
    ControlReply,
    ControlRequest,
    DaemonStats,
    JobProgress,
    JobState,
    Keys,
    QueuedJob,
    TriggerAccepted,
    TriggerError,
    TriggerRequest,
    handle_trigger,
    new_job_id,
    now_utc,
    parse_control,
    read_payload,
)
from cellctl.api.session import (
    ZenohSetupError,
    build_zenoh_config,
    close_session,
    declare_async_queryable,
    open_session,
)
from cellctl.config import CellConfig, ConfigError
from cellctl.daemon.active import ActiveJob
from cellctl.daemon.audit import AuditLog
from cellctl.daemon.dispatch import Dispatcher, DispatchHooks, DispatchSettings
from cellctl.daemon.handover import Handover
from cellctl.daemon.preflight import PreflightError, probe_writable
from cellctl.daemon.scan import ScanRunner
from cellctl.daemon.states import CellStateMachine, Transition
from cellctl.daemon.stream import ScanStream
from cellctl.daemon.wiring import CellDrivers, build_drivers, rws_password
from cellctl.jobstore.jobs import (
    JobRecord,
    JobStore,
    JobStoreError,
    RecordRetry,
    lock_data_dir,
    reanalysis_problem,
)
from cellctl.logging import bind_context
from cellctl.motion import ProgressEvent
from cellctl.motion.link import MotionLinkError
from drivers.abb_egm import rws_protocol as rw
from drivers.runtime import (
    heap_summary,
    hold_cpu_wakeup_latency,
    release_freed_memory,
    rss_mb,
    stop_on_signals,
    use_realtime_loop,
)

log = structlog.get_logger(__name__)


class DaemonError(Exception):
    """The daemon cannot start (configuration, ports, Zenoh)."""


#: controller states (RWS ctrl-state) in which an emergency stop counts as released and reset
CONTROLLER_RESET_STATES = (rw.MOTOROFF, rw.MOTORON, rw.EMERGENCYSTOPRESET)
#: ended jobs kept in the state publication's ``recent`` list
RECENT_JOBS = 8


class CellDaemon:
    """The service. ``await run(stop)`` until ``stop`` is set; returns the exit code."""

    def __init__(self, cfg: CellConfig) -> None:
        self.cfg = cfg
        self.settings = cfg.daemon  # the [daemon] section: one source of truth
        self.keys = Keys(cfg.key_prefix)
        self.store = JobStore(cfg.cell.data_dir)
        self.audit = AuditLog(cfg.cell.data_dir)  # who asked for what (docs/api.md, "Who asked")
        self.designs_dir = Path(cfg.cell.designs_dir)
        self.sm = CellStateMachine(self._on_transition)
        self.session: zenoh.Session | None = None
        self.dispatcher: Dispatcher | None = None
        self.drivers: CellDrivers | None = None
        self.handover: Handover | None = None
        self._scanner: ScanRunner | None = None
        self._publisher: zenoh.Publisher | None = None
        self._entities: list[Any] = []  # Zenoh queryables and tokens, undeclared at the end
        self._current: ActiveJob | None = None  # the job shown in the state publication
        self._scan_job: ActiveJob | None = None  # the job holding the robot
        self._analyses: set[asyncio.Task] = set()
        self._analysing: dict[str, ActiveJob] = {}  # scanned jobs whose report is pending, by id
        self._queue: collections.deque[ActiveJob] = collections.deque()  # triggers waiting for the robot
        self._recent: collections.deque[JobProgress] = collections.deque(maxlen=RECENT_JOBS)
        self._workers: list[str] = []
        self._incompatible: list[str] = []
        self._analysis_tasks: dict[str, asyncio.Task] = {}
        self._loop: asyncio.AbstractEventLoop | None = None
        self._unsaved = RecordRetry(self.store)  # records the disk refused, written again later

    # ------------------------------------------------------------------------- life cycle

    async def run(self, stop: asyncio.Event) -> int:
        """Start everything, serve until ``stop``, stop smoothly. Returns 0 (or 2 on a start failure)."""
        self._loop = asyncio.get_running_loop()
        cfg = self.cfg
        bind_context(cell_id=cfg.cell.id)
        try:  # before anything else touches the job store: one daemon per data directory
            lock_fd = lock_data_dir(cfg.cell.data_dir)
        except JobStoreError as exc:
            log.error("data_dir_locked", error=str(exc))
            return 2
        try:
            return await self._serve(stop)
        finally:
            os.close(lock_fd)

    async def _serve(self, stop: asyncio.Event) -> int:
        cfg = self.cfg
        interrupted = self.store.recover()
        for rec in interrupted[-RECENT_JOBS:]:
            # published with the first state: a client still waiting on one of them (`cellctl scan
            # --wait` across the restart) learns that it ended instead of waiting for its timeout
            self._recent.append(self._progress(ActiveJob(rec)))
        try:
            password = rws_password(cfg.robot)
            zcfg = build_zenoh_config(cfg.zenoh, role="serve", key_prefix=cfg.key_prefix)
        except (ConfigError, ZenohSetupError) as exc:
            log.error("daemon_config_invalid", error=str(exc))
            return 2
        drv = self.drivers = build_drivers(cfg, password)
        drv.motion.on_death = self._on_motion_death
        try:
            # the motion process binds the EGM port and answers the controller from here on
            await drv.motion.start()
        except MotionLinkError as exc:
            log.error("motion_start_failed", host=cfg.robot.egm_host, port=cfg.robot.egm_port, error=str(exc))
            return 2
        try:
            self.session = await asyncio.to_thread(open_session, zcfg, what="daemon session")
        except ZenohSetupError as exc:
            log.error("zenoh_open_failed", error=str(exc))
            await drv.motion.close()
            await drv.rws.close()
            return 2
        self._scanner = ScanRunner(cfg, self.store, drv, self)
        periodic = None
        try:
            s = self.session
            self._entities.append(declare_async_queryable(s, self.keys.trigger, self._on_trigger))
            for action in ("pause", "resume", "abort", "reset", "reanalyse"):
                self._entities.append(
                    declare_async_queryable(s, self.keys.control(action), self._control_handler(action))
                )
            self._entities.append(declare_async_queryable(s, self.keys.stats, self._on_stats))
            self._entities.append(s.liveliness().declare_token(self.keys.daemon_alive))
            self._publisher = s.declare_publisher(self.keys.state, encoding=zenoh.Encoding.APPLICATION_JSON)
            self.dispatcher = Dispatcher(
                s, self.keys, DispatchSettings.from_config(cfg),
                DispatchHooks(on_workers=self._on_workers, on_assigned=self._on_assigned, on_retry=self._on_retry),
            )  # fmt: skip
            self.handover = Handover(cfg, self.store, self.dispatcher, self._job_state)
            await self.dispatcher.start()
            n_cancelled = sum(r.state == JobState.CANCELLED.value for r in interrupted)
            n_interrupted = len(interrupted) - n_cancelled
            msg = (
                f"{n_interrupted} interrupted job(s) recovered, {n_cancelled} queued job(s) cancelled"
                if interrupted
                else "ready"
            )
            self.sm.to(CellState.IDLE, msg)
            periodic = asyncio.create_task(self._publish_periodically(), name="state-publisher")
            log.info("daemon_ready", key_prefix=self.keys.prefix, egm_port=self.endpoint_port)
            await stop.wait()
            await self._shutdown()
        finally:
            if periodic is not None:
                periodic.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await periodic
            if self.dispatcher is not None:
                await self.dispatcher.close()
            for ent in self._entities:
                with contextlib.suppress(Exception):
                    ent.undeclare()
            if self._publisher is not None:
                with contextlib.suppress(Exception):
                    self._publisher.undeclare()
            await asyncio.to_thread(close_session, self.session)
            await drv.motion.close()
            await drv.rws.close()
        log.info("daemon_stopped")
        return 0

    @property
    def endpoint_port(self) -> int | None:
        motion = None if self.drivers is None else self.drivers.motion
        return None if motion is None or not motion.alive else int(motion.local_address[1])

    def _on_motion_death(self, reason: str) -> None:
        """The motion process ended on its own: a running scan fails with the reason (its execution
        ends FAULTED), and the cell is faulted until ``reset`` brings up a new one."""
        if self.sm.state not in (CellState.STOPPING, CellState.FAULTED, CellState.EMERGENCY_STOPPED):
            self.sm.to(CellState.FAULTED, f"motion fault: {reason}; reset starts a new motion process")

    async def _shutdown(self) -> None:
        """Stop a scan smoothly (job interrupted, raw flushed), stop waiting for reports."""
        self.sm.to(CellState.STOPPING, "shutdown requested")
        self._cancel_queue("the daemon stopped while the job was queued; trigger it again")
        self._publish()
        job = self._scan_job
        if job is not None and job.task is not None:
            job.stop_reason = "shutdown"
            if job.executor is not None:
                job.executor.abort()
            with contextlib.suppress(Exception, asyncio.CancelledError):
                await asyncio.wait_for(asyncio.shield(job.task), 60.0)
            if not job.task.done():
                job.task.cancel()
        for task in list(self._analyses):
            task.cancel()
        for task in list(self._analyses):
            with contextlib.suppress(Exception, asyncio.CancelledError):
                await task
        if self.handover is not None:
            self.handover.try_now()  # results the disk refused: one last attempt
        self._unsaved.try_now()  # a record the disk still refuses is logged; start-up recovers it
        self._publish()

    # ------------------------------------------------------------------------- publication

    async def _on_stats(self, query: zenoh.Query) -> None:
        """``<prefix>/stats``: the daemon's counters since it started (docs/api.md) for monitoring and the
        soak: the EGM endpoint's statistics, resident memory, malformed worker messages."""
        heap = None
        if tracemalloc.is_tracing():  # PYTHONTRACEMALLOC=1: where the Python heap is, for a leak hunt
            heap = await asyncio.to_thread(heap_summary)  # a snapshot takes seconds
        body = DaemonStats(
            cell_id=self.cfg.cell.id, t_utc=now_utc(), rss_mb=rss_mb(),
            egm=(self.drivers.motion.stats.snapshot() or None) if self.drivers is not None else None,
            motion_realtime=None if self.drivers is None else (self.drivers.motion.realtime),
            dispatch_malformed=0 if self.dispatcher is None else self.dispatcher.malformed, python_heap=heap,
        )  # fmt: skip
        query.reply(query.key_expr, body.to_json(), encoding=JSON)

    def _on_transition(self, tr: Transition) -> None:
        self._publish()

    def _on_assigned(self, job_id: str, worker_id: str, attempt: int) -> None:
        job = self._analysing.get(job_id)
        if job is not None and job.record.state not in {s.value for s in FINAL_JOB_STATES}:
            job.worker_id = worker_id
            self._job_state(job, JobState.ANALYSING, f"analysing on {worker_id} (attempt {attempt})")

    def _on_retry(self, job_id: str, worker_id: str, reason: str) -> None:
        job = self._analysing.get(job_id)
        if job is not None and job.record.state not in {s.value for s in FINAL_JOB_STATES}:
            job.worker_id = None
            self._job_state(job, JobState.WAITING_FOR_WORKER, f"taken back from {worker_id}: {reason}")

    def _on_workers(self, workers: list[str]) -> None:
        self._workers = list(workers)
        if self.dispatcher is not None:
            self._incompatible = [f"{w}: {why}" for w, why in self.dispatcher.incompatible.items()]
        self._publish()

    @staticmethod
    def _progress(job: ActiveJob) -> JobProgress:
        return JobProgress(
            job_id=job.record.job_id,
            plate_id=job.record.plate_id,
            state=JobState(job.record.state),
            stage=job.stage,
            fraction=float(min(max(job.fraction, 0.0), 1.0)),
            profiles=job.profiles if job.session is None else job.session.profiles,
            points=job.points,
            worker_id=job.worker_id,
            message=(job.record.history[-1]["message"] if job.record.history else "")[:500],
            motion=job.motion,
        )

    def status(self) -> CellStatus:
        """The state publication's payload."""
        job = self._current
        queue = [
            QueuedJob(job_id=j.record.job_id, plate_id=j.record.plate_id, position=i + 1,
                      queued_utc=j.record.created_utc)
            for i, j in enumerate(self._queue)
        ]  # fmt: skip
        return CellStatus(
            cell_id=self.cfg.cell.id,
            state=self.sm.state,
            t_utc=now_utc(),
            job=None if job is None else self._progress(job),
            queued=len(queue),
            queue=queue,
            analyses=[self._progress(j) for j in self._analysing.values()],
            recent=list(self._recent),
            workers=self._workers,
            workers_refused=self._incompatible,
            message=self.sm.message[:500],
        )

    def _publish(self) -> None:
        pub = self._publisher
        if pub is None:
            return
        try:
            pub.put(self.status().to_json())
        except Exception as exc:  # the session may be closing
            log.warning("state_publish_failed", error=str(exc))

    async def _publish_periodically(self) -> None:
        while True:
            await asyncio.sleep(self.settings.status_period_s)
            self._publish()

    # ------------------------------------------------------------------------- API handlers

    async def _on_trigger(self, query: zenoh.Query) -> None:
        await handle_trigger(query, self.designs_dir, self._accept)

    async def _ctrl_state(self) -> str:
        """The controller's state through RWS ("" when it cannot be read)."""
        try:
            assert self.drivers is not None
            return await self.drivers.rws.get_ctrl_state()
        except Exception as exc:
            log.warning("rws_state_unreadable", error=str(exc))
            return ""

    def _check_cell_accepts(self) -> None:
        """Refuse a trigger the cell cannot take now (TriggerError naming why)."""
        if self.sm.state == CellState.EMERGENCY_STOPPED:
            # an e-stop is cleared by the operator (control/reset), never by a remote trigger
            raise TriggerError(
                "not_allowed", "payload",
                "the cell is emergency-stopped: release and reset the controller's emergency stop, "
                "then send control/reset (cellctl reset)",
            )  # fmt: skip
        if self.sm.state in (CellState.STARTING, CellState.STOPPING):
            raise TriggerError("not_allowed", "payload", f"the cell is {self.sm.state.value}")
        busy = self._scan_job is not None or bool(self._queue)
        if not busy:
            return
        holder = self._scan_job.record.job_id if self._scan_job is not None else self._queue[0].record.job_id
        qmax = self.settings.queue_max
        if qmax == 0:
            raise TriggerError("busy", "payload", f"the cell is scanning job {holder}; try again later")
        if len(self._queue) >= qmax:
            raise TriggerError(
                "queue_full", "payload",
                f"{len(self._queue)} job(s) already wait behind job {holder} ([daemon] queue_max = {qmax}); "
                "try again when one has started",
            )  # fmt: skip

    async def _accept(self, req: TriggerRequest, design_path: Path) -> TriggerAccepted:
        """A valid trigger taken (started or queued) or refused (TriggerError); either is audited."""
        try:
            accepted = await self._accept_inner(req, design_path)
        except TriggerError as err:
            self.audit.write("trigger", user=req.requested_by, job_id=None, outcome=f"refused: {err.code}",
                             message=err.message)  # fmt: skip
            raise
        self.audit.write("trigger", user=req.requested_by, job_id=accepted.job_id, outcome=accepted.state)
        return accepted

    async def _accept_inner(self, req: TriggerRequest, design_path: Path) -> TriggerAccepted:
        self._check_cell_accepts()  # before the slower checks: a refusal costs nothing
        if req.placement is not None and any(abs(v) > 1e-9 for v in req.placement.rpy_deg[:2]):
            raise TriggerError(
                "invalid", "placement.rpy_deg", "plates lie flat on the bed: roll and pitch must be 0"
            )
        try:  # a read-only or full data directory refuses the trigger: no record, no motion
            await asyncio.to_thread(probe_writable, self.store.root)
        except PreflightError as exc:
            raise TriggerError("not_allowed", exc.field, exc.message) from None
        record = JobRecord(
            job_id=new_job_id(),
            plate_id=req.plate_id,
            design=req.design,
            design_path=str(design_path),
            placement=req.placement,
            note=req.note,
            analysis=req.analysis_options().record(),
        )
        if req.requested_by is not None:  # who asked: the first line of the job's history
            record.history.append({"state": record.state, "t_utc": record.created_utc,
                                   "message": f"triggered by {req.requested_by}", "by": req.requested_by})  # fmt: skip
        # Decide again after the awaits above (another trigger may have been taken meanwhile); from
        # here to the reply nothing awaits, so two triggers can never both start.
        self._check_cell_accepts()
        job = ActiveJob(record)
        if self._scan_job is None and not self._queue:
            self._create_record(record)
            self._start_job(job)
            return TriggerAccepted(job_id=record.job_id, state="started")
        position = len(self._queue) + 1
        record.history.append(
            {"state": record.state, "t_utc": record.created_utc, "message": f"queued at position {position}"}
        )
        self._create_record(record)
        job.stage = JobState.QUEUED.value
        self._queue.append(job)
        log.info("job_queued", job_id=record.job_id, position=position)
        self._publish()
        return TriggerAccepted(job_id=record.job_id, state="queued", queue_position=position)

    def _create_record(self, record: JobRecord) -> None:
        try:
            self.store.create(record)
        except (JobStoreError, OSError) as exc:  # the trigger is refused, the daemon serves on
            log.error("job_record_failed", job_id=record.job_id, error=str(exc))
            raise TriggerError("internal", "payload", f"cannot store the job: {exc}") from None

    def _start_job(self, job: ActiveJob) -> None:
        self._scan_job = self._current = job
        job.task = asyncio.create_task(self._run_job(job), name=f"job-{job.record.job_id}")

    def _recheck_queued(self, job: ActiveJob) -> str:
        """Cheap checks before a queued job starts: what changed since its trigger ("" when nothing)."""
        path = Path(job.record.design_path)
        root = self.designs_dir.resolve()
        if not path.resolve().is_relative_to(root) or not path.is_file():
            return f"the design file {job.record.design!r} is gone from designs_dir"
        return ""

    def _start_next(self) -> None:
        """Start the first queued job when the robot is free and the cell is idle."""
        while self._queue and self._scan_job is None and self.sm.state == CellState.IDLE:
            job = self._queue.popleft()
            problem = self._recheck_queued(job)
            if problem:
                self._job_state(job, JobState.FAILED, f"refused at start: {problem}; nothing moved")
                continue
            log.info("job_dequeued", job_id=job.record.job_id, waiting=len(self._queue))
            self._start_job(job)
        self._publish()

    def _cancel_queue(self, reason: str) -> None:
        """Every queued job cancelled (never started): after a fault, an e-stop or a shutdown the
        robot moves again only on a fresh trigger."""
        while self._queue:
            self._job_state(self._queue.popleft(), JobState.CANCELLED, reason)

    def _after_scan(self, job: ActiveJob) -> None:
        """The robot is free again: go on with the queue, or drop it if the cell must not move."""
        if self.sm.state in (CellState.FAULTED, CellState.EMERGENCY_STOPPED):
            self._cancel_queue(
                f"cancelled: the cell went {self.sm.state.value} during job {job.record.job_id}; "
                "trigger it again once the cell is reset"
            )
        elif self.sm.state != CellState.STOPPING:
            self._start_next()

    def _control_handler(self, action: str):
        """A control queryable: parse, act, reply (ControlReply, or an ApiError naming the field)."""

        async def handler(query: zenoh.Query) -> None:
            req: ControlRequest | None = None
            try:
                req = parse_control(read_payload(query, ControlError))
                reply = await self._control(action, req)
            except ControlError as err:
                CONTROL_LOG.refused_one(err)
                if req is not None:  # a request that said who and what, refused: audited
                    self.audit.write(action, user=req.requested_by, job_id=req.job_id,
                                     outcome=f"refused: {err.code}", message=err.message)  # fmt: skip
                query.reply_err(err.to_api_error().to_json(), encoding=JSON)
                return
            log.info("control", action=action, job_id=reply.job_id, job_state=reply.job_state,
                     requested_by=req.requested_by)  # fmt: skip
            self.audit.write(
                action, user=req.requested_by, job_id=reply.job_id, outcome=reply.job_state or "ok"
            )
            if req.requested_by is not None and reply.job_id is not None:
                self._note_by(reply.job_id, f"{action} by {req.requested_by}", req.requested_by)
            query.reply(query.key_expr, reply.to_json(), encoding=JSON)

        return handler

    def _note_by(self, job_id: str, message: str, user: str) -> None:
        """A line in a job's history naming who asked for what (the live record when the job is
        held here, else the one on disk)."""
        live = (self._scan_job, self._current, *self._analysing.values(), *self._queue)
        rec = next((j.record for j in live if j is not None and j.record.job_id == job_id), None)
        try:
            if rec is None:
                rec = self.store.load(job_id)
            rec.history.append({"state": rec.state, "t_utc": now_utc(), "message": message, "by": user})
            self.store.save(rec)
        except JobStoreError as exc:
            log.error("job_record_write_failed", job_id=job_id, error=str(exc))
            if rec is not None:
                self._unsaved.add(rec)

    async def _control(self, action: str, req: ControlRequest) -> ControlReply:
        if action == "reset":
            return await self._reset(req)
        if action == "reanalyse":
            return self._reanalyse(req)
        if action == "abort" and req.job_id is not None:
            queued = next((j for j in self._queue if j.record.job_id == req.job_id), None)
            if queued is not None:
                self._queue.remove(queued)
                self._job_state(queued, JobState.CANCELLED, "cancelled while queued (abort); nothing moved")
                return ControlReply(
                    action="abort", job_id=req.job_id, state=self.sm.state.value, job_state="cancelled"
                )
            analysing = self._analysing.get(req.job_id)
            scanning = self._scan_job is not None and self._scan_job.record.job_id == req.job_id
            if analysing is not None and not scanning:
                return self._abort_analysis(analysing)
        job = self._scan_job
        if req.job_id is not None and (job is None or job.record.job_id != req.job_id):
            where = "scanning, queued or analysing" if action == "abort" else "scanning"
            raise ControlError("no_job", "job_id", f"job {req.job_id} is not {where}")
        if job is None or (job.executor is None and action != "abort"):
            raise ControlError("no_job", "", f"no scan in progress to {action}")
        if action != "abort" and job.stop_reason is not None:
            # the executor would take the request and ignore it: a stopping job never moves again
            why = "aborted" if job.stop_reason == "abort" else f"stopping ({job.stop_reason})"
            raise ControlError(
                "not_allowed", "payload", f"job {job.record.job_id} is being {why}: it cannot be {action}d"
            )
        # the reply says where the job goes, not where the request found it: the executor pauses
        # along its path and reports paused when it holds (the publication follows then)
        state, job_state = self.sm.state.value, job.record.state
        if action == "pause":
            job.executor.pause()
            state, job_state = CellState.PAUSED.value, JobState.PAUSED.value
        elif action == "resume":
            job.executor.resume()
            state, job_state = CellState.SCANNING.value, JobState.SCANNING.value
        else:
            # before the executor exists (planning, program start) the flag stops the job before motion
            job.stop_reason = "abort"
            if job.executor is not None:
                job.executor.abort()
        return ControlReply(
            action=action,  # type: ignore[arg-type]
            job_id=job.record.job_id,
            state=state,
            job_state=job_state,
        )

    async def _motion_up(self) -> None:
        """A motion process that is gone is started again (``reset``); ControlError if it cannot be."""
        motion = None if self.drivers is None else self.drivers.motion
        if motion is None or motion.alive:
            return
        try:
            await motion.restart()
        except MotionLinkError as exc:
            raise ControlError(
                "not_allowed", "payload", f"the motion process did not start again: {exc}"
            ) from None
        log.info("motion_process_restarted", pid=motion.pid)

    async def _reset(self, req: ControlRequest) -> ControlReply:
        """Clear ``emergency_stopped`` (the controller must be released and reset) or ``faulted``."""
        if req.job_id is not None:
            raise ControlError("invalid", "job_id", "reset takes no job_id")
        if self.sm.state == CellState.EMERGENCY_STOPPED:
            ctrl = await self._ctrl_state()
            if ctrl not in CONTROLLER_RESET_STATES:
                raise ControlError(
                    "not_allowed", "payload",
                    f"the controller is {ctrl or 'unreadable over RWS'}: release its emergency stop and "
                    "reset it (motors off) first",
                )  # fmt: skip
            await self._motion_up()
            if self.sm.state == CellState.EMERGENCY_STOPPED:  # unchanged while RWS answered
                self.sm.to(
                    CellState.IDLE, f"reset by the operator after the emergency stop (controller {ctrl})"
                )
        elif self.sm.state == CellState.FAULTED:
            await self._motion_up()
            self.sm.to(CellState.IDLE, "reset by the operator after a fault")
        elif self.sm.state != CellState.IDLE:
            raise ControlError(
                "not_allowed", "payload", f"the cell is {self.sm.state.value}: nothing to reset"
            )
        return ControlReply(action="reset", job_id=None, state=self.sm.state.value)

    def _reanalyse(self, req: ControlRequest) -> ControlReply:
        """Rebuild an interrupted (or failed) job's cloud from its raw files and send it to the workers
        again; the robot does not move."""
        if req.job_id is None:
            raise ControlError("invalid", "job_id", 'required: {"job_id": ...}')
        job_id = req.job_id
        if job_id in self._analysing:
            raise ControlError("not_allowed", "job_id", f"job {job_id} is being analysed already")
        try:
            record = self.store.load(job_id)
        except JobStoreError as exc:
            if (
                not (self.store.job_dir(job_id) / "job.json").exists()
                or not (self.store.raw_dir(job_id) / "profiles.craw").exists()
            ):
                raise ControlError("no_job", "job_id", f"no job {job_id} in the job store") from None
            try:  # the record is unreadable but the raw data is there: set the record aside, go on
                record = self.store.quarantine(job_id, exc.reason)
            except JobStoreError as exc2:
                raise ControlError("internal", "job_id", f"job {job_id}: {exc2}") from None
        if record.state not in (JobState.INTERRUPTED.value, JobState.FAILED.value, JobState.ABORTED.value):
            raise ControlError("not_allowed", "job_id", f"job is {record.state}")
        if not (self.store.raw_dir(job_id) / "profiles.craw").exists():
            raise ControlError("not_allowed", "job_id", "job has no raw profiles")
        if problem := reanalysis_problem(record, self.designs_dir):
            raise ControlError("not_allowed", "job_id", f"job {job_id}: {problem}")
        job = ActiveJob(record)
        self._current = job
        self._track_analysis(job, asyncio.create_task(self._analyse(job), name=f"reanalyse-{job_id}"))
        return ControlReply(
            action="reanalyse", job_id=job_id, state=self.sm.state.value, job_state="waiting_for_worker"
        )

    def _abort_analysis(self, job: ActiveJob) -> ControlReply:
        """Abort a job's analysis (a re-analysis, or the analysis of a scan that ended): the worker
        holding it is told to stop, the job ends ``aborted`` with its raw data (it can be
        re-analysed again). The robot is not concerned."""
        job_id = job.record.job_id
        job.stop_reason = "abort"
        if self.dispatcher is not None and job_id in self.dispatcher.pending:
            self.dispatcher.abandon(job_id, "aborted by the operator")
        task = self._analysis_tasks.get(job_id)
        if task is not None:
            task.cancel()
        log.info("analysis_aborted", job_id=job_id)
        return ControlReply(action="abort", job_id=job_id, state=self.sm.state.value, job_state="aborted")

    def _track_analysis(self, job: ActiveJob, task: asyncio.Task) -> None:
        self._analyses.add(task)
        self._analysing[job.record.job_id] = job
        self._analysis_tasks[job.record.job_id] = task

        def done(t: asyncio.Task) -> None:
            self._analyses.discard(t)
            self._analysing.pop(job.record.job_id, None)
            if self._analysis_tasks.get(job.record.job_id) is t:
                del self._analysis_tasks[job.record.job_id]
            self._publish()

        task.add_done_callback(done)

    # ------------------------------------------------------------------------- the job

    def _job_state(self, job: ActiveJob, state: JobState, message: str = "", **info: Any) -> None:
        """Record a job's state: in memory, on disk, in the publication. Never raises: a record the
        disk does not take (full, read-only) keeps its new state in memory and in the publication,
        and its write is retried until it succeeds (:class:`~cellctl.jobstore.jobs.RecordRetry`)."""
        job.stage = state.value
        try:
            self.store.set_state(job.record, state, message, **info)
        except JobStoreError as exc:  # set_state changed the record before it failed to write it
            log.error("job_record_write_failed", job_id=job.record.job_id, state=state.value, error=str(exc))
            self._unsaved.add(job.record)
        if state in FINAL_JOB_STATES:
            self._recent.append(self._progress(job))
            if self.sm.state == CellState.IDLE and self.sm.message.startswith(f"job {job.record.job_id} "):
                # the idle cell's message named this job as analysing: say how it ended
                self.sm.message = f"job {job.record.job_id} {state.value}"
            # a job's arrays are freed now; hand the freed heap pages back (off the loop)
            if self._loop is not None:
                self._loop.run_in_executor(None, release_freed_memory)
        self._publish()

    def _record_progress(self, job: ActiveJob, state: JobState, message: str) -> None:
        """A pause / resume in the job's record (never raises, as :meth:`_job_state`)."""
        stage = job.stage
        self._job_state(job, state, message)
        job.stage = stage

    async def _run_job(self, job: ActiveJob) -> None:
        rec = job.record
        bind_context(job_id=rec.job_id)
        try:
            assert self._scanner is not None
            ok = await self._scanner.scan(job)
        except Exception as exc:
            log.exception("job_scan_failed", job_id=rec.job_id)
            why = f"{type(exc).__name__}: {exc}"
            info: dict[str, Any] = {}
            if job.stop_reason == "disk":
                why = f"raw data could not be written ({exc}); the scan was stopped, what was written is kept"
                # the profiles on disk, and those counted before the failure that never got there
                lost = getattr(exc, "profiles_lost", None)
                info = {"profiles": job.profiles, **({"profiles_lost": lost} if lost is not None else {})}
            self._job_state(job, JobState.FAILED, why, **info)
            self._scan_job = None
            if self.sm.state != CellState.STOPPING:
                # an e-stop before the executor ran shows up here (motors on refused, EGM never came)
                if await self._ctrl_state() == rw.EMERGENCYSTOP:
                    self.sm.to(CellState.EMERGENCY_STOPPED, f"emergency stop during job {rec.job_id}")
                elif self.sm.state not in (CellState.STOPPING, CellState.EMERGENCY_STOPPED):
                    self.sm.to(CellState.FAULTED, f"job {rec.job_id}: {exc}")
            self._after_scan(job)
            return
        self._scan_job = None
        if not ok:
            if self.sm.state not in (CellState.STOPPING, CellState.FAULTED, CellState.EMERGENCY_STOPPED):
                self.sm.to(CellState.IDLE, f"job {rec.job_id} {rec.state}")
            self._after_scan(job)
            return
        if self.sm.state == CellState.STOPPING:
            self._job_state(job, JobState.INTERRUPTED, "the daemon stopped before the analysis")
            return
        if self.sm.state in (CellState.SCANNING, CellState.PAUSED):
            # the robot is free: idle (the next queued job may start) while the analysis runs
            self.sm.to(CellState.IDLE, f"job {rec.job_id} scanned; analysing")
        self._track_analysis(job, asyncio.create_task(self._analyse(job), name=f"analyse-{rec.job_id}"))
        self._after_scan(job)

    # ------------------------------------------------------------------------- the scan's host (ScanHost)

    @property
    def cell_state(self) -> CellState:
        return self.sm.state

    def to_cell(self, state: CellState, message: str) -> None:
        self.sm.to(state, message)
        if state in (CellState.FAULTED, CellState.EMERGENCY_STOPPED):
            # at once, not when the scan's task has wound down: an operator's reset in between
            # would otherwise find the queue waiting and start the next job after the stop
            self._cancel_queue(
                f"cancelled: the cell went {state.value} ({message}); trigger it again once the cell is reset"
            )

    def live_feed(self, job_id: str) -> Callable[[list, int], None] | None:
        """The scan's thinned live cloud for displays (``Keys.live_cloud``, cellctl/daemon/live.py)."""
        if self.session is None:
            return None
        from cellctl.daemon.live import LiveCloudFeed

        feed = LiveCloudFeed(
            self.session, self.keys.live_cloud(job_id), job_id, rate_hz=self.cfg.laser.rate_hz
        )
        return feed.add

    async def cloud_stream(self, job: ActiveJob) -> ScanStream | None:
        """The scan's cloud streamed to a worker pass by pass (cellctl/daemon/stream.py); None when it
        cannot be (the cloud then goes whole after the scan)."""
        if self.handover is None:
            return None
        try:
            return await self.handover.open_stream(job)
        except Exception as exc:
            log.warning("stream_not_opened", job_id=job.record.job_id, error=str(exc))
            return None

    def job_state(self, job: ActiveJob, state: JobState, message: str = "", **info: Any) -> None:
        self._job_state(job, state, message, **info)

    async def ctrl_state(self) -> str:
        return await self._ctrl_state()

    def stop_requested(self, job: ActiveJob) -> bool:
        return job.stop_reason is not None or self.sm.state == CellState.STOPPING

    def on_progress(self, job: ActiveJob, ev: ProgressEvent) -> None:
        job.fraction = ev.percent / 100.0
        job.stage = f"{ev.segment} ({ev.pass_index}/{ev.pass_count})"
        if ev.state == "paused" and self.sm.state == CellState.SCANNING:
            self.sm.to(CellState.PAUSED, f"job {job.record.job_id} paused")
            self._record_progress(job, JobState.PAUSED, "paused")
        elif ev.state in ("running", "resuming", "moving_to_start") and self.sm.state == CellState.PAUSED:
            self.sm.to(CellState.SCANNING, f"job {job.record.job_id} resumed")
            self._record_progress(job, JobState.SCANNING, "resumed")
        self._publish()

    # ------------------------------------------------------------------------- the analysis

    async def _analyse(self, job: ActiveJob) -> None:
        """The hand-over (:mod:`cellctl.daemon.handover`); the robot is free meanwhile."""
        assert self.handover is not None
        if self._scan_job is None and self.sm.state not in (CellState.STOPPING, CellState.FAULTED):
            self.sm.to(CellState.IDLE, f"job {job.record.job_id} scanned; analysing")
        await self.handover.analyse(job)


async def run_daemon(cfg: CellConfig) -> int:
    """Run the daemon (``cfg.daemon`` holds its knobs) until SIGTERM / SIGINT; returns the exit code."""
    stop = asyncio.Event()
    if cfg.daemon.realtime:
        use_realtime_loop()
        hold_cpu_wakeup_latency(0)
    release_signals = stop_on_signals(stop)
    try:
        return await CellDaemon(cfg).run(stop)
    finally:
        release_signals()
