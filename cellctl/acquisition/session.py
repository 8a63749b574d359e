"""One scan's acquisition session: the feed loop that runs while the arm moves.

Three things run together during a scan, and this module is where they meet:

* the **sensor consumer**: every profile batch the source delivers goes into the
  :class:`~cellctl.acquisition.pipeline.Acquisition` (raw files first, then stamping and assembly);
* the **feedback pump**: the EGM endpoint's joint feedback history reaches the acquisition every
  few milliseconds, only what is new since the last pump;
* the **pass markers**: at the cycle the motion's playback time crosses a pass's planned window a
  pass begins or ends (``begin_pass`` / ``end_pass`` at the host time it was seen).

The session knows nothing of Zenoh, jobs or the state machine: the daemon gives it a started
source, the endpoint's history, the plan's pass windows and two callables of the motion (its
playback time and whether it has ended). A write that fails (disk full, quota, file-size limit)
calls ``on_write_error`` once, so that the owner stops the arm smoothly, and ends the session with
that ``OSError`` from :meth:`finish`: everything written before stays readable.

Usage::

    session = AcquisitionSession(acq, sensor, endpoint.history, windows_s, settings, on_write_error=stop)
    await session.start()                      # consumer running, sensor streaming, settled
    tracker = asyncio.create_task(session.track(playback_s, ended))
    ...                                        # the motion runs
    await tracker
    await session.finish()                     # sensor stopped, in-flight frames read, flushed
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import structlog

from cellctl.acquisition.pipeline import Acquisition
from drivers.abb_egm.endpoint import FeedbackArrays
from drivers.laser.source import ProfileSource

__all__ = ["AcquisitionSession", "FeedbackSource", "SessionSettings", "pass_windows_s"]

log = structlog.get_logger(__name__)


class FeedbackSource(Protocol):
    """What the session reads of the EGM endpoint's feedback history."""

    def since(self, t_host_ns: int) -> FeedbackArrays: ...


@dataclass(frozen=True)
class SessionSettings:
    """Timing of the feed loop (``[daemon]`` of cell.toml for the first two)."""

    #: pass markers (and the feedback pump) check the playback time this often, s
    marker_period_s: float = 0.01
    #: sensor streaming before the arm moves: the clock fits gather pairs, the sensor settles, s
    settle_s: float = 1.0
    #: wait after the sensor's stop for frames still in flight, s
    drain_s: float = 0.1
    #: the consumer must end this soon after the source closed, s
    consumer_timeout_s: float = 10.0


def pass_windows_s(starts_s: np.ndarray, durations_s: np.ndarray) -> np.ndarray:
    """(n, 2) playback-time windows ``[start, start + duration)`` of the plan's passes, s."""
    starts = np.asarray(starts_s, dtype=np.float64).reshape(-1)
    return np.stack([starts, starts + np.asarray(durations_s, dtype=np.float64).reshape(-1)], axis=1)


