"""The analysis worker (`cellctl worker`): receives clouds over Zenoh, analyses, publishes reports.

Shape of one worker process:

* the main process holds the Zenoh session and an asyncio loop: a liveliness token
  (``Keys.worker_alive``), a subscriber for jobs addressed to it (``Keys.worker_job``), one for
  cancellations, an info queryable, heartbeats while a job runs;
* the analysis runs in a *spawned* child process (:class:`AnalysisProcess`), so neither Zenoh
  callbacks nor heartbeats wait for it, and a crash or a cancellation kills only the child. The
  child is spawned, never forked: Zenoh's threads must not be forked.

The analysis callable is resolved from a dotted path ``"package.module:function"`` (default
``analysis.pipeline:analyse_job``) and called in the child as
``fn(cloud: ScanCloud, job: AnalysisJob) -> Report | dict``: ``cloud`` is the decoded cloud as
:class:`analysis.cloud_io.ScanCloud` (``xyz_mm`` (n, 3) mm, and when sent the organisation
``pass_id``, ``profile_index``, ``point_index`` and the times ``t_s``), ``job`` is the JobSpec's
:class:`~analysis.job.AnalysisJob` (validated again in the child: ids, design, the trigger's
placement, settings, ``out_dir``). What it returns is validated as a :class:`~analysis.job.Report`
before it leaves the child (numpy scalars and arrays are converted); a report that does not fit
the schema is an analysis error.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import importlib
import json
import multiprocessing as mp
import os
import shutil
import signal
import socket
import sys
import threading
import time
import traceback
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import structlog
import zenoh
from pydantic import BaseModel, ConfigDict, model_validator

from analysis.contracts.job import AnalysisJob, Report
from cellctl.api import (
    JobEvent,
    JobSpec,
    Keys,
    ReportEnvelope,
    WorkerAnnouncement,
    default_worker_id,
    now_utc,
)
from cellctl.api.models import StreamChunk, StreamEnd
from cellctl.api.proof import chunk_mac, sign
from cellctl.api.session import (
    ZenohSetupError,
    async_get,
    build_zenoh_config,
    close_session,
    declare_async_queryable,
    open_session,
    subscribe,
)
from cellctl.api.transfer import (
    ResultChunk,
    ResultManifest,
    TransferError,
    cache_design,
    cached_design,
    pack_results,
)
from cellctl.heap import HeapReserve, single_arena
from drivers.runtime import stop_on_signals

log = structlog.get_logger(__name__)

DEFAULT_ANALYSIS = "analysis.pipeline:analyse_job"


class AnalysisLoadError(Exception):
    """The analysis callable cannot be imported (bad dotted path, import error in its module)."""


class AnalysisCrashed(Exception):
    """The analysis child process died (signal, out of memory) before returning a result."""


@dataclass(frozen=True)
class WorkerSettings:
    """How a worker behaves; defaults suit a worker beside the daemon on the cell PC."""

    worker_id: str = ""
    analysis: str = DEFAULT_ANALYSIS
    heartbeat_s: float = 1.0
    start_timeout_s: float = 120.0
    connect_retry_s: float = 2.0
    # BLAS threads in the analysis process (0: the library's default). One: the analysis' matrix
    # products are (n, 3) x (3, 3), memory-bound, and on a busy 2-core machine OpenBLAS' spinning
    # threads made one such product of 2.5 M points take 1.5 s instead of 0.1 s (load 8).
    blas_threads: int = 1
    # MB of touched free heap the analysis process keeps ready while a streamed scan arrives (at
    # most; cellctl.heap.RESERVE_BYTES_PER_POINT a point received), and it keeps what it frees until
    # the job ends: page faults were half the analysis' time on the sail plate. 0: neither.
    heap_reserve_mb: int = 1536
    # the worker's own files (design cache, a job's results until sent): never the daemon's
    data_dir: Path = Path("worker-data")
    design_timeout_s: float = 60.0
    # a free slot is held this long for a cell passed over while busy (longer than the dispatcher's
    # busy back-off, 2 s, so that cell's next offer finds it)
    fair_hold_s: float = 4.0
    # a streamed job: after StreamEnd a missing chunk is awaited this long before the whole cloud
    # is fetched from the daemon; no chunk at all for stream_idle_s (a pass takes minutes at most)
    # gives the attempt up; the whole cloud's fetch may take cloud_timeout_s
    stream_grace_s: float = 2.0
    stream_idle_s: float = 900.0
    cloud_timeout_s: float = 120.0
    # the chunk the daemon marks ``last_pass`` starts the analysis at once (the arm retracts); the
    # report stands when the rest of the stream adds no point, else the analysis runs again
    analyse_ahead: bool = True

    @classmethod
    def from_config(cls, config: Any, **override: Any) -> WorkerSettings:
        """From ``[analysis]`` and ``[worker]`` of a CellConfig; keyword arguments override (the
        command line)."""
        a = config.analysis
        values = {
            "analysis": a.callable,
            "heartbeat_s": a.heartbeat_s,
            "data_dir": config.worker.data_dir,
            "heap_reserve_mb": config.worker.heap_reserve_mb,
        }
        values.update({k: v for k, v in override.items() if v is not None})
        return cls(**values)


@dataclass
class _StreamInbox:
    """The chunks of the streamed job this worker holds, as they arrive (any order, duplicates)."""

    job_id: str
    attempt: int
    chunks: dict[int, tuple[StreamChunk, bytes]] = field(default_factory=dict)
    end: StreamEnd | None = None
    next_seq: int = 0
    points: int = 0
    duplicates: int = 0
    corrupt: int = 0
    # set when the daemon that streams this job is gone (its liveliness token ended) before the end
    daemon_gone: bool = False
    wake: asyncio.Event = field(default_factory=asyncio.Event)


def resolve_callable(path: str) -> Callable[..., Any]:
    """``"pkg.module:function"`` -> the function; AnalysisLoadError says what failed."""
    module_name, sep, attr = path.partition(":")
    if not sep or not module_name or not attr:
        raise AnalysisLoadError(f"analysis {path!r}: expected 'package.module:function'")
    try:
        module = importlib.import_module(module_name)
    except Exception as exc:
        raise AnalysisLoadError(f"analysis {path!r}: cannot import {module_name}: {exc!r}") from None
    fn: Any = module
    for part in attr.split("."):
        fn = getattr(fn, part, None)
        if fn is None:
            raise AnalysisLoadError(f"analysis {path!r}: {module_name} has no attribute {attr!r}")
    if not callable(fn):
        raise AnalysisLoadError(f"analysis {path!r}: {attr} is not callable")
    return fn


def _json_default(obj: Any) -> Any:
    # numpy scalars and arrays, without importing numpy in this module's top level
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if hasattr(obj, "item"):
        return obj.item()
    if isinstance(obj, set | frozenset | tuple):
        return list(obj)
    return str(obj)


def _watch_parent(parent_pid: int) -> None:
    # A killed worker must not leave its analysis child behind.
    while True:
        time.sleep(0.5)
        if os.getppid() != parent_pid:
            os._exit(3)


_BLAS_THREAD_VARS = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def limit_blas_threads(n: int) -> None:
    """Ask the BLAS libraries for ``n`` threads (0: leave their default). Works only before numpy is
    first imported in this process (they read the environment when they load); an explicit setting
    in the environment wins."""
    if n > 0:
        for var in _BLAS_THREAD_VARS:
            os.environ.setdefault(var, str(n))


@contextlib.contextmanager
def blas_threads_for_children(n: int) -> Iterator[None]:
    """The environment a process spawned inside inherits asks its BLAS libraries for ``n`` threads
    (0: unchanged; an explicit setting in the environment wins); this process's environment is
    restored after. A spawned child imports numpy (and loads its OpenBLAS, which reads the variable
    once) before its own code runs, so the variable must be there when the child starts."""
    saved = {var: os.environ.get(var) for var in _BLAS_THREAD_VARS}
    limit_blas_threads(n)
    try:
        yield
    finally:
        for var, value in saved.items():
            if value is None:
                os.environ.pop(var, None)
            else:
                os.environ[var] = value


def _outcome_text(result: Any, timings_s: dict[str, float]) -> str:
    if not isinstance(result, Report):
        result = Report.model_validate_json(json.dumps(result, default=_json_default, allow_nan=False))
    answer = ChildAnswer(ok=True, report=result, timings_s=timings_s)
    # NaN in a figure is an error here (JSON has none), as it is where the report is written
    return json.dumps(answer.model_dump(mode="json", exclude={"error", "traceback"}), allow_nan=False)


def _error_text(exc: BaseException, t0: float) -> str:
    return ChildAnswer(
        ok=False,
        error=f"{type(exc).__name__}: {exc}",
        traceback=traceback.format_exc(limit=8),
        timings_s={"total": time.perf_counter() - t0},
    ).model_dump_json(exclude_none=True)


class ChildHello(BaseModel):
    """The analysis child's first message: it loaded the analysis callable (``ready``), or why not."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    ready: bool
    error: str | None = None


