"""The daemon's plan step: the line-heating plan of a done job, in a child process after its report.

``cellctl heat-plan --json`` on the job's results directory with the daemon's ``[forming]``, in a
process of its own at normal priority (:func:`cellctl.daemon.render.run_cellctl_child`, as the HTML
render): the planner is seconds of numpy and scikit-fem holding the GIL, which the daemon's event
loop (EGM) must not wait on. It runs once the job is done with its report.json, so the report's
timing and the job's verdict never depend on it. The job record names heating-plan.json
(``heating_plan``), its status and the step's time. A child that fails or is stopped leaves
heating-plan.json with the reason (``no_plan``); ``cellctl heat-plan <results>`` makes it again.
"""

from __future__ import annotations

import asyncio
import logging
from datetime import UTC, datetime
from typing import Any

import structlog
from pydantic import BaseModel, ConfigDict, ValidationError

from analysis.forming.plan_file import DISABLED, HEATING_PLAN_FILE, HeatingPlanFile, write_heating_plan
from cellctl.config import CellConfig
from cellctl.daemon.active import ActiveJob
from cellctl.daemon.render import last_line, run_cellctl_child
from cellctl.jobstore.jobs import JobStore, JobStoreError

__all__ = ["HeatPlanAnswer", "make_heating_plan"]

log = structlog.get_logger(__name__)


class HeatPlanAnswer(BaseModel):
    """What ``cellctl heat-plan --json`` prints as its one line of output: the files written and the
    plan's status."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    json_path: str
    dxf_path: str | None
    status: str
    reason: str | None = None
    lines: int = 0
    planning_s: float | None = None


async def make_heating_plan(
    cfg: CellConfig, store: JobStore, job: ActiveJob, *, kill_after_s: float = 5.0
) -> bool:
    """Make the plan of a done job (its results directory holds report.json) and record it with the
    job; True when a plan (``status`` ``plan``) was written. Never raises for a plan that fails
    (heating-plan.json says why, the log too); a cancellation stops the child, records the reason and
    raises :class:`asyncio.CancelledError`."""
    rec = job.record
    results = store.results_dir(rec.job_id).resolve()
    if not cfg.forming.enabled:  # no child to start: the file only says so
        await _record(store, job, {"heating_plan_s": 0.0}, None, DISABLED)
        return False
    argv = ["heat-plan", "--json", "--forming", cfg.forming.model_dump_json(), str(results)]
    run = await run_cellctl_child(argv, kill_after_s=kill_after_s)
    answer: HeatPlanAnswer | None = None
    reason = ""
    if run.stopped:
        reason = f"the daemon stopped while planning; `cellctl heat-plan {results}` makes the plan"
    elif run.returncode != 0:
        why = run.error or run.err.decode(errors="replace").strip()[-300:]
        reason = f"the plan child failed (exit {run.returncode}): {why}"
    else:
        try:
            answer = HeatPlanAnswer.model_validate_json(last_line(run.out))
        except ValidationError as exc:  # a child of another version: its answer is not this one's
            reason = f"the plan child's answer: {exc.errors()[0]['msg']}"
    await _record(store, job, {"heating_plan_s": round(run.elapsed_s, 3)}, answer, reason)
    if run.stopped:
        raise asyncio.CancelledError
    return answer is not None and answer.status == "plan"


async def _record(
    store: JobStore, job: ActiveJob, info: dict[str, Any], answer: HeatPlanAnswer | None, reason: str
) -> None:
    """The child's answer (or ``reason`` in heating-plan.json when there is none) into the job record."""
    rec = job.record
    if answer is not None:
        info.update(heating_plan=answer.json_path, heating_plan_status=answer.status)
        log.info("heating_plan_written", job_id=rec.job_id, status=answer.status, lines=answer.lines,
                 reason=answer.reason, **info)  # fmt: skip
    else:
        log.log(logging.INFO if reason == DISABLED else logging.WARNING, "heating_plan_none", job_id=rec.job_id,
                reason=reason, **info)  # fmt: skip
        plan = HeatingPlanFile(
            status="no_plan", reason=reason, job_id=rec.job_id, plate_id=rec.plate_id,
            created_utc=datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        )  # fmt: skip
        try:
            path = await asyncio.to_thread(
                write_heating_plan, plan, store.results_dir(rec.job_id).resolve() / HEATING_PLAN_FILE
            )
            info.update(heating_plan=str(path), heating_plan_status="no_plan")
        except OSError as exc:  # the report stands; only the plan's reason is lost
            log.warning("heating_plan_write_failed", job_id=rec.job_id, error=str(exc))
    rec.info = rec.info.updated(**info)
    try:
        store.save(rec)
    except JobStoreError as exc:  # the job is done with its report.json; only the plan's note is lost
        log.warning("job_record_write_failed", job_id=rec.job_id, error=str(exc))
