"""Process signals for the long-running services (daemon, worker, simulated cell)."""

from __future__ import annotations

import asyncio
import contextlib
import signal
from collections.abc import Callable

__all__ = ["stop_on_signals"]

_STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)


def stop_on_signals(stop: asyncio.Event) -> Callable[[], None]:
    """Set ``stop`` on SIGTERM or SIGINT (systemd's stop, Ctrl-C); call it in the running loop.

    Returns a function that removes the handlers again (call it when the service has stopped). Where
    the loop cannot take signal handlers (not the main thread, or a platform without them) the service
    still runs and stops through ``stop`` alone.
    """
    loop = asyncio.get_running_loop()
    for sig in _STOP_SIGNALS:
        with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
            loop.add_signal_handler(sig, stop.set)

    def release() -> None:
        for sig in _STOP_SIGNALS:
            with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
                loop.remove_signal_handler(sig)

    return release
