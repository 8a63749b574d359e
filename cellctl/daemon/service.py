"""`cellctl run`: the cell daemon, one asyncio service owning the EGM endpoint, RWS and the sensor.

A job (one remote trigger): validate -> plan (in a thread) -> motors on and the EGM program started
through RWS -> execute the plan over EGM while the HD8 client streams profiles into the acquisition
(raw files first) -> EGM program ended -> the whole-scan cloud rebuilt from the raw files ->
published to the analysis workers through the :class:`~cellctl.api.dispatch.Dispatcher` -> the report
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
import ctypes
import json
import os
import signal
import struct
import time
import tracemalloc
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import structlog

from analysis.placement import Placement
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
from cellctl.config import CellConfig, ConfigError, resolve_secret
from cellctl.daemon.jobs import JobRecord, JobStore, JobStoreError
from cellctl.daemon.preflight import PreflightError, check_data_dir, probe_writable, raw_bytes_estimate
from cellctl.daemon.states import CellStateMachine, Transition
from cellctl.logging import bind_context
from cellctl.signals import stop_on_signals

log = structlog.get_logger(__name__)


class DaemonError(Exception):
    """The daemon cannot start (configuration, ports, Zenoh)."""


#: controller states (RWS ctrl-state) in which an emergency stop counts as released and reset
CONTROLLER_RESET_STATES = ("motoroff", "motoron", "emergencystopreset")
#: ended jobs kept in the state publication's ``recent`` list
RECENT_JOBS = 8


class _Job:
    """The running job's live objects (executor, counters) beside its stored record."""

    def __init__(self, record: JobRecord) -> None:
        self.record = record
        self.executor: Any = None
        self.profiles = 0
        self.points = 0
        self.fraction = 0.0
        self.stage = "queued"
        self.worker_id: str | None = None
        self.stop_reason: str | None = None  # "shutdown" or "abort"
        self.cloud: Any = None  # the live AssembledScan of a finished scan, until published
        self.task: asyncio.Task | None = None


