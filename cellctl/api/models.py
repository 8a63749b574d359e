"""The payload models of the cell's Zenoh API, both ways (documented in docs/api.md).

Payloads are UTF-8 JSON validated by the pydantic models below (unknown fields refused) on both
sides, except the cloud, which uses the binary layout of :mod:`cellctl.api.cloud_codec`. The job a
worker is given (:class:`JobSpec` with its :class:`~analysis.contracts.job.AnalysisJob`) and the report it
returns (:class:`ReportEnvelope` with its :class:`~analysis.contracts.job.Report`) carry the analysis
package's own models, so the daemon, the worker and the analysis check one schema. Inbound
requests are parsed with :func:`parse_trigger`, which raises :class:`TriggerError` naming the
offending field. The key expressions are in :mod:`cellctl.api.keys`.
"""

from __future__ import annotations

import json
import os
import socket
import time
from collections.abc import Awaitable, Callable
from enum import StrEnum
from pathlib import Path, PurePosixPath
from typing import Annotated, Any, Literal, TypeVar

import structlog
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from analysis.contracts.job import AnalysisJob, Report
from analysis.contracts.placement import Placement
from analysis.design.cad import DESIGN_SUFFIXES  # the formats analysis.design.cad.read_design reads: one list
from analysis.design.template_table import MAX_ROWS as MAX_TEMPLATE_ROWS
from analysis.design.template_table import TableTemplate, row_problem
from cellctl.api.keys import ControlAction
from cellctl.api.transfer import ResultManifest, TransferSpec

log = structlog.get_logger(__name__)

__all__ = [
    "API_VERSION",
    "CONTROL_LOG",
    "DESIGN_SUFFIXES",
    "FINAL_JOB_STATES",
    "ID_PATTERN",
    "JSON",
    "MAX_TRIGGER_BYTES",
    "STREAM_FORMAT",
    "TRIGGER_LOG",
    "AnalysisJob",
    "AnalysisOptions",
    "ApiError",
    "CellState",
    "CellStatus",
    "ControlError",
    "ControlReply",
    "ControlRequest",
    "DaemonStats",
    "EgmStats",
    "HeapLine",
    "HeapSummary",
    "Ident",
    "JobEvent",
    "JobProgress",
    "JobSpec",
    "JobState",
    "LiveCloudChunk",
    "Model",
    "MotionCounters",
    "Placement",
    "QueuedJob",
    "RefusalLog",
    "Report",
    "ReportEnvelope",
    "StreamChunk",
    "StreamEnd",
    "TriggerAccepted",
    "TriggerError",
    "TriggerRequest",
    "UserName",
    "WorkerAnnouncement",
    "default_worker_id",
    "handle_trigger",
    "new_job_id",
    "now_utc",
    "parse_control",
    "parse_model",
    "parse_trigger",
    "read_payload",
]

#: the job protocol's version: a worker is given jobs only when it announces this one (2: the
#: worker's events, reports and result chunks are signed with the offer's key, cellctl.api.proof)
API_VERSION = 2
#: the stream chunk format (StreamChunk / StreamEnd and the chunk payloads, cellctl.api.cloud_codec)
#: a streamed job's worker must speak
STREAM_FORMAT = 1
# The largest valid trigger as any JSON encoder writes it (json.dumps escapes non-ASCII as \uXXXX):
# 200 template rows of at most ~150 bytes, a note and a design path of escaped characters, the
# placement. tests/security/test_trigger_limits.py builds that trigger and checks it fits.
MAX_TRIGGER_BYTES = 48 * 1024
JSON = "application/json"

#: the grammar of every id in the API (job, plate, worker, cell): also a job directory's name, so it
#: can name no path (no "/", never "." or "..")
ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}$"
_ID = ID_PATTERN
Ident = Annotated[str, Field(pattern=_ID)]
#: a person's name as the HMI authenticated them (its users file's names, a Zenoh user's)
UserName = Annotated[str, Field(pattern=r"^[A-Za-z0-9_.@\-]{1,64}$")]
Finite = Annotated[float, Field(allow_inf_nan=False)]
Vec3 = Annotated[list[Finite], Field(min_length=3, max_length=3)]


