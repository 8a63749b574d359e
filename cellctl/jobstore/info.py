"""A job record's ``info``: what the daemon learnt while it ran the job, as one pydantic model.

``job.json``'s ``info`` object has been written since the first daemon (2026-11-22) by keyword: the
daemon's ``job_state(..., key=value)`` calls and a few direct updates. :class:`JobInfo` names every
key this version writes and gives each its type; a reader holds the model (``record.info.plan``,
``record.info.placement_found``), never a string key.

Versions:

- every key is optional, so a record of any version so far loads: a record from before the locate
  run (no ``placement_found``), before the motion process (no ``motion``), before the HTML render
  (no ``html_s``), a quarantined one (``quarantined`` and ``raw_files`` only);
- a key this version does not name is *allowed and kept as it was read* (``model_extra``): the
  record is the job's log too, and a key a later (or earlier) daemon wrote must survive this
  daemon's rewrite of the record (a recovery, a re-analysis). Nothing reads such a key. The one
  family of names that is not fixed, a locate run's own counters (``locate_along``,
  ``locate_across``, ``locate_across_2``, ...), is validated as :class:`RunInfo` all the same;
- a key this version names with a value of another type refuses the record (ValueError naming
  ``info.<key>``): the job store quarantines it at start-up rather than failing a re-analysis later;
- this version writes only the keys it names (:meth:`JobInfo.updated` refuses any other, a
  programming error), and leaves out the ones that are None.
"""

from __future__ import annotations

import re
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from analysis.contracts.job import PlacementFinding
from cellctl.api.models import MotionCounters

__all__ = ["JobInfo", "PlanCounts", "RunInfo", "is_locate_run_key"]

Count = Annotated[int, Field(ge=0)]
Seconds = Annotated[float, Field(allow_inf_nan=False)]

#: the keys of a locate run's counters: its name (``locate along``, ``locate across 2``) with ``_``
_LOCATE_RUN_KEY = re.compile(r"locate_(along|across)(_[0-9]+)?")


def is_locate_run_key(key: str) -> bool:
    """Whether ``key`` names a locate run's :class:`RunInfo` in ``info``."""
    return _LOCATE_RUN_KEY.fullmatch(key) is not None


class PlanCounts(BaseModel):
    """The plan's summary (``ScanPlan.summary()``, what ``cellctl plan`` prints): the pass counts a
    stream and a re-analysis read are typed; the rest of the summary (coverage, times, choices) is
    kept as written, for people."""

    model_config = ConfigDict(extra="allow", frozen=True)

    passes: Count | None = None
    edge_passes: Count | None = None


class RunInfo(BaseModel):
    """One motion run's counters (the scan's, at the top of ``info``; a locate run's, under its name):
    how long it took, what the sensor and the links went through."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    scan_s: Seconds | None = None
    profiles: Count | None = None
    execution: str | None = None  # the executor's end state: finished, aborted, faulted
    move_to_start_s: Seconds | None = None
    max_tracking_error_mm: float | None = None
    motion: MotionCounters | None = None
    last_profile_utc_s: Seconds | None = None
    acquisition: dict[str, Any] | None = None  # clock fits and the acquisition's counters
    egm: dict[str, int] | None = None  # EGM counters during the run
    sensor: dict[str, int] | None = None  # the sensor client's counters


class JobInfo(RunInfo):
    """``job.json``'s ``info`` (see the module's docstring for versions and unknown keys)."""

    model_config = ConfigDict(extra="allow", frozen=True)

    # planning and the locate run
    plan: PlanCounts | None = None
    plan_s: Seconds | None = None
    plan_cache: Literal["hit", "miss"] | None = None
    placement_found: PlacementFinding | None = None
    locate: dict[str, Any] | None = None  # the outline fit's figures (LocateResult.summary())
    locate_s: Seconds | None = None
    # the scan's end
    cloud: Literal["live"] | None = None
    stopped_by: str | None = None
    profiles_lost: Count | None = None
    # publication and analysis
    points: Count | None = None
    cloud_bytes: Count | None = None
    stream_chunks: Count | None = None
    assemble_s: Seconds | None = None
    published_utc_s: Seconds | None = None
    worker_id: str | None = None
    verdict: Literal["pass", "fail", "incomplete"] | None = None
    report: str | None = None  # report.json's path (None while the results wait for disk space)
    report_utc_s: Seconds | None = None
    analysis_timings_s: dict[str, float] | None = None
    results_bytes: Count | None = None
    results_pending: bool | None = None
    results_stored_utc_s: Seconds | None = None
    html_s: Seconds | None = None
    report_html: str | None = None
    html_after_last_profile_s: Seconds | None = None
    # the line-heating plan made after the report (cellctl.daemon.heat_plan): heating-plan.json's
    # path, whether it holds a plan or the reason there is none, the plan child's time
    heating_plan: str | None = None
    heating_plan_status: Literal["plan", "no_plan"] | None = None
    heating_plan_s: Seconds | None = None
    html_with_plan_s: Seconds | None = None  # report.html / .pdf rendered again with the plan drawn
    # recovery
    interrupted_in: str | None = None
    cancelled_in: str | None = None
    raw_files: list[str] | None = None
    quarantined: str | None = None  # where the unreadable record was set aside
    quarantine_reason: str | None = None

    @model_validator(mode="after")
    def _locate_runs_are_runs(self) -> JobInfo:
        for key, value in (self.model_extra or {}).items():
            if is_locate_run_key(key) and not isinstance(value, RunInfo):
                try:
                    self.model_extra[key] = RunInfo.model_validate(value)  # type: ignore[index]
                except ValidationError as exc:
                    first = exc.errors()[0]
                    raise ValueError(
                        ".".join(str(p) for p in (key, *first["loc"])) + f": {first['msg']}"
                    ) from None
        return self

    @classmethod
    def read(cls, value: Any) -> JobInfo:
        """``info`` as read from a file; ValueError naming ``info.<key>`` when it is not one."""
        try:
            return cls.model_validate(value)
        except ValidationError as exc:
            first = exc.errors()[0]
            where = ".".join(str(p) for p in ("info", *first["loc"]))
            raise ValueError(f"{where}: {first['msg']}") from None

    def updated(self, **changes: Any) -> JobInfo:
        """This info with ``changes`` (validated); ValueError for a key this version does not name."""
        unknown = [k for k in changes if k not in type(self).model_fields and not is_locate_run_key(k)]
        if unknown:
            raise ValueError(f"info: {', '.join(unknown)}: not a key of a job record's info")
        return type(self).read({**self.record(), **changes})

    def locate_runs(self) -> dict[str, RunInfo]:
        """The locate runs' counters by key (``locate_along``, ...)."""
        return {k: v for k, v in (self.model_extra or {}).items() if isinstance(v, RunInfo)}

    def record(self) -> dict[str, Any]:
        """``info`` as job.json holds it: the keys set, kept ones included, a key whose value is None
        left out; inside a value, the fields as they were set, None included (``placement_found``'s
        ``"given": null`` says no placement was given: readers of job.json rely on it)."""
        dumped = self.model_dump(mode="json", exclude_unset=True)
        return {k: v for k, v in dumped.items() if v is not None}