class ChildAnswer(BaseModel):
    """The analysis child's answer to a ``job`` or ``finish`` request: the report (``ok``), or the
    error with its traceback; the timings of the child's stages (s) either way."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    ok: bool
    report: Report | None = None
    error: str | None = None
    traceback: str | None = None
    timings_s: dict[str, float]

    @model_validator(mode="after")
    def _report_or_error(self) -> ChildAnswer:
        if self.ok != (self.report is not None) or self.ok == (self.error is not None):
            raise ValueError("an answer carries a report when ok, else an error")
        return self


class ChildRequest(BaseModel):
    """The header of one request from the worker to its analysis child (the body follows as raw
    bytes): ``job`` (body: the whole cloud) and ``open`` carry ``spec``, the AnalysisJob's JSON;
    ``chunk`` (body: the next encoded chunk), ``ahead`` (every pass is in: analyse before the end),
    ``finish`` and ``drop`` carry nothing."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    op: Literal["job", "open", "chunk", "ahead", "finish", "drop"]
    spec: str | None = None


class _ChildStream:
    """A streamed job in the analysis child: the analysis' own stream (``fn.stream``, e.g.
    :class:`analysis.pipeline.CloudStream`) fed chunk by chunk, or, for an analysis without one, the
    chunks kept and the callable run on their concatenation. An error is kept for :meth:`finish`."""

    def __init__(self, fn: Callable[..., Any], spec_raw: bytes, reserve: HeapReserve | None = None) -> None:
        self.fn = fn
        self.error: BaseException | None = None
        self.decode_s = 0.0
        self.reserve = reserve
        self.reserve_s = 0.0
        self.points = 0
        self.stream: Any = None
        self.clouds: list[Any] = []
        self.t_open = time.perf_counter()
        try:
            self.job = AnalysisJob.model_validate_json(spec_raw)
            factory = getattr(fn, "stream", None)
            self.stream = factory(self.job) if factory is not None else None
        except Exception as exc:
            self.error = exc
        self.open_s = time.perf_counter() - self.t_open

    def add(self, raw: bytes) -> None:
        if self.error is not None:
            return
        from cellctl.api.cloud_codec import decode_cloud

        t0 = time.perf_counter()
        try:
            cloud = decode_cloud(raw).scan_cloud()
            self.points += len(cloud)
            if self.stream is not None:
                self.stream.add(cloud)
            else:
                self.clouds.append(cloud)
        except Exception as exc:
            self.error = exc
        t1 = time.perf_counter()
        self.decode_s += t1 - t0
        if self.reserve is not None and self.error is None:
            self.reserve.top_up(self.points)  # the scan goes on meanwhile: the child has time
            self.reserve_s += time.perf_counter() - t1

    def ahead(self) -> None:
        """Every pass is in: an analysis that can (``stream.ahead``) runs now, before the stream's
        end; its report stands if nothing after changes the cloud."""
        ahead = getattr(self.stream, "ahead", None)
        if self.error is None and ahead is not None:
            try:
                ahead()
            except Exception as exc:  # an analysis' own early run failed: the end runs it as always
                print(f"analysis child: the analysis ahead of the end failed: {exc!r}", file=sys.stderr)

    def finish(self) -> str:
        t0 = time.perf_counter()
        try:
            if self.error is not None:
                raise self.error
            if self.stream is not None:
                result = self.stream.finish()
            else:
                from analysis.pipeline import concat_clouds

                result = self.fn(concat_clouds(self.clouds), self.job)
            timings = {
                "stream_open": self.open_s,
                "decode": self.decode_s,
                "analysis": time.perf_counter() - t0,
                **(
                    {"heap_reserve": self.reserve_s, "heap_reserve_mb": self.reserve.touched_bytes / 2**20}
                    if self.reserve is not None
                    else {}
                ),
                # the analysis made ahead of the stream's end, when it was kept
                **{k: v for k, v in getattr(self.stream, "timings_s", {}).items() if k.startswith("ahead")},
            }
            return _outcome_text(result, timings)
        except Exception as exc:
            return _error_text(exc, t0)
        finally:
            self.close()

    def close(self) -> None:
        self.clouds = []
        if self.stream is not None and hasattr(self.stream, "close"):
            with contextlib.suppress(Exception):
                self.stream.close()
        self.stream = None


