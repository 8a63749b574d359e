"""The job store: one directory per job under ``<data_dir>/jobs/<job_id>/``.

Layout of a job directory::

    job.json        this record: trigger, state, state history, results (rewritten atomically)
    raw/            the acquisition's raw files (cellctl.jobstore.rawstore: job.json + *.craw)
    cloud.bin       the published cloud, exactly the bytes sent (cellctl.api.cloud_codec layout, base frame, mm)
    results/        the worker's results directory (report.json, report.csv, results.npz, cloud.ply)
    report.json     the report as the daemon received it

After a restart, :meth:`JobStore.recover` marks every job that was not finished ``interrupted``; its
raw files are left as they are (they are append-only and fsync'ed), so the job can be re-analysed
from them (:func:`cellctl.acquisition.reassemble.reassemble` on ``raw/``). A job still ``queued``
(never started) is marked ``cancelled`` instead: after a restart the robot moves only on a fresh
trigger, never on its own.
"""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import json
import os
from dataclasses import asdict, field
from pathlib import Path
from typing import Any

import structlog
from pydantic import BaseModel, ConfigDict, ValidationError
from pydantic.dataclasses import dataclass

from analysis.contracts.placement import Placement
from cellctl.api import FINAL_JOB_STATES, JobState, now_utc
from cellctl.api.models import AnalysisOptions
from cellctl.jobstore.info import JobInfo
from cellctl.jobstore.records import check_job_id, is_job_id, read_json_file

log = structlog.get_logger(__name__)

#: states a job can end in; any other state found at start-up means the daemon died during the job
TERMINAL = FINAL_JOB_STATES


#: Job directories hold a shipyard's raw scans and reports, which are confidential: the service user
#: reads and writes them, its group (QA viewers, the backup agent) may read them, nobody else may
#: even list them. 0o750 rather than 0o700 so that reports can be shared through group membership.
DIR_MODE = 0o750


def make_private_dir(path: Path) -> None:
    """Create ``path`` (and missing parents) and set it to :data:`DIR_MODE` whatever the umask.

    Raises JobStoreError naming the path when it cannot be created or its mode cannot be set.
    """
    try:
        path.mkdir(mode=DIR_MODE, parents=True, exist_ok=True)
        if path.stat().st_mode & 0o777 != DIR_MODE:
            os.chmod(path, DIR_MODE)
    except OSError as exc:
        raise JobStoreError(f"{path}: cannot create a private directory: {exc.strerror or exc}") from None


class JobStoreError(Exception):
    """A job directory or record that cannot be read or written (names the path); ``reason`` is
    what was wrong, without the path."""

    def __init__(self, message: str, reason: str = "") -> None:
        super().__init__(message)
        self.reason = reason or message


class DataDirLocked(JobStoreError):
    """Another daemon holds the data directory (names it and, when known, that daemon's pid)."""


#: the lock file a daemon holds in its data directory while it runs
LOCK_NAME = "daemon.lock"


def lock_data_dir(data_dir: str | Path) -> int:
    """Take the data directory's exclusive lock (``flock`` on ``<data_dir>/daemon.lock``) without
    waiting; returns the open descriptor (the lock lives as long as it; the kernel drops it when the
    process dies, so a ``kill -9`` leaves no stale lock). Raises :class:`DataDirLocked` when another
    process holds it: a second daemon on the same data stops before it touches a record."""
    path = Path(data_dir) / LOCK_NAME
    try:
        # held read-only: an open file for writing would keep the data directory's file system from
        # being remounted read-only (the operator's way to freeze a cell's data)
        fd = os.open(path, os.O_RDONLY | os.O_CREAT, 0o640)
    except OSError as exc:
        raise JobStoreError(f"{path}: cannot open the lock file: {exc.strerror or exc}") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        holder = ""
        with contextlib.suppress(OSError, ValueError):
            holder = os.pread(fd, 32, 0).decode().strip()
        os.close(fd)
        raise DataDirLocked(
            f"{Path(data_dir)}: another daemon is running on this data directory"
            + (f" (pid {holder})" if holder else "")
        ) from None
    with contextlib.suppress(OSError):  # the holder's pid, for the second daemon's message
        path.write_text(f"{os.getpid()}\n", encoding="ascii")
    return fd


