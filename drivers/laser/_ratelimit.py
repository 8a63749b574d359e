"""Rate-limited logging for per-packet problems (a flood of bad packets must not flood the log)."""

from __future__ import annotations

import time
from typing import Any


class RateLimitedLog:
    """Emit at most one event per ``interval_s`` per key; report how many were suppressed meanwhile."""

    def __init__(self, logger: Any, interval_s: float = 1.0) -> None:
        self._log = logger
        self._interval_ns = int(interval_s * 1e9)
        self._last_ns: dict[str, int] = {}
        self._suppressed: dict[str, int] = {}

    def warning(self, event: str, **kw: Any) -> None:
        """Log ``event`` as a warning unless the same event was logged within the interval."""
        now = time.monotonic_ns()
        last = self._last_ns.get(event)
        if last is not None and now - last < self._interval_ns:
            self._suppressed[event] = self._suppressed.get(event, 0) + 1
            return
        self._last_ns[event] = now
        suppressed = self._suppressed.pop(event, 0)
        self._log.warning(event, suppressed=suppressed, **kw)