class CellDaemon:
    """The service. ``await run(stop)`` until ``stop`` is set; returns the exit code."""

    def __init__(self, cfg: CellConfig) -> None:
        self.cfg = cfg
        self.settings = cfg.daemon  # the [daemon] section: one source of truth
        self.keys = Keys(cfg.key_prefix)
        self.store = JobStore(cfg.cell.data_dir)
        self.designs_dir = Path(cfg.cell.designs_dir)
        self.sm = CellStateMachine(self._on_transition)
        self.session: Any = None
        self.dispatcher: Any = None
        self.endpoint: Any = None
        self.rws: Any = None
        self.program: Any = None
        self._entities: list[Any] = []
        self._current: _Job | None = None  # the job shown in the state publication
        self._scan_job: _Job | None = None  # the job holding the robot
        self._analyses: set[asyncio.Task] = set()
        self._analysing: dict[str, _Job] = {}  # scanned jobs whose report is pending, by id
        self._queue: collections.deque[_Job] = collections.deque()  # triggers waiting for the robot
        self._recent: collections.deque[JobProgress] = collections.deque(maxlen=RECENT_JOBS)
        self._workers: list[str] = []
        self._loop: asyncio.AbstractEventLoop | None = None

    # ------------------------------------------------------------------------- life cycle

    async def run(self, stop: asyncio.Event) -> int:
        """Start everything, serve until ``stop``, stop smoothly. Returns 0 (or 2 on a start failure)."""
        import zenoh

        from cellctl.api.dispatch import Dispatcher, DispatchHooks, DispatchSettings
        from cellctl.api.session import (
            ZenohSetupError,
            build_zenoh_config,
            close_session,
            declare_async_queryable,
            open_session,
        )
        from drivers.abb_egm.endpoint import EgmEndpoint, EgmEndpointConfig
        from drivers.abb_egm.rws_client import CellEgmProgram, EgmProgramSettings, RwsClient, RwsClientConfig

        self._loop = asyncio.get_running_loop()
        cfg = self.cfg
        bind_context(cell_id=cfg.cell.id)
        interrupted = self.store.recover()
        try:
            password = resolve_secret(
                cfg.robot.rws_password_env, cfg.robot.rws_password_file, what="robot.rws password"
            ).get_secret_value()
            zcfg = build_zenoh_config(cfg.zenoh, role="serve", key_prefix=cfg.key_prefix)
        except (ConfigError, ZenohSetupError) as exc:
            log.error("daemon_config_invalid", error=str(exc))
            return 2
        r = cfg.robot
        self.endpoint = EgmEndpoint(
            EgmEndpointConfig(
                host=r.egm_host,
                port=r.egm_port,
                watchdog_s=r.egm_watchdog_s,
                history_len=r.egm_history_len,
                # replies from their own SCHED_FIFO thread, off this loop, with a short GIL hand-over
                # (benchmarks/README.md, egm_latency; docs/robot-setup.md section 12)
                reply_thread=r.egm_reply_thread,
                reply_thread_priority=r.egm_reply_priority,
                reply_thread_cpus=tuple(r.egm_reply_cpus),
                switch_interval_s=r.egm_switch_interval_s,
                reply_spin_us=r.egm_reply_spin_us,
            )
        )
        try:
            await self.endpoint.start()
        except OSError as exc:
            log.error("egm_bind_failed", host=r.egm_host, port=r.egm_port, error=str(exc))
            return 2
        self.rws = RwsClient(
            RwsClientConfig(
                base_url=r.rws_url,
                profile=r.rws_profile,
                username=r.rws_user,
                password=password,
                timeout_s=r.rws_timeout_s,
                tls_ca_file=None if r.rws_ca_file is None else str(r.rws_ca_file),
                poll_interval_s=r.rws_poll_interval_s,
                mechunit=r.rws_mechunit,
            )
        )
        self.program = CellEgmProgram(
            self.rws,
            EgmProgramSettings(
                comm_timeout_s=r.egm_comm_timeout_s,
                pos_corr_gain=min(r.egm_pos_corr_gain, 1.0),
                max_speed_deviation_deg_s=r.egm_max_speed_deviation_deg_s,
                max_pos_deviation_deg=r.egm_max_pos_deviation_deg,
                cond_time_s=r.egm_cond_time_s,
                ramp_in_time_s=r.egm_ramp_in_s,
                lp_filter_hz=r.egm_lp_filter_hz,
                sample_rate_ms=float(r.egm_sample_rate_ms),
                task=r.rapid_task,
                module=r.rapid_module,
            ),
        )
        try:
            self.session = await asyncio.to_thread(open_session, zcfg, what="daemon session")
        except ZenohSetupError as exc:
            log.error("zenoh_open_failed", error=str(exc))
            await self.endpoint.close()
            await self.rws.close()
            return 2
        publisher = None
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
            publisher = s.declare_publisher(self.keys.state, encoding=zenoh.Encoding.APPLICATION_JSON)
            self._publisher = publisher
            self.dispatcher = Dispatcher(
                s, self.keys, DispatchSettings.from_config(cfg), DispatchHooks(on_workers=self._on_workers)
            )
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
            if publisher is not None:
                with contextlib.suppress(Exception):
                    publisher.undeclare()
            await asyncio.to_thread(close_session, self.session)
            await self.endpoint.close()
            await self.rws.close()
        log.info("daemon_stopped")
        return 0

    @property
    def endpoint_port(self) -> int | None:
        addr = getattr(self.endpoint, "local_address", None)
        return None if not addr else int(addr[1])

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
        self._publish()

    # ------------------------------------------------------------------------- publication

    async def _on_stats(self, query: Any) -> None:
        """``<prefix>/stats``: the daemon's counters since it started (docs/api.md) for monitoring and the
        soak: the EGM endpoint's statistics, resident memory, malformed worker messages."""
        heap = None
        if tracemalloc.is_tracing():  # PYTHONTRACEMALLOC=1: where the Python heap is, for a leak hunt
            heap = await asyncio.to_thread(_heap_summary)  # a snapshot takes seconds
        body = DaemonStats(
            cell_id=self.cfg.cell.id, t_utc=now_utc(), rss_mb=_rss_mb(),
            egm=self.endpoint.stats.snapshot() if self.endpoint is not None else None,
            dispatch_malformed=getattr(self.dispatcher, "malformed", 0), python_heap=heap,
        )  # fmt: skip
        query.reply(query.key_expr, body.to_json(), encoding=JSON)

    def _on_transition(self, tr: Transition) -> None:
        self._publish()

    def _on_workers(self, workers: list[str]) -> None:
        self._workers = list(workers)
        self._publish()

    @staticmethod
    def _progress(job: _Job) -> JobProgress:
        return JobProgress(
            job_id=job.record.job_id,
            plate_id=job.record.plate_id,
            state=JobState(job.record.state),
            stage=job.stage,
            fraction=float(min(max(job.fraction, 0.0), 1.0)),
            profiles=job.profiles,
            points=job.points,
            worker_id=job.worker_id,
            message=(job.record.history[-1]["message"] if job.record.history else "")[:500],
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
            message=self.sm.message[:500],
        )

    def _publish(self) -> None:
        pub = getattr(self, "_publisher", None)
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

    async def _on_trigger(self, query: Any) -> None:
        await handle_trigger(query, self.designs_dir, self._accept)

    async def _ctrl_state(self) -> str:
        """The controller's state through RWS ("" when it cannot be read)."""
        try:
            return await self.rws.get_ctrl_state()
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
        self._check_cell_accepts()  # before the slower checks: a refusal costs nothing
        if any(abs(v) > 1e-9 for v in req.placement.rpy_deg[:2]):
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
            placement=req.placement.model_dump(),
            note=req.note,
            analysis=req.analysis_options(),
        )
        # Decide again after the awaits above (another trigger may have been taken meanwhile); from
        # here to the reply nothing awaits, so two triggers can never both start.
        self._check_cell_accepts()
        job = _Job(record)
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

    def _start_job(self, job: _Job) -> None:
        self._scan_job = self._current = job
        job.task = asyncio.create_task(self._run_job(job), name=f"job-{job.record.job_id}")

    def _recheck_queued(self, job: _Job) -> str:
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

    def _after_scan(self, job: _Job) -> None:
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

        async def handler(query: Any) -> None:
            try:
                req = parse_control(read_payload(query, ControlError))
                reply = await self._control(action, req)
            except ControlError as err:
                CONTROL_LOG.refused_one(err)
                query.reply_err(err.to_api_error().to_json(), encoding=JSON)
                return
            log.info("control", action=action, job_id=reply.job_id, job_state=reply.job_state)
            query.reply(query.key_expr, reply.to_json(), encoding=JSON)

        return handler

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
        job = self._scan_job
        if req.job_id is not None and (job is None or job.record.job_id != req.job_id):
            where = "scanning or queued" if action == "abort" else "scanning"
            raise ControlError("no_job", "job_id", f"job {req.job_id} is not {where}")
        if job is None or (job.executor is None and action != "abort"):
            raise ControlError("no_job", "", f"no scan in progress to {action}")
        if action == "pause":
            job.executor.pause()
        elif action == "resume":
            job.executor.resume()
        else:
            # before the executor exists (planning, program start) the flag stops the job before motion
            job.stop_reason = "abort"
            if job.executor is not None:
                job.executor.abort()
        return ControlReply(
            action=action,  # type: ignore[arg-type]
            job_id=job.record.job_id,
            state=self.sm.state.value,
            job_state=job.record.state,
        )

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
            if self.sm.state == CellState.EMERGENCY_STOPPED:  # unchanged while RWS answered
                self.sm.to(
                    CellState.IDLE, f"reset by the operator after the emergency stop (controller {ctrl})"
                )
        elif self.sm.state == CellState.FAULTED:
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
        except JobStoreError:
            raise ControlError("no_job", "job_id", f"no job {job_id} in the job store") from None
        if record.state not in (JobState.INTERRUPTED.value, JobState.FAILED.value):
            raise ControlError("not_allowed", "job_id", f"job is {record.state}")
        if not (self.store.raw_dir(job_id) / "profiles.craw").exists():
            raise ControlError("not_allowed", "job_id", "job has no raw profiles")
        job = _Job(record)
        self._current = job
        self._track_analysis(job, asyncio.create_task(self._analyse(job), name=f"reanalyse-{job_id}"))
        return ControlReply(
            action="reanalyse", job_id=job_id, state=self.sm.state.value, job_state="waiting_for_worker"
        )

    def _track_analysis(self, job: _Job, task: asyncio.Task) -> None:
        self._analyses.add(task)
        self._analysing[job.record.job_id] = job

        def done(t: asyncio.Task) -> None:
            self._analyses.discard(t)
            self._analysing.pop(job.record.job_id, None)
            self._publish()

        task.add_done_callback(done)

    # ------------------------------------------------------------------------- the job

    def _job_state(self, job: _Job, state: JobState, message: str = "", **info: Any) -> None:
        job.stage = state.value
        self.store.set_state(job.record, state, message, **info)
        if state in FINAL_JOB_STATES:
            self._recent.append(self._progress(job))
            # a job's arrays are freed now; hand the freed heap pages back (off the loop)
            if self._loop is not None:
                self._loop.run_in_executor(None, release_freed_memory)
        self._publish()

    async def _run_job(self, job: _Job) -> None:
        rec = job.record
        bind_context(job_id=rec.job_id)
        try:
            ok = await self._scan(job)
        except Exception as exc:
            log.exception("job_scan_failed", job_id=rec.job_id)
            why = f"{type(exc).__name__}: {exc}"
            if job.stop_reason == "disk":
                why = f"raw data could not be written ({exc}); the scan was stopped, what was written is kept"
            self._job_state(job, JobState.FAILED, why)
            self._scan_job = None
            if self.sm.state != CellState.STOPPING:
                # an e-stop before the executor ran shows up here (motors on refused, EGM never came)
                if await self._ctrl_state() == "emergencystop":
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

    async def _scan(self, job: _Job) -> bool:
        """Plan, execute and acquire. True when the scan completed (raw files closed)."""
        from analysis.cad import design_mesh_from_file
        from analysis.mesh import MeshError
        from analysis.plates import PlateError
        from cellctl.acquisition.pipeline import Acquisition, AcquisitionSettings
        from cellctl.acquisition.rawstore import RawWriter
        from cellctl.motion import ExecState, ExecutorConfig, MotionExecutor
        from cellctl.planning import PlanInputError, PlannerSettings, PlanRefused, plan_scan
        from drivers.laser.client import HD8Client

        cfg, rec = self.cfg, job.record
        self.sm.to(CellState.PLANNING, f"planning job {rec.job_id}")
        self._job_state(job, JobState.PLANNING)
        try:
            design = await asyncio.to_thread(design_mesh_from_file, Path(rec.design_path))
            placement = Placement.model_validate(rec.placement)
            settings = PlannerSettings.from_config(cfg)
            t0 = time.perf_counter()
            plan = await asyncio.to_thread(plan_scan, design, placement, settings, with_coverage=False)
        except (MeshError, PlateError, PlanInputError, PlanRefused) as exc:
            self._job_state(job, JobState.FAILED, f"plan refused: {exc}")
            return False
        summary = plan.summary()
        self.store.set_state(
            rec, JobState.PLANNING, "planned", plan=summary, plan_s=round(time.perf_counter() - t0, 3)
        )
        if self._stop_requested(job):
            if job.stop_reason == "abort":
                self._job_state(job, JobState.ABORTED, "aborted by request before the scan; nothing moved")
            else:
                self._job_state(job, JobState.INTERRUPTED, "stopped before the scan")
            return False
        est = raw_bytes_estimate(
            plan.scan_time_s, rate_hz=cfg.laser.rate_hz, points_per_profile=cfg.laser.points_per_profile,
            settle_s=self.settings.settle_s,
        )  # fmt: skip
        try:  # before motion: the raw files of this scan must fit
            await asyncio.to_thread(check_data_dir, self.store.root, est.bytes, self.settings.min_free_mb)
        except PreflightError as exc:
            self._job_state(job, JobState.FAILED, f"pre-flight: {exc}; nothing moved")
            return False

        client = HD8Client(cfg.laser.host, cfg.laser.control_port, cfg.laser.data_port)
        await client.connect()
        writer = None
        consumer = None
        feeder = None
        try:
            await client.configure(rate_hz=cfg.laser.rate_hz, exposure_ns=round(cfg.laser.exposure_us * 1000))
            await self.program.start()
            await self.endpoint.wait_for_feedback(self.settings.feedback_timeout_s)
            acq_settings = AcquisitionSettings.from_config(cfg, epoch_ns=time.monotonic_ns())
            # Off the loop: the files are fsync'ed, and a busy disk must not hold up the EGM replies of
            # the session just started (the controller ends it after its communication timeout).
            writer = await asyncio.to_thread(
                RawWriter,
                self.store.raw_dir(rec.job_id),
                {"acquisition": acq_settings.to_json(), "job_id": rec.job_id, "plate_id": rec.plate_id},
            )
            acq = Acquisition(acq_settings, writer, keep_batches=True)
            egm0 = _counters(self.endpoint.stats, _EGM_COUNTERS)
            executor = MotionExecutor.for_plan(
                self.endpoint,
                plan,
                settings,
                ExecutorConfig.from_settings(
                    settings,
                    tracking_error_max_mm=cfg.robot.tracking_error_max_mm,
                    feedback_timeout_s=cfg.robot.egm_watchdog_s,  # [robot] egm_watchdog_s, not 0.1 s
                ),
                on_progress=lambda ev: self._on_progress(job, ev),
            )
            job.executor = executor
            if job.stop_reason is not None:  # aborted while the program started: stop before motion
                executor.abort()
            last_robot_ns = [-1]

            def feed_robot() -> None:
                a = self.endpoint.history.since(last_robot_ns[0])  # only what is new (every 10 ms)
                if len(a):
                    acq.feed_robot(a.t_host_ns, a.t_ctrl_us, a.q_deg[:, :6])
                    last_robot_ns[0] = int(a.t_host_ns[-1])

            feed_robot()

            def disk_fault() -> None:
                # The raw files take no more (disk full, quota, file size limit): stop smoothly along
                # the path instead of scanning blind; everything written so far stays readable.
                job.stop_reason = job.stop_reason or "disk"
                executor.abort()

            async def consume() -> None:
                async for batch in client:
                    try:
                        acq.feed_profiles(batch)
                    except OSError:
                        disk_fault()
                        raise
                    job.profiles += len(batch)

            sweeps = plan.passes
            bounds = np.array([[s.t_start_s, s.t_start_s + s.duration_s] for s in sweeps]).reshape(-1, 2)

            async def mark_and_feed() -> None:
                # Pass markers at the cycle the playback time crosses a sweep's bounds; the
                # feedback history reaches the acquisition every few cycles (cheap, ordered).
                open_pass = -1
                try:
                    while executor.state not in (ExecState.FINISHED, ExecState.ABORTED, ExecState.FAULTED):
                        await asyncio.sleep(self.settings.marker_period_s)
                        tau = executor.progress().t_traj_s
                        inside = np.nonzero((bounds[:, 0] <= tau) & (tau < bounds[:, 1]))[0]
                        k = int(inside[0]) if inside.size else -1
                        if k != open_pass:
                            now = time.monotonic_ns()
                            if open_pass >= 0:
                                acq.end_pass(now)
                            if k >= 0:
                                acq.begin_pass(k, now)
                            open_pass = k
                        feed_robot()
                    if open_pass >= 0:
                        acq.end_pass(time.monotonic_ns())
                except OSError:
                    disk_fault()
                    raise

            consumer = asyncio.create_task(consume(), name="hd8-consumer")
            await client.start()
            # The arm waits while the clock fits gather their first pairs (and a sensor that has just
            # started streaming settles) before the first reference moves it.
            await asyncio.sleep(self.settings.settle_s)
            self.sm.to(CellState.SCANNING, f"scanning job {rec.job_id}")
            self._job_state(job, JobState.SCANNING)
            feeder = asyncio.create_task(mark_and_feed(), name="pass-marker")
            t_scan = time.perf_counter()
            result = await executor.run()
            scan_s = time.perf_counter() - t_scan
            await feeder
            t_last_profile = time.time()
            with contextlib.suppress(Exception):
                await client.stop()
            await asyncio.sleep(0.1)  # frames in flight
            await client.close()
            await asyncio.wait_for(consumer, 10.0)
            feed_robot()
            await asyncio.to_thread(acq.finish)
            await asyncio.to_thread(writer.close)
            writer = None
            with contextlib.suppress(Exception):
                await self.program.end()
            job.executor = None
            info = {
                "scan_s": round(scan_s, 3),
                "profiles": job.profiles,
                "execution": result.state.value,
                "max_tracking_error_mm": round(float(result.max_tracking_error_mm), 3),
                "last_profile_utc_s": t_last_profile,
                "acquisition": json.loads(json.dumps(acq.quality(), default=_plain)),
                # what the links went through during this job: said plainly in the job record
                "egm": {k: v - egm0[k] for k, v in _counters(self.endpoint.stats, _EGM_COUNTERS).items()},
                "sensor": _counters(client.stats, _SENSOR_COUNTERS),
            }
            if result.state == ExecState.FINISHED:
                # The live cloud is bit for bit what `cellctl reassemble --live` rebuilds from the raw
                # files; rebuilding with whole-scan clock fits costs tens of seconds, so it is left to
                # re-analysis (the report is due seconds after the last profile).
                job.cloud = acq.cloud()
                self.store.set_state(rec, JobState.SCANNING, "scan complete", cloud="live", **info)
                return True
            if job.stop_reason == "shutdown":
                self._job_state(
                    job, JobState.INTERRUPTED, "the daemon stopped during the scan; raw data kept", **info
                )
            elif job.stop_reason == "abort":
                self._job_state(job, JobState.ABORTED, "aborted by request; raw data kept", **info)
            else:
                ctrl = "" if self.sm.state == CellState.STOPPING else await self._ctrl_state()
                if ctrl == "emergencystop":
                    # Not a failure of the job: the raw data up to the stop is intact and can be
                    # re-analysed (control/reanalyse), or the plate scanned again after the reset.
                    self._job_state(
                        job, JobState.INTERRUPTED,
                        "emergency stop during the scan; raw data kept (re-analyse, or trigger again "
                        "after control/reset)",
                        stopped_by="emergency_stop", **info,
                    )  # fmt: skip
                    self.sm.to(CellState.EMERGENCY_STOPPED, f"emergency stop during job {rec.job_id}")
                else:
                    self._job_state(job, JobState.FAILED, f"motion fault: {result.fault}", **info)
                    if self.sm.state not in (CellState.STOPPING, CellState.EMERGENCY_STOPPED):
                        self.sm.to(CellState.FAULTED, f"motion fault: {result.fault}")
            return False
        finally:
            job.executor = None
            for task in (feeder, consumer):
                if task is not None and not task.done():
                    task.cancel()
            if writer is not None:
                with contextlib.suppress(Exception):
                    writer.close()
                # cut short by an error (a full disk): the EGM program ends too, the arm holds
                with contextlib.suppress(Exception):
                    await self.program.end()
            with contextlib.suppress(Exception):
                await client.close()

    def _stop_requested(self, job: _Job) -> bool:
        return job.stop_reason is not None or self.sm.state == CellState.STOPPING

    def _on_progress(self, job: _Job, ev: Any) -> None:
        job.fraction = ev.percent / 100.0
        job.stage = f"{ev.segment} ({ev.pass_index}/{ev.pass_count})"
        if ev.state == "paused" and self.sm.state == CellState.SCANNING:
            self.sm.to(CellState.PAUSED, f"job {job.record.job_id} paused")
            self.store.set_state(job.record, JobState.PAUSED, "paused")
        elif ev.state in ("running", "resuming", "moving_to_start") and self.sm.state == CellState.PAUSED:
            self.sm.to(CellState.SCANNING, f"job {job.record.job_id} resumed")
            self.store.set_state(job.record, JobState.SCANNING, "resumed")
        self._publish()

    async def _analyse(self, job: _Job) -> None:
        """Publish the cloud to the workers and store the report; any failure fails the job (logged),
        it never leaves the job hanging."""
        try:
            await self._analyse_inner(job)
        except asyncio.CancelledError:
            raise
        except Exception as exc:
            log.exception("job_analysis_failed", job_id=job.record.job_id)
            self._job_state(job, JobState.FAILED, f"{type(exc).__name__}: {exc}")

    async def _analyse_inner(self, job: _Job) -> None:
        from cellctl.acquisition.publish import PublishSettings, column_steps, encode_scan
        from cellctl.acquisition.reassemble import reassemble
        from cellctl.api.analysis_job import analysis_job
        from cellctl.api.dispatch import JobFailed

        rec = job.record
        bind_context(job_id=rec.job_id)
        job.fraction = 0.0
        self._job_state(job, JobState.WAITING_FOR_WORKER, "cloud being assembled")
        if self._scan_job is None and self.sm.state not in (CellState.STOPPING, CellState.FAULTED):
            self.sm.to(CellState.IDLE, f"job {rec.job_id} scanned; analysing")
        try:
            t0 = time.perf_counter()
            scan_cloud = job.cloud
            job.cloud = None
            if scan_cloud is None:  # re-analysis: whole-scan clock fits from the raw files
                scan_cloud = (await asyncio.to_thread(reassemble, self.store.raw_dir(rec.job_id))).cloud
            # The plan puts the raster passes first and the edge passes after them (pass ids index
            # plan.passes), so the plan's raster count is the first edge pass.
            first_edge = (rec.info.get("plan") or {}).get("passes")
            steps = column_steps(scan_cloud.pass_id, first_edge, PublishSettings.from_config(self.cfg))
            meta = {"frame": "robot base", "cell_id": self.cfg.cell.id, "placement": rec.placement}
            # thinned and encoded in one pass off the loop: the only copy of the points is the payload
            payload, job.points = await asyncio.to_thread(
                encode_scan,
                scan_cloud,
                job_id=rec.job_id,
                plate_id=rec.plate_id,
                column_step=steps,
                meta=meta,
            )
            del scan_cloud, steps
            assemble_s = time.perf_counter() - t0
            params = analysis_job(
                self.cfg, job_id=rec.job_id, plate_id=rec.plate_id, design=rec.design_path,
                placement=rec.placement, out_dir=self.store.results_dir(rec.job_id).resolve(),
                analysis=rec.analysis,
            )  # fmt: skip
            fut = self.dispatcher.submit(params, payload)
            # the published bytes, kept with the job (cellctl.api.cloud_codec layout); written while the
            # worker analyses, and on disk before the job is done
            cloud_path = self.store.job_dir(rec.job_id) / "cloud.bin"
            written = asyncio.ensure_future(asyncio.to_thread(cloud_path.write_bytes, payload))
            self._job_state(
                job, JobState.WAITING_FOR_WORKER, "cloud published", points=job.points,
                cloud_bytes=len(payload), assemble_s=round(assemble_s, 3), published_utc_s=time.time(),
            )  # fmt: skip
            del payload
            self._job_state(job, JobState.ANALYSING, "analysing")
            try:
                env = await fut
            finally:
                await asyncio.shield(written)
        except asyncio.CancelledError:
            self._job_state(
                job, JobState.INTERRUPTED, "the daemon stopped during the analysis; raw data kept"
            )
            raise
        except JobFailed as exc:
            self._job_state(job, JobState.FAILED, f"analysis failed: {exc.reason}")
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
        report_path = (jd / "report.json").resolve()
        report_path.write_text(env.report.model_dump_json(indent=2), encoding="utf-8")
        job.fraction = 1.0
        # The JSON report (per-line verdicts) completes the job; the HTML / PDF render follows.
        self._job_state(
            job, JobState.DONE, str(report_path), verdict=env.report.verdict,
            report=str(report_path), worker_id=env.worker_id, analysis_timings_s=env.timings_s,
            report_utc_s=time.time(),
        )  # fmt: skip
        if self.settings.write_html_report and (self.store.results_dir(rec.job_id) / "report.json").exists():
            await self._render_html(job)

    async def _render_html(self, job: _Job) -> None:
        """Render report.html / .pdf of a done job (``cellctl report`` in a child process); record
        where and when in the job.

        A child process, not a thread: the render is tens of seconds of matplotlib holding the GIL,
        which would delay the event loop (EGM) of the next scan. It runs at normal priority even when
        the loop runs under SCHED_FIFO. A shutdown meanwhile stops the render (SIGTERM, then SIGKILL
        after 5 s): the job is already done with its report.json, and ``cellctl report <results>``
        renders the HTML / PDF again at any time, so a stop never waits tens of seconds on it.
        """
        import sys

        rec = job.record
        t0 = time.perf_counter()
        results = self.store.results_dir(rec.job_id).resolve()
        try:
            proc = await asyncio.create_subprocess_exec(
                sys.executable, "-m", "cellctl", "report", str(results),
                stdin=asyncio.subprocess.DEVNULL, stdout=asyncio.subprocess.PIPE,
                stderr=asyncio.subprocess.PIPE, preexec_fn=_normal_priority,
            )  # fmt: skip
        except OSError as exc:  # the job is done with its JSON report; only the HTML is missing
            log.warning("html_report_failed", error=str(exc))
            return
        render = asyncio.ensure_future(proc.communicate())
        cancelled = False
        try:
            await asyncio.shield(render)
        except asyncio.CancelledError:
            cancelled = True
            with contextlib.suppress(ProcessLookupError):
                proc.terminate()
            try:
                await asyncio.wait_for(asyncio.shield(render), 5.0)
            except Exception:  # TimeoutError included
                with contextlib.suppress(ProcessLookupError):
                    proc.kill()
                with contextlib.suppress(Exception):
                    await render
            log.warning("html_report_stopped", job_id=rec.job_id, reason="daemon stopping",
                        regenerate=f"cellctl report {results}")  # fmt: skip
        html: list[str] = []
        try:
            out, err = render.result()
            html = [line for line in out.decode(errors="replace").splitlines() if line.endswith(".html")]
            if proc.returncode != 0 or not html:
                html = []
                log.warning(
                    "html_report_failed", code=proc.returncode, error=err.decode(errors="replace")[-500:]
                )
        except Exception as exc:  # the JSON report stands on its own
            log.warning("html_report_failed", error=str(exc))
        info: dict[str, Any] = {"html_s": round(time.perf_counter() - t0, 3)}
        if html:
            info["report_html"] = str(results / Path(html[0]).name)
            last = rec.info.get("last_profile_utc_s")
            if last is not None:
                info["html_after_last_profile_s"] = round(time.time() - float(last), 3)
        rec.info.update(info)
        self.store.save(rec)
        log.info("html_report_written", job_id=rec.job_id, **info)
        if cancelled:
            raise asyncio.CancelledError