@dataclass(config=ConfigDict(extra="forbid"))
class JobRecord:
    """What ``job.json`` holds: a pydantic dataclass, so a record is validated whenever it is made or
    read (a field of the wrong type, a field this version does not know: ValueError, and a record
    read so is quarantined); :func:`_checked` adds the state, history and options checks.

    Attributes:
        job_id, plate_id: identity. design: the trigger's design path (relative to designs_dir);
        design_path: resolved absolute path. placement: the :class:`~analysis.contracts.placement.Placement`
        the scan is planned from (``{"pos_mm": [...], "rpy_deg": [...]}`` in job.json; a dict given
        here is validated into one, ValueError naming ``placement`` when it is not one): the
        trigger's, or (after the locate run) the one found; None until then when the trigger gave
        none (``info.placement_found`` says which and how well).
        state: a :class:`cellctl.api.JobState` value. history: ``[{"state", "t_utc", "message"}]``.
        info: counters and results, a :class:`~cellctl.jobstore.info.JobInfo` (plan counts, the
        placement's finding, verdict, report path, motion counters, ...; its keys and versions there).
        analysis: the trigger's per-plate analysis options (``template_table`` rows, ``design_side``,
        ``thickness_mm``), kept so a re-analysis judges the plate the same way.
    """

    job_id: str
    plate_id: str
    design: str
    design_path: str
    placement: Placement | None
    note: str = ""
    state: str = JobState.QUEUED.value
    created_utc: str = field(default_factory=now_utc)
    history: list[dict[str, str]] = field(default_factory=list)
    info: JobInfo = field(default_factory=JobInfo)
    analysis: dict[str, Any] = field(default_factory=dict)

    @property
    def terminal(self) -> bool:
        return JobState(self.state) in TERMINAL

    def as_json(self) -> dict[str, Any]:
        """The record as job.json's object (the placement as ``{"pos_mm", "rpy_deg"}``, ``info`` as
        :meth:`JobInfo.record`)."""
        data = {**asdict(self), "info": self.info.record()}
        return json.loads(json.dumps(data, default=_json_default))

    @classmethod
    def read(cls, data: Any, dir_name: str) -> JobRecord:
        """A record from job.json's object, found in the job directory ``dir_name``: ValueError (or
        TypeError) naming the field when it is not a record this version reads."""
        if not isinstance(data, dict):
            raise ValueError(f"expected a JSON object, got {type(data).__name__}")
        check_job_id(data.get("job_id"), dir_name)
        if "info" in data:
            data = {**data, "info": JobInfo.read(data["info"])}
        return _checked(cls(**data))