class Model(BaseModel):
    """Base of every payload: unknown fields refused, JSON in and out."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    def to_json(self) -> bytes:
        return self.model_dump_json().encode("utf-8")


M = TypeVar("M", bound=Model)


def now_utc() -> str:
    """ISO-8601 UTC timestamp with milliseconds."""
    t = time.time()
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(t)) + f".{int(t % 1 * 1000):03d}Z"


def new_job_id() -> str:
    """A sortable, unique job id: UTC time plus random hex."""
    return time.strftime("%Y%m%dT%H%M%S", time.gmtime()) + "-" + os.urandom(4).hex()


# --------------------------------------------------------------------------------------------- trigger


def _usable_rows(rows: tuple[TableTemplate, ...]) -> tuple[TableTemplate, ...]:
    """The template rows as a CSV's are checked (analysis.design.template_table.row_problem), names unique."""
    seen: set[str] = set()
    for k, row in enumerate(rows):
        if (problem := row_problem(row)) is not None:
            raise ValueError(f"row {k + 1}: {problem}")
        if row.name in seen:
            raise ValueError(f"row {k + 1}: template {row.name!r} appears twice")
        seen.add(row.name)
    return rows


TemplateRows = Annotated[
    tuple[TableTemplate, ...],
    Field(max_length=MAX_TEMPLATE_ROWS),
    AfterValidator(_usable_rows),
]


class AnalysisOptions(Model):
    """The per-plate analysis options a trigger may give, kept in the job record (a re-analysis judges
    the plate the same way) and carried into the job's settings.

    ``template_table``: the yard's template table of this plate, as rows (the CSV's content, read by
    ``cellctl scan --template-table``, not a path): one named detection line per row, added to the
    ``[analysis]`` layout (docs/designs.md). ``design_side``: which face of the plate the design is
    and whether it faces up; ``moulded_down`` (the plate turned over) needs ``thickness_mm``, the
    design is then offset by it (:mod:`analysis.design.moulded`).
    """

    template_table: TemplateRows = ()
    design_side: Literal["moulded_up", "moulded_down"] = "moulded_up"
    thickness_mm: Annotated[Finite, Field(ge=0.0, lt=1000.0)] = 0.0

    @model_validator(mode="after")
    def _thickness_when_turned(self) -> AnalysisOptions:
        if self.design_side == "moulded_down" and self.thickness_mm <= 0:
            raise ValueError("thickness_mm: a plate laid moulded side down needs its thickness (> 0 mm)")
        return self

    def record(self) -> dict[str, Any]:
        """The options as the job record stores them (JSON; only what differs from the defaults)."""
        return self.model_dump(mode="json", exclude_defaults=True)