_EGM_COUNTERS = ("received", "lost", "duplicated", "out_of_order", "malformed", "watchdog_events")
_SENSOR_COUNTERS = (
    "frames", "gaps", "missing_frames", "duplicates_dropped", "decode_errors", "reconnects", "overflow_frames",
)  # fmt: skip


def _counters(stats: Any, names: tuple[str, ...]) -> dict[str, int]:
    """Integer counters of a statistics object, by name."""
    return {n: int(getattr(stats, n)) for n in names}


def release_freed_memory() -> bool:
    """Return the C heap's free pages to the system (glibc ``malloc_trim``); False where unavailable.

    A job's numpy temporaries (assembly, encoding: ~100 MB at peak for the small plate) are freed
    when it ends, but glibc keeps the pages of its heaps: over a 30-job soak the daemon's RSS crept
    up ~2 MB per job with its traced Python heap flat (126.3 -> 126.5 MB over 10 jobs).
    """
    try:
        libc = ctypes.CDLL("libc.so.6")
        return bool(libc.malloc_trim(0))
    except (OSError, AttributeError):
        return False


def _rss_mb() -> float:
    """This process's resident memory, MB (Linux /proc; 0.0 where it cannot be read)."""
    try:
        return int(Path("/proc/self/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        return 0.0


def _plain(obj: Any) -> Any:
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if hasattr(obj, "__dict__"):
        return {k: v for k, v in vars(obj).items() if not k.startswith("_")}
    return str(obj)


def _normal_priority() -> None:
    with contextlib.suppress(AttributeError, PermissionError, OSError):
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


_CPU_LATENCY_FD: int | None = None


def hold_cpu_wakeup_latency(max_us: int = 0) -> bool:
    """Keep the CPUs out of deep idle states while this process lives (Linux PM QoS through
    /dev/cpu_dma_latency; released when the process exits). Measured on the 2-core reference VM:
    with idle cores the EGM reply latency was p50 815 us / p99 3.5 ms; holding 0 us gave
    p50 370 us / p99 577 us. Needs root (or the device's permission); returns whether it is held."""
    global _CPU_LATENCY_FD
    if _CPU_LATENCY_FD is not None:
        return True
    try:
        fd = os.open("/dev/cpu_dma_latency", os.O_WRONLY)
        os.write(fd, struct.pack("i", int(max_us)))
    except OSError as exc:
        log.info("cpu_wakeup_latency_unavailable", reason=exc.strerror)
        return False
    _CPU_LATENCY_FD = fd
    log.info("cpu_wakeup_latency_held", max_us=max_us)
    return True


def use_realtime_loop(priority: int = 10) -> bool:
    """Run the calling thread (the event loop's) under SCHED_FIFO when permitted, as a cell PC runs its
    EGM loop; the loop's default executor gets normal-priority threads so heavy work (planning,
    assembly) never starves the machine. Returns whether the priority was granted."""
    loop = asyncio.get_running_loop()
    loop.set_default_executor(ThreadPoolExecutor(max_workers=4, initializer=_normal_priority))
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (AttributeError, PermissionError, OSError):
        log.info("realtime_priority_unavailable")
        return False
    log.info("realtime_priority", priority=priority)
    return True


def _heap_summary(top: int = 15) -> dict[str, Any]:
    """Traced Python heap: current and peak MB, the ``top`` source lines holding the most."""
    current, peak = tracemalloc.get_traced_memory()
    stats = tracemalloc.take_snapshot().statistics("lineno")[:top]
    return {
        "traced_mb": round(current / 1e6, 2),
        "peak_mb": round(peak / 1e6, 2),
        "top": [
            {"where": str(st.traceback), "kb": round(st.size / 1e3, 1), "blocks": st.count} for st in stats
        ],
    }


async def run_daemon(cfg: CellConfig) -> int:
    """Run the daemon (``cfg.daemon`` holds its knobs) until SIGTERM / SIGINT; returns the exit code."""
    stop = asyncio.Event()
    if cfg.daemon.realtime:
        use_realtime_loop()
        hold_cpu_wakeup_latency(0)
    release_signals = stop_on_signals(stop)
    # A write past a file-size limit must fail (EFBIG, a smooth stop), not kill the daemon.
    with contextlib.suppress(AttributeError, ValueError):
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    try:
        return await CellDaemon(cfg).run(stop)
    finally:
        release_signals()
