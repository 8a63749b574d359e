"""Process runtime tuning for the cell's long-running processes: one home, one implementation.

What lives here: the precise event loop (microsecond timers), real-time scheduling (SCHED_FIFO for
a loop or a thread, normal priority for helper threads and child processes), the CPU wake-up
latency hold, handing freed C-heap pages back (``malloc_trim``), resident memory and the traced
Python heap, the stop signals of a service (SIGTERM / SIGINT, SIGXFSZ ignored), and rate-limited
warnings for per-message problems (a flood of bad packets or messages must not flood the log).

Why in ``drivers`` and not in ``cellctl``: the users are on both sides of the one-way door. The EGM
endpoint (``drivers.abb_egm.endpoint``) puts its reply thread under SCHED_FIFO, the controller and
sensor simulators run their cycles on the precise loop, and the daemon, the worker and the simulated
cell (``cellctl``) use all of it. ``drivers`` may not import ``cellctl``, so a ``cellctl`` module
could serve only half of them; a module of ``drivers`` can serve all. It sits at the top of
``drivers`` rather than in ``abb_egm`` or ``laser`` so that neither driver owns it (the laser
simulator needs it as much as the EGM side), and it is not a simulator, so production code (the
daemon, the endpoint) importing it imports nothing of a simulator. It depends only on the standard
library and structlog.
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import os
import selectors
import signal
import struct
import threading
import time
import tracemalloc
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import structlog

__all__ = [
    "RateLimitedLog",
    "heap_summary",
    "hold_cpu_wakeup_latency",
    "lock_memory",
    "normal_priority",
    "precise_event_loop",
    "release_freed_memory",
    "rss_mb",
    "set_thread_realtime",
    "stop_on_signals",
    "use_realtime_loop",
]

log = structlog.get_logger(__name__)

_STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)


# ---------------------------------------------------------------------------------- the event loop


def precise_event_loop() -> asyncio.AbstractEventLoop:
    """An asyncio loop whose timers wake with microsecond rather than millisecond resolution.

    The default epoll selector rounds every wait up to a whole millisecond, which makes a 4.032 ms
    cycle jitter by up to 1 ms; ``select()`` takes a ``timeval`` and wakes within tens of us. With the
    few sockets of a cell process the O(n) cost of ``select`` does not matter.
    """
    return asyncio.SelectorEventLoop(selectors.SelectSelector())


# ---------------------------------------------------------------------------------- scheduling


def normal_priority() -> None:
    """Put the calling thread (or a child process before exec) back under SCHED_OTHER.

    Used as a thread-pool initializer and as ``preexec_fn`` of child processes, so that heavy work
    started from a SCHED_FIFO loop (planning, assembly, a report render) never starves the machine.
    """
    with contextlib.suppress(AttributeError, PermissionError, OSError):
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))


def set_thread_realtime(priority: int, cpus: tuple[int, ...] = ()) -> list[str]:
    """Pin the calling thread to ``cpus`` (when given) and, for ``priority`` > 0, run it under
    SCHED_FIFO at that priority.

    Returns what was refused, one line each (empty: everything granted). Needs CAP_SYS_NICE or an
    RLIMIT_RTPRIO (systemd ``LimitRTPRIO``); a refusal is never fatal, the caller logs it.
    """
    refused = []
    if cpus:
        try:
            os.sched_setaffinity(0, cpus)
        except OSError as exc:
            refused.append(f"affinity {cpus}: {exc.strerror or exc}")
    if priority > 0:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        except (AttributeError, OSError) as exc:
            refused.append(f"SCHED_FIFO {priority}: {getattr(exc, 'strerror', None) or exc}")
    return refused


def realtime_other_threads(priority: int) -> tuple[int, list[str]]:
    """Put every other thread of this process that exists now under SCHED_FIFO at ``priority``.

    For a process whose loop thread is real-time and whose few helper threads (a process pool's
    result thread, a library's callback threads) take the GIL: a helper at normal priority holding
    the GIL while the OS runs busy processes instead holds the real-time thread back with it
    (priority inversion through the GIL). Returns (threads raised, refusals one line each)."""
    me = threading.get_native_id()
    raised, refused = 0, []
    try:
        tids = [int(t) for t in os.listdir("/proc/self/task")]
    except OSError as exc:
        return 0, [f"threads: {exc.strerror or exc}"]
    for tid in tids:
        if tid == me:
            continue
        try:
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority))
            raised += 1
        except ProcessLookupError:
            continue  # the thread ended meanwhile
        except (AttributeError, OSError) as exc:
            refused.append(f"thread {tid} SCHED_FIFO {priority}: {getattr(exc, 'strerror', None) or exc}")
    return raised, refused


def lock_memory() -> str | None:
    """Lock every page of this process in RAM, now and later (``mlockall(MCL_CURRENT | MCL_FUTURE)``),
    so a cycle never waits for a page to come back from swap or a lazily mapped one to be faulted in.
    Returns None when granted, else the reason (needs CAP_IPC_LOCK or a large RLIMIT_MEMLOCK)."""
    mcl_current, mcl_future = 1, 2
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.mlockall(mcl_current | mcl_future) == 0:
            return None
        err = ctypes.get_errno()
        return f"mlockall: {os.strerror(err)}"
    except (OSError, AttributeError) as exc:
        return f"mlockall: {exc}"


def use_realtime_loop(priority: int = 10) -> bool:
    """Run the calling thread (the event loop's) under SCHED_FIFO when permitted, as a cell PC runs its
    EGM loop; the loop's default executor gets normal-priority threads so heavy work (planning,
    assembly) never starves the machine. Returns whether the priority was granted."""
    loop = asyncio.get_running_loop()
    loop.set_default_executor(ThreadPoolExecutor(max_workers=4, initializer=normal_priority))
    if priority <= 0:
        log.info("realtime_priority_off", reason="configured priority 0: normal scheduling")
        return False
    refused = set_thread_realtime(priority)
    if refused:
        log.info("realtime_priority_unavailable", reason=refused[0])
        return False
    log.info("realtime_priority", priority=priority)
    return True


_CPU_LATENCY_FD: int | None = None


def hold_cpu_wakeup_latency(max_us: int = 0) -> bool:
    """Keep the CPUs out of deep idle states while this process lives (Linux PM QoS through
    /dev/cpu_dma_latency; released when the process exits). Measured on the 2-core reference VM:
    with idle cores the EGM reply latency was p50 815 us / p99 3.5 ms; holding 0 us gave
    p50 370 us / p99 577 us. Needs root (or the device's permission); returns whether it is held."""
    global _CPU_LATENCY_FD
    if _CPU_LATENCY_FD is not None:
        return True
    try:
        fd = os.open("/dev/cpu_dma_latency", os.O_WRONLY)
        os.write(fd, struct.pack("i", int(max_us)))
    except OSError as exc:
        log.info("cpu_wakeup_latency_unavailable", reason=exc.strerror)
        return False
    _CPU_LATENCY_FD = fd
    log.info("cpu_wakeup_latency_held", max_us=max_us)
    return True


# ---------------------------------------------------------------------------------- memory


def release_freed_memory() -> bool:
    """Return the C heap's free pages to the system (glibc ``malloc_trim``); False where unavailable.

    A job's numpy temporaries (assembly, encoding: ~100 MB at peak for the small plate) are freed
    when it ends, but glibc keeps the pages of its heaps: over a 30-job soak the daemon's RSS crept
    up ~2 MB per job with its traced Python heap flat (126.3 -> 126.5 MB over 10 jobs).
    """
    try:
        libc = ctypes.CDLL("libc.so.6")
        return bool(libc.malloc_trim(0))
    except (OSError, AttributeError):
        return False


def rss_mb() -> float:
    """This process's resident memory, MB (Linux /proc; 0.0 where it cannot be read)."""
    try:
        return int(Path("/proc/self/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        return 0.0


def heap_summary(top: int = 15) -> dict[str, Any]:
    """Traced Python heap (``PYTHONTRACEMALLOC``): current and peak MB, the ``top`` source lines
    holding the most. A snapshot takes seconds: call it off the event loop."""
    current, peak = tracemalloc.get_traced_memory()
    stats = tracemalloc.take_snapshot().statistics("lineno")[:top]
    return {
        "traced_mb": round(current / 1e6, 2),
        "peak_mb": round(peak / 1e6, 2),
        "top": [
            {"where": str(st.traceback), "kb": round(st.size / 1e3, 1), "blocks": st.count} for st in stats
        ],
    }


# ---------------------------------------------------------------------------------- signals


def stop_on_signals(stop: asyncio.Event) -> Callable[[], None]:
    """Set ``stop`` on SIGTERM or SIGINT (systemd's stop, Ctrl-C); call it in the running loop.

    Also ignores SIGXFSZ: a write past a file-size limit must fail (EFBIG, a smooth stop of the scan
    that writes), not kill the process. Returns a function that removes the stop handlers again
    (call it when the service has stopped). Where the loop cannot take signal handlers (not the
    main thread, or a platform without them) the service still runs and stops through ``stop``.
    """
    loop = asyncio.get_running_loop()
    for sig in _STOP_SIGNALS:
        with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
            loop.add_signal_handler(sig, stop.set)
    with contextlib.suppress(AttributeError, ValueError):
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)

    def release() -> None:
        for sig in _STOP_SIGNALS:
            with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
                loop.remove_signal_handler(sig)

    return release


# ---------------------------------------------------------------------------------- logging


class RateLimitedLog:
    """Emit at most one warning per ``interval_s`` per event; each says how many of that event were
    suppressed since the last one and how many there were in all (``total``, also
    :meth:`count`). The sensor clients, the simulators and the worker use it for malformed packets
    and messages."""

    def __init__(self, logger: Any, interval_s: float = 1.0) -> None:
        self._log = logger
        self._interval_ns = int(interval_s * 1e9)
        self._last_ns: dict[str, int] = {}
        self._suppressed: dict[str, int] = {}
        self._total: dict[str, int] = {}

    def count(self, event: str | None = None) -> int:
        """How many times ``event`` (None: any event) was warned of, suppressed ones included."""
        return sum(self._total.values()) if event is None else self._total.get(event, 0)

    def warning(self, event: str, **kw: Any) -> None:
        """Log ``event`` as a warning unless the same event was logged within the interval."""
        now = time.monotonic_ns()
        self._total[event] = total = self._total.get(event, 0) + 1
        last = self._last_ns.get(event)
        if last is not None and now - last < self._interval_ns:
            self._suppressed[event] = self._suppressed.get(event, 0) + 1
            return
        self._last_ns[event] = now
        suppressed = self._suppressed.pop(event, 0)
        self._log.warning(event, suppressed=suppressed, total=total, **kw)
