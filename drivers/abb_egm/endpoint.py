"""EGM endpoint, sensor side: an asyncio datagram protocol that answers the controller in phase.

The controller is the UDP client. It sends one ``EgmRobot`` every 4 ms (4.032 ms on a real
robot); this endpoint learns the controller's address from the first packet and answers every valid
``EgmRobot`` at once with one ``EgmSensor`` (``MSGTYPE_CORRECTION``, seqno + 1 per reply) carrying the
current reference, in joint mode (planned joints, optional speed reference) or pose mode.

Besides the reply it keeps:

- the latest controller state (:class:`EgmState`) and the "ok to command" rule;
- a bounded history of feedback samples stamped with the host receive time (``time.monotonic_ns``)
  and the controller's own clock, exposed as numpy arrays for pose interpolation
  (:class:`FeedbackHistory`);
- statistics (:class:`EgmStatistics`): received, lost, duplicated, out-of-order, malformed, receive
  interval jitter, reply latency histogram;
- a watchdog that reports when the controller goes quiet and when it comes back.

A malformed datagram is counted and logged (rate limited) and never ends the endpoint.

Two ways to serve the controller (``EgmEndpointConfig.reply_thread``):

- on the asyncio loop (a datagram protocol): simplest, but every reply waits for whatever the loop is
  doing (zenoh hand-offs, status publication, job bookkeeping);
- on a dedicated reply thread with a blocking socket: receive, decode, reply with the current
  reference (read under a short lock), then update state and history, nothing else. Everything that belongs to the loop
  (waking ``wait_for_feedback``, the watchdog callback, log lines) is handed over with
  ``call_soon_threadsafe``. The thread can run under SCHED_FIFO and on chosen CPUs.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import socket
import struct
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import structlog

from drivers.abb_egm.codec import (
    EgmEncodeError,
    MciState,
    MotorState,
    RapidState,
    RobotMessage,
    SensorMessage,
    encode_sensor,
    encode_sensor_header,
    parse_robot_pb,
    robot_from_pb,
)
from drivers.abb_egm.limits import EGM_CYCLE_S
from drivers.abb_egm.ring import ring_indices, ring_search, ring_start
from drivers.runtime import set_thread_realtime

__all__ = [
    "LATENCY_BIN_EDGES_US",
    "EgmEndpoint",
    "EgmEndpointConfig",
    "EgmEndpointError",
    "EgmState",
    "EgmStatistics",
    "FeedbackArrays",
    "FeedbackHistory",
    "HistoryRangeError",
    "axes_of",
    "interpolate_q_deg",
    "latency_percentile_us",
    "ok_to_command",
]

log = structlog.get_logger(__name__)

_U32 = 2**32
#: a forward seqno jump beyond this (4 s of packets) waits for the next packet to confirm it
_SEQNO_JUMP = 1000
#: reply latency histogram bin edges (us): 10 us bins up to 2 ms (fine enough to tell 0.3 ms from
#: 0.5 ms), coarser beyond; the last bin is open ended
LATENCY_BIN_EDGES_US = np.concatenate(
    [np.arange(0, 2000, 10), [2000, 2500, 3000, 4000, 5000, 10000, 20000, 50000, 100000]]
).astype(np.int64)


def latency_percentile_us(counts: np.ndarray, q: float) -> float | None:
    """The ``q`` (0..100) percentile of a :data:`LATENCY_BIN_EDGES_US` histogram, as the upper edge
    of the bin it falls in (10 us resolution below 2 ms); None for an empty histogram."""
    counts = np.asarray(counts, dtype=np.int64)
    total = int(counts.sum())
    if total == 0:
        return None
    i = int(np.searchsorted(np.cumsum(counts), q / 100.0 * total, side="left"))
    edges = LATENCY_BIN_EDGES_US
    return float(edges[i + 1]) if i + 1 < edges.shape[0] else float(edges[-1])


CycleHook = Callable[["RobotMessage", int, str], None]


class EgmEndpointError(Exception):
    """The endpoint cannot do what was asked (not started, bad reference shape, ...)."""


class HistoryRangeError(EgmEndpointError, ValueError):
    """An interpolation time lies outside the feedback history that is still kept."""


@dataclass(frozen=True)
class EgmEndpointConfig:
    """Settings of the sensor-side EGM endpoint (cell.toml ``[robot]`` egm_* keys).

    ``watchdog_s``: no ``EgmRobot`` for this long raises the watchdog event.
    ``history_len``: feedback samples kept (30 000 = 120 s at 250 Hz).
    ``malformed_log_interval_s``: at most one log line per interval for malformed packets.
    ``jitter_window``: receive intervals kept for the jitter figure.
    ``n_axes``: joints in the reference (6 for the IRB 4600).
    ``n_external``: additional axes of the robot's motion group in ``externalJoints`` (1 for a linear
    track, 0 for none). With them, references, the state's ``axes_mm_deg`` and the history's rows
    hold the external axes first, then the joints (``axes_mm_deg``: track mm, then joints deg).

    Reply path (see the module docstring): ``reply_thread`` serves the controller from a dedicated
    thread instead of the asyncio loop. For that thread: ``reply_thread_priority`` > 0 asks for
    SCHED_FIFO at that priority (needs CAP_SYS_NICE / ``LimitRTPRIO``; refused -> normal scheduling
    and a log line), ``reply_thread_cpus`` pins it to those CPUs (empty: any), and
    ``switch_interval_s`` sets ``sys.setswitchinterval`` while the endpoint runs, so a busy
    Python thread hands the GIL to the reply thread sooner (None: leave the interpreter's 5 ms).
    Feedback plausibility: a sample whose joints leave the straight-line prediction from the two
    samples before it by more than ``plausible_tol_deg + accel dt^2 / 2``, or whose controller time
    did not advance by its seqno step (at least one ``cycle_s`` per message, at most
    ``plausible_late_s`` more: a sender that fell behind sends late samples with their true times),
    is held back as suspect (EGM has no checksum; a datagram corrupted past the UDP checksum can
    still decode). The prediction runs on the controller's time when the samples carry it, on the
    seqno otherwise. A suspect is taken once the next sample agrees with it within
    ``plausible_speed_deg_s`` (a real change, e.g. a hard stop, persists), otherwise dropped and
    counted in ``implausible``; pose interpolation never sees it.
    ``cycle_s`` is the controller's nominal period.
    ``reply_spin_us`` > 0 makes the thread poll its socket without sleeping from that long before
    the next packet is due (one receive interval after the last) until it comes or as long again
    after, so the reply does not wait for a wake-up; it costs about twice that per cycle of a core.
    """

    host: str = "127.0.0.1"
    port: int = 6511
    watchdog_s: float = 0.1
    history_len: int = 30_000
    malformed_log_interval_s: float = 1.0
    jitter_window: int = 2_500
    n_axes: int = 6
    n_external: int = 0
    reply_thread: bool = False
    reply_thread_priority: int = 0
    reply_thread_cpus: tuple[int, ...] = ()
    switch_interval_s: float | None = None
    reply_spin_us: float = 0.0
    plausible_accel_deg_s2: float = 5000.0
    plausible_tol_deg: float = 0.05
    plausible_speed_deg_s: float = 600.0
    plausible_late_s: float = 0.25
    cycle_s: float = EGM_CYCLE_S


def ok_to_command(
    motor_state: MotorState | None, mci_state: MciState | None, rapid_state: RapidState | None
) -> bool:
    """abb_libegm's rule: motors on, EGM running, and RAPID running or undefined.

    RAPID_UNDEFINED is accepted because controllers report it after a restart while RAPID runs.
    """
    return (
        motor_state == MotorState.ON
        and mci_state == MciState.RUNNING
        and rapid_state in (RapidState.RUNNING, RapidState.UNDEFINED, None)
    )


@dataclass(frozen=True, slots=True)
class EgmState:
    """The latest ``EgmRobot`` as the endpoint saw it.

    ``t_host_ns``: host receive time (``time.monotonic_ns``); ``feedback_time_us``: controller clock
    (us since the epoch) or None; ``q_deg`` (n_axes,) deg; ``pos_mm`` (3,) and ``quat_wxyz`` (4,) or None;
    ``external_joints`` (n_ext,) the additional axes (a track in mm) or None when none were sent.
    """

    seqno: int | None
    tm_ms: int | None
    t_host_ns: int
    q_deg: np.ndarray
    pos_mm: np.ndarray | None
    quat_wxyz: np.ndarray | None
    feedback_time_us: int | None
    planned_q_deg: np.ndarray | None
    motor_state: MotorState | None
    mci_state: MciState | None
    rapid_exec_state: RapidState | None
    convergence_met: bool | None
    utilization_pct: float | None
    external_joints: np.ndarray | None = None

    @property
    def axes_mm_deg(self) -> np.ndarray:
        """Every axis of the motion group: the external axes (a track, mm) first, then the joints."""
        if self.external_joints is None or self.external_joints.shape[0] == 0:
            return self.q_deg
        return np.concatenate([self.external_joints, self.q_deg])

    @property
    def ok_to_command(self) -> bool:
        """Motors on, EGM running, RAPID running (or undefined)."""
        return ok_to_command(self.motor_state, self.mci_state, self.rapid_exec_state)


@dataclass(frozen=True, slots=True)
class FeedbackArrays:
    """A chronological copy of the feedback history (n samples).

    ``t_host_ns`` (n,) int64 host receive time, ``t_ctrl_us`` (n,) int64 controller clock (-1 where the
    controller sent none), ``seqno`` (n,) int64, ``q_deg`` (n, n_axes) deg, ``pos_mm`` (n, 3) mm and
    ``quat_wxyz`` (n, 4) (NaN where the controller sent no pose). With external axes (a track) the
    rows of ``q_deg`` are ``axes_mm_deg``: the external axes first (mm), then the joints.
    """

    t_host_ns: np.ndarray
    t_ctrl_us: np.ndarray
    seqno: np.ndarray
    q_deg: np.ndarray
    pos_mm: np.ndarray
    quat_wxyz: np.ndarray

    def __len__(self) -> int:
        return int(self.t_host_ns.shape[0])


class FeedbackHistory:
    """Bounded ring buffer of feedback samples; appends are O(1), reads return numpy copies.

    Thread-safe (a lock guards append and copy) so acquisition code in another thread can read it.
    """

    def __init__(self, capacity: int, n_axes: int = 6) -> None:
        if capacity < 2:
            raise ValueError(f"history capacity must be >= 2, got {capacity}")
        self.capacity = capacity
        self._t_host_ns = np.zeros(capacity, dtype=np.int64)
        self._t_ctrl_us = np.full(capacity, -1, dtype=np.int64)
        self._seqno = np.zeros(capacity, dtype=np.int64)
        self._q_deg = np.zeros((capacity, n_axes))
        self._pos_mm = np.full((capacity, 3), np.nan)
        self._quat = np.full((capacity, 4), np.nan)
        self._next = 0
        self._count = 0
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return self._count

    def append(
        self,
        t_host_ns: int,
        t_ctrl_us: int | None,
        seqno: int | None,
        q_deg: np.ndarray,
        pos_mm: np.ndarray | None,
        quat_wxyz: np.ndarray | None,
        states: tuple[object, object, object] | None = None,
    ) -> None:
        """Add one sample (called by the endpoint for every in-order ``EgmRobot``). ``states``
        (motor, EGM, RAPID) is for histories that keep them (the shared ring); this one does not."""
        with self._lock:
            i = self._next
            self._t_host_ns[i] = t_host_ns
            self._t_ctrl_us[i] = -1 if t_ctrl_us is None else t_ctrl_us
            self._seqno[i] = -1 if seqno is None else seqno
            n = min(q_deg.shape[0], self._q_deg.shape[1])
            self._q_deg[i, :n] = q_deg[:n]
            self._pos_mm[i] = np.nan if pos_mm is None else pos_mm
            self._quat[i] = np.nan if quat_wxyz is None else quat_wxyz
            self._next = (i + 1) % self.capacity
            self._count = min(self._count + 1, self.capacity)

    def clear(self) -> None:
        """Forget every sample."""
        with self._lock:
            self._next = 0
            self._count = 0

    def arrays(self) -> FeedbackArrays:
        """All kept samples, oldest first, as numpy copies."""
        with self._lock:
            start = ring_start(self._next, self._count, self.capacity)
            return self._take(ring_indices(start, 0, self._count, self.capacity))

    def since(self, t_host_ns: int) -> FeedbackArrays:
        """The samples received after ``t_host_ns`` (host clock), oldest first, as numpy copies; costs
        what it returns, not the whole record (for a reader that polls for what is new)."""
        with self._lock:
            start = ring_start(self._next, self._count, self.capacity)
            v0 = ring_search(self._t_host_ns, start, self._count, t_host_ns, "right")
            return self._take(ring_indices(start, v0, self._count, self.capacity))

    def _take(self, idx: np.ndarray) -> FeedbackArrays:
        return FeedbackArrays(
            t_host_ns=self._t_host_ns[idx],
            t_ctrl_us=self._t_ctrl_us[idx],
            seqno=self._seqno[idx],
            q_deg=self._q_deg[idx],
            pos_mm=self._pos_mm[idx],
            quat_wxyz=self._quat[idx],
        )

    def q_deg_at(self, t: np.ndarray, *, time_base: str = "host") -> np.ndarray:
        """Joint angles linearly interpolated at times ``t``.

        Args:
            t: (m,) times; int64 ns of ``time.monotonic_ns`` for ``time_base="host"``, int64 us of the
                controller clock for ``time_base="controller"``.

        Returns:
            (m, n_axes) deg.

        Raises:
            HistoryRangeError: a time before the oldest or after the newest kept sample, or a
                controller time base when the controller sent no clock.
        """
        return interpolate_q_deg(self.arrays(), t, time_base)


def interpolate_q_deg(a: FeedbackArrays, t: np.ndarray, time_base: str = "host") -> np.ndarray:
    """Joint angles of the samples ``a`` linearly interpolated at ``t`` (see
    :meth:`FeedbackHistory.q_deg_at`): one implementation for every history kept in any memory."""
    if time_base == "host":
        ts = a.t_host_ns
    elif time_base == "controller":
        ts = a.t_ctrl_us
        if len(a) and np.any(ts < 0):
            raise HistoryRangeError("the controller sent no feedback time; use time_base='host'")
    else:
        raise ValueError(f"time_base must be 'host' or 'controller', got {time_base!r}")
    return _interp_rows(np.asarray(t, dtype=np.int64), ts, a.q_deg)


def _interp_rows(t: np.ndarray, ts: np.ndarray, values: np.ndarray) -> np.ndarray:
    if ts.shape[0] < 2:
        raise HistoryRangeError(f"need at least 2 samples to interpolate, have {ts.shape[0]}")
    t = np.atleast_1d(t)
    if t.size and (t.min() < ts[0] or t.max() > ts[-1]):
        raise HistoryRangeError(f"times [{t.min()}, {t.max()}] outside the history [{ts[0]}, {ts[-1]}]")
    # integer times: subtract the origin before going to float so ns precision survives
    tf = (t - ts[0]).astype(np.float64)
    tsf = (ts - ts[0]).astype(np.float64)
    i = np.clip(np.searchsorted(tsf, tf, side="right") - 1, 0, tsf.shape[0] - 2)
    span = tsf[i + 1] - tsf[i]
    w = np.divide(tf - tsf[i], span, out=np.zeros_like(tf), where=span > 0)[:, None]
    return values[i] * (1.0 - w) + values[i + 1] * w


@dataclass
class EgmStatistics:
    """Counters of the endpoint. ``lost`` counts seqno gaps and shrinks when a late packet fills one.
    ``handled`` counts datagrams whose work is complete (reply, state, history), malformed ones too."""

    received: int = 0
    replies_sent: int = 0
    lost: int = 0
    duplicated: int = 0
    out_of_order: int = 0
    malformed: int = 0
    implausible: int = 0
    sessions: int = 0
    handled: int = 0
    watchdog_events: int = 0
    send_errors: int = 0
    #: replies that left more than one cycle after their packet arrived, or that answered a cycle
    #: for which the cycle hook set no reference of its own (see :meth:`EgmEndpoint.set_cycle_hook`)
    stale: int = 0
    latency_counts: np.ndarray = field(
        default_factory=lambda: np.zeros(LATENCY_BIN_EDGES_US.shape[0], dtype=np.int64)
    )
    latency_max_us: float = 0.0
    #: the latest stale replies (at most 4096): (host monotonic ns when the reply left, latency ns
    #: from the packet's arrival), to set against what else the machine was doing then
    stale_events: deque = field(default_factory=lambda: deque(maxlen=4096))
    _intervals_us: deque = field(default_factory=lambda: deque(maxlen=2_500))

    def receive_interval_us(self) -> np.ndarray:
        """Recent receive intervals between consecutive in-order ``EgmRobot`` messages, us."""
        # copy() is one C call, so a reply thread appending meanwhile cannot break the iteration
        recent = self._intervals_us.copy()
        return np.fromiter(recent, dtype=np.float64, count=len(recent))

    def snapshot(self) -> dict:
        """A plain dict for logs and status publications."""
        iv = self.receive_interval_us()
        return {
            "received": self.received,
            "handled": self.handled,
            "replies_sent": self.replies_sent,
            "lost": self.lost,
            "duplicated": self.duplicated,
            "out_of_order": self.out_of_order,
            "malformed": self.malformed,
            "sessions": self.sessions,
            "watchdog_events": self.watchdog_events,
            "send_errors": self.send_errors,
            "stale": self.stale,
            "interval_mean_us": float(iv.mean()) if iv.size else None,
            "interval_jitter_us": float(iv.std()) if iv.size else None,
            "interval_max_us": float(iv.max()) if iv.size else None,
            "latency_bins_us": LATENCY_BIN_EDGES_US.tolist(),
            "latency_counts": self.latency_counts.tolist(),
            "latency_max_us": self.latency_max_us,
        }


@dataclass(frozen=True, slots=True)
class _Reference:
    mode: str  # "joint" | "pose"
    body: bytes  # EgmSensor without header, encoded once per command instead of once per cycle
    q_deg: np.ndarray | None = None


def _joint_reference(q_deg: np.ndarray, speed_deg_s: np.ndarray | None = None, n_ext: int = 0) -> _Reference:
    """A joint-mode reference; with ``n_ext`` external axes the first ``n_ext`` values of ``q_deg``
    (and of ``speed_deg_s``) go to ``externalJoints``, the rest to ``joints``."""
    ext = q_deg[:n_ext] if n_ext else None
    ext_v = speed_deg_s[:n_ext] if n_ext and speed_deg_s is not None else None
    try:
        body = encode_sensor(
            SensorMessage(
                planned_q_deg=q_deg[n_ext:],
                speed_ref_q_deg_s=None if speed_deg_s is None else speed_deg_s[n_ext:],
                planned_external_joints=ext,
                speed_ref_external_joints=ext_v,
            ),
            with_header=False,
        )
    except EgmEncodeError as exc:
        raise EgmEndpointError(str(exc)) from None
    return _Reference("joint", body, q_deg=q_deg)


WatchdogCallback = Callable[[str, float], None]


class EgmEndpoint(asyncio.DatagramProtocol):
    """Sensor-side EGM server. Use ``await start()``, then ``command_joints`` / ``command_pose``.

    Args:
        config: address and sizes.
        on_watchdog: ``cb(event, quiet_s)`` with event ``"quiet"`` when no ``EgmRobot`` came for
            ``watchdog_s`` and ``"resumed"`` when traffic returns. Called on the event loop.
        clock_ns: host clock, ``time.monotonic_ns`` (replaceable for tests of the history only).
    """

    def __init__(
        self,
        config: EgmEndpointConfig | None = None,
        *,
        on_watchdog: WatchdogCallback | None = None,
        clock_ns: Callable[[], int] = time.monotonic_ns,
        history: FeedbackHistory | None = None,
    ) -> None:
        self.config = config or EgmEndpointConfig()
        self.stats = EgmStatistics(_intervals_us=deque(maxlen=self.config.jitter_window))
        #: the feedback history (a caller may hand one in, e.g. a ring in shared memory that another
        #: process reads: anything with FeedbackHistory's ``append``)
        self.history = (
            history
            if history is not None
            else FeedbackHistory(self.config.history_len, self.config.n_external + self.config.n_axes)
        )
        self._cycle_hook: CycleHook | None = None
        self._hook_commanded = False  # set by command_joints / hold while the hook runs
        #: the next packet's reference, computed ahead by the cycle hook: (reference, controller
        #: time us or None, seqno or None) of the packet it is for
        self._prepared: tuple | None = None
        self._on_watchdog = on_watchdog
        self._clock_ns = clock_ns
        self._transport: asyncio.DatagramTransport | None = None
        self._controller_addr: tuple[str, int] | None = None
        self._latest: EgmState | None = None
        # the last two accepted (seqno, q_deg, t_ctrl_us), a held-back suspect (seqno, q, msg, t_rx_ns, t)
        self._plaus: list[tuple[int, np.ndarray, int | None]] = []
        self._suspect: tuple | None = None
        self._seqno_suspect: int | None = None
        self._reference: _Reference | None = None
        self._last_seqno: int | None = None
        self._last_tm: int | None = None
        self._recent: deque[int] = deque(maxlen=256)
        self._reply_seqno = 0
        self._last_rx_ns: int | None = None
        self._quiet = False
        self._watchdog_handle: asyncio.TimerHandle | None = None
        self._malformed_logged_ns = -(10**18)
        self._malformed_suppressed = 0
        self._feedback_waiters: list[asyncio.Future] = []
        # the reference is swapped by the loop and read (or replaced by a hold) by the reply path
        self._ref_lock = threading.Lock()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._stop_thread = False
        self._saved_switch_interval: float | None = None
        self._handover: EgmState | None = None  # reply thread: the sample to hand to the loop

    # ---- lifecycle ----------------------------------------------------------------------------

    async def start(self) -> tuple[str, int]:
        """Bind the configured host/port (port 0 picks a free one); returns the bound address."""
        if self._transport is not None or self._thread is not None:
            raise EgmEndpointError("endpoint already started")
        loop = asyncio.get_running_loop()
        self._loop = loop
        if self.config.reply_thread:
            self._start_reply_thread()
        else:
            await loop.create_datagram_endpoint(lambda: self, local_addr=(self.config.host, self.config.port))
        self._schedule_watchdog()
        addr = self.local_address
        log.info("egm_endpoint_started", host=addr[0], port=addr[1])
        return addr

    async def close(self) -> None:
        """Stop answering and release the socket."""
        if self._watchdog_handle is not None:
            self._watchdog_handle.cancel()
            self._watchdog_handle = None
        if self._thread is not None:
            await self._stop_reply_thread()
            log.info("egm_endpoint_closed", **self.stats.snapshot())
        if self._transport is not None:
            self._transport.close()
            self._transport = None
            log.info("egm_endpoint_closed", **self.stats.snapshot())
        for fut in self._feedback_waiters:
            if not fut.done():
                fut.set_exception(EgmEndpointError("endpoint closed"))
        self._feedback_waiters.clear()

    async def __aenter__(self) -> EgmEndpoint:
        await self.start()
        return self

    async def __aexit__(self, *exc) -> None:
        await self.close()

    @property
    def local_address(self) -> tuple[str, int]:
        """(host, port) the endpoint listens on."""
        if self._sock is not None:
            return self._sock.getsockname()[:2]
        if self._transport is None:
            raise EgmEndpointError("endpoint not started")
        return self._transport.get_extra_info("sockname")[:2]

    @property
    def controller_address(self) -> tuple[str, int] | None:
        """Where the controller sends from (learnt from its first packet), or None."""
        return self._controller_addr

    @property
    def latest(self) -> EgmState | None:
        """The latest in-order controller state, or None before the first packet."""
        return self._latest

    @property
    def ok_to_command(self) -> bool:
        """True when the latest state has motors on, EGM running and RAPID running (or undefined)."""
        return self._latest is not None and self._latest.ok_to_command

    @property
    def quiet(self) -> bool:
        """True while the watchdog considers the controller silent."""
        return self._quiet

    async def wait_for_feedback(self, timeout_s: float) -> EgmState:
        """Wait for the next in-order ``EgmRobot``; raises ``TimeoutError`` after ``timeout_s``."""
        fut = asyncio.get_running_loop().create_future()
        self._feedback_waiters.append(fut)
        try:
            # asyncio.timeout, not wait_for: on Python 3.11 wait_for drops a cancellation that arrives
            # as the feedback does, and at 250 Hz a cancelled waiter loop would carry on.
            async with asyncio.timeout(timeout_s):
                return await fut
        finally:
            if fut in self._feedback_waiters:
                self._feedback_waiters.remove(fut)

    # ---- references ---------------------------------------------------------------------------

    def command_joints(self, q_deg: np.ndarray, speed_deg_s: np.ndarray | None = None) -> None:
        """Joint mode: from the next reply on, send ``q_deg`` (n_axes,) deg and the optional feed-forward
        ``speed_deg_s`` (n_axes,) deg/s as ``planned.joints`` / ``speedRef.joints``. With external
        axes both are ``axes_mm_deg`` (n_external + n_axes,): the first values go to ``externalJoints``.

        When the controller starts a new session (seqno back to 0) the endpoint drops the reference
        and holds the arm where the session found it, so a stale target never makes it jump.
        """
        n = self.config.n_external + self.config.n_axes
        q = self._vector(q_deg, n, "q_deg")
        qd = None if speed_deg_s is None else self._vector(speed_deg_s, n, "speed_deg_s")
        ref = _joint_reference(q, qd, self.config.n_external)
        with self._ref_lock:
            self._reference = ref
            self._prepared = None
            self._hook_commanded = True

    def command_pose(
        self, pos_mm: np.ndarray, quat_wxyz: np.ndarray, speed_ref: np.ndarray | None = None
    ) -> None:
        """Pose mode: send ``pos_mm`` (3,) mm and ``quat_wxyz`` (4,) as ``planned.cartesian``, with an
        optional ``speed_ref`` (6,) mm/s and deg/s as ``speedRef.cartesians``."""
        p = self._vector(pos_mm, 3, "pos_mm")
        quat = self._vector(quat_wxyz, 4, "quat_wxyz")
        norm = float(np.linalg.norm(quat))
        if norm < 1e-9:
            raise EgmEndpointError("quat_wxyz must not be zero")
        v = None if speed_ref is None else self._vector(speed_ref, 6, "speed_ref")
        msg = SensorMessage(planned_pos_mm=p, planned_quat_wxyz=quat / norm, speed_ref_cart=v)
        try:
            body = encode_sensor(msg, with_header=False)
        except EgmEncodeError as exc:
            raise EgmEndpointError(str(exc)) from None
        with self._ref_lock:
            self._reference = _Reference("pose", body)
            self._prepared = None

    def hold(self) -> None:
        """Reference := the latest feedback joints (the robot stops where it is)."""
        latest = self._latest
        ref = None if latest is None else self._hold_reference(latest.axes_mm_deg.copy())
        with self._ref_lock:
            self._reference = ref
            self._prepared = None
            self._hook_commanded = True

    @property
    def reference_q_deg(self) -> np.ndarray | None:
        """The joint reference being sent (None in pose mode or before the first packet)."""
        ref = self._reference
        return None if ref is None or ref.q_deg is None else ref.q_deg.copy()

    def _hold_reference(self, axes: np.ndarray) -> _Reference | None:
        """A reference that holds the robot at ``axes`` (what the controller reported), or None when
        the report lacks an axis the reference needs."""
        n = self.config.n_external + self.config.n_axes
        if self.config.n_external and axes.shape[0] < n:
            return None
        return _joint_reference(axes[:n].copy(), None, self.config.n_external)

    @staticmethod
    def _vector(values, n: int, name: str) -> np.ndarray:
        arr = np.array(values, dtype=np.float64).reshape(-1)
        if arr.shape != (n,):
            raise EgmEndpointError(f"{name} must have {n} values, got {arr.shape[0]}")
        if not np.all(np.isfinite(arr)):
            raise EgmEndpointError(f"{name} has non-finite values: {arr}")
        return arr

    # ---- datagram protocol --------------------------------------------------------------------

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self._transport = transport  # type: ignore[assignment]

    def error_received(self, exc: Exception) -> None:
        # ICMP port unreachable after the controller went away etc.: note it, keep serving.
        self.stats.send_errors += 1
        log.warning("egm_socket_error", error=str(exc))

    def connection_lost(self, exc: Exception | None) -> None:
        if exc is not None:
            log.warning("egm_socket_lost", error=str(exc))

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        try:
            self._on_datagram(data, addr, self._clock_ns())
        finally:
            self.stats.handled += 1

    # ---- the reply path (both modes) ----------------------------------------------------------

    def _on_datagram(
        self, data: bytes, addr: tuple[str, int], t_rx_ns: int, t_arrival_real_ns: int | None = None
    ) -> None:
        """Handle one datagram: classify, reply at once, then update state and history (with a cycle
        hook: classify, update, compute the reference for this packet, reply).

        Runs on the loop or on the reply thread; whatever belongs to the loop goes through ``_post``.
        ``t_arrival_real_ns``: the kernel's arrival time of the datagram (CLOCK_REALTIME), when known.
        """
        try:
            pb = parse_robot_pb(data)  # about a microsecond; the full conversion waits for the reply
        except Exception as exc:  # EgmDecodeError, or anything else: one datagram never ends us
            self._malformed(exc, addr, t_rx_ns)
            return
        if self._cycle_hook is not None:
            self._on_cycle_datagram(pb, data, addr, t_rx_ns, t_arrival_real_ns)
            return
        h = pb.header
        seqno = h.seqno if h.HasField("seqno") else None
        tm_ms = h.tm if h.HasField("tm") else None
        if self._controller_addr != addr:
            if self._controller_addr is not None:
                self._post(log.warning, "egm_controller_address_changed", old=self._controller_addr, new=addr)
            else:
                self._post(log.info, "egm_controller_seen", host=addr[0], port=addr[1])
            self._controller_addr = addr
        self.stats.received += 1
        msg: RobotMessage | None = None
        with self._ref_lock:
            in_order = self._track_seqno(seqno, tm_ms)
            if self._reference is None:
                # A new session starts from where the robot is: hold it until someone commands.
                msg = self._convert(pb, data, addr, t_rx_ns)
                if msg is None:
                    return
                self._reference = self._hold_reference(axes_of(msg, self.config.n_external))
            ref = self._reference
        # The reply goes out before the conversion, state and history (on this VM, putting them first
        # raised the reply thread's p50 from ~200 to ~450 us). On the reply thread the state therefore
        # lags the reply by that work: ``stats.handled`` counts datagrams whose work is complete.
        self._handover = None
        self._reply(addr, t_rx_ns, ref, t_arrival_real_ns)
        self._record(pb, data, addr, t_rx_ns, msg, in_order)
        if self._handover is not None:
            # wake the loop only now: woken earlier, it would take the GIL while the reply waits
            self._post(self._wake_waiters, self._handover)

    def _on_cycle_datagram(
        self, pb, data: bytes, addr: tuple[str, int], t_rx_ns: int, t_arrival_real_ns: int | None
    ) -> None:
        """The reply path with a cycle hook: every reply carries a reference computed for the cycle
        it answers. The fast way: the hook prepared this packet's reference after the previous one
        (:meth:`prepare_joints`, tagged with the controller clock or sequence number it expects), so
        the reply goes out at once and the hook then prepares the next. Otherwise (the first packet,
        a lost one, a clock that jumped) the hook computes this packet's reference before the reply."""
        if self._controller_addr != addr:
            if self._controller_addr is not None:
                self._post(log.warning, "egm_controller_address_changed", old=self._controller_addr, new=addr)
            else:
                self._post(log.info, "egm_controller_seen", host=addr[0], port=addr[1])
            self._controller_addr = addr
        self.stats.received += 1
        h = pb.header
        seqno = h.seqno if h.HasField("seqno") else None
        tm_ms = h.tm if h.HasField("tm") else None
        with self._ref_lock:
            in_order = self._track_seqno(seqno, tm_ms)
            prepared = self._prepared
            fast = in_order and prepared is not None and self._matches(prepared, pb, seqno)
            if fast:
                self._reference = prepared[0]
            self._prepared = None
            ref = self._reference
        self._handover = None
        hook = self._cycle_hook
        if fast and ref is not None:
            self._reply(addr, t_rx_ns, ref, t_arrival_real_ns)
            msg = self._convert(pb, data, addr, t_rx_ns)
            if msg is None:
                return
            self._record(pb, data, addr, t_rx_ns, msg, in_order)
        else:
            msg = self._convert(pb, data, addr, t_rx_ns)
            if msg is None:
                return
            self._record(pb, data, addr, t_rx_ns, msg, in_order)
            fresh = not in_order  # a duplicate or late packet repeats the reference of its cycle
            if in_order and hook is not None:
                self._hook_commanded = False
                self._call_hook(hook, msg, t_rx_ns, "now")
                fresh = self._hook_commanded
            with self._ref_lock:
                if self._reference is None:
                    self._reference = self._hold_reference(axes_of(msg, self.config.n_external))
                ref = self._reference
            self._reply(addr, t_rx_ns, ref, t_arrival_real_ns, fresh=fresh)
        if in_order and hook is not None:
            self._call_hook(hook, msg, t_rx_ns, "next")
        if self._handover is not None:
            self._post(self._wake_waiters, self._handover)

    def _call_hook(self, hook: CycleHook, msg: RobotMessage, t_rx_ns: int, phase: str) -> None:
        try:
            hook(msg, t_rx_ns, phase)
        except Exception as exc:  # the hook's own faults are its to handle; never ours
            self._post(log.error, "egm_cycle_hook_failed", error=repr(exc), phase=phase)

    def _matches(self, prepared: tuple, pb, seqno: int | None) -> bool:
        """Whether a prepared reference is for this packet's cycle: by the controller's clock when the
        packet has one (within half a cycle), else by its sequence number."""
        _ref, t_us, want_seqno = prepared
        if t_us is not None and pb.HasField("feedBack") and pb.feedBack.HasField("time"):
            t = int(pb.feedBack.time.sec) * 1_000_000 + int(pb.feedBack.time.usec)
            return abs(t - t_us) * 2 < self.config.cycle_s * 1e6
        return want_seqno is not None and seqno == want_seqno

    def prepare_joints(
        self,
        q_deg: np.ndarray,
        speed_deg_s: np.ndarray | None,
        *,
        for_t_ctrl_us: int | None,
        for_seqno: int | None,
    ) -> None:
        """Joint mode, for the next packet only: the reference the reply to the packet of controller
        time ``for_t_ctrl_us`` (or, without a clock, sequence number ``for_seqno``) carries. A packet
        that is not that one gets the cycle hook's reference computed on the spot instead."""
        n = self.config.n_external + self.config.n_axes
        q = self._vector(q_deg, n, "q_deg")
        qd = None if speed_deg_s is None else self._vector(speed_deg_s, n, "speed_deg_s")
        ref = _joint_reference(q, qd, self.config.n_external)
        with self._ref_lock:
            self._prepared = (ref, for_t_ctrl_us, for_seqno)

    def _record(
        self, pb, data: bytes, addr: tuple[str, int], t_rx_ns: int, msg: RobotMessage | None, in_order: bool
    ) -> None:
        """After the reply: watchdog, statistics, state, history."""
        if self._quiet:
            self._quiet = False
            self._post(self._resumed, (t_rx_ns - (self._last_rx_ns or t_rx_ns)) / 1e9)
        if not in_order:
            return
        if msg is None:
            msg = self._convert(pb, data, addr, t_rx_ns)
            if msg is None:
                return
        if self._last_rx_ns is not None:
            self.stats._intervals_us.append((t_rx_ns - self._last_rx_ns) / 1000.0)
        self._last_rx_ns = t_rx_ns
        verdict = self._plausibility(msg, t_rx_ns)
        if verdict is None:
            return
        for m, t in verdict:
            self._update_state(m, t)

    def _plausibility(self, msg: RobotMessage, t_rx_ns: int) -> list[tuple[RobotMessage, int]] | None:
        """The samples to take now (this one, possibly after a confirmed suspect), or None to hold."""
        c = self.config
        n = c.n_axes
        q = np.asarray(msg.feedback_q_deg[:n], dtype=np.float64)
        s = msg.seqno
        if q.shape[0] < n or s is None:
            return [(msg, t_rx_ns)]
        if not np.isfinite(q).all() or np.abs(q).max() > 720.0:
            self._implausible(msg, t_rx_ns, "joint value out of any range")
            return None
        t = msg.feedback_time_us
        take: list[tuple[RobotMessage, int]] = []
        if len(self._plaus) == 2:
            (s0, q0, t0), (s1, q1, t1) = self._plaus
            k, k01 = s - s1, s1 - s0
            if 0 < k <= 25 and k01 > 0:
                if t is not None and t0 is not None and t1 is not None and t1 > t0:
                    # on the controller's clock: the robot clock fit uses it, so it must be sane too
                    off = not self._clock_step_ok(t - t1, k)
                    dt, ratio = (t - t1) * 1e-6, (t - t1) / (t1 - t0)
                else:
                    off, dt, ratio = False, k * c.cycle_s, k / k01
                tol = c.plausible_tol_deg + 0.5 * c.plausible_accel_deg_s2 * dt * dt
                off = off or np.abs(q - (q1 + (q1 - q0) * ratio)).max() > tol
                if off:
                    sus = self._suspect
                    ks = None if sus is None else s - sus[0]
                    agree = sus is not None and 0 < ks <= 3
                    if agree:
                        timed = t is not None and sus[4] is not None
                        dts = (t - sus[4]) * 1e-6 if timed else ks * c.cycle_s
                        agree = (not timed or self._clock_step_ok(t - sus[4], ks)) and np.abs(
                            q - sus[1]
                        ).max() <= c.plausible_tol_deg + c.plausible_speed_deg_s * max(dts, 0.0)
                    if not agree:
                        if sus is not None:  # the earlier suspect was alone: corrupt
                            self._implausible(sus[2], sus[3], "jump not confirmed")
                        self._suspect = (s, q, msg, t_rx_ns, t)
                        return None
                    take.append((sus[2], sus[3]))  # two samples agree: a real change
                    self._plaus = [(sus[0], sus[1], sus[4])]
        if self._suspect is not None and not take:
            self._implausible(self._suspect[2], self._suspect[3], "jump not confirmed")
        self._suspect = None
        self._plaus = [*self._plaus, (s, q, t)][-2:]
        take.append((msg, t_rx_ns))
        return take

    def _clock_step_ok(self, dt_us: int, k: int) -> bool:
        """The controller's clock moved ``dt_us`` over ``k`` messages: at least ``k`` periods (2 ms of
        rounding), at most ``plausible_late_s`` more."""
        c = self.config
        return k * c.cycle_s * 1e6 - 2000 <= dt_us <= (k * c.cycle_s + c.plausible_late_s) * 1e6

    def _implausible(self, msg: RobotMessage, t_rx_ns: int, why: str) -> None:
        self.stats.implausible += 1
        self._malformed(
            ValueError(f"implausible feedback (seqno {msg.seqno}): {why}"),
            self._controller_addr or ("?", 0),
            t_rx_ns,
        )

    def _resumed(self, quiet_s: float) -> None:
        log.info("egm_controller_resumed", quiet_s=round(quiet_s, 4))
        if self._on_watchdog is not None:
            self._call_watchdog("resumed", quiet_s)

    def _post(self, fn: Callable[..., object], *args, **kwargs) -> None:
        """Run ``fn`` on the event loop: at once on the loop's own reply path, handed over (without
        waiting) from the reply thread, so the thread never blocks on loop-side work."""
        thread = self._thread
        if thread is None or thread.ident != threading.get_ident():
            fn(*args, **kwargs)
            return
        loop = self._loop
        if loop is None:
            return
        with contextlib.suppress(RuntimeError):  # the loop is closing: the endpoint goes with it
            loop.call_soon_threadsafe(functools.partial(fn, *args, **kwargs))

    # ---- the reply thread ---------------------------------------------------------------------

    # ---- per-cycle references ---------------------------------------------------------------

    def set_cycle_hook(self, hook: CycleHook | None) -> None:
        """Compute each reply's reference for the packet it answers: ``hook(msg, t_rx_ns, phase)``
        runs on the reply path for every new in-order ``EgmRobot`` after the state and history took
        it: with phase ``"next"`` after the reply, to :meth:`prepare_joints` the next packet's
        reference, and first with phase ``"now"`` before the reply when no prepared reference fits
        this packet, to set its reference with :meth:`command_joints` (or :meth:`hold`). A reply
        whose packet got no reference of its own counts as stale, as does any reply that leaves more
        than one EGM cycle after its packet arrived. None removes the hook."""
        with self._ref_lock:
            self._cycle_hook = hook
            self._prepared = None

    @property
    def reply_thread_native_id(self) -> int | None:
        """The reply thread's kernel thread id (for ``chrt`` / ``taskset``), or None in loop mode."""
        thread = self._thread
        return None if thread is None else thread.native_id

    def _bind_socket(self, idle_timeout_ns: int) -> socket.socket:
        cfg = self.config
        family = socket.AF_INET6 if ":" in cfg.host else socket.AF_INET
        sock = socket.socket(family, socket.SOCK_DGRAM)
        try:
            sock.bind((cfg.host, cfg.port))
            # a kernel-side receive timeout keeps each receive one blocking syscall and still lets the
            # thread look at its stop flag every 100 ms
            _set_receive_timeout(sock, idle_timeout_ns)
            # the kernel stamps each datagram's arrival: the reply latency then includes any time the
            # packet waited in the socket for this process (what the controller sees)
            with contextlib.suppress(OSError, AttributeError):
                sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
        except OSError:
            sock.close()
            raise
        return sock

    def _start_reply_thread(self) -> None:
        cfg = self.config
        sock = self._bind_socket(_IDLE_RECEIVE_TIMEOUT_NS)
        if cfg.switch_interval_s is not None:
            self._saved_switch_interval = sys.getswitchinterval()
            sys.setswitchinterval(cfg.switch_interval_s)
        self._sock = sock
        self._stop_thread = False
        self._thread = threading.Thread(target=self._serve, args=(sock,), name="egm-reply", daemon=True)
        self._thread.start()

    # ---- serving from the calling thread (a process of its own) --------------------------------

    def bind_blocking(self, idle_timeout_s: float = 0.005) -> tuple[str, int]:
        """Bind the configured address for :meth:`serve_blocking` (no event loop, no thread): the
        caller's own thread serves the controller. Returns the bound address."""
        if self._transport is not None or self._thread is not None or self._sock is not None:
            raise EgmEndpointError("endpoint already started")
        self._sock = self._bind_socket(int(idle_timeout_s * 1e9))
        self._stop_thread = False
        addr = self.local_address
        log.info("egm_endpoint_started", host=addr[0], port=addr[1], mode="blocking")
        return addr

    def serve_blocking(self, stop: Callable[[], bool], idle: Callable[[], None] | None = None) -> None:
        """Serve the controller from the calling thread until ``stop()`` is true; ``idle()`` runs after
        every datagram and every receive timeout (``bind_blocking``'s ``idle_timeout_s``), as does the
        watchdog's check. The socket is closed on return."""
        sock = self._sock
        if sock is None:
            raise EgmEndpointError("bind_blocking first")
        try:
            self._serve(sock, stop=stop, idle=idle)
        finally:
            sock.close()
            self._sock = None
            log.info("egm_endpoint_closed", **self.stats.snapshot())

    def stop_blocking(self) -> None:
        """Make a :meth:`serve_blocking` return (from another thread)."""
        self._stop_thread = True
        sock = self._sock
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)

    async def _stop_reply_thread(self) -> None:
        thread, sock = self._thread, self._sock
        assert thread is not None and sock is not None
        self._stop_thread = True
        # shutdown wakes a receive that is blocked right now (Linux answers ENOTCONN but still wakes it)
        with contextlib.suppress(OSError):
            sock.shutdown(socket.SHUT_RDWR)
        await asyncio.to_thread(thread.join, 2.0)
        if thread.is_alive():  # cannot happen short of a hung interpreter; say so rather than hang
            log.error("egm_reply_thread_did_not_stop")
        sock.close()
        self._thread = None
        self._sock = None
        if self._saved_switch_interval is not None:
            sys.setswitchinterval(self._saved_switch_interval)
            self._saved_switch_interval = None

    def _serve(
        self,
        sock: socket.socket,
        stop: Callable[[], bool] | None = None,
        idle: Callable[[], None] | None = None,
    ) -> None:
        """The reply thread (or, from :meth:`serve_blocking`, the caller's thread): receive, handle,
        repeat until the stop flag is set (or ``stop()`` is true)."""
        idle_timeout_ns = _IDLE_RECEIVE_TIMEOUT_NS
        if stop is None:
            self._configure_reply_thread()
            stop = self._stopping
        else:
            idle_timeout_ns = _receive_timeout_ns(sock)
        spin_ns = int(self.config.reply_spin_us * 1000)
        due_ns: int | None = None  # when the next packet is expected (spin mode)
        last_ns: int | None = None
        while not stop():
            try:
                if spin_ns and due_ns is not None:
                    data, addr, t_arrival = self._receive_spinning(sock, due_ns, spin_ns, idle_timeout_ns)
                else:
                    if spin_ns:  # the spin shortened the receive timeout; sleep the long one again
                        _set_receive_timeout(sock, idle_timeout_ns)
                    data, addr, t_arrival = _receive(sock)
            except (BlockingIOError, InterruptedError):  # the receive timeout: look at the stop flag
                if idle is not None:
                    self._watchdog_check()
                    idle()
                continue
            except OSError as exc:
                if stop():
                    break
                self.stats.send_errors += 1  # e.g. an ICMP error reported on the socket
                self._post(log.warning, "egm_socket_error", error=str(exc))
                time.sleep(0.001)  # a persistent error must not turn into a busy loop
                continue
            t_rx_ns = self._clock_ns()
            if stop() or addr is None:
                break
            if spin_ns:
                now_ns = time.monotonic_ns()
                # the controller's cadence is the last interval; a gap (loss, pause) spins once in vain
                period_ns = None if last_ns is None else now_ns - last_ns
                due_ns = now_ns + period_ns if period_ns is not None and period_ns < 100_000_000 else None
                last_ns = now_ns
            try:
                self._on_datagram(data, addr, t_rx_ns, t_arrival)
            except Exception as exc:  # one datagram never ends the thread
                self._post(log.error, "egm_reply_thread_error", error=repr(exc))
            finally:
                self.stats.handled += 1
            if idle is not None:
                self._watchdog_check()
                idle()

    def _stopping(self) -> bool:
        return self._stop_thread

    @staticmethod
    def _receive_spinning(
        sock: socket.socket, due_ns: int, spin_ns: int, idle_timeout_ns: int = 100_000_000
    ) -> tuple[bytes, tuple, int | None]:
        """Sleep until ``spin_ns`` before ``due_ns``, then poll without sleeping until a datagram
        comes or ``spin_ns`` after ``due_ns``; then fall back to the blocking receive."""
        # The sleep is a blocking receive with a microsecond timeout (SO_RCVTIMEO): a packet that comes
        # early is taken at once, and unlike select() it works for any descriptor number.
        wait_ns = due_ns - spin_ns - time.monotonic_ns()
        if wait_ns >= 1000:
            _set_receive_timeout(sock, wait_ns)
            try:
                return _receive(sock)  # early: no spin this cycle
            except BlockingIOError:
                pass
        end_ns = due_ns + spin_ns
        while time.monotonic_ns() < end_ns:
            try:
                return _receive(sock, socket.MSG_DONTWAIT)
            except BlockingIOError:
                pass
        _set_receive_timeout(sock, idle_timeout_ns)
        return _receive(sock)

    def _configure_reply_thread(self) -> None:
        """Pin and prioritise the calling (reply) thread as configured; refusals are logged, not fatal."""
        cfg = self.config
        refused = set_thread_realtime(cfg.reply_thread_priority, tuple(cfg.reply_thread_cpus))
        for why in refused:
            if why.startswith("affinity"):
                self._post(log.warning, "egm_reply_thread_affinity_refused", cpus=cfg.reply_thread_cpus,
                           error=why)  # fmt: skip
            else:
                self._post(log.warning, "egm_reply_thread_realtime_refused",
                           priority=cfg.reply_thread_priority, error=why)  # fmt: skip
        if cfg.reply_thread_priority > 0 and not any(w.startswith("SCHED_FIFO") for w in refused):
            self._post(log.info, "egm_reply_thread_realtime", priority=cfg.reply_thread_priority)

    # ---- internals ----------------------------------------------------------------------------

    def _convert(self, pb, data: bytes, addr: tuple[str, int], t_rx_ns: int) -> RobotMessage | None:
        try:
            msg = robot_from_pb(pb, data)
            # a flipped byte can leave well-formed protobuf with fewer joints than the arm has: such
            # feedback must never become the robot's state (the envelope and the executor take n_axes)
            fb = msg.feedback_q_deg
            if fb is not None and len(fb) < self.config.n_axes:
                raise ValueError(f"feedBack.joints has {len(fb)} values, the arm has {self.config.n_axes}")
            return msg
        except Exception as exc:  # well-formed protobuf with unusable values (NaN, 8 axes, ...)
            self.stats.received -= 1
            self._malformed(exc, addr, t_rx_ns)
            return None

    def _track_seqno(self, seqno: int | None, tm_ms: int | None) -> bool:
        """Classify ``seqno``; returns True for a new in-order message (state and history update)."""
        if seqno is None:
            return True  # a controller without seqno: nothing to check
        last, last_tm = self._last_seqno, self._last_tm
        self._last_tm = tm_ms
        # The controller restarts its counter at 0 per session. A 0 is a restart only if it was sent
        # later than the previous packet (tm, modulo its wrap): a late or duplicated 0 of the current
        # session carries an older or the same send time.
        restarted = seqno == 0 and (
            (last != 0 and (tm_ms is None or last_tm is None or _after(tm_ms, last_tm)))
            or (last == 0 and tm_ms is not None and last_tm is not None and _after(tm_ms, last_tm))
        )
        if last is None or restarted:
            self._new_session(seqno)
            return True
        diff = (seqno - last) % _U32
        if diff == 0 or seqno in self._recent:
            self.stats.duplicated += 1
            return False
        if diff < _U32 // 2:
            if diff > _SEQNO_JUMP and seqno != (self._seqno_suspect or -2) + 1:
                # a forward jump of seconds' worth of packets: a corrupted seqno (EGM has no checksum),
                # unless the next packet continues from it; taken as the newest it would make every
                # genuine packet after it look stale
                self._seqno_suspect = seqno
                self.stats.implausible += 1
                return False
            self._seqno_suspect = None
            self.stats.lost += diff - 1
            self._last_seqno = seqno
            self._recent.append(seqno)
            return True
        # older than the newest: a packet overtaken by a later one; it filled a gap counted as lost
        self.stats.out_of_order += 1
        self.stats.lost = max(0, self.stats.lost - 1)
        self._recent.append(seqno)
        return False

    def _new_session(self, seqno: int) -> None:
        self.stats.sessions += 1
        self._last_seqno = seqno
        self._recent.clear()
        self._recent.append(seqno)
        # reply k answers robot message k while nothing is lost, which makes latency measurable
        self._reply_seqno = seqno
        # a stale reference from a previous session could make the robot jump: hold instead
        self._reference = None
        self._prepared = None
        self._plaus = []
        self._suspect = None
        self._seqno_suspect = None
        self._post(log.info, "egm_session_seen", seqno=seqno, session=self.stats.sessions)

    def _reply(
        self,
        addr: tuple[str, int],
        t_rx_ns: int,
        ref: _Reference | None,
        t_arrival_real_ns: int | None = None,
        *,
        fresh: bool = True,
    ) -> None:
        if ref is None:
            return
        seqno = self._reply_seqno
        self._reply_seqno = (seqno + 1) % _U32
        tm_ms = (self._clock_ns() // 1_000_000) % _U32
        payload = encode_sensor_header(seqno, tm_ms) + ref.body
        sock, transport = self._sock, self._transport
        try:
            if sock is not None:
                sock.sendto(payload, addr)
            elif transport is not None:
                transport.sendto(payload, addr)
            else:
                return
        except OSError as exc:
            self.stats.send_errors += 1
            self._post(log.warning, "egm_reply_send_failed", error=str(exc))
            return
        if t_arrival_real_ns is not None:
            # from the kernel's arrival stamp: a reply that waited in the socket counts its wait
            latency_us = (time.time_ns() - t_arrival_real_ns) / 1000.0
        else:
            latency_us = (self._clock_ns() - t_rx_ns) / 1000.0
        if not fresh or latency_us > self.config.cycle_s * 1e6:
            self.stats.stale += 1
            self.stats.stale_events.append((time.monotonic_ns(), int(latency_us * 1000.0)))
        self.stats.replies_sent += 1
        b = int(np.searchsorted(LATENCY_BIN_EDGES_US, latency_us, side="right")) - 1
        self.stats.latency_counts[max(b, 0)] += 1
        if latency_us > self.stats.latency_max_us:
            self.stats.latency_max_us = latency_us

    def _update_state(self, msg: RobotMessage, t_rx_ns: int) -> None:
        q = msg.feedback_q_deg
        n_ext = self.config.n_external
        state = EgmState(
            seqno=msg.seqno,
            tm_ms=msg.tm_ms,
            t_host_ns=t_rx_ns,
            q_deg=q,
            pos_mm=msg.feedback_pos_mm,
            quat_wxyz=msg.feedback_quat_wxyz,
            feedback_time_us=msg.feedback_time_us,
            planned_q_deg=msg.planned_q_deg,
            motor_state=msg.motor_state,
            mci_state=msg.mci_state,
            rapid_exec_state=msg.rapid_exec_state,
            convergence_met=msg.mci_convergence_met,
            utilization_pct=msg.utilization_pct,
            external_joints=msg.feedback_external_joints,
        )
        previous = self._latest
        self._latest = state
        ext = msg.feedback_external_joints
        if q.shape[0] >= self.config.n_axes and (n_ext == 0 or (ext is not None and ext.shape[0] >= n_ext)):
            self.history.append(
                t_rx_ns,
                msg.feedback_time_us,
                msg.seqno,
                axes_of(msg, n_ext),
                msg.feedback_pos_mm,
                msg.feedback_quat_wxyz,
                (msg.motor_state, msg.mci_state, msg.rapid_exec_state),
            )
        if previous is None or (
            previous.motor_state,
            previous.mci_state,
            previous.rapid_exec_state,
        ) != (state.motor_state, state.mci_state, state.rapid_exec_state):
            self._post(
                log.info,
                "egm_controller_state",
                motors=_name(state.motor_state),
                mci=_name(state.mci_state),
                rapid=_name(state.rapid_exec_state),
                ok_to_command=state.ok_to_command,
            )
        if self._feedback_waiters:
            if self._thread is not None:
                self._handover = state  # posted by _on_datagram once the reply is out
            else:
                self._wake_waiters(state)

    def _wake_waiters(self, state: EgmState) -> None:
        """Resolve every pending ``wait_for_feedback`` with ``state`` (on the loop)."""
        if self._feedback_waiters:
            waiters, self._feedback_waiters = self._feedback_waiters, []
            for fut in waiters:
                if not fut.done():
                    fut.set_result(state)

    def _malformed(self, exc: Exception, addr: tuple[str, int], t_rx_ns: int) -> None:
        self.stats.malformed += 1
        interval_ns = int(self.config.malformed_log_interval_s * 1e9)
        if t_rx_ns - self._malformed_logged_ns >= interval_ns:
            self._post(
                log.warning,
                "egm_malformed_packet",
                error=str(exc),
                host=addr[0],
                port=addr[1],
                suppressed=self._malformed_suppressed,
                total=self.stats.malformed,
            )
            self._malformed_logged_ns = t_rx_ns
            self._malformed_suppressed = 0
        else:
            self._malformed_suppressed += 1

    def _schedule_watchdog(self) -> None:
        loop = asyncio.get_running_loop()
        # check at a quarter of the timeout: the event comes at most 25 % late and costs nothing
        period = max(self.config.watchdog_s / 4.0, 0.001)
        self._watchdog_handle = loop.call_later(period, self._watchdog_tick)

    def _watchdog_tick(self) -> None:
        if self._transport is None and self._thread is None:
            return
        self._schedule_watchdog()
        self._watchdog_check()

    def _watchdog_check(self) -> None:
        if self._last_rx_ns is None or self._quiet:
            return
        quiet_s = (self._clock_ns() - self._last_rx_ns) / 1e9
        if quiet_s >= self.config.watchdog_s:
            self._quiet = True
            self.stats.watchdog_events += 1
            log.warning("egm_controller_quiet", quiet_s=round(quiet_s, 4), watchdog_s=self.config.watchdog_s)
            self._call_watchdog("quiet", quiet_s)

    def _call_watchdog(self, event: str, quiet_s: float) -> None:
        if self._on_watchdog is None:
            return
        try:
            self._on_watchdog(event, quiet_s)
        except Exception:  # a broken callback must not stop the endpoint
            log.exception("egm_watchdog_callback_failed", watchdog_event=event)


_IDLE_RECEIVE_TIMEOUT_NS = 100_000_000
_SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)  # Linux's value where Python lacks the name
_TIMESPEC = struct.Struct("qq")


