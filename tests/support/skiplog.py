"""The run's log of skips and fallbacks (one JSON object a line), which .ci/check_skips.py checks.

Written where ``CELLCTL_SKIP_LOG`` names a file: by tests/conftest.py for every skip and expected
failure, and by :func:`record_fallback` for a fallback a case took without skipping (a scan lost to
a starved simulator and run again): that one counts against ``CELLCTL_MAX_FALLBACKS`` like a skip.
"""

from __future__ import annotations

import json
import os
import warnings

SKIP_LOG_ENV = "CELLCTL_SKIP_LOG"
FALLBACK = "fallback:"


def log_entry(nodeid: str, when: str, reason: str, kind: str = "skip") -> None:
    """Append one entry (``kind`` "skip" or "retry") to the log, when the run keeps one."""
    path = os.environ.get(SKIP_LOG_ENV)
    if not path:
        return
    with open(path, "a", encoding="utf-8") as f:
        f.write(json.dumps({"nodeid": nodeid, "when": when, "reason": reason, "kind": kind}) + "\n")


class FallbackWarning(UserWarning):
    """A case fell back (a retry after a starved simulator) and went on: shown in pytest's summary."""


def record_fallback(reason: str) -> None:
    """Record that the running test fell back and continues (it does not skip): ``reason`` must
    begin "fallback:" and say what was starved, with the overrun counts. Logged for .ci/run (which
    counts it and fails past CELLCTL_MAX_FALLBACKS) and warned, so a local run shows it too."""
    if not reason.startswith(FALLBACK):
        raise ValueError(f"a fallback's reason begins {FALLBACK!r}, got {reason!r}")
    nodeid = os.environ.get("PYTEST_CURRENT_TEST", "?").rsplit(" (", 1)[0]
    log_entry(nodeid, "call", reason, kind="retry")
    warnings.warn(reason, FallbackWarning, stacklevel=2)