class TriggerRequest(Model):
    """Start an inspection. ``design`` is a path relative to ``[cell] designs_dir``.

    ``placement``: where the plate lies (optional). Without it the cell finds the plate by a locate
    run; with it the locate run checks it (``[locate] check_given``) and the job fails, saying by how
    much, when the plate lies further from it than ``[locate] max_offset_mm`` / ``max_angle_deg``
    (docs/locate.md). A plate that looks the same turned by half a turn is taken at the given yaw.
    ``template_table``, ``design_side``, ``thickness_mm``: the plate's :class:`AnalysisOptions`.
    """

    plate_id: Ident
    design: Annotated[str, Field(min_length=1, max_length=255)]
    placement: Placement | None = None
    note: Annotated[str, Field(max_length=500)] = ""
    template_table: TemplateRows = ()
    design_side: Literal["moulded_up", "moulded_down"] = "moulded_up"
    thickness_mm: Annotated[Finite, Field(ge=0.0, lt=1000.0)] = 0.0
    #: the person who asked, as the HMI authenticated them (the HMI sets it, whatever its page sent);
    #: recorded in the job's history and the audit log. None: not said (a CLI or MES trigger)
    requested_by: UserName | None = None

    @model_validator(mode="after")
    def _options_hold(self) -> TriggerRequest:
        self.analysis_options()  # one rule for the options, in their model
        return self

    def analysis_options(self) -> AnalysisOptions:
        """The per-plate analysis options the job record keeps and the job's settings carry."""
        return AnalysisOptions(
            template_table=self.template_table, design_side=self.design_side, thickness_mm=self.thickness_mm
        )

    @field_validator("design")
    @classmethod
    def _relative_and_plain(cls, v: str) -> str:
        if "\0" in v or "\\" in v:
            raise ValueError("must not contain NUL or backslashes")
        p = PurePosixPath(v)
        if p.is_absolute():
            raise ValueError("must be relative to designs_dir, not absolute")
        # the raw components: PurePosixPath drops "." ("./x.ply" has the parts ("x.ply",))
        if any(part in ("..", ".") for part in v.split("/")) or v.startswith("~"):
            raise ValueError("must not contain '..', '.' or '~' components")
        if p.suffix.lower() not in DESIGN_SUFFIXES:
            raise ValueError(f"must end in one of {', '.join(DESIGN_SUFFIXES)}")
        return v


class TriggerError(ValueError):
    """A trigger payload that is refused; ``field`` names the offending field (or 'payload')."""

    def __init__(self, code: str, field: str, message: str) -> None:
        self.code = code
        self.field = field
        self.message = message
        super().__init__(f"{field}: {message}")

    def to_api_error(self) -> ApiError:
        return ApiError(code=self.code, field=self.field, message=self.message)


def parse_model(
    payload: bytes | bytearray | str | None,
    model: type[M],
    error: Callable[[str, str, str], Exception] = TriggerError,
    *,
    limit: int = MAX_TRIGGER_BYTES,
    unknown: str = "unknown field",
) -> M:
    """Validate a JSON-object payload against ``model``; refusals raise ``error(code, field, message)``.

    The size is checked before parsing. Codes: ``too_large``, ``malformed`` (empty, not UTF-8 JSON,
    nested too deeply, not an object), ``invalid`` (the first failing field, dotted:
    ``placement.pos_mm``; an unknown field says ``unknown``).
    """
    if payload is None or len(payload) == 0:
        raise error("malformed", "payload", "empty; expected a JSON object")
    if len(payload) > limit:
        raise error("too_large", "payload", f"{len(payload)} bytes, limit {limit}")
    try:
        data = json.loads(payload)
    except RecursionError:
        raise error("malformed", "payload", "JSON nested too deeply") from None
    except ValueError as exc:  # JSONDecodeError, UnicodeDecodeError, and integers beyond 4300 digits
        raise error("malformed", "payload", f"not UTF-8 JSON: {str(exc)[:200]}") from None
    if not isinstance(data, dict):
        raise error("malformed", "payload", f"expected a JSON object, got {type(data).__name__}")
    try:
        return model.model_validate(data)
    except ValidationError as err:
        e = err.errors(include_url=False)[0]
        loc = ".".join(str(p) for p in e["loc"]) or "payload"
        msg = unknown if e["type"] == "extra_forbidden" else e["msg"].removeprefix("Value error, ")
        raise error("invalid", loc, msg) from None


def parse_trigger(payload: bytes | bytearray | str | None, designs_dir: Path) -> tuple[TriggerRequest, Path]:
    """Validate a trigger payload; returns the request and the resolved design file.

    The size is checked before parsing; the design path must resolve (symlinks followed) to an
    existing file inside ``designs_dir``. Raises TriggerError with code ``too_large``,
    ``malformed``, ``invalid`` or ``design_not_found``.
    """
    req = parse_model(payload, TriggerRequest)
    root = Path(designs_dir).resolve()
    try:
        path = (root / req.design).resolve()
        inside = path.is_relative_to(root)
        is_file = inside and path.is_file()
    except (OSError, RuntimeError) as exc:  # a name too long for the file system, a symlink loop
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc).split(" from ")[0]
        raise TriggerError("invalid", "design", f"cannot be resolved in designs_dir: {reason}") from None
    if not inside:
        raise TriggerError("invalid", "design", "resolves outside designs_dir")
    if not is_file:
        raise TriggerError("design_not_found", "design", f"no such file in designs_dir: {req.design!r}")
    return req, path


