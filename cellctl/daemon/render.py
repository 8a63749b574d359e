"""The report render child: ``cellctl report <results>`` in a process of its own, at normal priority.

A child process, not a thread: the render is tens of seconds of matplotlib holding the GIL, which
would delay the event loop (EGM) of the next scan. It runs at normal priority even when the loop
runs under SCHED_FIFO. A cancellation meanwhile (the daemon stopping) stops the render (SIGTERM,
then SIGKILL after ``kill_after_s``): the job is already done with its report.json, and ``cellctl
report <results>`` renders the HTML / PDF again at any time, so a stop never waits tens of seconds.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import structlog
from pydantic import BaseModel, ConfigDict, ValidationError

from drivers.runtime import normal_priority

__all__ = ["ChildRun", "RenderAnswer", "RenderResult", "last_line", "render_report", "run_cellctl_child"]

log = structlog.get_logger(__name__)


class RenderAnswer(BaseModel):
    """What ``cellctl report --json`` prints as its one line of output: the files it wrote."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    csv: str
    html: str
    pdf: str


@dataclass(frozen=True)
class RenderResult:
    """What a render left: the HTML file (None when it failed or was stopped) and its duration."""

    html: Path | None
    elapsed_s: float
    stopped: bool = False


@dataclass(frozen=True)
class ChildRun:
    """A ``cellctl`` child's end: its output, exit code (None when it could not start: ``error``
    says why), whether a cancellation stopped it, and how long it took."""

    out: bytes
    err: bytes
    returncode: int | None
    stopped: bool
    elapsed_s: float
    error: str = ""


async def run_cellctl_child(argv: list[str], *, kill_after_s: float = 5.0) -> ChildRun:
    """``python -m cellctl *argv`` in a child process at normal priority, to its end. A cancellation
    stops it (SIGTERM, then SIGKILL after ``kill_after_s``) and returns with ``stopped`` set: the
    caller records what it has and raises :class:`asyncio.CancelledError` again. Never raises.

    The child is waited for in a thread (``Popen.communicate``), not with asyncio's subprocess
    transport: a cancellation that met the transport while it was being set up (the daemon stopping
    just as a job's report was stored) waited for the child's exit with nothing left to end it."""
    t0 = time.perf_counter()
    loop = asyncio.get_running_loop()
    # futures, not tasks: a cancellation of every task (the loop closing) leaves them to finish
    spawn = loop.run_in_executor(None, functools.partial(
        subprocess.Popen, [sys.executable, "-m", "cellctl", *argv], stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, preexec_fn=normal_priority,
    ))  # fmt: skip
    try:
        proc = await asyncio.shield(spawn)
    except OSError as exc:
        return ChildRun(b"", b"", None, False, time.perf_counter() - t0, str(exc))
    except asyncio.CancelledError:  # stopped while it starts: it is ended once started
        spawn.add_done_callback(_kill_started)
        return ChildRun(b"", b"", None, True, time.perf_counter() - t0, "stopped while starting")
    done = loop.run_in_executor(None, proc.communicate)
    stopped = False
    try:
        out, err = await asyncio.shield(done)
    except asyncio.CancelledError:
        stopped = True
        with contextlib.suppress(ProcessLookupError):
            proc.terminate()
        out, err = b"", b""
        try:
            out, err = await asyncio.wait_for(asyncio.shield(done), kill_after_s)
        except BaseException:  # TimeoutError, or cancelled again: it ends now, its thread with it
            with contextlib.suppress(ProcessLookupError):
                proc.kill()
    return ChildRun(out, err, proc.returncode, stopped, time.perf_counter() - t0)


def _kill_started(spawn: asyncio.Future[subprocess.Popen[bytes]]) -> None:
    if not spawn.cancelled() and spawn.exception() is None:
        proc = spawn.result()
        with contextlib.suppress(ProcessLookupError):
            proc.kill()
        threading.Thread(target=proc.communicate, daemon=True).start()  # reaped, its pipes closed


def last_line(out: bytes) -> bytes:
    """A child's answer: the last line of its output (the logs go to stderr)."""
    return (out.strip().splitlines() or [b""])[-1]


async def render_report(results: Path, *, kill_after_s: float = 5.0) -> RenderResult:
    """Render ``results/report.html`` (and .pdf) from ``results/report.json`` in a child process.

    Never raises for a failed render (logged; the JSON report stands on its own). A cancellation
    stops the child and returns with ``stopped`` set: the caller records what it has and raises
    :class:`asyncio.CancelledError` again.
    """
    run = await run_cellctl_child(["report", "--json", str(results)], kill_after_s=kill_after_s)
    if run.stopped:
        log.warning("html_report_stopped", reason="daemon stopping", regenerate=f"cellctl report {results}")
    html: Path | None = None
    if run.returncode is None:  # the job is done with its JSON report; only the HTML is missing
        log.warning("html_report_failed", error=run.error)
    elif run.returncode == 0:
        try:
            html = results / Path(RenderAnswer.model_validate_json(last_line(run.out)).html).name
        except ValidationError as exc:  # a child of another version: its answer is not this one's
            log.warning("html_report_failed", error=f"the render's answer: {exc.errors()[0]['msg']}")
    elif not run.stopped:
        log.warning("html_report_failed", code=run.returncode, error=run.err.decode(errors="replace")[-500:])
    return RenderResult(html, run.elapsed_s, run.stopped)
