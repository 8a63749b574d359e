"""The job store: one directory per job under ``<data_dir>/jobs/<job_id>/``.

Layout of a job directory::

    job.json        this record: trigger, state, state history, results (rewritten atomically)
    raw/            the acquisition's raw files (cellctl.acquisition.rawstore: job.json + *.craw)
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

import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import structlog

from cellctl.api import FINAL_JOB_STATES, JobState, now_utc

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
    """A job directory or record that cannot be read or written (names the path)."""


@dataclass
class JobRecord:
    """What ``job.json`` holds.

    Attributes:
        job_id, plate_id: identity. design: the trigger's design path (relative to designs_dir);
        design_path: resolved absolute path. placement: ``{"pos_mm": [...], "rpy_deg": [...]}``.
        state: a :class:`cellctl.api.JobState` value. history: ``[{"state", "t_utc", "message"}]``.
        info: counters and results (profiles, points, scan_s, verdict, report path, ...).
        analysis: the trigger's per-plate analysis options (``template_table``: the table's rows).
    """

    job_id: str
    plate_id: str
    design: str
    design_path: str
    placement: dict[str, Any]
    note: str = ""
    state: str = JobState.QUEUED.value
    created_utc: str = field(default_factory=now_utc)
    history: list[dict[str, str]] = field(default_factory=list)
    info: dict[str, Any] = field(default_factory=dict)
    analysis: dict[str, Any] = field(default_factory=dict)

    @property
    def terminal(self) -> bool:
        return JobState(self.state) in TERMINAL


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
        data = json.dumps(asdict(record), indent=2, default=_json_default)
        try:
            with open(tmp, "w", encoding="utf-8") as f:
                f.write(data)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, path)
        except OSError as exc:
            raise JobStoreError(f"{path}: cannot write the job record: {exc.strerror or exc}") from None

    def set_state(self, record: JobRecord, state: JobState, message: str = "", **info: Any) -> None:
        """Record a state change (appended to the history) and any info, then save."""
        record.state = JobState(state).value
        record.history.append({"state": record.state, "t_utc": now_utc(), "message": message})
        record.info.update(info)
        self.save(record)
        log.info("job_state", job_id=record.job_id, state=record.state, message=message)

    def load(self, job_id: str) -> JobRecord:
        """Read one record."""
        path = self.job_dir(job_id) / "job.json"
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
            return JobRecord(**data)
        except (OSError, ValueError, TypeError) as exc:
            raise JobStoreError(f"{path}: unreadable job record: {exc}") from None

    def list(self) -> list[JobRecord]:
        """Every readable record, oldest first (job ids sort by time); unreadable ones are logged."""
        out = []
        for d in sorted(p for p in self.root.iterdir() if p.is_dir()):
            if not (d / "job.json").exists():
                continue
            try:
                out.append(self.load(d.name))
            except JobStoreError as exc:
                log.warning("job_record_unreadable", error=str(exc))
        return out

    def recover(self) -> list[JobRecord]:
        """Mark every unfinished job interrupted (raw data left intact) and every queued one cancelled;
        returns those jobs."""
        found = []
        for rec in self.list():
            if rec.terminal:
                continue
            if rec.state == JobState.QUEUED.value:
                self.set_state(
                    rec,
                    JobState.CANCELLED,
                    "the daemon restarted while the job was queued; queued jobs never start on their own "
                    "after a restart: trigger it again",
                    cancelled_in=rec.state,
                )
                found.append(rec)
                continue
            raw = self.raw_dir(rec.job_id)
            raw_files = sorted(p.name for p in raw.glob("*.craw")) if raw.is_dir() else []
            self.set_state(
                rec,
                JobState.INTERRUPTED,
                f"the daemon stopped during {rec.state}; raw data kept",
                interrupted_in=rec.state,
                raw_files=raw_files,
            )
            found.append(rec)
        if found:
            log.warning("jobs_interrupted", jobs=[r.job_id for r in found])
        return found


def _json_default(obj: Any) -> Any:
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON-able: {type(obj).__name__}")