class TriggerAccepted(Model):
    """Reply of the trigger queryable when the scan is accepted."""

    job_id: str
    state: Literal["queued", "started"]
    queue_position: Annotated[int, Field(ge=0)] = 0


class ApiError(Model):
    """Error reply (``query.reply_err``) of every queryable."""

    code: Literal[
        "too_large",
        "malformed",
        "invalid",
        "design_not_found",
        "busy",
        "queue_full",
        "not_allowed",
        "no_job",
        "internal",
    ]
    field: str = ""
    message: str


class ControlRequest(Model):
    """Payload of a control queryable: empty, or the job it is meant for.

    pause / resume / abort: ``job_id`` must be the scanning job, or a queued one (abort only: the
    queued job is cancelled; a job being analysed, a re-analysis among them: its analysis is
    aborted); omitted, the scanning job is meant. reanalyse: required. reset: none.
    ``requested_by``: the person who asked, as in TriggerRequest.
    """

    job_id: Ident | None = None
    requested_by: UserName | None = None


class ControlError(TriggerError):
    """A control request that is refused (same shape as a refused trigger: code, field, message)."""


def parse_control(payload: bytes | bytearray | str | None) -> ControlRequest:
    """Validate a control payload (empty means ``{}``); raises ControlError naming the field."""
    if payload is None or len(payload) == 0:
        return ControlRequest()
    return parse_model(payload, ControlRequest, ControlError)


class ControlReply(Model):
    """Reply of the control queryables: what was done to which job, and the cell state after it.

    ``job_state`` is the job's state after the action (``cancelled`` for a queued job that was
    aborted, ``waiting_for_worker`` for a re-analysis, ...), None where no job is concerned.
    """

    action: ControlAction
    job_id: str | None
    state: str
    job_state: str | None = None


# --------------------------------------------------------------------------------------------- state


class CellState(StrEnum):
    STARTING = "starting"
    IDLE = "idle"
    PLANNING = "planning"
    SCANNING = "scanning"
    PAUSED = "paused"
    ANALYSING = "analysing"
    STOPPING = "stopping"
    FAULTED = "faulted"
    EMERGENCY_STOPPED = "emergency_stopped"


class JobState(StrEnum):
    QUEUED = "queued"
    PLANNING = "planning"
    SCANNING = "scanning"
    PAUSED = "paused"
    WAITING_FOR_WORKER = "waiting_for_worker"
    ANALYSING = "analysing"
    DONE = "done"
    FAILED = "failed"
    ABORTED = "aborted"
    INTERRUPTED = "interrupted"
    CANCELLED = "cancelled"


#: states a job ends in (``interrupted`` and ``failed`` jobs with raw data can be re-analysed)
FINAL_JOB_STATES = frozenset(
    {JobState.DONE, JobState.FAILED, JobState.ABORTED, JobState.INTERRUPTED, JobState.CANCELLED}
)


class MotionCounters(Model):
    """How the motion process served the controller during a job's motion (issue 41).

    ``egm_stale_cycles``: replies that answered a controller cycle with a reference computed for
    another one, or that left more than one EGM cycle after the controller's packet arrived (the
    controller had sent its next packet by then). ``egm_lost_cycles``: controller cycles for which
    no packet reached the motion process (the controller's clock or sequence number jumped).
    ``egm_reply_*_us``: reply latency, packet arrival (kernel) to reply sent, from a histogram of
    10 us bins up to 2 ms. ``max_tracking_error_mm``: the worst monitored TCP tracking error, and
    ``max_tracking_t_traj_s`` where on the plan it was seen (playback time, s: the segment and pass
    follow from the plan). ``cycles``: references sent.
    """

    cycles: Annotated[int, Field(ge=0)] = 0
    egm_stale_cycles: Annotated[int, Field(ge=0)] = 0
    egm_lost_cycles: Annotated[int, Field(ge=0)] = 0
    egm_reply_p50_us: float | None = None
    egm_reply_p99_us: float | None = None
    egm_reply_max_us: float | None = None
    max_tracking_error_mm: float = 0.0
    max_tracking_t_traj_s: float | None = None


