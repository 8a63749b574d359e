"""One scan of a job: locate, plan, pre-flight, drivers to a known state, motion with the acquisition session.

Without a placement in the trigger (or with ``[locate] check_given``) the scan starts with the
locate run (docs/locate.md): its passes (:mod:`cellctl.daemon.locate`) go through the same
acquisition as the scan, each run's cloud is written to the job's ``locate/`` folder, the design's
outline is fitted to it (:mod:`analysis.register.locate`), and the scan is planned from the placement found
(a given placement off by more than the bound fails the job with the reason).

:class:`ScanRunner` holds what a scan needs of the cell (configuration, job store, the named
drivers) and tells its host (the daemon) about job and cell states through :class:`ScanHost`. The
feed loop that runs during the motion is :class:`~cellctl.acquisition.session.AcquisitionSession`;
the cloud's hand-over to the analysis is :mod:`cellctl.daemon.handover`.

Before every scan the sensor and the controller are brought to a known state whatever the previous
run left (a killed daemon, a disk fault): the sensor is stopped before it is configured, and an EGM
session still open on the controller is ended before the program starts again.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import structlog

from analysis.cloud_io import ScanCloud, write_cloud_npz
from analysis.contracts.placement import Placement
from analysis.design.cad import design_mesh_from_file
from analysis.design.mesh import MeshError, TriMesh
from analysis.design.plates import PlateError
from analysis.register.locate import LocateError, LocateResult, locate_plate, placement_offset
from cellctl.acquisition.assembly import AssembledScan
from cellctl.acquisition.pipeline import Acquisition, AcquisitionSettings
from cellctl.acquisition.publish import PublishSettings
from cellctl.acquisition.session import AcquisitionSession, SessionSettings, pass_windows_s
from cellctl.api import CellState, JobState
from cellctl.config import CellConfig
from cellctl.daemon.active import ActiveJob
from cellctl.daemon.locate import (
    LocatePlan,
    face_down_refusal,
    given_placement_refusal,
    locate_settings,
    next_locate_plans,
)
from cellctl.daemon.preflight import (
    PreflightError,
    check_data_dir,
    expected_profiles,
    raw_bytes_estimate,
    spill_bytes_estimate,
)
from cellctl.daemon.stream import ScanStream
from cellctl.daemon.wiring import CellDrivers, laser_exposure_ns, laser_source
from cellctl.jobstore.jobs import JobStore
from cellctl.jobstore.rawstore import RawWriter
from cellctl.motion import ExecState, ExecutionResult, ExecutorConfig, ProgressEvent
from cellctl.planning import PlanInputError, PlannerSettings, PlanRefused, ScanPlan, start_corner_near
from cellctl.planning.cache import PlanCache
from drivers.abb_egm import rws_protocol as rw
from drivers.abb_egm.rws_client import RwsError
from drivers.laser.client import HD8Client

__all__ = ["ScanHost", "ScanRunner"]

log = structlog.get_logger(__name__)

_EGM_COUNTERS = ("received", "lost", "duplicated", "out_of_order", "malformed", "watchdog_events")
_SENSOR_COUNTERS = (
    "frames", "gaps", "missing_frames", "duplicates_dropped", "decode_errors", "reconnects", "overflow_frames",
)  # fmt: skip


class ScanHost(Protocol):
    """What the scan tells (and asks) the daemon."""

    @property
    def cell_state(self) -> CellState: ...

    def to_cell(self, state: CellState, message: str) -> None: ...

    def job_state(self, job: ActiveJob, state: JobState, message: str = "", **info: Any) -> None: ...

    def stop_requested(self, job: ActiveJob) -> bool: ...

    async def ctrl_state(self) -> str: ...

    def on_progress(self, job: ActiveJob, ev: ProgressEvent) -> None: ...

    def live_feed(self, job_id: str) -> Callable[[list, int], None] | None: ...

    async def cloud_stream(self, job: ActiveJob) -> ScanStream | None: ...


class ScanRunner:
    """Runs the scan of one job at a time for its :class:`ScanHost`."""

    def __init__(self, cfg: CellConfig, store: JobStore, drivers: CellDrivers, host: ScanHost) -> None:
        self.cfg = cfg
        self.store = store
        self.drivers = drivers
        self.host = host

    async def scan(self, job: ActiveJob) -> bool:
        """Plan, execute and acquire. True when the scan completed (raw files closed, ``job.cloud`` set).

        False when it ended otherwise (the job's state says how); raises on an error (the job's
        ``stop_reason`` is ``"disk"`` when the raw files took no more)."""
        host, rec = self.host, job.record
        if not self.drivers.motion.alive:
            why = self.drivers.motion.death or "not running"
            host.job_state(
                job, JobState.FAILED, f"the motion process is gone ({why}): reset the cell (cellctl reset)"
            )
            return False
        host.to_cell(CellState.PLANNING, f"planning job {rec.job_id}")
        host.job_state(job, JobState.PLANNING)
        try:
            design = await asyncio.to_thread(design_mesh_from_file, Path(rec.design_path))
        except (MeshError, PlateError) as exc:
            host.job_state(job, JobState.FAILED, f"plan refused: {exc}")
            return False
        if rec.placement is None or self.cfg.locate.check_given:
            if not await self._locate(job, design):
                return False
        else:
            host.job_state(
                job, JobState.PLANNING, "placement as given (not checked: [locate] check_given = false)",
                placement_found={"source": "given", "given": rec.placement},
            )  # fmt: skip
        # The sensor comes up while the scan is planned, the EGM program once it is planned: from the
        # program's start the controller wants an answer every cycle and ends the session after its
        # communication timeout (1 s), and the planner's thread holds the interpreter for up to 0.3 s
        # on the sail, 2-3 s on a 6 m plate (the long cell's scan faulted "no commandable feedback"
        # right after its plan). Nothing moves until the executor runs the plan.
        planned_event = asyncio.Event()
        bring_up = asyncio.create_task(self._bring_up(after=planned_event), name="bring-up")
        handed_over = False
        keep: Callable[[], None] | None = None
        try:
            planned = await self._plan(job, design)
            if planned is None:
                return False
            planned_event.set()
            plan, settings, keep = planned
            if self._stopped_before_motion(job) or not await self._preflight(job, plan):
                return False
            handed_over = True
            raw_dir = self.store.raw_dir(rec.job_id)
            return await self._acquire(job, plan, settings, raw_dir=raw_dir, ready=bring_up) is not None
        finally:
            if not handed_over:
                await self._drop_bring_up(bring_up)
            if keep is not None:
                # a fresh plan goes into the cache once the arm is at rest (and before the next job
                # can start): writing it holds the interpreter ~0.1 s on the sail, which would sit
                # between the plan and the motion, or hold up EGM replies during it
                await asyncio.to_thread(keep)

    async def _bring_up(self, after: asyncio.Event | None = None) -> HD8Client:
        """The sensor connected, stopped and configured, and (once ``after`` is set, when given) the
        EGM program (re)started with its feedback arriving; the arm holds where it is. Raises
        (everything it started ended again)."""
        cfg, drv = self.cfg, self.drivers
        client = await self._sensor_ready()
        try:
            if after is not None:
                await after.wait()
            # an EGM session the controller still runs (the previous daemon died mid-scan) ends first
            with contextlib.suppress(Exception):
                await drv.program.end()
            await drv.program.start()
            await drv.motion.wait_for_feedback(cfg.daemon.feedback_timeout_s)
        except BaseException:
            with contextlib.suppress(Exception):
                await drv.program.end()
            with contextlib.suppress(Exception):
                await client.close()
            raise
        return client

    async def _drop_bring_up(self, task: asyncio.Task[HD8Client]) -> None:
        """A bring-up the scan did not use (the plan was refused, a stop came first): cancel it or end
        what it started."""
        if not task.done():
            task.cancel()
        try:
            client = await task
        except BaseException:  # cancelled, or it failed (and ended what it started)
            return
        with contextlib.suppress(Exception):
            await self.drivers.program.end()
        with contextlib.suppress(Exception):
            await client.close()

    def _stopped_before_motion(self, job: ActiveJob) -> bool:
        """True (and the job ended) when a stop was asked for before the next motion."""
        if not self.host.stop_requested(job):
            return False
        if job.stop_reason == "abort":
            self.host.job_state(job, JobState.ABORTED, "aborted by request before the scan; nothing moved")
        else:
            self.host.job_state(job, JobState.INTERRUPTED, "stopped before the scan")
        return True

    async def _preflight(self, job: ActiveJob, plan: ScanPlan) -> bool:
        """Before motion: the raw files of this plan must fit (False: the job failed, nothing moved)."""
        d = self.cfg.daemon
        las = self.cfg.laser
        est = raw_bytes_estimate(
            plan.scan_time_s, rate_hz=las.rate_hz, points_per_profile=las.points_per_profile, settle_s=d.settle_s,
        )  # fmt: skip
        # and the spill files beside them while the scan runs (its arrays reserved when it starts)
        pub = PublishSettings.from_config(self.cfg)
        spill = spill_bytes_estimate(
            expected_profiles(plan.scan_time_s, rate_hz=las.rate_hz, settle_s=d.settle_s),
            points_per_profile=las.points_per_profile, publish_step=pub.step(min(pub.pitch_mm, pub.edge_pitch_mm)),
        )  # fmt: skip
        try:
            await asyncio.to_thread(check_data_dir, self.store.root, est.bytes + spill, d.min_free_mb)
        except PreflightError as exc:
            self.host.job_state(job, JobState.FAILED, f"pre-flight: {exc}; nothing moved")
            return False
        return True

    async def _locate(self, job: ActiveJob, design: TriMesh) -> bool:
        """The locate run: passes along the bed, the outline fit, and passes across it when the first
        left the fit sliding along one direction or crossed the plate's edges square-on
        (:func:`~cellctl.daemon.locate.next_locate_plans`: across at the heights of the outline the
        first fit puts under them). Each run's cloud is on disk before it is fitted.

        True with ``job.record.placement`` the placement found; False when the job ended (the plate
        was not found, a given placement is refused, the run was stopped or failed)."""
        host, rec, cfg = self.host, job.record, self.cfg
        given = rec.placement
        t0 = time.perf_counter()
        lst = locate_settings(cfg, design, None if given is None else given.yaw_deg)
        run: list[LocatePlan] = []
        clouds: list[ScanCloud] = []
        found: LocateResult | None = None
        reason = ""
        # the passes along the bed start at its corner nearest the arm
        start_axes = await self._arm_axes(PlannerSettings.from_config(cfg))
        while True:
            try:
                plans = await asyncio.to_thread(next_locate_plans, cfg, design, run, found, start_axes)
            except (PlanInputError, PlanRefused) as exc:
                host.job_state(
                    job, JobState.FAILED, f"locate run refused by the planner: {exc} ([locate] bed, standoff)"
                )
                return False
            if not plans:
                break
            for lp in plans:
                if self._stopped_before_motion(job) or not await self._preflight(job, lp.plan):
                    return False
                raw_dir = self.store.job_dir(rec.job_id) / "locate" / lp.name.replace(" ", "-")
                scan = await self._acquire(job, lp.plan, lp.settings, raw_dir=raw_dir, phase=lp.name)
                if scan is None:
                    return False
                # its passes from 1, the transit apart under 0: the fit reads pass by pass
                cloud = scan.scan_cloud(transit_apart=True)
                # acquired data reaches disk before anything else can fail
                await asyncio.to_thread(write_cloud_npz, cloud, raw_dir / "cloud.npz")
                clouds.append(cloud)
                run.append(lp)
            try:
                ranges = [lp.range_z_mm for lp in run]
                found = await asyncio.to_thread(locate_plate, clouds, design, lst, ranges)
            except LocateError as exc:
                found, reason = None, str(exc)
        locate_s = round(time.perf_counter() - t0, 3)
        if found is None:
            host.job_state(
                job, JobState.FAILED, f"locate: the plate was not found: {reason}", locate_s=locate_s
            )
            return False
        if not found.constrained:
            reason = (
                f"the locate passes pinned the plate in one direction only ({found.constraint_points:.0f} "
                "boundary points across it); is the plate narrower than [locate] pass_spacing_mm?"
            )
            host.job_state(
                job, JobState.FAILED, f"locate: {reason}", locate_s=locate_s, locate=found.summary()
            )
            return False
        finding: dict[str, Any] = {
            "source": "located" if given is None else "checked",
            "given": None if given is None else given.model_dump(),
            "rms_mm": round(found.rms_mm, 4),
            "height_rms_mm": round(found.height_rms_mm, 4),
            "coverage": round(found.coverage, 4),
            "boundary_points": found.boundary_points,
            "resolved_by": found.resolved_by,
            "locate_s": locate_s,
        }
        if given is not None:
            d_mm, d_deg = placement_offset(found.placement, given)
            finding.update(offset_mm=round(d_mm, 3), offset_deg=round(d_deg, 4))
        refusal = face_down_refusal(found) or (
            None if given is None else given_placement_refusal(cfg, found, given)
        )
        info = {"placement_found": finding, "locate": found.summary(), "locate_s": locate_s}
        if refusal is not None:
            host.job_state(job, JobState.FAILED, f"placement refused: {refusal}", **info)
            return False
        rec.placement = found.placement
        f = found.placement
        host.job_state(
            job, JobState.PLANNING,
            f"plate {finding['source']} at x {f.x_mm:.1f}, y {f.y_mm:.1f}, z {f.z_mm:.1f} mm, yaw {f.yaw_deg:.2f} deg "
            f"(outline fit RMS {found.rms_mm:.2f} mm, {found.coverage:.0%} of the outline seen) in {locate_s:.1f} s",
            **info,
        )  # fmt: skip
        return True

    async def _plan(
        self, job: ActiveJob, design: TriMesh
    ) -> tuple[ScanPlan, PlannerSettings, Callable[[], None] | None] | None:
        """The scan's plan and settings, and for a fresh plan the call that writes it into the plan
        cache (None on a cache hit); None when the plan was refused (the job failed)."""
        rec = job.record
        try:
            placement = rec.placement
            if placement is None:  # the locate run sets it, or the job ended before the plan
                raise PlanInputError("no placement to plan the scan from")
            settings = PlannerSettings.from_config(self.cfg)
            t0 = time.perf_counter()
            corner = await self._start_corner(design, placement, settings)
            if corner is not None:
                settings = settings.with_(start_corner=corner)
            # a plan for the same design, placement and settings is reused after the envelope check
            cache = PlanCache(self.store.root.parent / "plan-cache")
            got = await asyncio.to_thread(
                cache.plan, design, placement, settings, with_coverage=False, store=False
            )
        except (MeshError, PlateError, PlanInputError, PlanRefused) as exc:
            self.host.job_state(job, JobState.FAILED, f"plan refused: {exc}")
            return None
        plan = got.plan
        self.host.job_state(
            job, JobState.PLANNING, "planned", plan=plan.summary(), plan_s=round(time.perf_counter() - t0, 3),
            plan_cache="hit" if got.hit else "miss",
        )  # fmt: skip
        return plan, settings, None if got.hit else functools.partial(cache.store, got.key, plan)

    async def _arm_axes(self, settings: PlannerSettings) -> np.ndarray | None:
        """Where the arm is (RWS: the mechanical unit's jointtarget): (6,) deg, or (7,) the track's mm
        first. None (with a log line) when the controller does not say; only where a run starts
        depends on it (:meth:`_start_corner`, the locate run's first passes)."""
        try:
            joints = await self.drivers.rws.get_mechunit_joints()
        except RwsError as exc:
            log.warning("start_corner_unknown", reason=f"the arm's joints could not be read: {exc}")
            return None
        axes = joints.q_deg
        if settings.track is not None:
            track_mm = joints.external_axes_mm[0]
            if track_mm is None:
                log.warning("start_corner_unknown", reason="the controller reports no track position (eax_a)")
                return None
            axes = np.concatenate([[track_mm], axes])
        return axes

    async def _start_corner(
        self, design: TriMesh, placement: Placement, settings: PlannerSettings
    ) -> tuple[int, int] | None:
        """The plate's corner nearest the arm (read before the plan): the serpentine starts there,
        leaving the shortest move to the plan's start. None (the planner's default corner, with a
        log line) when the controller does not say where the arm is; nothing depends on it but the
        move's length."""
        axes = await self._arm_axes(settings)
        if axes is None:
            return None
        try:
            return start_corner_near(design, placement, settings, axes)
        except PlanInputError as exc:
            log.warning("start_corner_unknown", reason=str(exc))
            return None

    async def _sensor_ready(self) -> HD8Client:
        """A connected sensor client, the sensor stopped and configured."""
        las = self.cfg.laser
        client = laser_source(las)
        await client.connect()
        try:
            # whatever a previous run left streaming (a killed daemon): SET_RATE needs it stopped
            await client.stop()
            await client.configure(rate_hz=las.rate_hz, exposure_ns=laser_exposure_ns(las))
        except BaseException:
            with contextlib.suppress(Exception):
                await client.close()
            raise
        return client

    async def _acquire(
        self,
        job: ActiveJob,
        plan: ScanPlan,
        settings: PlannerSettings,
        *,
        raw_dir: Path,
        phase: str = "scan",
        ready: asyncio.Task[HD8Client] | None = None,
    ) -> AssembledScan | None:
        """Run ``plan`` with the acquisition session, raw files into ``raw_dir``. The assembled scan
        when the motion finished (for the scan, also ``job.cloud``); None when it ended otherwise (the
        job's state says how). ``phase``: ``"scan"``, or the name of a locate run. ``ready``: a
        :meth:`_bring_up` already under way (started while planning), else it runs here."""
        cfg, host, rec, drv = self.cfg, self.host, job.record, self.drivers
        client = await (ready if ready is not None else self._bring_up())
        writer: RawWriter | None = None
        session: AcquisitionSession | None = None
        tracker: asyncio.Task[None] | None = None
        stream: ScanStream | None = None
        program_started = True
        try:
            acq_settings = AcquisitionSettings.from_config(cfg, epoch_ns=time.monotonic_ns())
            # Off the loop: the files are fsync'ed, and a busy disk must not hold up the EGM replies of
            # the session just started (the controller ends it after its communication timeout).
            writer = await asyncio.to_thread(
                RawWriter,
                raw_dir,
                {
                    "acquisition": acq_settings.to_json(),
                    "job_id": rec.job_id,
                    "plate_id": rec.plate_id,
                    "phase": phase,
                },
            )
            # the whole scan's arrays reserved once at the plan's profile count (a 6 m plate: 340 000)
            expected = expected_profiles(
                plan.scan_time_s, rate_hz=cfg.laser.rate_hz, settle_s=cfg.daemon.settle_s
            )
            acq = Acquisition(acq_settings, writer, keep_batches=True, expected_profiles=expected)
            if phase == "scan":
                # the analysis follows the scan: each pass's points go out once the pass is on disk
                stream = await host.cloud_stream(job)
                if stream is not None:
                    stream.follow(acq, writer)
            egm0 = _counters(drv.motion.stats, _EGM_COUNTERS)

            def progressed(ev: ProgressEvent) -> None:
                job.motion = executor.counters
                host.on_progress(job, ev)

            # the plan runs in the motion process (its own real-time process: docs/architecture.md);
            # its files (the plan it ran, the record of what it commanded) stay with the raw data
            executor = drv.motion.execution(
                plan.trajectory,
                ExecutorConfig.from_settings(
                    settings,
                    tracking_error_max_mm=cfg.robot.tracking_error_max_mm,
                    feedback_timeout_s=cfg.robot.egm_watchdog_s,  # [robot] egm_watchdog_s, not 0.1 s
                ),
                segment_labels=[s.label for s in plan.segments],
                segment_kinds=[s.kind for s in plan.segments],
                work_dir=raw_dir,
                on_progress=progressed,
            )
            job.executor = executor
            if job.stop_reason is not None:  # aborted while the program started: stop before motion
                executor.abort()

            def write_failed(exc: OSError) -> None:
                # The raw files take no more (disk full, quota, file size limit): stop smoothly along
                # the path instead of scanning blind; everything written so far stays readable.
                job.stop_reason = job.stop_reason or "disk"
                executor.abort()

            session = AcquisitionSession(
                acq, client, drv.motion.history,
                pass_windows_s([s.t_start_s for s in plan.passes], [s.duration_s for s in plan.passes]),
                SessionSettings(marker_period_s=cfg.daemon.marker_period_s, settle_s=cfg.daemon.settle_s),
                on_write_error=write_failed, on_assembled=host.live_feed(rec.job_id),
            )  # fmt: skip
            job.session = session
            # The plan waits while the clock fits gather their first pairs (and a sensor that has just
            # started streaming settles) before its first reference; the move to the plan's start
            # (no pass records during it) overlaps that wait.
            executor.start_not_before_s = await session.start(wait_settle=False)
            what = "scanning" if phase == "scan" else f"{phase} run of"
            host.to_cell(CellState.SCANNING, f"{what} job {rec.job_id}")
            host.job_state(job, JobState.SCANNING, "" if phase == "scan" else f"{phase} run")
            tracker = asyncio.create_task(
                session.track(
                    lambda: executor.progress().t_traj_s,
                    lambda: executor.state in (ExecState.FINISHED, ExecState.ABORTED, ExecState.FAULTED),
                ),
                name="pass-marker",
            )
            t_scan = time.perf_counter()
            result = await executor.run()
            scan_s = time.perf_counter() - t_scan
            await tracker
            t_last_profile = time.time()
            await session.finish()
            job.profiles = session.profiles
            await asyncio.to_thread(writer.close)
            writer = None
            if stream is not None and result.state == ExecState.FINISHED:
                await stream.finish()  # the rows after the last pass, and the end of the stream
            with contextlib.suppress(Exception):
                await drv.program.end()
            program_started = False
            job.executor = None
            job.motion = executor.counters
            info = {
                "scan_s": round(scan_s, 3),
                "profiles": job.profiles,
                "execution": result.state.value,
                "move_to_start_s": round(result.move_to_start_s, 3),
                "max_tracking_error_mm": round(float(result.max_tracking_error_mm), 3),
                # how the motion process served the controller (issue 41): stale and lost cycles,
                # reply latency, tracking
                "motion": executor.counters.model_dump(),
                "last_profile_utc_s": t_last_profile,
                "acquisition": json.loads(json.dumps(acq.quality(), default=_plain)),
                # what the links went through during this job: said plainly in the job record
                "egm": {k: v - egm0[k] for k, v in _counters(drv.motion.stats, _EGM_COUNTERS).items()},
                "sensor": _counters(client.stats, _SENSOR_COUNTERS),
            }
            if result.state == ExecState.FINISHED and phase != "scan":
                host.job_state(
                    job, JobState.SCANNING, f"{phase} run complete", **{phase.replace(" ", "_"): info}
                )
                return acq.cloud()
            if result.state == ExecState.FINISHED:
                # The live cloud is bit for bit what `cellctl reassemble --live` rebuilds from the raw
                # files; rebuilding with whole-scan clock fits costs tens of seconds, so it is left to
                # re-analysis (the report is due seconds after the last profile).
                job.cloud = acq.cloud()
                host.job_state(job, JobState.SCANNING, "scan complete", cloud="live", **info)
                return job.cloud
            await self._ended_early(job, result, info)
            return None
        finally:
            if stream is not None and not stream.finished:
                with contextlib.suppress(Exception):
                    await stream.abandon("the scan ended before its last profile")
            job.executor = None
            if session is not None:
                job.profiles = max(job.profiles, session.profiles)
            job.session = None
            if tracker is not None and not tracker.done():
                tracker.cancel()
            if session is not None:
                await session.abort()
            if writer is not None:
                with contextlib.suppress(Exception):
                    writer.close()
            if program_started:
                # cut short by an error (a full disk): the EGM program ends too, the arm holds
                with contextlib.suppress(Exception):
                    await drv.program.end()
            with contextlib.suppress(Exception):
                await client.close()

    async def _ended_early(self, job: ActiveJob, result: ExecutionResult, info: dict[str, Any]) -> None:
        """An aborted, interrupted or faulted motion: the job's end and, for a fault, the cell's."""
        host, rec = self.host, job.record
        if job.stop_reason == "shutdown":
            host.job_state(
                job, JobState.INTERRUPTED, "the daemon stopped during the scan; raw data kept", **info
            )
            return
        if job.stop_reason == "abort":
            host.job_state(job, JobState.ABORTED, "aborted by request; raw data kept", **info)
            return
        ctrl = "" if host.cell_state == CellState.STOPPING else await host.ctrl_state()
        if ctrl == rw.EMERGENCYSTOP:
            # Not a failure of the job: the raw data up to the stop is intact and can be
            # re-analysed (control/reanalyse), or the plate scanned again after the reset.
            host.job_state(
                job, JobState.INTERRUPTED,
                "emergency stop during the scan; raw data kept (re-analyse, or trigger again "
                "after control/reset)",
                stopped_by="emergency_stop", **info,
            )  # fmt: skip
            host.to_cell(CellState.EMERGENCY_STOPPED, f"emergency stop during job {rec.job_id}")
            return
        host.job_state(job, JobState.FAILED, f"motion fault: {result.fault}", **info)
        if host.cell_state not in (CellState.STOPPING, CellState.EMERGENCY_STOPPED):
            host.to_cell(CellState.FAULTED, f"motion fault: {result.fault}")


def _counters(stats: Any, names: tuple[str, ...]) -> dict[str, int]:
    """Integer counters of a statistics object, by name."""
    return {n: int(getattr(stats, n)) for n in names}


def _plain(obj: Any) -> Any:
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if hasattr(obj, "__dict__"):
        return {k: v for k, v in vars(obj).items() if not k.startswith("_")}
    return str(obj)