def _child_main(
    conn: Any, analysis: str, parent_pid: int, blas_threads: int = 1, heap_reserve_mb: int = 0
) -> None:
    """Entry point of the spawned analysis process: load the callable, then serve jobs from the pipe.

    Messages from the parent are pairs of frames (a JSON header ``{"op": ...}``, a body): ``job``
    (body: the cloud; header ``spec``) answered with the outcome; ``open`` (a streamed job, header
    ``spec``), ``chunk`` (body: the next chunk) and ``finish`` (answered with the outcome); ``drop``
    forgets an open stream. ``heap_reserve_mb`` > 0: the process keeps the memory it frees and a
    streamed job tops up a reserve of touched heap as its chunks arrive (:mod:`cellctl.heap`); the
    free heap goes back to the system when that job is answered."""
    limit_blas_threads(blas_threads)  # for the libraries the analysis loads (the parent set it for numpy's)
    if heap_reserve_mb > 0:
        single_arena()  # before the analysis starts its threads
    threading.Thread(target=_watch_parent, args=(parent_pid,), daemon=True).start()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides when the child stops
    try:
        fn = resolve_callable(analysis)
    except AnalysisLoadError as exc:
        conn.send_bytes(ChildHello(ready=False, error=str(exc)).model_dump_json().encode())
        return
    from cellctl.api.cloud_codec import decode_cloud

    conn.send_bytes(ChildHello(ready=True).model_dump_json(exclude_none=True).encode())
    stream: _ChildStream | None = None
    reserve: HeapReserve | None = None
    while True:
        try:
            raw_head = conn.recv_bytes()
            body = conn.recv_bytes()
        except (EOFError, OSError):
            return
        try:
            head = ChildRequest.model_validate_json(raw_head)
            if head.op in ("job", "open") and head.spec is None:
                raise ValueError(f"a {head.op!r} request without its job spec")
        except ValueError as exc:  # pydantic's ValidationError is one
            # only the worker writes to this pipe: a request it cannot have meant is a broken
            # pipe protocol, and answering it could pair an answer with the wrong request. Exit:
            # the worker sees the child die (AnalysisCrashed), restarts it and retries the job.
            print(f"analysis child: unusable request from the worker: {exc}", file=sys.stderr)
            sys.exit(2)
        t0 = time.perf_counter()
        op = head.op
        if op == "open":
            if stream is not None:
                stream.close()
            if reserve is not None:
                reserve.stop()
            reserve = HeapReserve(heap_reserve_mb << 20) if heap_reserve_mb > 0 else None
            if reserve is not None and not reserve.start():
                reserve = None  # not glibc: nothing to keep
            stream = _ChildStream(fn, head.spec.encode(), reserve)
            continue
        if op == "chunk":
            if stream is not None:
                stream.add(body)
            continue
        if op == "ahead":
            if stream is not None:
                stream.ahead()
            continue
        if op == "drop":
            if stream is not None:
                stream.close()
            stream = None
            if reserve is not None:
                reserve.stop()
            reserve = None
            continue
        if op == "finish":
            text = stream.finish() if stream is not None else _error_text(RuntimeError("no open stream"), t0)
            stream = None
        else:  # "job": the whole cloud
            try:
                job = AnalysisJob.model_validate_json(head.spec)
                cloud = decode_cloud(body)
                t1 = time.perf_counter()
                result = fn(cloud.scan_cloud(), job)
                text = _outcome_text(result, {"decode": t1 - t0, "analysis": time.perf_counter() - t1})
            except Exception as exc:
                text = _error_text(exc, t0)
        del body
        try:
            conn.send_bytes(text.encode("utf-8"))
        except (BrokenPipeError, OSError):
            return
        if reserve is not None:  # the streamed job is answered: an idle worker holds no peak
            reserve.stop()
            reserve = None


