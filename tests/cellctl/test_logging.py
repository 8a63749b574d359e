"""Logging: JSON lines for the service, readable lines on a terminal, context per task, no secrets."""

from __future__ import annotations

import asyncio
import io
import json

import structlog
from pydantic import SecretStr

from cellctl.logging import bind_context, configure_logging, get_logger


class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def _lines(stream: io.StringIO) -> list[dict]:
    return [json.loads(line) for line in stream.getvalue().splitlines() if line.strip()]


def test_json_lines_when_not_a_terminal() -> None:
    out = io.StringIO()
    configure_logging("auto", stream=out)
    get_logger("t").info("egm.started", port=6511)
    (line,) = _lines(out)
    assert line["event"] == "egm.started" and line["port"] == 6511 and line["level"] == "info"
    assert "timestamp" in line


def test_readable_lines_on_a_terminal() -> None:
    out = _Tty()
    configure_logging("auto", stream=out)
    get_logger("t").warning("sensor.dropped", frames=3)
    text = out.getvalue()
    assert "sensor.dropped" in text and "frames" in text
    assert not text.lstrip().startswith("{")


def test_secrets_are_never_rendered() -> None:
    out = io.StringIO()
    configure_logging("json", stream=out)
    get_logger("t").info(
        "rws.login",
        user="Default User",
        password="robotics",
        auth=SecretStr("hunter2"),
        headers={"Authorization": "Digest abc", "Accept": "json"},
        rws_password_env="CELL_RWS_PASSWORD",
    )
    text = out.getvalue()
    assert "robotics" not in text and "hunter2" not in text and "Digest abc" not in text
    (line,) = _lines(out)
    assert line["user"] == "Default User" and line["headers"]["Accept"] == "json"
    assert line["rws_password_env"] == "CELL_RWS_PASSWORD"  # the variable's name is not a secret


def test_context_is_bound_per_asyncio_task() -> None:
    out = io.StringIO()
    configure_logging("json", stream=out)
    structlog.contextvars.clear_contextvars()
    bind_context(cell_id="sim1")

    async def job(job_id: str) -> None:
        bind_context(job_id=job_id)
        await asyncio.sleep(0.01)  # stays: the two jobs interleave across an await (the point)
        get_logger("t").info("job.step")

    async def main() -> None:
        await asyncio.gather(job("A"), job("B"))
        get_logger("t").info("after")

    asyncio.run(main())
    lines = _lines(out)
    steps = sorted(line["job_id"] for line in lines if line["event"] == "job.step")
    assert steps == ["A", "B"]
    assert all(line["cell_id"] == "sim1" for line in lines)
    after = next(line for line in lines if line["event"] == "after")
    assert "job_id" not in after
    structlog.contextvars.clear_contextvars()


def test_standard_library_logging_goes_through_the_same_output() -> None:
    import logging

    out = io.StringIO()
    configure_logging("json", stream=out)
    logging.getLogger("some.lib").warning("careful %s", "now")
    (line,) = _lines(out)
    assert line["event"] == "careful now" and line["level"] == "warning"
