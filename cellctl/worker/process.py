"""The worker's side of the pipe: :class:`AnalysisProcess`, one spawned analysis child
(:mod:`cellctl.worker.child`) running one job at a time."""

from __future__ import annotations

import asyncio
import contextlib
import multiprocessing as mp
import os
from typing import Any

import structlog

from analysis.contracts.job import AnalysisJob
from cellctl.worker.child import AnalysisLoadError, ChildAnswer, ChildHello, ChildRequest, _child_main
from cellctl.worker.settings import WorkerSettings, blas_threads_for_children

log = structlog.get_logger(__name__)


class AnalysisCrashed(Exception):
    """The analysis child process died (signal, out of memory) before returning a result."""


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
