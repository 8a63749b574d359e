"""The analysis child's side of the pipe: the spawned process that loads the analysis callable and
answers the worker's requests (:func:`_child_main`), and the messages both ends speak
(:class:`ChildRequest`, :class:`ChildHello`, :class:`ChildAnswer`)."""

from __future__ import annotations

import contextlib
import importlib
import json
import os
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, model_validator

from analysis.contracts.job import AnalysisJob, Report
from cellctl.worker.heap import HeapReserve, single_arena
from cellctl.worker.settings import limit_blas_threads


class AnalysisLoadError(Exception):
    """The analysis callable cannot be imported (bad dotted path, import error in its module)."""


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
    streamed job tops up a reserve of touched heap as its chunks arrive (:mod:`cellctl.worker.heap`); the
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
