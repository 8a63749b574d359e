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
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import structlog
from pydantic import BaseModel, ConfigDict, ValidationError

from drivers.runtime import normal_priority

__all__ = ["RenderAnswer", "RenderResult", "render_report"]

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


async def render_report(results: Path, *, kill_after_s: float = 5.0) -> RenderResult:
    """Render ``results/report.html`` (and .pdf) from ``results/report.json`` in a child process.

    Never raises for a failed render (logged; the JSON report stands on its own). A cancellation
    stops the child and returns with ``stopped`` set: the caller records what it has and raises
    :class:`asyncio.CancelledError` again.
    """
    t0 = time.perf_counter()
    try:
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "cellctl", "report", "--json", str(results),
            stdin=asyncio.subprocess.DEVNULL, stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.PIPE, preexec_fn=normal_priority,
        )  # fmt: skip
    except OSError as exc:  # the job is done with its JSON report; only the HTML is missing
        log.warning("html_report_failed", error=str(exc))
        return RenderResult(None, time.perf_counter() - t0)
    render = asyncio.ensure_future(proc.communicate())
    stopped = False
    try:
        await asyncio.shield(render)
    except asyncio.CancelledError:
        stopped = True
        with contextlib.suppress(ProcessLookupError):
            proc.terminate()
        try:
            await asyncio.wait_for(asyncio.shield(render), kill_after_s)
        except Exception:  # TimeoutError included
            with contextlib.suppress(ProcessLookupError):
                proc.kill()
            with contextlib.suppress(Exception):
                await render
        log.warning("html_report_stopped", reason="daemon stopping", regenerate=f"cellctl report {results}")
    html: Path | None = None
    try:
        out, err = render.result()
        if proc.returncode == 0:  # the answer is the last line (the logs go to stderr)
            answer = RenderAnswer.model_validate_json((out.strip().splitlines() or [b""])[-1])
            html = results / Path(answer.html).name
        else:
            log.warning("html_report_failed", code=proc.returncode, error=err.decode(errors="replace")[-500:])
    except ValidationError as exc:  # a child of another version: its answer is not this one's
        log.warning("html_report_failed", error=f"the render's answer: {exc.errors()[0]['msg']}")
    except Exception as exc:  # the JSON report stands on its own
        log.warning("html_report_failed", error=str(exc))
    return RenderResult(html, time.perf_counter() - t0, stopped)