class AnalysisProcess:
    """One spawned child process running the analysis callable, one job at a time."""

    def __init__(
        self,
        analysis: str,
        *,
        start_timeout_s: float = 120.0,
        blas_threads: int = 1,
        heap_reserve_mb: int = 0,
    ) -> None:
        self.analysis = analysis
        self.start_timeout_s = start_timeout_s
        self.blas_threads = blas_threads
        self.heap_reserve_mb = heap_reserve_mb
        self._ctx = mp.get_context("spawn")
        self._proc: Any = None
        self._conn: Any = None

    @classmethod
    def from_settings(cls, settings: WorkerSettings) -> AnalysisProcess:
        """The analysis process of a worker with these settings (callable, start timeout, BLAS
        threads, heap reserve)."""
        return cls(
            settings.analysis,
            start_timeout_s=settings.start_timeout_s,
            blas_threads=settings.blas_threads,
            heap_reserve_mb=settings.heap_reserve_mb,
        )

    @property
    def pid(self) -> int | None:
        return self._proc.pid if self._proc is not None else None

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.is_alive()

    async def start(self) -> None:
        """Spawn the child and wait until it has imported the callable (AnalysisLoadError if not)."""
        parent, child = self._ctx.Pipe(duplex=True)
        proc = self._ctx.Process(
            target=_child_main,
            args=(child, self.analysis, os.getpid(), self.blas_threads, self.heap_reserve_mb),
            name="cellctl-analysis",
        )
        with blas_threads_for_children(self.blas_threads):  # numpy's OpenBLAS loads before _child_main
            proc.start()
        child.close()
        self._proc, self._conn = proc, parent
        ready = await asyncio.to_thread(parent.poll, self.start_timeout_s)
        if not ready:
            self.kill()
            raise AnalysisLoadError(
                f"analysis {self.analysis!r}: child not ready after {self.start_timeout_s} s"
            )
        try:
            hello = ChildHello.model_validate_json(parent.recv_bytes())
        except (EOFError, OSError):
            self.kill()
            raise AnalysisLoadError(f"analysis {self.analysis!r}: child exited while starting") from None
        if not hello.ready:
            self.kill()
            raise AnalysisLoadError(hello.error or "analysis child refused to start")
        log.info("analysis_process_ready", pid=proc.pid, analysis=self.analysis)

    def _wait_result(self) -> bytes:
        # Runs in a thread; polls so a dead child is noticed instead of waiting forever.
        conn, proc = self._conn, self._proc
        while True:
            try:
                if conn.poll(0.2):
                    return conn.recv_bytes()
            except (EOFError, OSError):
                raise AnalysisCrashed(f"analysis process died (exit code {proc.exitcode})") from None
            if not proc.is_alive():
                proc.join(0.1)
                raise AnalysisCrashed(f"analysis process died (exit code {proc.exitcode})")

    async def _send(self, head: ChildRequest, body: bytes | bytearray = b"") -> None:
        if self._proc is None or not self._proc.is_alive():
            raise AnalysisCrashed("analysis process is not running")
        head_raw = head.model_dump_json(exclude_none=True).encode("utf-8")

        def send() -> None:
            self._conn.send_bytes(head_raw)
            self._conn.send_bytes(body)

        try:
            await asyncio.to_thread(send)
        except (BrokenPipeError, OSError) as exc:
            raise AnalysisCrashed(f"analysis process unreachable: {exc}") from None

    async def run(self, job: AnalysisJob, cloud: bytes) -> ChildAnswer:
        """Analyse one cloud in the child. AnalysisCrashed if the child dies meanwhile."""
        await self._send(ChildRequest(op="job", spec=job.model_dump_json()), cloud)
        return await self._outcome()

    async def open_stream(self, job: AnalysisJob) -> None:
        """Start a streamed job in the child (the analysis prepares what needs no cloud)."""
        await self._send(ChildRequest(op="open", spec=job.model_dump_json()))

    async def add_chunk(self, chunk: bytes | bytearray) -> None:
        """The next chunk of the open stream (an encoded cloud), in order."""
        await self._send(ChildRequest(op="chunk"), chunk)

    async def ahead_stream(self) -> None:
        """Every pass of the open stream is in: the analysis runs now (the chunks after it are taken
        once it is done; its report stands if they add nothing to the cloud)."""
        await self._send(ChildRequest(op="ahead"))

    async def finish_stream(self) -> ChildAnswer:
        """The open stream is complete: the analysis finishes and reports."""
        await self._send(ChildRequest(op="finish"))
        return await self._outcome()

    async def drop_stream(self) -> None:
        """Forget the open stream (the whole cloud follows by :meth:`run`)."""
        await self._send(ChildRequest(op="drop"))

    async def _outcome(self) -> ChildAnswer:
        raw = await asyncio.to_thread(self._wait_result)
        out = ChildAnswer.model_validate_json(raw)
        if not out.ok:
            log.warning("analysis_failed", error=out.error, traceback=out.traceback)
        return out

    def kill(self) -> None:
        """Stop the child now (cancellation, shutdown)."""
        proc, self._proc = self._proc, None
        if self._conn is not None:
            with contextlib.suppress(OSError):
                self._conn.close()
            self._conn = None
        if proc is not None and proc.is_alive():
            proc.kill()
            proc.join(5)


class _RateLimitedLog:
    """At most one warning per ``every_s`` for a noisy event, with the count of those suppressed."""

    def __init__(self, every_s: float = 5.0) -> None:
        self.every_s = every_s
        self.count = 0
        self._last = -1e9
        self._suppressed = 0

    def warn(self, event: str, **kw: Any) -> None:
        self.count += 1
        now = time.monotonic()
        if now - self._last >= self.every_s:
            log.warning(event, suppressed=self._suppressed, total=self.count, **kw)
            self._last, self._suppressed = now, 0
        else:
            self._suppressed += 1


