"""Waiting on an event in asyncio tests, with a bound that load cannot trip."""

from __future__ import annotations

import asyncio
from collections.abc import Callable


async def wait_until(pred: Callable[[], bool], timeout_s: float) -> None:
    """Wait for ``pred``; ``timeout_s`` is the time it takes on an idle machine, the bound is ten
    times that (at least 10 s): waits on an event, not a timing check (figures: benchmarks/)."""
    timeout_s = max(10.0, 10.0 * timeout_s)
    deadline = asyncio.get_running_loop().time() + timeout_s
    while not pred():
        if asyncio.get_running_loop().time() > deadline:
            raise AssertionError(f"condition not met within {timeout_s} s")
        await asyncio.sleep(0.005)
