"""The scan planner in a child process of its own, so the daemon's event loop never waits for it.

The daemon brings the sensor and the EGM program up while the scan is planned (issue 22): from then
on the controller sends a state every 4 ms and ends the session when nothing comes back for its
communication timeout (1 s: elog 41822 "No data from the UdpUc device"). A planner run in a thread
of the daemon holds the interpreter for long stretches (pinocchio, toppra and numpy calls that do
not let go, the plan cache's JSON of a 30 min plan: 2-3 s on the 6 m plate), and the long cell's
end-to-end run faulted "no commandable feedback from the controller within 5.0 s" right after its
26 s plan. In a child process the planner has its own interpreter; the daemon only waits on a pipe.

:class:`PlanProcess` keeps one spawned child (spawn, not fork: the daemon runs Zenoh's and the
EGM endpoint's threads), started and warmed (the planner's imports) when the daemon starts, so a
plan costs no start-up. The request and the reply are pydantic models (:class:`PlanRequest`,
:class:`PlanReply`) pickled over the pool's pipe; the plan comes back as the planner's own
:class:`~cellctl.planning.plan.ScanPlan`, a refusal as the planner's
:class:`~cellctl.planning.plan.PlanRefused` or :class:`~cellctl.planning.plan.PlanInputError`
with every field. The child uses the plan cache exactly as the daemon did (``plan-cache/``).
A child that dies (killed, out of memory) fails that plan with :class:`PlanProcessError` and is
replaced for the next one; its log lines go to the daemon's stderr in the daemon's format, with the
job's id.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import multiprocessing as mp
import os
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

import structlog
from pydantic import BaseModel, ConfigDict

from analysis.mesh import TriMesh
from analysis.placement import Placement
from cellctl.logging import bind_context, configure_logging, logging_configured
from cellctl.planning.cache import CachedPlan, PlanCache
from cellctl.planning.plan import ScanPlan
from cellctl.planning.settings import PlannerSettings

__all__ = ["PlanProcess", "PlanProcessError", "PlanReply", "PlanRequest"]

log = structlog.get_logger(__name__)


class PlanProcessError(RuntimeError):
    """The planning process died or could not start; the plan was not made."""


class PlanRequest(BaseModel):
    """What the child plans: the design (plate frame), the placement, the settings and the cache."""

    model_config = ConfigDict(arbitrary_types_allowed=True, frozen=True)

    design: TriMesh
    placement: Placement
    settings: PlannerSettings
    cache_dir: Path
    with_coverage: bool = False
    job_id: str | None = None


class PlanReply(BaseModel):
    """The plan, whether it came from the cache, its cache key and the child's process id."""

    model_config = ConfigDict(arbitrary_types_allowed=True, frozen=True)

    plan: ScanPlan
    hit: bool
    key: str
    pid: int


def _child_init(fmt: str, level: int) -> None:
    configure_logging(fmt, level)  # type: ignore[arg-type]


def _warm() -> int:
    """The planner's imports done (pinocchio, toppra, open3d): the first plan costs no import."""
    import cellctl.planning.planner  # noqa: F401

    return os.getpid()


def _plan_in_child(req: PlanRequest) -> PlanReply:
    if req.job_id is not None:
        bind_context(job_id=req.job_id)
    got = PlanCache(req.cache_dir).plan(
        req.design, req.placement, req.settings, with_coverage=req.with_coverage
    )
    return PlanReply(plan=got.plan, hit=got.hit, key=got.key, pid=os.getpid())


class PlanProcess:
    """One spawned child that plans scans (:meth:`plan`); :meth:`start` warms it, :meth:`close` ends it."""

    def __init__(self) -> None:
        self._pool: concurrent.futures.ProcessPoolExecutor | None = None
        self.pid: int | None = None  # the child's, once it has answered

    def _ensure(self) -> concurrent.futures.ProcessPoolExecutor:
        if self._pool is None:
            fmt, level = logging_configured()
            self._pool = concurrent.futures.ProcessPoolExecutor(
                max_workers=1,
                mp_context=mp.get_context("spawn"),
                initializer=_child_init,
                initargs=(fmt, level),
            )
        return self._pool

    async def start(self) -> None:
        """Start the child and import the planner in it (a failure is logged; :meth:`plan` retries)."""
        try:
            self.pid = await asyncio.get_running_loop().run_in_executor(self._ensure(), _warm)
            log.info("plan_process_ready", pid=self.pid)
        except (BrokenProcessPool, OSError) as exc:
            log.warning("plan_process_start_failed", error=str(exc))
            self._drop()

    async def plan(
        self,
        design: TriMesh,
        placement: Placement,
        settings: PlannerSettings,
        cache_dir: Path,
        *,
        with_coverage: bool = False,
        job_id: str | None = None,
    ) -> CachedPlan:
        """:meth:`PlanCache.plan` in the child.

        Raises:
            PlanRefused, PlanInputError: as the planner does.
            PlanProcessError: the child died (it is replaced for the next plan).
        """
        req = PlanRequest(
            design=design, placement=placement, settings=settings, cache_dir=cache_dir,
            with_coverage=with_coverage, job_id=job_id,
        )  # fmt: skip
        try:
            reply = await asyncio.get_running_loop().run_in_executor(self._ensure(), _plan_in_child, req)
        except BrokenProcessPool as exc:
            self._drop()
            raise PlanProcessError(
                f"the planning process died ({exc}); the next plan starts a new one"
            ) from None
        except OSError as exc:
            self._drop()
            raise PlanProcessError(f"the planning process could not start: {exc}") from None
        self.pid = reply.pid
        return CachedPlan(reply.plan, reply.hit, reply.key)

    def _drop(self) -> None:
        pool, self._pool, self.pid = self._pool, None, None
        if pool is not None:
            pool.shutdown(wait=False, cancel_futures=True)

    def close(self) -> None:
        """End the child (a plan running in it is not waited for)."""
        pool, self._pool, self.pid = self._pool, None, None
        if pool is None:
            return
        procs = list(getattr(pool, "_processes", {}).values())
        pool.shutdown(wait=False, cancel_futures=True)
        for p in procs:  # a plan still running would keep the child (and the daemon's exit) waiting
            if p.is_alive():
                p.terminate()