class JobProgress(Model):
    """Where one job stands; ``fraction`` is 0..1 of the current stage. ``motion``: the motion
    process's counters while the job holds the robot (and at its end), else None."""

    job_id: str
    plate_id: str
    state: JobState
    stage: str = ""
    fraction: Annotated[float, Field(ge=0, le=1)] = 0.0
    profiles: Annotated[int, Field(ge=0)] = 0
    points: Annotated[int, Field(ge=0)] = 0
    worker_id: str | None = None
    message: str = ""
    motion: MotionCounters | None = None


class QueuedJob(Model):
    """A trigger waiting for the robot; ``position`` 1 starts next."""

    job_id: str
    plate_id: str
    position: Annotated[int, Field(ge=1)]
    queued_utc: str = ""


class CellStatus(Model):
    """The state publication (``Keys.state``).

    ``job``: the job holding the robot, else the last one shown. ``queued`` / ``queue``: triggers
    waiting for the robot, in start order. ``analyses``: scanned jobs whose report is pending.
    ``recent``: the last jobs that ended (newest last), so a follower never misses an end that was
    published between two of its reads. ``workers``: the workers jobs go to.
    """

    cell_id: str
    state: CellState
    t_utc: str
    job: JobProgress | None = None
    queued: Annotated[int, Field(ge=0)] = 0
    queue: list[QueuedJob] = []
    analyses: list[JobProgress] = []
    recent: list[JobProgress] = []
    workers: list[str] = []
    #: live workers that get no job, each "<worker>: <why>" (another API_VERSION or STREAM_FORMAT,
    #: or no announcement read): during a rolling upgrade, the workers not yet upgraded
    workers_refused: list[str] = []
    message: str = ""

    def jobs(self) -> list[JobProgress]:
        """Every job this publication reports on (recent first, so a live entry wins on overwrite)."""
        return [*self.recent, *self.analyses, *([self.job] if self.job is not None else [])]


# --------------------------------------------------------------------------------------------- workers


class EgmStats(Model):
    """The EGM endpoint's counters since the daemon started (``EgmStatistics.snapshot()`` of the driver)."""

    received: int
    handled: int
    replies_sent: int
    lost: int
    duplicated: int
    out_of_order: int
    malformed: int
    sessions: int
    watchdog_events: int
    send_errors: int
    stale: int = 0
    interval_mean_us: float | None = None
    interval_jitter_us: float | None = None
    interval_max_us: float | None = None
    latency_bins_us: list[float] = []
    latency_counts: list[int] = []
    latency_max_us: float = 0.0


class HeapLine(Model):
    """One source line holding traced Python memory."""

    where: str
    kb: float
    blocks: int


class HeapSummary(Model):
    """The traced Python heap (only under ``PYTHONTRACEMALLOC``): current and peak MB, top lines."""

    traced_mb: float
    peak_mb: float
    top: list[HeapLine] = []


class MotionRealtime(Model):
    """What the OS granted the motion process's cycle thread (issue 41): its SCHED_FIFO priority
    (0: normal scheduling), the CPUs it may run on, whether its memory is locked, and one line per
    setting the OS refused (``refused``, empty when everything was granted)."""

    priority: Annotated[int, Field(ge=0, le=99)] = 0
    sched_fifo: bool = False
    cpus: list[int] = []
    memory_locked: bool = False
    refused: str = ""