def _receive(sock: socket.socket, flags: int = 0) -> tuple[bytes, tuple, int | None]:
    """One datagram: (data, source address, the kernel's arrival time in CLOCK_REALTIME ns or None)."""
    data, ancdata, _flags, addr = sock.recvmsg(65535, 64, flags)
    for level, kind, payload in ancdata:
        if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS and len(payload) >= _TIMESPEC.size:
            sec, nsec = _TIMESPEC.unpack_from(payload)
            return data, addr, sec * 1_000_000_000 + nsec
    return data, addr, None


def _receive_timeout_ns(sock: socket.socket) -> int:
    sec, usec = struct.unpack("ll", sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVTIMEO, 16))
    return (sec * 1_000_000 + usec) * 1000 or _IDLE_RECEIVE_TIMEOUT_NS


def axes_of(msg: RobotMessage, n_ext: int) -> np.ndarray:
    """The feedback of every axis, ``axes_mm_deg`` order: ``n_ext`` external axes, then the joints
    (just the joints without external axes; fewer values when the controller sent fewer)."""
    if n_ext == 0:
        return msg.feedback_q_deg
    ext = msg.feedback_external_joints
    ext = np.zeros(0) if ext is None else ext[:n_ext]
    if ext.shape[0] < n_ext:
        return ext  # too short for a reference: the caller refuses it
    return np.concatenate([ext, msg.feedback_q_deg])


def _set_receive_timeout(sock: socket.socket, timeout_ns: int) -> None:
    """SO_RCVTIMEO of a blocking socket (struct timeval); a receive then ends with BlockingIOError."""
    sec, usec = divmod(max(1, timeout_ns // 1000), 1_000_000)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVTIMEO, struct.pack("ll", sec, usec))


def _after(tm_ms: int, other_ms: int) -> bool:
    """True if ``tm_ms`` is later than ``other_ms`` on the controller's wrapping 32-bit ms clock."""
    d = (tm_ms - other_ms) % _U32
    return 0 < d < _U32 // 2


def _name(value) -> str | None:
    return None if value is None else value.name