class JobStore:
    """Reads and writes job records under ``<data_dir>/jobs``."""

    def __init__(self, data_dir: str | Path) -> None:
        data = Path(data_dir)
        if not data.exists():
            make_private_dir(data)
        elif data.stat().st_mode & 0o007:
            log.warning("data_dir_open_to_others", path=str(data), mode=f"{data.stat().st_mode & 0o777:03o}")
        self.root = data / "jobs"
        make_private_dir(self.root)

    def job_dir(self, job_id: str) -> Path:
        """``<root>/<job_id>``; JobStoreError for a name that is not a job id (a path, ``..``): no
        record, wherever it came from, is read or written outside its own directory."""
        if not isinstance(job_id, str) or not is_job_id(job_id):
            raise JobStoreError(f"{str(job_id)[:80]!r}: not a job id", "not a job id")
        return self.root / job_id

    def raw_dir(self, job_id: str) -> Path:
        return self.root / job_id / "raw"

    def results_dir(self, job_id: str) -> Path:
        return self.root / job_id / "results"

    def create(self, record: JobRecord) -> JobRecord:
        """Make the job's directory and its first record (state queued)."""
        d = self.job_dir(record.job_id)
        d.mkdir(mode=DIR_MODE, exist_ok=False)
        os.chmod(d, DIR_MODE)  # mkdir's mode is filtered by the umask; make it exact
        if not record.history:
            record.history.append({"state": record.state, "t_utc": record.created_utc, "message": "accepted"})
        self.save(record)
        return record

    def save(self, record: JobRecord) -> None:
        """Write ``job.json`` atomically (temp file, fsync, rename): a crash leaves the old or the new."""
        path = self.job_dir(record.job_id) / "job.json"
        tmp = path.with_suffix(".json.tmp")
        data = json.dumps(record.as_json(), indent=2)
        try:
            with open(tmp, "w", encoding="utf-8") as f:
                f.write(data)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, path)
        except OSError as exc:
            with contextlib.suppress(OSError):  # no half-written temp file left beside the record
                tmp.unlink()
            raise JobStoreError(f"{path}: cannot write the job record: {exc.strerror or exc}") from None

    def set_state(self, record: JobRecord, state: JobState, message: str = "", **info: Any) -> None:
        """Record a state change (appended to the history) and any info, then save."""
        record.state = JobState(state).value
        record.history.append({"state": record.state, "t_utc": now_utc(), "message": message})
        record.info = record.info.updated(**info)
        self.save(record)
        log.info("job_state", job_id=record.job_id, state=record.state, message=message)

    def load(self, job_id: str) -> JobRecord:
        """Read one record; JobStoreError when it cannot be read or is not a record this version knows
        (an unknown state, a field of the wrong type)."""
        return read_job_record(self.job_dir(job_id))

    def list(self) -> list[JobRecord]:
        """Every readable record, oldest first (job ids sort by time); unreadable ones are logged."""
        out = []
        for d in self._job_dirs():
            try:
                out.append(self.load(d.name))
            except JobStoreError as exc:
                log.warning("job_record_unreadable", error=str(exc))
        return out

    def _job_dirs(self) -> list[Path]:
        """The job directories holding a record, by name; a directory whose name is not a job id is
        logged and left alone (no record is read or written there)."""
        out = []
        for d in sorted(p for p in self.root.iterdir() if p.is_dir()):
            if not (d / "job.json").exists() and not (d / "job.json").is_symlink():
                continue
            if not is_job_id(d.name):
                log.warning("job_dir_not_a_job_id", path=str(d))
                continue
            out.append(d)
        return out

    def quarantine(self, job_id: str, why: str) -> JobRecord:
        """Set an unreadable or unknown record aside (``job.json.quarantined``, kept as it was) and
        write a fresh ``interrupted`` one in its place, so the job's raw data stays re-analysable
        (``control/reanalyse``); what could be read of the old record (plate, design, placement)
        is carried over."""
        d = self.job_dir(job_id)
        path = d / "job.json"
        old: dict[str, Any] = {}
        with contextlib.suppress(OSError, ValueError):
            data = read_json_file(path)
            old = data if isinstance(data, dict) else {}
        aside = d / "job.json.quarantined"
        for n in range(1, 100):  # an earlier quarantine's copy is kept too
            if not aside.exists() and not aside.is_symlink():
                break
            aside = d / f"job.json.quarantined.{n}"
        with contextlib.suppress(OSError):
            os.replace(path, aside)

        def text(key: str) -> str:
            v = old.get(key)
            return v if isinstance(v, str) else ""

        try:
            placement = Placement.model_validate(old.get("placement"))
        except ValidationError:
            placement = None
        rec = JobRecord(
            job_id=job_id,
            plate_id=text("plate_id") or "unknown",
            design=text("design"),
            design_path=text("design_path"),
            placement=placement,
            state=JobState.INTERRUPTED.value,
            analysis=_options_or_none(old.get("analysis")),
        )
        raw = self.raw_dir(job_id)
        rec.history.append(
            {"state": rec.state, "t_utc": now_utc(),
             "message": f"job record quarantined at start-up ({why}); raw data kept, re-analysable"}
        )  # fmt: skip
        rec.info = rec.info.updated(
            quarantined=str(aside), quarantine_reason=why,
            raw_files=sorted(p.name for p in raw.glob("*.craw")) if raw.is_dir() else [],
        )  # fmt: skip
        self.save(rec)
        log.error("job_record_quarantined", job_id=job_id, reason=why, kept_as=str(aside))
        return rec

    def recover(self) -> list[JobRecord]:
        """Mark every unfinished job interrupted (raw data left intact) and every queued one cancelled;
        quarantine records that cannot be read (:meth:`quarantine`). Returns those jobs; never raises
        for one bad record (a record that cannot be written is logged and left as it is)."""
        found = []
        for d in self._job_dirs():
            try:
                try:
                    rec = self.load(d.name)
                except JobStoreError as exc:
                    found.append(self.quarantine(d.name, exc.reason))
                    continue
                if not rec.terminal:
                    found.append(self._recover_one(rec))
            except JobStoreError as exc:
                log.error("job_recovery_failed", job_id=d.name, error=str(exc))
        if found:
            log.warning("jobs_interrupted", jobs=[r.job_id for r in found])
        return found

    def _recover_one(self, rec: JobRecord) -> JobRecord:
        if rec.state == JobState.QUEUED.value:
            self.set_state(
                rec,
                JobState.CANCELLED,
                "the daemon restarted while the job was queued; queued jobs never start on their own "
                "after a restart: trigger it again",
                cancelled_in=rec.state,
            )
            return rec
        raw = self.raw_dir(rec.job_id)
        raw_files = sorted(p.name for p in raw.glob("*.craw")) if raw.is_dir() else []
        self.set_state(
            rec,
            JobState.INTERRUPTED,
            f"the daemon stopped during {rec.state}; raw data kept",
            interrupted_in=rec.state,
            raw_files=raw_files,
        )
        return rec