class DaemonStats(Model):
    """Reply of ``Keys.stats``: the daemon's counters since it started, for monitoring and the soak."""

    cell_id: str
    t_utc: str
    rss_mb: float
    dispatch_malformed: Annotated[int, Field(ge=0)] = 0
    egm: EgmStats | None = None
    #: what the OS granted the motion process and what it refused
    motion_realtime: MotionRealtime | None = None
    python_heap: HeapSummary | None = None


class WorkerAnnouncement(Model):
    """What a worker says about itself (``Keys.worker_info``)."""

    worker_id: Ident
    host: str
    pid: int
    api_version: int = API_VERSION
    #: the stream chunk format it reads (STREAM_FORMAT; an announcement without it: none)
    stream_format: int = STREAM_FORMAT
    analysis: str
    started_utc: str
    busy_job: str | None = None
    jobs_done: Annotated[int, Field(ge=0)] = 0


def default_worker_id() -> str:
    """host-pid, cleaned into a key-safe identifier."""
    host = "".join(c if c.isalnum() or c in "-_" else "-" for c in socket.gethostname())[:40] or "host"
    return f"{host}-{os.getpid()}"


class JobSpec(Model):
    """Sent with the cloud (as attachment) to the worker that is to analyse it: the job parameters
    (ids, design, the trigger's placement, analysis settings, where to write results) and the attempt.
    ``transfer`` set: the design comes by hash from the daemon and the results go back over Zenoh
    (:mod:`cellctl.api.transfer`); the job's ``design`` and ``out_dir`` paths are the daemon's, not
    the worker's."""

    attempt: Annotated[int, Field(ge=1)]
    job: AnalysisJob
    transfer: TransferSpec | None = None
    #: True: the job message carries no cloud; it comes pass by pass as StreamChunks on
    #: ``Keys.worker_stream`` (after this attempt's ``accepted``), closed by a StreamEnd
    stream: bool = False
    #: unique to this offer (the dispatcher draws it): a restarted daemon offers the same job and
    #: attempt number again, and its offer is another one; the worker echoes it in its JobEvents and
    #: ReportEnvelope so that neither side takes the other offer's messages for its own ("": unnamed)
    offer_id: Annotated[str, Field(pattern=r"^[0-9a-f]{0,32}$")] = ""
    #: the offer's secret, sent only to the assigned worker: it signs its JobEvents, its
    #: ReportEnvelope (the HMAC as the sample's attachment) and its ResultChunks with it
    #: (:mod:`cellctl.api.proof`); never logged, never published elsewhere
    offer_key: Annotated[str, Field(pattern=r"^([0-9a-f]{64})?$", repr=False)] = ""

    @property
    def job_id(self) -> str:
        return self.job.job_id

    @property
    def plate_id(self) -> str:
        return self.job.plate_id


class StreamChunk(Model):
    """The daemon -> the worker holding a streamed job, as the attachment of one chunk on
    ``Keys.worker_stream``: the payload is a cloud (``cellctl.api.cloud_codec``) of the rows assembled
    since the previous chunk, cut where a pass ended. The chunks in ``seq`` order, concatenated, are
    the job's cloud; ``sha256`` is the payload's."""

    job_id: str
    attempt: Annotated[int, Field(ge=1)]
    seq: Annotated[int, Field(ge=0)]
    #: the pass this chunk completes (-1: the rows after the last pass, at the scan's end)
    pass_index: Annotated[int, Field(ge=-1)]
    points: Annotated[int, Field(ge=0)]
    sha256: Annotated[str, Field(pattern=r"^[0-9a-f]{64}$")]
    #: this chunk completes the plan's last pass: what follows is the retract's rows (the worker may
    #: analyse now; the chunks after it seldom hold a point)
    last_pass: bool = False


class StreamEnd(Model):
    """The daemon -> the worker holding a streamed job, on ``Keys.worker_stream_end``: the stream is
    complete with ``chunks`` chunks (seq 0 .. chunks - 1) of ``points`` points in all. A worker
    missing a chunk fetches the whole cloud on ``Keys.job_cloud``."""

    job_id: str
    attempt: Annotated[int, Field(ge=1)]
    chunks: Annotated[int, Field(ge=0)]
    points: Annotated[int, Field(ge=0)]


