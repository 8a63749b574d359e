"""The plate history: an SQLite index of the job directories (``<data_dir>/history.sqlite``).

The job directories stay the record (``job.json``, ``report.json``); the index is rebuilt from them at
start (:meth:`History.rebuild`) and updated as jobs end (:meth:`History.index_job`). A plate is
formed in rounds (heat, inspect, heat again): its rounds are its finished jobs in creation order,
each with Zmax per line, so the rounds can be set side by side.

One implementation for both readers: the HMI keeps the index in the data directory; the report
render (``cellctl report``, the daemon's render child) asks :func:`previous_round_for` for the
previous round of the job it renders, from an index of that plate's job directories in memory.
"""

from __future__ import annotations

import json
import sqlite3
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Any

import structlog

from analysis.contracts.job import Report
from analysis.contracts.results import ReportError, read_report
from cellctl.jobstore.jobs import JobStoreError, read_job_record
from cellctl.jobstore.records import RecordError, read_json_file

if TYPE_CHECKING:
    from analysis.report.load import PreviousRound

log = structlog.get_logger(__name__)

SCHEMA = """
CREATE TABLE IF NOT EXISTS jobs (
    job_id TEXT PRIMARY KEY,
    plate_id TEXT NOT NULL,
    state TEXT NOT NULL,
    verdict TEXT,
    created_utc TEXT NOT NULL,
    ended_utc TEXT,
    design TEXT,
    message TEXT,
    max_abs_zmax_mm REAL,
    lines_json TEXT
);
CREATE INDEX IF NOT EXISTS jobs_plate ON jobs (plate_id, created_utc);
"""
DB_NAME = "history.sqlite"


def _line_summary(report: Report) -> list[dict[str, Any]]:
    """The figures per line the history keeps (its ``lines_json`` column: the HMI's rounds table)."""
    return [
        {
            "name": ln.name,
            "family": ln.family,
            "index": ln.index,
            "zmax_mm": ln.zmax_mm,
            "sz_avg_mm": ln.sz_avg_mm,
            "pass": ln.passed,
        }
        for ln in report.lines
    ]


def read_job_dir(job_dir: Path, plate_id: str | None = None) -> dict[str, Any] | None:
    """One row from a job directory; None when it holds no job.json, or no readable record (or,
    with ``plate_id``, a job of another plate: its report is not read then).

    The record is read as the job store reads it (:func:`~cellctl.jobstore.jobs.read_job_record`):
    one that cannot be read, or is not a record (too large, nested too deep, a ``job_id`` that is
    not its directory's, a field missing or of the wrong type), is skipped with a log line
    (``history_record_skipped``); an unreadable report.json leaves the job without a verdict
    (``history_report_unreadable``). Neither ever stops the reader (the HMI, ``cellctl history``).
    """
    path = job_dir / "job.json"
    if not path.exists() and not path.is_symlink():  # a symlink is refused by the reader, with its line
        return None
    try:
        rec = read_job_record(job_dir)
    except JobStoreError as exc:
        log.warning("history_record_skipped", path=str(path), reason=exc.reason)
        return None
    if plate_id is not None and rec.plate_id != plate_id:
        return None
    verdict, lines = None, []
    rp = job_dir / "report.json"
    if rp.exists():
        try:
            report = read_report(rp, load=read_json_file)
            verdict, lines = report.verdict, _line_summary(report)
        except (OSError, RecordError, ReportError) as exc:
            log.warning("history_report_unreadable", path=str(rp), reason=str(exc)[:300])
    last = rec.history[-1] if rec.history else None
    return {
        "job_id": rec.job_id,
        "plate_id": rec.plate_id,
        "state": rec.state,
        "verdict": verdict,
        "created_utc": rec.created_utc,
        "ended_utc": last.get("t_utc") if last else None,
        "design": rec.design,
        "message": last.get("message", "") if last else "",
        "max_abs_zmax_mm": max((abs(ln["zmax_mm"]) for ln in lines), default=None),
        "lines_json": json.dumps(lines),
    }


