"""Logging for the cell: structlog, JSON lines for the service, readable lines on a terminal.

``configure_logging()`` once per process. Context (cell id, job id) is bound per asyncio task with
:func:`bind_context` / :func:`bound_context`; each task has its own copy, so two jobs never mix.
Secrets are never rendered: values of keys that look like secrets, and any pydantic ``SecretStr``,
are replaced before rendering.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Iterator, Mapping, MutableMapping
from contextlib import contextmanager
from typing import Any, Literal, TextIO

import structlog
from pydantic import SecretBytes, SecretStr

LogFormat = Literal["auto", "json", "console"]
REDACTED = "***"
_SECRET_KEY_WORDS = ("password", "passwd", "secret", "token", "authorization", "cookie", "credential")


def _is_secret_key(key: str) -> bool:
    k = key.lower()
    return any(w in k for w in _SECRET_KEY_WORDS) and not k.endswith(("_env", "_file"))


def _redact(value: Any, depth: int = 0) -> Any:
    if isinstance(value, SecretStr | SecretBytes):
        return REDACTED
    if depth < 4 and isinstance(value, Mapping):
        return {k: (REDACTED if _is_secret_key(str(k)) else _redact(v, depth + 1)) for k, v in value.items()}
    if depth < 4 and isinstance(value, list | tuple):
        return type(value)(_redact(v, depth + 1) for v in value)
    return value


def redact_secrets(
    _logger: Any, _method: str, event_dict: MutableMapping[str, Any]
) -> MutableMapping[str, Any]:
    """structlog processor: blank out secret-looking keys and SecretStr values anywhere in the event."""
    for key in list(event_dict):
        event_dict[key] = REDACTED if _is_secret_key(key) else _redact(event_dict[key])
    return event_dict


def configure_logging(
    fmt: LogFormat = "auto", level: str | int = "INFO", stream: TextIO | None = None
) -> None:
    """Set up structlog (and route the standard library's logging through the same output).

    fmt "auto" picks readable coloured lines when ``stream`` is a terminal, JSON lines otherwise.
    Logs go to stderr by default so that a command's own output on stdout stays clean.
    """
    stream = stream if stream is not None else sys.stderr
    level_no = logging.getLevelName(level.upper()) if isinstance(level, str) else level
    if not isinstance(level_no, int):
        raise ValueError(f"unknown log level {level!r}")
    use_json = fmt == "json" or (fmt == "auto" and not _isatty(stream))
    global _CURRENT
    _CURRENT = ("json" if use_json else "console", logging.getLevelName(level_no).lower())
    shared: list[Any] = [
        structlog.contextvars.merge_contextvars,
        structlog.processors.add_log_level,
        structlog.processors.TimeStamper(fmt="iso", utc=True),
        redact_secrets,
    ]
    renderer: Any
    if use_json:
        renderer = [structlog.processors.dict_tracebacks, structlog.processors.JSONRenderer(sort_keys=False)]
    else:
        renderer = [structlog.dev.ConsoleRenderer(colors=_isatty(stream))]
    structlog.configure(
        processors=[*shared, structlog.processors.StackInfoRenderer(), *renderer],
        wrapper_class=structlog.make_filtering_bound_logger(level_no),
        logger_factory=structlog.WriteLoggerFactory(file=stream),
        cache_logger_on_first_use=False,
    )
    # Third-party libraries (toppra, asyncio, aiohttp) log through the standard library.
    handler = logging.StreamHandler(stream)
    handler.setFormatter(
        structlog.stdlib.ProcessorFormatter(
            foreign_pre_chain=[*shared, structlog.stdlib.add_logger_name],
            processors=[structlog.stdlib.ProcessorFormatter.remove_processors_meta, *renderer],
        )
    )
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(max(level_no, logging.INFO) if level_no < logging.INFO else level_no)
    # libraries that log every step at INFO (toppra's planner; scikit-fem's assembly and ezdxf's
    # document set-up in the heating plan): their warnings only
    for name in ("toppra", "skfem", "ezdxf"):
        logging.getLogger(name).setLevel(logging.WARNING)


_CURRENT: tuple[str, str] = ("json", "info")


def current_logging() -> tuple[str, str]:
    """(format, level) of the last :func:`configure_logging`: a child process logs the same way."""
    return _CURRENT


def _isatty(stream: TextIO) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, ValueError):
        return False


def bind_context(**values: Any) -> None:
    """Bind context (cell_id=..., job_id=...) to every log line of the current task."""
    structlog.contextvars.bind_contextvars(**values)


@contextmanager
def bound_context(**values: Any) -> Iterator[None]:
    """Bind context for the duration of a ``with`` block (restored afterwards)."""
    with structlog.contextvars.bound_contextvars(**values):
        yield


def get_logger(name: str | None = None, **initial: Any) -> Any:
    """A structlog logger, optionally with initial bound values."""
    return structlog.get_logger(name, **initial)