class JobEvent(Model):
    """Worker -> dispatcher, on ``Keys.job_event``: the life of one attempt."""

    job_id: str
    worker_id: str
    attempt: Annotated[int, Field(ge=1)]
    event: Literal["accepted", "heartbeat", "done", "failed", "rejected", "cancelled"]
    message: str = ""
    t_utc: str = ""
    #: the JobSpec's ``offer_id`` this event is about
    offer_id: Annotated[str, Field(pattern=r"^[0-9a-f]{0,32}$")] = ""


class LiveCloudChunk(Model):
    """The daemon -> displays, on ``Keys.live_cloud`` during a scan: the points assembled since the
    previous chunk, thinned (every few profiles, every few points along the line), base frame, mm,
    rounded to 0.1 mm. ``seq`` counts from 0 per job (a gap: a chunk was dropped); ``profiles``: the
    scan's profiles so far. For the eye only: the analysis gets the full cloud on ``worker_job``."""

    job_id: str
    seq: Annotated[int, Field(ge=0)]
    profiles: Annotated[int, Field(ge=0)] = 0
    xyz_mm: list[tuple[float, float, float]] = []


class ReportEnvelope(Model):
    """The report publication: the analysis result (or its error) and where it came from."""

    job_id: str
    plate_id: str
    worker_id: str
    attempt: Annotated[int, Field(ge=1)]
    ok: bool
    report: Report | None = None
    error: str | None = None
    timings_s: dict[str, float] = {}
    t_utc: str = ""
    #: the result bundle sent before this envelope (JobSpec ``transfer``); None: nothing sent
    results: ResultManifest | None = None
    #: the JobSpec's ``offer_id`` this report answers
    offer_id: Annotated[str, Field(pattern=r"^[0-9a-f]{0,32}$")] = ""


class RefusalLog:
    """Refused requests are counted; the log says so (``event``) at most once per ``every_s``."""

    def __init__(self, event: str, every_s: float = 5.0) -> None:
        self.event = event
        self.every_s = every_s
        self.refused = 0
        self._last = -1e9

    def refused_one(self, err: TriggerError) -> None:
        self.refused += 1
        now = time.monotonic()
        if now - self._last >= self.every_s:
            self._last = now
            log.warning(self.event, code=err.code, field=err.field, error=err.message, total=self.refused)


TRIGGER_LOG = RefusalLog("trigger_refused")
CONTROL_LOG = RefusalLog("control_refused")


def read_payload(query: Any, error: type[TriggerError] = TriggerError) -> bytes | None:
    """A query's payload as bytes (None when it has none); the size is checked before the copy, so a
    huge payload never costs a huge copy (``error("too_large", ...)``)."""
    payload = query.payload
    if payload is None:
        return None
    if len(payload) > MAX_TRIGGER_BYTES:
        raise error("too_large", "payload", f"{len(payload)} bytes, limit {MAX_TRIGGER_BYTES}")
    return payload.to_bytes()


async def handle_trigger(
    query: Any,
    designs_dir: Path,
    accept: Callable[[TriggerRequest, Path], Awaitable[TriggerAccepted]],
) -> TriggerAccepted | None:
    """Answer one trigger query (a ``zenoh.Query``): validate, call ``accept``, reply.

    A refused payload gets ``reply_err`` with an ApiError JSON naming the field and changes
    nothing; ``accept`` may raise TriggerError (for example ``busy``) to refuse as well. Returns
    what was accepted, or None.
    """
    try:
        req, design_path = parse_trigger(read_payload(query), designs_dir)
        accepted = await accept(req, design_path)
    except TriggerError as err:
        TRIGGER_LOG.refused_one(err)
        query.reply_err(err.to_api_error().to_json(), encoding=JSON)
        return None
    query.reply(query.key_expr, accepted.to_json(), encoding=JSON)
    return accepted