class Worker:
    """Serves analysis jobs over an open session, for one cell (``keys``) and every cell of ``cells``
    (key prefixes, or key expressions of prefixes such as ``cell/*``: each cell whose daemon is
    alive under it is served from the moment it appears). One job at a time, whichever cell it is
    from; when several cells wait (a cell's job offered while busy), the next free slot goes to
    the cell passed over longest (for ``fair_hold_s``), so no cell is starved by a busier one.
    Use :meth:`serve` until ``stop`` is set."""

    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys | None,
        settings: WorkerSettings,
        runner: AnalysisProcess | None = None,
        cells: list[str] | tuple[str, ...] = (),
    ) -> None:
        self.session = session
        self.keys = keys
        self.cells = tuple(cells)
        self.settings = settings
        self.worker_id = settings.worker_id or default_worker_id()
        self.runner = runner or AnalysisProcess.from_settings(settings)
        self.jobs_done = 0
        self.malformed = _RateLimitedLog()
        self._current: JobSpec | None = None
        self._current_cell: str | None = None
        self._stream: _StreamInbox | None = None
        self._restarting: asyncio.Task[None] | None = None
        self._served: dict[str, Keys] = {}
        self._entities: list[Any] = []
        # cells whose offer was turned down while busy (prefix -> when first), and since when idle
        self._passed_over: dict[str, float] = {}
        self._idle_since = time.monotonic()
        self._task: asyncio.Task[None] | None = None
        self._started_utc = now_utc()
        self._stopping = False

    def announcement(self) -> WorkerAnnouncement:
        return WorkerAnnouncement(
            worker_id=self.worker_id,
            host=socket.gethostname(),
            pid=os.getpid(),
            analysis=self.settings.analysis,
            started_utc=self._started_utc,
            busy_job=self._current.job_id if self._current else None,
            jobs_done=self.jobs_done,
        )

    def _event(self, keys: Keys, spec: JobSpec, event: str, message: str = "") -> None:
        ev = JobEvent(
            job_id=spec.job_id,
            worker_id=self.worker_id,
            attempt=spec.attempt,
            event=event,  # type: ignore[arg-type]
            message=message,
            t_utc=now_utc(),
            offer_id=spec.offer_id,
        )
        payload = ev.to_json()
        self.session.put(
            keys.job_event(spec.job_id), payload, encoding="application/json", attachment=_mac(spec, payload)
        )

    async def serve(self, stop: asyncio.Event) -> None:
        """Start the analysis child, declare the worker's entities, serve until ``stop``; undeclare all."""
        if not self.runner.running:
            await self.runner.start()
        entities = self._entities
        try:
            if self.keys is not None:
                self._serve_cell(self.keys.prefix)
            for cell in self.cells:
                if "*" in cell:  # a key expression: serve each cell whose daemon is alive under it
                    entities.append(
                        subscribe(self.session, f"{cell}/alive/daemon", self._on_daemon, liveliness=True)
                    )
                else:
                    self._serve_cell(cell)
            log.info("worker_ready", worker_id=self.worker_id, analysis=self.settings.analysis,
                     cells=sorted(self._served), patterns=[c for c in self.cells if "*" in c])  # fmt: skip
            await stop.wait()
        finally:
            self._stopping = True
            if self._task is not None:
                self._task.cancel()
                with contextlib.suppress(BaseException):
                    await self._task
            for ent in reversed(entities):
                with contextlib.suppress(Exception):
                    ent.undeclare()
            self.runner.kill()
            log.info("worker_stopped", worker_id=self.worker_id, jobs_done=self.jobs_done)

    def _serve_cell(self, prefix: str) -> None:
        """Declare this worker's entities in one cell (once)."""
        if prefix in self._served:
            return
        keys = self._served[prefix] = Keys(prefix)
        wid, ents = self.worker_id, self._entities
        ents.append(subscribe(self.session, keys.worker_job(wid), lambda s: self._on_job(keys, s)))
        ents.append(subscribe(self.session, keys.worker_cancel(wid), self._on_cancel))
        ents.append(subscribe(self.session, keys.worker_stream(wid), self._on_stream))
        ents.append(
            declare_async_queryable(self.session, keys.worker_info(wid), lambda q: self._on_info(keys, q))
        )
        ents.append(
            subscribe(
                self.session, keys.daemon_alive, lambda s: self._on_daemon_token(keys, s), liveliness=True
            )
        )
        # The token comes last: once the dispatcher sees it, the job subscriber already exists.
        ents.append(self.session.liveliness().declare_token(keys.worker_alive(wid)))
        log.info("worker_serves_cell", worker_id=wid, prefix=prefix)

    def _on_daemon(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            key = str(sample.key_expr)
            self._serve_cell(key[: -len("/alive/daemon")])

    def _on_daemon_token(self, keys: Keys, sample: zenoh.Sample) -> None:
        """The daemon of a served cell went away (killed, its link down): a stream it was sending to
        this worker can never end, so the attempt is given up now rather than after ``stream_idle_s``
        (a restarted daemon's re-analysis of the same job would find this worker busy with it)."""
        inbox = self._stream
        if sample.kind != zenoh.SampleKind.DELETE or inbox is None or inbox.end is not None:
            return
        if self._current_cell != keys.prefix:
            return
        log.warning("stream_daemon_gone", job_id=inbox.job_id, attempt=inbox.attempt, cell=keys.prefix)
        inbox.daemon_gone = True
        inbox.wake.set()

    async def _on_info(self, keys: Keys, query: zenoh.Query) -> None:
        # Reply on our own key, not the (possibly wildcard) query key: replies on one key are
        # consolidated into one, and every worker must be heard.
        query.reply(
            keys.worker_info(self.worker_id), self.announcement().to_json(), encoding="application/json"
        )

    def _turn_down(self, keys: Keys, spec: JobSpec) -> str | None:
        """Why this offer is turned down (busy, or the slot is held for a cell passed over), or None."""
        now = time.monotonic()
        if self._current is not None:
            if keys.prefix != self._current_cell:
                self._passed_over.setdefault(keys.prefix, now)
            return f"busy with {self._current.job_id}"
        if now - self._idle_since >= self.settings.fair_hold_s:
            return None  # the held cell did not come back in time: first come, first served
        waiting = {p: t for p, t in self._passed_over.items() if p in self._served}
        first = min(waiting, key=waiting.__getitem__) if waiting else keys.prefix
        if first == keys.prefix:
            return None
        self._passed_over.setdefault(keys.prefix, now)
        return f"next slot held for {first}"

    def _on_job(self, keys: Keys, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            if sample.attachment is None:
                raise ValueError("no JobSpec attachment")
            spec = JobSpec.model_validate_json(sample.attachment.to_bytes())
            if spec.job_id != Keys.last_chunk(key):
                raise ValueError(f"attachment job_id {spec.job_id!r} does not match the key")
        except ValueError as exc:
            self.malformed.warn("job_message_malformed", key=key, error=str(exc)[:300])
            return
        cur, task = self._current, self._task
        if cur is not None and (cur.job_id, cur.attempt, cur.offer_id) == (
            spec.job_id,
            spec.attempt,
            spec.offer_id,
        ):
            return  # the same offer again
        # Another offer of the job held: the dispatcher took this streamed job back (a link cut, its
        # cancel lost) and offers it again, or a restarted daemon offers it afresh (the same attempt
        # number, another offer): the old attempt's stream will never end, its daemon is not there
        # to take its report, so it makes way for the new one.
        again = cur is not None and cur.job_id == spec.job_id
        newer = again and (
            (cur.stream and spec.attempt > cur.attempt)
            or (spec.attempt == cur.attempt and spec.offer_id != cur.offer_id)
        )
        if newer and task:
            log.info(
                "job_superseded", job_id=spec.job_id, attempt=cur.attempt, by_attempt=spec.attempt,
                by_offer=spec.offer_id,
            )  # fmt: skip
            task.cancel()

            async def take_over() -> None:
                with contextlib.suppress(BaseException):
                    await task
                self._on_job(keys, sample)

            asyncio.get_running_loop().create_task(take_over())
            return
        why = self._turn_down(keys, spec)
        if why is not None:
            log.info("job_turned_down", job_id=spec.job_id, cell=keys.prefix, reason=why)
            self._event(keys, spec, "rejected", why)
            return
        self._passed_over.pop(keys.prefix, None)
        self._current, self._current_cell = spec, keys.prefix
        # the inbox exists before "accepted" goes out: the dispatcher streams only after it
        self._stream = _StreamInbox(spec.job_id, spec.attempt) if spec.stream else None
        self._event(keys, spec, "accepted")
        self._task = asyncio.get_running_loop().create_task(self._run(keys, spec, sample))

    def _on_stream(self, sample: zenoh.Sample) -> None:
        """A chunk or the end of the streamed job held: kept once, checked against its checksum;
        anything for another job or attempt is ignored."""
        key = str(sample.key_expr)
        job_id, attempt, last = key.rsplit("/", 3)[-3:]
        inbox = self._stream
        if inbox is None or job_id != inbox.job_id or attempt != str(inbox.attempt):
            log.debug("stream_message_ignored", key=key)
            return
        try:
            if last == "end":
                end = StreamEnd.model_validate_json(sample.payload.to_bytes())
                if end.job_id != inbox.job_id or end.attempt != inbox.attempt:
                    raise ValueError("StreamEnd does not match the key")
                inbox.end = end
            else:
                if sample.attachment is None:
                    raise ValueError("no StreamChunk attachment")
                head = StreamChunk.model_validate_json(sample.attachment.to_bytes())
                if (head.job_id, str(head.attempt), str(head.seq)) != (job_id, attempt, last):
                    raise ValueError("StreamChunk attachment does not match the key")
                if head.seq < inbox.next_seq or head.seq in inbox.chunks:
                    inbox.duplicates += 1
                    return
                data = sample.payload.to_bytes()
                if hashlib.sha256(data).hexdigest() != head.sha256:
                    inbox.corrupt += 1
                    log.warning("stream_chunk_corrupt", job_id=job_id, seq=head.seq, bytes=len(data))
                    return
                inbox.chunks[head.seq] = (head, data)
        except ValueError as exc:
            self.malformed.warn("stream_message_malformed", key=key, error=str(exc)[:300])
            return
        inbox.wake.set()

    async def _run_stream(self, keys: Keys, spec: JobSpec, job: AnalysisJob) -> ChildAnswer:
        """A streamed job: the chunks go to the analysis child in ``seq`` order as they arrive; after
        StreamEnd with every chunk the analysis finishes. A chunk still missing ``stream_grace_s``
        after the end (or totals that disagree): the whole cloud from the daemon, analysed whole."""
        inbox = self._stream
        assert inbox is not None
        st = self.settings
        await self.runner.open_stream(job)
        while True:
            inbox.wake.clear()
            while inbox.next_seq in inbox.chunks:
                head, data = inbox.chunks.pop(inbox.next_seq)
                await self.runner.add_chunk(data)
                inbox.next_seq += 1
                inbox.points += head.points
                if head.last_pass and st.analyse_ahead:
                    # the arm retracts: the analysis runs now, the rest of the stream seldom adds a point
                    await self.runner.ahead_stream()
            end = inbox.end
            if end is None and inbox.daemon_gone:
                raise TransferError(
                    f"stream of job {spec.job_id}: the daemon sending it is gone (its liveliness token ended)"
                )
            if end is not None and inbox.next_seq >= end.chunks:
                if inbox.next_seq == end.chunks and inbox.points == end.points:
                    out = await self.runner.finish_stream()
                    return self._stream_outcome(out, inbox, fallback=False)
                why = f"{inbox.next_seq} chunks of {inbox.points} points, the end says {end.chunks} of {end.points}"
                return await self._stream_fallback(keys, spec, job, inbox, why)
            try:
                await asyncio.wait_for(inbox.wake.wait(), st.stream_grace_s if end else st.stream_idle_s)
            except TimeoutError:
                if end is None:
                    raise TransferError(
                        f"stream of job {spec.job_id}: nothing for {st.stream_idle_s} s"
                    ) from None
                why = f"chunk {inbox.next_seq} of {end.chunks} missing {st.stream_grace_s} s after the end"
                return await self._stream_fallback(keys, spec, job, inbox, why)

    async def _stream_fallback(
        self, keys: Keys, spec: JobSpec, job: AnalysisJob, inbox: _StreamInbox, why: str
    ) -> ChildAnswer:
        """The stream is incomplete: the whole cloud from the daemon (``Keys.job_cloud``), analysed whole."""
        log.warning("stream_incomplete", job_id=spec.job_id, reason=why, corrupt=inbox.corrupt)
        await self.runner.drop_stream()
        cloud = await self._get_bytes(
            keys.job_cloud(spec.job_id),
            self.settings.cloud_timeout_s,
            f"stream incomplete ({why}) and the whole cloud unavailable",
        )
        log.info("stream_cloud_fetched", job_id=spec.job_id, bytes=len(cloud))
        out = await self.runner.run(job, cloud)
        return self._stream_outcome(out, inbox, fallback=True)

    @staticmethod
    def _stream_outcome(out: ChildAnswer, inbox: _StreamInbox, *, fallback: bool) -> ChildAnswer:
        extra = {"stream_chunks": float(inbox.next_seq), "stream_duplicates": float(inbox.duplicates),
                 "stream_fallback": float(fallback)}  # fmt: skip
        return out.model_copy(update={"timings_s": {**out.timings_s, **extra}})

    def _on_cancel(self, sample: zenoh.Sample) -> None:
        job_id = Keys.last_chunk(str(sample.key_expr))
        said = sample.payload.to_bytes().decode(errors="replace").strip()
        attempt = int(said) if said.isdigit() else None  # empty: whichever attempt is held
        if attempt is not None and self._current is not None and attempt < self._current.attempt:
            log.info("job_cancel_ignored", job_id=job_id, attempt=attempt, holding=self._current.attempt)
            return
        if self._current is not None and self._current.job_id == job_id and self._task is not None:
            log.info("job_cancelled", job_id=job_id)
            self._task.cancel()

    async def _heartbeat(self, keys: Keys, spec: JobSpec) -> None:
        while True:
            await asyncio.sleep(self.settings.heartbeat_s)
            self._event(keys, spec, "heartbeat")

    async def _run(self, keys: Keys, spec: JobSpec, sample: zenoh.Sample) -> None:
        log.info("job_started", job_id=spec.job_id, attempt=spec.attempt, cell=keys.prefix)
        hb = asyncio.get_running_loop().create_task(self._heartbeat(keys, spec))
        t0 = time.perf_counter()
        out_dir: Path | None = None
        try:
            if self._restarting is not None and not self._restarting.done():
                with contextlib.suppress(Exception):
                    await asyncio.shield(self._restarting)  # the analysis child of the previous job
            cloud = await asyncio.to_thread(sample.payload.to_bytes)
            del sample
            job = spec.job
            if spec.transfer is not None:
                try:
                    job, out_dir = await self._local_job(keys, spec)
                except TransferError as exc:
                    log.warning("design_unavailable", job_id=spec.job_id, error=str(exc))
                    self._event(keys, spec, "failed", str(exc))
                    return
            try:
                if spec.stream:
                    outcome = await self._run_stream(keys, spec, job)
                else:
                    outcome = await self.runner.run(job, cloud)
            except TransferError as exc:
                log.warning("stream_failed", job_id=spec.job_id, error=str(exc))
                self._event(keys, spec, "failed", str(exc))
                await self._restart_runner()  # the child may hold half a stream
                return
            except AnalysisCrashed as exc:
                log.error("analysis_crashed", job_id=spec.job_id, error=str(exc))
                self._event(keys, spec, "failed", str(exc))
                await self._restart_runner()
                return
            del cloud
            manifest = None
            if (
                outcome.ok
                and out_dir is not None
                and spec.transfer is not None
                and spec.transfer.return_results
            ):
                manifest = await self._send_results(keys, spec, out_dir)
            env = ReportEnvelope(
                job_id=spec.job_id,
                plate_id=spec.plate_id,
                worker_id=self.worker_id,
                attempt=spec.attempt,
                ok=outcome.ok,
                report=outcome.report,
                error=outcome.error,
                timings_s={**outcome.timings_s, "worker_total": time.perf_counter() - t0},
                t_utc=now_utc(),
                results=manifest,
                offer_id=spec.offer_id,
            )
            payload = env.to_json()
            # Reports can be large (per-line curves): BLOCK, never silently dropped.
            await asyncio.to_thread(
                self.session.put,
                keys.report(spec.job_id),
                payload,
                encoding="application/json",
                attachment=_mac(spec, payload),
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
            self.jobs_done += 1
            log.info(
                "job_reported", job_id=spec.job_id, ok=outcome.ok, seconds=round(time.perf_counter() - t0, 3)
            )
        except asyncio.CancelledError:
            with contextlib.suppress(Exception):  # the link may be down: the restart below must run
                self._event(
                    keys,
                    spec,
                    "cancelled",
                    "worker stopping" if self._stopping else "cancelled by the dispatcher",
                )
            if not self._stopping:  # the analysis child may be mid-job: start a clean one
                await self._restart_runner()
            raise
        except Exception as exc:
            # Anything else (a put refused, an unreadable result): the job goes elsewhere, we go on.
            log.exception("job_error", job_id=spec.job_id)
            with contextlib.suppress(Exception):
                self._event(keys, spec, "failed", f"{type(exc).__name__}: {exc}")
        finally:
            hb.cancel()
            self._stream = None
            self._current = self._current_cell = None
            self._task = None
            self._idle_since = time.monotonic()
            if out_dir is not None:
                shutil.rmtree(out_dir, ignore_errors=True)

    async def _local_job(self, keys: Keys, spec: JobSpec) -> tuple[AnalysisJob, Path]:
        """The job as this worker runs it: the design from its cache (fetched by hash from the
        daemon when missing), the results into a fresh directory of its own."""
        transfer = spec.transfer
        assert transfer is not None
        update: dict[str, Any] = {}
        if transfer.design is not None:
            update["design"] = str(await self._design(keys, transfer.design))
        out_dir = self.settings.data_dir / "jobs" / f"{spec.job_id}-{spec.attempt}"
        await asyncio.to_thread(shutil.rmtree, out_dir, True)
        out_dir.mkdir(parents=True)
        update["out_dir"] = str(out_dir.resolve())
        return spec.job.model_copy(update=update), out_dir

    async def _get_bytes(self, key: str, timeout_s: float, what: str) -> bytes:
        """The payload of the first good reply to a query on ``key``; none -> TransferError naming
        ``what`` and the first error reply (or "no reply")."""
        replies = await async_get(self.session, key, timeout_s=timeout_s)
        ok = [r.ok for r in replies if r.ok is not None]
        if not ok:
            why = replies[0].err.payload.to_bytes().decode(errors="replace") if replies else "no reply"
            raise TransferError(f"{what}: {why}")
        return await asyncio.to_thread(ok[0].payload.to_bytes)

    async def _design(self, keys: Keys, ref: Any) -> Path:
        cache = self.settings.data_dir / "designs"
        path = await asyncio.to_thread(cached_design, cache, ref)
        if path is not None:
            return path
        data = await self._get_bytes(
            keys.design(ref.sha256), self.settings.design_timeout_s, f"design {ref.name} ({ref.sha256[:12]})"
        )
        path = await asyncio.to_thread(cache_design, cache, ref, data)
        log.info("design_cached", name=ref.name, sha256=ref.sha256[:12], bytes=len(data))
        return path

    async def _send_results(self, keys: Keys, spec: JobSpec, out_dir: Path) -> ResultManifest:
        """Pack the results directory and put its chunks (BLOCK) before the report goes out."""
        transfer = spec.transfer
        assert transfer is not None
        manifest, chunks = await asyncio.to_thread(
            pack_results, out_dir, chunk_bytes=transfer.chunk_bytes, max_bytes=transfer.max_result_bytes
        )

        def put_all() -> None:
            for i, data in enumerate(chunks):
                head = ResultChunk(
                    job_id=spec.job_id, worker_id=self.worker_id, attempt=spec.attempt, index=i,
                    chunks=len(chunks), sha256=(sha := hashlib.sha256(data).hexdigest()),
                    mac=chunk_mac(spec.offer_key, spec.job_id, spec.attempt, i, len(chunks), sha)
                    if spec.offer_key else "",
                )  # fmt: skip
                self.session.put(
                    keys.result_chunk(spec.job_id, spec.attempt, i), data, attachment=head.to_json(),
                    congestion_control=zenoh.CongestionControl.BLOCK,
                )  # fmt: skip

        await asyncio.to_thread(put_all)
        log.info("results_sent", job_id=spec.job_id, chunks=manifest.chunks, bytes=manifest.total_bytes)
        return manifest

    async def _restart_runner(self) -> None:
        # A task of its own, shielded: a second cancellation of the job (its cancel message after
        # a take-over) must not leave a child half started whose hello the next job would read.
        if self._restarting is None or self._restarting.done():
            self._restarting = asyncio.get_running_loop().create_task(self._restart())
        await asyncio.shield(self._restarting)

    async def _restart(self) -> None:
        await asyncio.to_thread(self.runner.kill)  # kill() joins the child: not on the loop
        try:
            await self.runner.start()
        except AnalysisLoadError as exc:
            log.error("analysis_restart_failed", error=str(exc))


def _mac(spec: JobSpec, payload: bytes) -> str | None:
    """The attachment that proves a message comes from the worker holding this offer
    (:mod:`cellctl.api.proof`); None for an offer without a key."""
    return sign(spec.offer_key, payload) if spec.offer_key else None


async def run_worker_async(
    section_zenoh: Any,
    key_prefix: str,
    settings: WorkerSettings,
    stop: asyncio.Event | None = None,
    cells: list[str] | tuple[str, ...] = (),
) -> int:
    """Open a client session (retrying until the daemon or router is reachable), serve, close.

    Returns the process exit code: 0 after a clean stop, 2 for configuration or analysis load errors.
    """
    stop = stop or asyncio.Event()
    release_signals = stop_on_signals(stop)
    try:
        cfg_factory = lambda: build_zenoh_config(section_zenoh, role="connect", key_prefix=key_prefix)  # noqa: E731
        cfg_factory()
    except ZenohSetupError as exc:
        log.error("worker_config_invalid", error=str(exc))
        return 2
    # The analysis callable is loaded first: a wrong dotted path fails now, not after connecting.
    runner = AnalysisProcess.from_settings(settings)
    try:
        await runner.start()
    except AnalysisLoadError as exc:
        log.error("analysis_load_failed", error=str(exc))
        return 2
    session = None
    try:
        while session is None and not stop.is_set():
            try:
                session = await asyncio.to_thread(open_session, cfg_factory(), what="worker session")
            except ZenohSetupError as exc:
                log.warning("worker_connect_failed", error=str(exc), retry_s=settings.connect_retry_s)
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(stop.wait(), settings.connect_retry_s)
        if session is None:
            return 0
        # [worker] cells given: those cells (the configured one only if listed); else this cell
        own = None if cells else Keys(key_prefix)
        await Worker(session, own, settings, runner, cells=cells).serve(stop)
        return 0
    finally:
        runner.kill()
        close_session(session)
        release_signals()


def run_worker(config: Any, settings: WorkerSettings) -> int:
    """Blocking entry point used by `cellctl worker`: one worker for ``config`` (a CellConfig).

    Under access control with roles, the worker's id is its Zenoh identity (the ACL lets the
    identity ``w1`` receive only ``workers/w1/**`` and declare only ``alive/workers/w1``): without
    ``--worker-id`` it is ``[zenoh.access] user`` (under ``auth = "tls"`` give the certificate's
    common name as ``--worker-id``)."""
    access = config.zenoh.access
    if not settings.worker_id and access.enabled and access.roles and access.auth != "tls":
        settings = replace(settings, worker_id=access.user)
    return asyncio.run(run_worker_async(config.zenoh, config.key_prefix, settings, cells=config.worker.cells))