def read_job_record(job_dir: Path) -> JobRecord:
    """The record in ``job_dir/job.json`` (the job store's, the plate history's, the HMI's and
    ``cellctl demo``'s one way to read one); JobStoreError naming the path when it cannot be read or
    is not a record this version knows (an unknown state, a field missing or of the wrong type)."""
    path = job_dir / "job.json"
    try:
        return JobRecord.read(read_json_file(path), job_dir.name)
    except (OSError, ValueError, TypeError) as exc:
        raise JobStoreError(f"{path}: unreadable job record: {exc}", str(exc)[:300]) from None


def reanalysis_problem(record: JobRecord, designs_dir: str | Path) -> str:
    """Why ``record`` cannot be re-analysed from its design ("" when it can): its design must be a
    file in ``designs_dir``, as a trigger's is (a quarantined record whose design could not be read
    names none: the worker was handed the directory "." before)."""
    why = f" (record quarantined: {record.info.quarantine_reason})" if record.info.quarantined else ""
    if not record.design_path:
        return (
            f"its record names no design{why}: re-analyse it offline (cellctl reassemble {record.job_id}, "
            "then cellctl inspect with the design)"
        )
    try:
        path = Path(record.design_path).resolve()
        inside = path.is_relative_to(Path(designs_dir).resolve())
        ok = inside and path.is_file()
    except (OSError, RuntimeError):
        inside = ok = False
    if not inside:
        return f"its design {record.design_path!r} is not in designs_dir{why}"
    if not ok:
        return f"its design file {record.design!r} is gone from designs_dir{why}"
    return ""


class RecordRetry:
    """Job records the disk refused (full, read-only), written again every ``period_s`` until it
    takes them; the newest state of a record wins (the record object is the live one)."""

    def __init__(self, store: JobStore, period_s: float = 2.0) -> None:
        self.store = store
        self.period_s = period_s
        self._pending: dict[str, JobRecord] = {}
        self._task: asyncio.Task[None] | None = None

    def __len__(self) -> int:
        return len(self._pending)

    def add(self, record: JobRecord) -> None:
        """Write ``record`` later (call it in the running loop)."""
        self._pending[record.job_id] = record
        if self._task is None or self._task.done():
            self._task = asyncio.get_running_loop().create_task(self._run(), name="job-record-retry")

    async def _run(self) -> None:
        while self._pending:
            await asyncio.sleep(self.period_s)
            for job_id, record in list(self._pending.items()):
                try:
                    await asyncio.to_thread(self.store.save, record)
                except JobStoreError as exc:
                    log.warning("job_record_write_retry_failed", job_id=job_id, error=str(exc))
                    continue
                if self._pending.get(job_id) is record:
                    del self._pending[job_id]
                log.info("job_record_written", job_id=job_id, state=record.state)

    def try_now(self) -> None:
        """One last attempt for each pending record (shutdown); what still fails is logged."""
        for job_id, record in list(self._pending.items()):
            try:
                self.store.save(record)
            except JobStoreError as exc:
                log.error("job_record_not_written", job_id=job_id, state=record.state, error=str(exc))
                continue
            del self._pending[job_id]
            log.info("job_record_written", job_id=job_id, state=record.state)
        if self._task is not None:
            self._task.cancel()


def _checked(rec: JobRecord) -> JobRecord:
    """``rec`` when every field has the type and the state a value this version knows (ValueError)."""
    JobState(rec.state)  # ValueError for a state of another version (e.g. "reanalysing")
    for name in ("job_id", "plate_id", "design", "design_path", "note", "created_utc"):
        if not isinstance(getattr(rec, name), str):
            raise ValueError(f"{name}: expected a string, got {type(getattr(rec, name)).__name__}")
    if not isinstance(rec.history, list) or not all(
        isinstance(h, dict) and isinstance(h.get("state"), str) and isinstance(h.get("message", ""), str)
        for h in rec.history
    ):
        raise ValueError("history: expected a list of {state, t_utc, message}")
    if not isinstance(rec.info, JobInfo):
        raise ValueError(f"info: expected an object, got {type(rec.info).__name__}")
    try:  # the options a re-analysis will judge the plate by: a record of another shape is quarantined
        AnalysisOptions.model_validate(rec.analysis)
    except ValidationError as exc:
        raise ValueError(f"analysis: {exc.errors()[0]['msg']} at {exc.errors()[0]['loc']}") from None
    if rec.placement is not None and not isinstance(rec.placement, Placement):
        raise ValueError(f"placement: expected a Placement or null, got {type(rec.placement).__name__}")
    return rec


def _json_default(obj: Any) -> Any:
    if isinstance(obj, BaseModel):  # the placement
        return obj.model_dump(mode="json")
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON-able: {type(obj).__name__}")


def _options_or_none(value: object) -> dict:
    """A quarantined record's analysis options when they still validate, else none (the defaults)."""
    try:
        return AnalysisOptions.model_validate(value).record()
    except ValidationError:
        return {}