class AcquisitionSession:
    """The feed loop of one scan (see the module docstring).

    Args:
        acq: the scan's acquisition (its raw writer attached).
        sensor: a connected and configured profile source; the session starts, stops and closes it.
        feedback: the EGM endpoint's feedback history (``endpoint.history``).
        windows_s: (n, 2) playback-time windows of the passes (:func:`pass_windows_s`); pass ``k`` is
            row ``k``.
        settings: timing.
        on_write_error: called once, in the loop, when the raw files take no more.
        on_assembled: called with the batches each profile batch assembled and the profile count so
            far (the daemon's live cloud for displays); None: nobody watches.
    """

    def __init__(
        self,
        acq: Acquisition,
        sensor: ProfileSource,
        feedback: FeedbackSource,
        windows_s: np.ndarray,
        settings: SessionSettings,
        *,
        on_write_error: Callable[[OSError], None],
        on_assembled: Callable[[list, int], None] | None = None,
    ) -> None:
        self.acq = acq
        self.sensor = sensor
        self.feedback = feedback
        self.windows_s = np.asarray(windows_s, dtype=np.float64).reshape(-1, 2)
        self.settings = settings
        #: profiles taken in; after a failed raw write, those on disk (``profiles_lost`` the rest)
        self.profiles = 0
        self.profiles_lost = 0
        self.write_error: OSError | None = None
        self._on_write_error = on_write_error
        self._on_assembled = on_assembled
        self._last_robot_ns = -1
        self._consumer: asyncio.Task[None] | None = None
        self._open_pass = -1
        self._finished = False

    # ---- the three feeds -------------------------------------------------------------------------

    def pump_feedback(self) -> None:
        """Hand the feedback that arrived since the last pump to the acquisition."""
        a = self.feedback.since(self._last_robot_ns)
        if len(a):
            self._guarded(
                self.acq.feed_robot, a.t_host_ns, a.t_ctrl_us, a.q_deg[:, : self.acq.settings.n_axes]
            )
            self._last_robot_ns = int(a.t_host_ns[-1])

    async def _consume(self) -> None:
        async for batch in self.sensor:
            made = self._guarded(self.acq.feed_profiles, batch)
            self.profiles += len(batch)
            if made and self._on_assembled is not None:
                self._on_assembled(made, self.profiles)

    def mark(self, tau_s: float, t_ns: int) -> None:
        """Open / close passes for playback time ``tau_s`` seen at host time ``t_ns``."""
        inside = np.nonzero((self.windows_s[:, 0] <= tau_s) & (tau_s < self.windows_s[:, 1]))[0]
        k = int(inside[0]) if inside.size else -1
        if k == self._open_pass:
            return
        if self._open_pass >= 0:
            self._guarded(self.acq.end_pass, t_ns)
        if k >= 0:
            self._guarded(self.acq.begin_pass, k, t_ns)
        self._open_pass = k

    def _guarded(self, fn: Callable[..., Any], *args: object) -> Any:
        try:
            return fn(*args)
        except OSError as exc:
            if self.write_error is None:
                self.write_error = exc
                self._count_lost()
                self._on_write_error(exc)
            raise

    def _count_lost(self) -> None:
        """After a failed raw write, the count says what is on disk: ``profiles`` the profiles the
        writer has written (and fsync'ed), ``profiles_lost`` those counted before that never got there
        (the chunk that failed and what was buffered or queued behind it)."""
        writer = self.acq.writer
        if writer is None:
            return
        on_disk = int(writer.items_written.get("profiles", 0))
        if on_disk < self.profiles:
            self.profiles_lost, self.profiles = self.profiles - on_disk, on_disk
            log.warning("profiles_lost", on_disk=on_disk, lost=self.profiles_lost)

    # ---- life cycle ------------------------------------------------------------------------------

    async def start(self, *, wait_settle: bool = True) -> float:
        """Pump the feedback so far, start consuming and streaming, and wait ``settle_s`` (or, with
        ``wait_settle=False``, leave the wait to the caller: the move to the plan's start overlaps
        it). Returns the host monotonic time (s) the settle ends at."""
        self.pump_feedback()
        self._consumer = asyncio.create_task(self._consume(), name="sensor-consumer")
        await self.sensor.start()
        settled_at = time.monotonic() + self.settings.settle_s
        if wait_settle:
            await asyncio.sleep(self.settings.settle_s)
        return settled_at

    async def track(self, playback_s: Callable[[], float], ended: Callable[[], bool]) -> None:
        """Mark passes and pump feedback every ``marker_period_s`` until ``ended()``; closes the last
        open pass. Raises the ``OSError`` of a failed write (after ``on_write_error``)."""
        while not ended():
            await asyncio.sleep(self.settings.marker_period_s)
            self.mark(playback_s(), time.monotonic_ns())
            self.pump_feedback()
        if self._open_pass >= 0:
            self._guarded(self.acq.end_pass, time.monotonic_ns())
            self._open_pass = -1

    async def finish(self) -> None:
        """Stop the sensor, read the frames in flight, pump the last feedback, flush the acquisition.

        Raises the ``OSError`` of a write that failed during the session (everything before it is
        on disk), or ``TimeoutError`` when the consumer does not end."""
        with contextlib.suppress(Exception):
            await self.sensor.stop()
        await asyncio.sleep(self.settings.drain_s)
        await self.sensor.close()
        if self._consumer is not None:
            await asyncio.wait_for(self._consumer, self.settings.consumer_timeout_s)
        self.pump_feedback()
        await asyncio.to_thread(self.acq.finish)
        self._finished = True

    async def abort(self) -> None:
        """Cut the session short (an error elsewhere): stop the consumer, leave the sensor stopped
        (not streaming into nowhere until the next scan), close it. Nothing to do after :meth:`finish`."""
        if self._finished:
            return
        if self._consumer is not None:
            if not self._consumer.done():
                self._consumer.cancel()
            # awaited even when it has ended: a consumer that ended on a failed write holds that
            # error, which asyncio would else log as never retrieved (at the next job's start)
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._consumer
        with contextlib.suppress(Exception):
            await asyncio.wait_for(self.sensor.stop(), 2.0)
        with contextlib.suppress(Exception):
            await self.sensor.close()