class History:
    """The index; safe to use from several threads (one connection, one lock)."""

    def __init__(self, data_dir: str | Path, db_path: str | Path | None = None) -> None:
        self.data_dir = Path(data_dir)
        self.db_path = Path(db_path) if db_path else self.data_dir / DB_NAME
        self._lock = threading.Lock()
        self._db = sqlite3.connect(self.db_path, check_same_thread=False)
        self._db.row_factory = sqlite3.Row
        self._db.executescript(SCHEMA)

    def close(self) -> None:
        with self._lock:
            self._db.close()

    def rebuild(self, plate_id: str | None = None) -> int:
        """Index every job directory again (rows of vanished jobs are dropped); returns the count.
        ``plate_id``: only that plate's jobs (the others are not indexed)."""
        rows = [r for d in sorted((self.data_dir / "jobs").glob("*/")) if (r := read_job_dir(d, plate_id))]
        with self._lock, self._db:
            self._db.execute("DELETE FROM jobs")
            self._db.executemany(_UPSERT, rows)
        return len(rows)

    def index_job(self, job_id: str) -> dict[str, Any] | None:
        """Index (again) one job directory, e.g. when its job ended."""
        row = read_job_dir(self.data_dir / "jobs" / job_id)
        if row is not None:
            with self._lock, self._db:
                self._db.execute(_UPSERT, row)
        return row

    def jobs(
        self,
        *,
        plate_id: str | None = None,
        verdict: str | None = None,
        date: str | None = None,
        limit: int = 200,
    ) -> list[dict[str, Any]]:
        """Jobs newest first; ``date``: a ``YYYY-MM-DD`` prefix of the creation time (UTC)."""
        q, args = "SELECT * FROM jobs WHERE 1=1", []
        if plate_id:
            q += " AND plate_id = ?"
            args.append(plate_id)
        if verdict:
            q += " AND verdict = ?"
            args.append(verdict)
        if date:
            q += " AND created_utc LIKE ?"
            args.append(date + "%")
        q += " ORDER BY created_utc DESC LIMIT ?"
        args.append(limit)
        with self._lock:
            return [_row(r) for r in self._db.execute(q, args)]

    def rounds(self, plate_id: str) -> list[dict[str, Any]]:
        """The plate's analysed jobs (a verdict) oldest first, numbered from 1: its forming rounds."""
        with self._lock:
            rows = self._db.execute(
                "SELECT * FROM jobs WHERE plate_id = ? AND verdict IS NOT NULL ORDER BY created_utc",
                (plate_id,),
            ).fetchall()
        return [{**_row(r), "round": k} for k, r in enumerate(rows, 1)]

    def previous_round(self, job_id: str) -> dict[str, Any] | None:
        """The round of the same plate before this job (None for a first round)."""
        with self._lock:
            me = self._db.execute(
                "SELECT plate_id, created_utc FROM jobs WHERE job_id = ?", (job_id,)
            ).fetchone()
            if me is None:
                return None
            r = self._db.execute(
                "SELECT * FROM jobs WHERE plate_id = ? AND verdict IS NOT NULL AND created_utc < ? "
                "ORDER BY created_utc DESC LIMIT 1",
                (me["plate_id"], me["created_utc"]),
            ).fetchone()
        return _row(r) if r else None


def previous_round_for(results_dir: str | Path) -> PreviousRound | None:
    """The previous round of the job whose report is rendered from ``results_dir``, for the report.

    ``results_dir`` is ``<data_dir>/jobs/<JOB>/results`` (or the job directory itself); the previous
    round is the latest analysed job (one with a report) of the same plate created before this one,
    as :meth:`History.previous_round` finds it, numbered as in :meth:`History.rounds`. None for a
    first round, or for a results directory outside a job directory (``cellctl inspect --out``).
    """
    from analysis.report.load import PreviousLine, PreviousRound  # matplotlib: only when a report is made

    d = Path(results_dir).resolve()
    job_dir = d.parent if d.name == "results" and (d.parent / "job.json").is_file() else d
    if job_dir.parent.name != "jobs" or (me := read_job_dir(job_dir)) is None:
        return None
    hist = History(job_dir.parent.parent, db_path=":memory:")
    try:
        hist.rebuild(plate_id=me["plate_id"])
        prev = hist.previous_round(me["job_id"])
        if prev is None:
            return None
        number = next(r["round"] for r in hist.rounds(me["plate_id"]) if r["job_id"] == prev["job_id"])
    finally:
        hist.close()
    return PreviousRound(
        round=number,
        job_id=prev["job_id"],
        created_utc=prev["created_utc"],
        verdict=prev["verdict"],
        lines=tuple(
            PreviousLine(
                name=ln["name"],
                zmax_mm=float(ln["zmax_mm"]),
                sz_avg_mm=float(ln["sz_avg_mm"]),
                passed=bool(ln["pass"]),
            )
            for ln in prev["lines"]
        ),
    )


_UPSERT = (
    "INSERT OR REPLACE INTO jobs (job_id, plate_id, state, verdict, created_utc, ended_utc, design, message, "
    "max_abs_zmax_mm, lines_json) VALUES (:job_id, :plate_id, :state, :verdict, :created_utc, :ended_utc, "
    ":design, :message, :max_abs_zmax_mm, :lines_json)"
)


def _row(r: sqlite3.Row) -> dict[str, Any]:
    d = dict(r)
    d["lines"] = json.loads(d.pop("lines_json") or "[]")
    return d


def format_history(hist: History, plate_id: str | None) -> str:
    """The text `cellctl history [PLATE]` prints: jobs, or one plate's rounds with Zmax per line."""
    if not plate_id:
        rows = hist.jobs()
        out = [f"{'job':26} {'plate':20} {'state':12} {'verdict':8} created"]
        out += [
            f"{r['job_id']:26} {r['plate_id']:20} {r['state']:12} {r['verdict'] or '-':8} {r['created_utc']}"
            for r in rows
        ]
        return "\n".join(out) if rows else "no jobs in the history"
    rounds = hist.rounds(plate_id)
    if not rounds:
        return f"plate {plate_id}: no analysed rounds"
    names = [ln["name"] for ln in rounds[-1]["lines"]]
    for r in rounds[:-1]:
        names += [ln["name"] for ln in r["lines"] if ln["name"] not in names]
    head = f"{'line':8}" + "".join(f" {'round ' + str(r['round']):>10}" for r in rounds)
    out = [f"plate {plate_id}: {len(rounds)} round(s), Zmax per line (mm)", head]
    for name in names:
        cells = []
        for r in rounds:
            ln = next((x for x in r["lines"] if x["name"] == name), None)
            cells.append(f" {ln['zmax_mm']:>9.2f}{'' if ln['pass'] else '!'}" if ln else f" {'-':>10}")
        out.append(f"{name:8}" + "".join(cells))
    out.append(f"{'verdict':8}" + "".join(f" {r['verdict']:>10}" for r in rounds))
    out.append(f"{'job':8}" + "".join(f" {r['job_id'][-10:]:>10}" for r in rounds))
    return "\n".join(out)
