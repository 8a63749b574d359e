"""Waiting on an event, not the clock, with a bound that load cannot trip.

Every helper takes ``timeout_s``, the time the event takes on an idle machine, and waits ten times
that (at least 10 s): a wait on an event, not a timing check (figures: benchmarks/). On expiry it
raises AssertionError naming ``what`` was awaited. A fixed sleep that stays in a test is there on
purpose (time passing so that nothing happens, pacing, a timeout under test) and says so.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T")

_POLL_S = 0.005


def bound_s(timeout_s: float) -> float:
    """The bound of a wait whose event takes ``timeout_s`` on an idle machine."""
    return max(10.0, 10.0 * timeout_s)


def _expired(what: str, bound: float) -> AssertionError:
    return AssertionError(f"{what}: not within {bound:g} s")


async def wait_until(pred: Callable[[], T], timeout_s: float, what: str = "condition") -> T:
    """Poll ``pred`` in an asyncio test until it is truthy and return its value."""
    bound = bound_s(timeout_s)
    loop = asyncio.get_running_loop()
    deadline = loop.time() + bound
    while not (v := pred()):
        if loop.time() > deadline:
            raise _expired(what, bound)
        await asyncio.sleep(_POLL_S)
    return v


def wait_until_sync(
    pred: Callable[[], T], timeout_s: float, what: str = "condition", poll_s: float = 0.01
) -> T:
    """Poll ``pred`` from a blocking test (threads, processes, files) until truthy; return its value."""
    bound = bound_s(timeout_s)
    deadline = time.monotonic() + bound
    while not (v := pred()):
        if time.monotonic() > deadline:
            raise _expired(what, bound)
        time.sleep(poll_s)
    return v


async def wait_count(read: Callable[[], int], n: int, timeout_s: float, what: str) -> int:
    """Wait until the counter ``read()`` has grown by ``n`` from now (a protocol's own count of
    cycles, messages or packets: time measured by the thing under test, not by the host's clock)."""
    start = read()
    await wait_until(lambda: read() - start >= n, timeout_s, f"{what} (+{n} from {start})")
    return read()


async def wait_subscribed(session, key_expr: str, timeout_s: float, what: str) -> None:
    """Wait until a Zenoh subscriber on ``key_expr`` is known to ``session`` (a put before that is
    lost: through a router a subscriber can become known after the liveliness token declared after
    it). The event the product's ``DispatchSettings.worker_settle_s`` waits for by the clock."""
    pub = session.declare_publisher(key_expr)
    try:
        await wait_until(
            lambda: pub.matching_status.matching, timeout_s, f"{what}: a subscriber on {key_expr}"
        )
    finally:
        pub.undeclare()
