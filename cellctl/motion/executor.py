"""Execution over EGM: stream a timed joint trajectory in phase with the controller's packets.

One reference per received ``EgmRobot``: the executor waits for each feedback packet from the
:class:`~drivers.abb_egm.endpoint.EgmEndpoint`, advances by as many cycles as the controller's
clock (or, without one, its sequence number) moved, and sets the reference the endpoint sends with
its next reply.

The reference is the plan's state at a playback time tau. The plan's time law is already
jerk-limited (ruckig, offline, in the timing), so streaming it needs no online filter; ruckig shapes
every transition online:

- a one-axis generator on tau (its velocity is the playback rate, 1 when running, 0 when stopped):
  pause, resume and abort ramp the rate jerk-limited, so the robot slows down and stops *on the
  planned path* and a resume continues the pass where it paused;
- a six-axis generator for the move from wherever the robot is to the plan's start (a straight line
  in joint space, slow enough for the TCP speed cap) and for fault stops (velocity interface, target
  velocity zero: a jerk-limited stop from any state).

Every reference passes the :class:`~cellctl.motion.envelope.SafetyEnvelope` last; a violation is a
fault and leads to a smooth stop, never to a clamped reference. The tracking error (feedback TCP
against the recently commanded TCP path) is monitored; above the threshold the executor stops
smoothly. A silent controller (no feedback within ``feedback_timeout_s``) or motors off / EGM not
running are faults too. Progress events (pass i of n, percent, time left) go to a callback and to an
async iterator (:meth:`MotionExecutor.events`).
"""

from __future__ import annotations

import asyncio
import enum
import threading
import time
from collections import deque
from collections.abc import AsyncIterator, Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import structlog
from ruckig import ControlInterface, InputParameter, OutputParameter, Result, Ruckig, Synchronization

from cellctl.motion.envelope import EnvelopeLimits, EnvelopeViolation, SafetyEnvelope
from cellctl.motion.trajectory import PLAN_JERK_SHARE, TimedTrajectory
from drivers.abb_egm.codec import RobotMessage
from drivers.abb_egm.endpoint import EgmEndpoint, axes_of, ok_to_command
from drivers.abb_egm.kinematics import fk_batch
from drivers.abb_egm.limits import EGM_CYCLE_S, RobotLimits

if TYPE_CHECKING:
    from cellctl.config import CellConfig

__all__ = [
    "STATE_CODES",
    "TERMINAL_STATES",
    "ExecState",
    "ExecutionResult",
    "ExecutorConfig",
    "ExecutorError",
    "MotionExecutor",
    "ProgressEvent",
]

log = structlog.get_logger(__name__)

_U32 = 2**32


class ExecutorError(Exception):
    """The executor cannot do what was asked (bad trajectory, started twice, no controller)."""


class ExecState(enum.StrEnum):
    """States of one execution. FINISHED, ABORTED and FAULTED are terminal."""

    IDLE = "idle"
    MOVING_TO_START = "moving_to_start"
    RUNNING = "running"
    PAUSING = "pausing"
    PAUSED = "paused"
    RESUMING = "resuming"
    ABORTING = "aborting"
    FAULT_STOPPING = "fault_stopping"
    FINISHED = "finished"
    ABORTED = "aborted"
    FAULTED = "faulted"


_TERMINAL = (ExecState.FINISHED, ExecState.ABORTED, ExecState.FAULTED)
#: the states as small numbers (the motion process publishes its state in shared memory)
STATE_CODES: dict[ExecState, int] = {s: i for i, s in enumerate(ExecState)}
TERMINAL_STATES = _TERMINAL
#: the move to the plan's start keeps the TCP under this share of the envelope's speed cap, as the
#: planned transits do (the straight joint-space line's TCP speed is estimated on :func:`start_path`)
_START_TCP_FRACTION = 0.9
#: shares of the joint jerk limits a playback-rate ramp's acceleration (3 q'' r r') and jerk (q' r'')
#: may use: what the plan's time law leaves, split 60 / 40
_RAMP_JERK_SHARE_ACCEL = 0.6 * (1.0 - PLAN_JERK_SHARE)
_RAMP_JERK_SHARE_JERK = 0.4 * (1.0 - PLAN_JERK_SHARE)
#: the move to the plan's start is checked against the envelope's positional rules before it starts,
#: sampled at least this finely in the joint that moves most (deg)
_START_PATH_STEP_DEG = 0.05
#: the joint limits when none are given (``cell.toml [robot]``'s defaults)
_DEFAULT_LIMITS = RobotLimits()


def start_path(q_from: np.ndarray, q_to: np.ndarray) -> np.ndarray:
    """The move to the plan's start, sampled: a straight line in joint space (the executor moves on
    it phase-synchronised, from rest), (n, axes) with n >= 129, consecutive rows at most
    ``_START_PATH_STEP_DEG`` apart in every joint (deg; the track's mm alike) up to 4097 rows."""
    dq = np.asarray(q_to, dtype=np.float64) - np.asarray(q_from, dtype=np.float64)
    n = int(np.clip(np.ceil(float(np.max(np.abs(dq))) / _START_PATH_STEP_DEG), 128, 4096)) + 1
    return q_from[None] + np.linspace(0.0, 1.0, n)[:, None] * dq[None]


@dataclass(frozen=True)
class ExecutorConfig:
    """Executor settings (s, deg, mm).

    cycle_s: EGM cycle of the controller. feedback_timeout_s: no feedback for this long is a stalled
    controller. start_timeout_s: wait this long for the first commandable feedback.
    tracking_error_max_mm: fault-stop threshold on the TCP tracking error; tracking_window_s: how far
    back the commanded path is searched (covers the controller's lag). start_tolerance_deg: the robot
    counts as at the plan's start within this; otherwise it first moves there, and the plan starts
    once the move's references are there and the arm within start_settle_tolerance_deg (the plan
    starts at rest on its approach, well before the first pass: the arm's last lag of at most
    ~1 mm at the TCP decays there, far inside the tracking limit), at
    move_to_start_speed_fraction of the joint speed limits, its TCP under ``_START_TCP_FRACTION`` of
    the envelope's cap. feedforward: send the joint speed
    reference too; feedforward_lead_s: how far ahead on the plan the speed reference is taken (the
    time constant of the controller's low-pass filter, 1 / (2 pi 20 Hz) by default).
    joint_*_max: limits of the move to the start and of the stops (deg/s, deg/s^2, deg/s^3).
    rate_accel_per_s2 / rate_jerk_per_s3: limits of the playback-rate ramps for pause / resume / abort
    (None: derived from the trajectory's speeds and the joint limits).
    progress_interval_s: time between progress events while moving.
    """

    cycle_s: float = EGM_CYCLE_S
    feedback_timeout_s: float = 0.1
    start_timeout_s: float = 5.0
    stall_give_up_s: float = 1.0
    tracking_error_max_mm: float = 5.0
    tracking_window_s: float = 0.3
    start_tolerance_deg: float = 0.01
    start_settle_tolerance_deg: float = 0.05
    move_to_start_speed_fraction: float = 0.5
    feedforward: bool = True
    feedforward_lead_s: float = 0.008
    joint_speed_max_deg_s: tuple[float, ...] = _DEFAULT_LIMITS.joint_speed_max_deg_s
    joint_accel_max_deg_s2: tuple[float, ...] = _DEFAULT_LIMITS.joint_accel_max_deg_s2
    joint_jerk_max_deg_s3: tuple[float, ...] = _DEFAULT_LIMITS.joint_jerk_max_deg_s3
    rate_accel_per_s2: float | None = None
    rate_jerk_per_s3: float | None = None
    progress_interval_s: float = 0.25

    @classmethod
    def from_config(cls, cfg: CellConfig, **changes) -> ExecutorConfig:
        """From a :class:`cellctl.config.CellConfig`: ``[robot]`` joint limits (with ``[robot.track]``
        the track's first), ``tracking_error_max_mm`` and ``egm_watchdog_s`` (a controller silent
        this long has stalled)."""
        r = cfg.robot
        track = None if r.track is None else r.track.linear_track()
        limits = r.limits()
        v, a, j = _axis_limits(
            track, limits.joint_speed_max_deg_s, limits.joint_accel_max_deg_s2, limits.joint_jerk_max_deg_s3
        )
        values = {
            "joint_speed_max_deg_s": v,
            "joint_accel_max_deg_s2": a,
            "joint_jerk_max_deg_s3": j,
            "tracking_error_max_mm": r.tracking_error_max_mm,
            "feedback_timeout_s": r.egm_watchdog_s,
        }
        values.update(changes)
        return cls(**values)

    @classmethod
    def from_settings(cls, settings, **changes) -> ExecutorConfig:
        """Limits from :class:`cellctl.planning.PlannerSettings` (``cell.toml [robot]``; with a track
        its speed, acceleration and jerk first)."""
        limits: RobotLimits = settings.limits
        v, a, j = _axis_limits(
            getattr(settings, "track", None),
            limits.joint_speed_max_deg_s,
            limits.joint_accel_max_deg_s2,
            limits.joint_jerk_max_deg_s3,
        )
        return cls(joint_speed_max_deg_s=v, joint_accel_max_deg_s2=a, joint_jerk_max_deg_s3=j, **changes)


def _axis_limits(track, v, a, j) -> tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]]:
    """Per-axis speed, acceleration and jerk limits: the joints', with a track's (mm) in front."""
    v, a, j = tuple(map(float, v)), tuple(map(float, a)), tuple(map(float, j))
    if track is None:
        return v, a, j
    return (
        (track.speed_max_mm_s, *v),
        (track.accel_max_mm_s2, *a),
        (track.jerk_max_mm_s3, *j),
    )


@dataclass(frozen=True)
class ProgressEvent:
    """What the daemon publishes while a scan runs.

    state: the executor state. segment: label of the current segment (``"scan 3"``, ``"link 2"``).
    pass_index / pass_count: 1-based number of the current (or last started) sweep and how many there
    are. percent: share of the trajectory time done. time_left_s: trajectory time left at full rate.
    fault: the fault's reason, or None.
    """

    state: str
    segment: str
    pass_index: int
    pass_count: int
    percent: float
    time_left_s: float
    t_traj_s: float
    fault: str | None = None


@dataclass
class ExecutionResult:
    """How an execution ended, with the record of what was commanded.

    state: FINISHED, ABORTED or FAULTED. fault: reason (FAULTED only). cycles: references sent.
    max_tracking_error_mm: worst monitored tracking error. t_host_s (n,), q_ref_deg (n, n_axes),
    qd_ref_deg_s (n, n_axes) (with a track ``axes_mm_deg``, its mm first), t_traj_s (n,), cycle (n,) int: one row per reference (host monotonic time of
    the packet it answered, the reference, the trajectory time it came from, the controller cycle
    it is meant for, counted from the first feedback). max_tracking_t_traj_s: the playback time at
    which the worst tracking error was seen; track_mm (n,) float32: the raw tracking error of the
    monitor check made since the previous reference (every fourth feedback; NaN where none was).
    move_to_start_s: controller time of the move
    to the plan's start (0: the arm was there), of which start_settle_s waited, after the move's
    references had reached the start, for the arm to come within ``start_tolerance_deg``.
    """

    state: ExecState
    fault: str | None
    cycles: int
    max_tracking_error_mm: float
    t_host_s: np.ndarray
    q_ref_deg: np.ndarray
    qd_ref_deg_s: np.ndarray
    t_traj_s: np.ndarray
    cycle: np.ndarray
    lost_cycles: int = 0
    events: list[ProgressEvent] = field(default_factory=list)
    move_to_start_s: float = 0.0
    start_settle_s: float = 0.0
    max_tracking_t_traj_s: float = 0.0
    track_mm: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.float32))


class _TimeScaler:
    """Trajectory time tau with a jerk-limited playback rate (ruckig, one axis, velocity interface)."""

    def __init__(self, cycle_s: float, accel: float, jerk: float) -> None:
        self.otg = Ruckig(1, cycle_s)
        self.inp = InputParameter(1)
        self.out = OutputParameter(1)
        self.inp.control_interface = ControlInterface.Velocity
        self.inp.max_velocity = [2.0]
        self.inp.max_acceleration = [accel]
        self.inp.max_jerk = [jerk]
        self.inp.current_position = [0.0]
        self.inp.current_velocity = [1.0]
        self.inp.current_acceleration = [0.0]
        self.inp.target_velocity = [1.0]
        self.inp.target_acceleration = [0.0]
        self.cycle_s = cycle_s

    @property
    def tau(self) -> float:
        return float(self.inp.current_position[0])

    @property
    def rate(self) -> float:
        return float(self.inp.current_velocity[0])

    @property
    def rate_dot(self) -> float:
        return float(self.inp.current_acceleration[0])

    def set_tau(self, tau: float) -> None:
        self.inp.current_position = [tau]

    def target(self, rate: float) -> None:
        self.inp.target_velocity = [rate]

    @property
    def settled(self) -> bool:
        return abs(self.rate - self.inp.target_velocity[0]) < 1e-9 and abs(self.rate_dot) < 1e-9

    def step(self) -> None:
        if self.settled:
            # steady rate: no generator call needed
            self.inp.current_position = [self.tau + self.rate * self.cycle_s]
            self.inp.current_velocity = [float(self.inp.target_velocity[0])]
            self.inp.current_acceleration = [0.0]
            return
        res = self.otg.update(self.inp, self.out)
        if res not in (Result.Working, Result.Finished):
            raise ExecutorError(f"playback-rate generator failed: {res}")
        self.out.pass_to_input(self.inp)
        if res == Result.Finished:
            self.inp.current_velocity = [float(self.inp.target_velocity[0])]
            self.inp.current_acceleration = [0.0]


class MotionExecutor:
    """Streams a :class:`TimedTrajectory` over an EGM endpoint. Use ``await run()``; call
    :meth:`pause`, :meth:`resume`, :meth:`abort` from the same event loop at any time.

    Args:
        endpoint: a started EGM endpoint (the controller sends to it).
        trajectory: the timed joint trajectory (the plan's).
        envelope: the safety envelope every reference passes last.
        config: limits and thresholds.
        segment_labels / segment_kinds: the plan's segments (for progress events); optional.
        on_progress: ``cb(ProgressEvent)``, called on the event loop; errors in it are logged.
    """

    def __init__(
        self,
        endpoint: EgmEndpoint,
        trajectory: TimedTrajectory,
        envelope: SafetyEnvelope,
        config: ExecutorConfig | None = None,
        *,
        segment_labels: Sequence[str] | None = None,
        segment_kinds: Sequence[str] | None = None,
        on_progress: Callable[[ProgressEvent], None] | None = None,
    ) -> None:
        #: axes commanded: the six joints, or the track and the six joints (``axes_mm_deg``)
        self._n = n = envelope.limits.n_axes
        if trajectory.t_s.size < 2 or trajectory.q_deg.shape != (trajectory.t_s.size, n):
            raise ExecutorError(f"trajectory needs at least 2 samples of {n} axes")
        self.endpoint = endpoint
        self.trajectory = trajectory
        self.envelope = envelope
        self.config = cfg = config or ExecutorConfig()
        limits = (cfg.joint_speed_max_deg_s, cfg.joint_accel_max_deg_s2, cfg.joint_jerk_max_deg_s3)
        if any(len(v) != n for v in limits):
            raise ExecutorError(f"the executor's limits must cover {n} axes (a track's first)")
        n_seg = int(trajectory.segment.max()) + 1
        self.segment_labels = list(segment_labels or [f"segment {i + 1}" for i in range(n_seg)])
        self.segment_kinds = list(segment_kinds or ["scan"] * n_seg)
        sweeps = [i for i, k in enumerate(self.segment_kinds) if k in ("scan", "edge")]
        self._pass_of_segment = np.searchsorted(
            np.array(sweeps, dtype=np.int64), np.arange(n_seg), side="right"
        )
        self._pass_count = len(sweeps)
        self._on_progress = on_progress
        self._queue: asyncio.Queue[ProgressEvent | None] = asyncio.Queue(maxsize=1024)
        self.state = ExecState.IDLE
        self.fault: str | None = None
        self._requests: deque[str] = deque()
        self._vmax = np.asarray(cfg.joint_speed_max_deg_s, dtype=np.float64)
        self._amax = np.asarray(cfg.joint_accel_max_deg_s2, dtype=np.float64)
        self._jmax = np.asarray(cfg.joint_jerk_max_deg_s3, dtype=np.float64)
        self._scaler = _TimeScaler(cfg.cycle_s, *self._rate_limits_at(0.0))
        self._otg = Ruckig(self._n, cfg.cycle_s)
        self._inp = InputParameter(self._n)
        self._out = OutputParameter(self._n)
        self._inp.synchronization = Synchronization.No
        self._set_limits(1.0)
        self._ref_q = np.zeros(n)
        self._ref_qd = np.zeros(n)
        self._last_seqno: int | None = None
        self._last_t_ctrl_us: int | None = None
        self._fb_count = 0
        self._lost = 0
        self._tcp_hist = deque(maxlen=max(2, int(cfg.tracking_window_s / cfg.cycle_s)))
        self._max_track = 0.0
        #: the playback time (s) at which the worst tracking error was seen: where on the plan to look
        self._max_track_tau = 0.0
        self._last_track = 0.0
        #: the raw error of the monitor check since the last reference (NaN: no check), recorded with it
        self._track_now = float("nan")
        self._not_ok = 0
        # the record of what was commanded: arrays sized for the plan (and grown by doubling past it),
        # so a cycle writes into memory it already has
        self._rec = _Record(int(trajectory.duration_s / cfg.cycle_s * 1.25) + 1024, n)
        #: the per-cycle work and the silence check may run on different threads
        self._lock = threading.Lock()
        #: where progress events go, called on the thread of the cycle (None: the in-process run()'s
        #: hand-over to its event loop); the motion process sets its channel here
        self.sink: Callable[[ProgressEvent | None], None] | None = None
        self._synced = False  # the first cycle after begin() takes the controller's count from there
        self._pkt_key: tuple | None = None  # the packet whose controller cycle is _pkt_cycle
        self._pkt_cycle = 0
        self._ref_cycle = 0  # the controller cycle the last computed reference is for
        self._sent_q: np.ndarray | None = None  # the last reference handed to the endpoint, and its
        self._sent_ff: np.ndarray | None = None  # speed feed-forward
        self._cycle_us = round(cfg.cycle_s * 1e6)
        self._cycle_ns = round(cfg.cycle_s * 1e9)
        self._real_move = False
        self._last_rx_ns = 0
        self._ended_cb: Callable[[], None] | None = None
        self._cycle = 0
        self._events: list[ProgressEvent] = []
        self._last_progress_t = -1e9
        self._started = False
        self._held = False
        self._joint_stop = False
        self._approach = False  # until the arm reached the plan's start (pause holds it in joint space)
        self._ff_qd: np.ndarray | None = None
        self._last_sent_qd = np.zeros(self._n)
        #: controller cycles of the move to the start, and of its wait for the arm to settle there
        self._start_cycles = 0
        self._settle_cycles = 0
        #: host monotonic time before which the plan does not start (the sensor's settle, which the
        #: move to the start overlaps); 0: at once
        self.start_not_before_s = 0.0

    #: trajectory time ahead of a ramp's start whose peaks bound the ramp (a ramp covers less)
    _RAMP_WINDOW_S = 1.5

    def _rate_limits_at(self, tau: float) -> tuple[float, float]:
        """Playback-rate acceleration and jerk for a ramp starting at trajectory time ``tau``.

        With the rate r(t) the joint jerk is q''' r^3 + 3 q'' r r' + q' r''. The plan uses
        :data:`~cellctl.motion.trajectory.PLAN_JERK_SHARE` (80 %) of the jerk budget; r' gets 12 % and
        r'' 8 %, bounded by the peaks of q' and q'' over the stretch of trajectory the ramp can cover,
        so a pause on a slow pass stops in a short distance and keeps the jerk and acceleration limits.
        """
        cfg, traj = self.config, self.trajectory
        i0 = max(int(np.searchsorted(traj.t_s, tau, side="right")) - 1, 0)
        i1 = int(np.searchsorted(traj.t_s, tau + self._RAMP_WINDOW_S, side="right")) + 1
        qd_peak = np.maximum(np.abs(traj.qd_deg_s[i0:i1]).max(axis=0), 1e-6)
        qdd_peak = np.maximum(np.abs(traj.qdd_deg_s2[i0:i1]).max(axis=0), 1e-6)
        a_r = cfg.rate_accel_per_s2 or float(
            np.clip(
                min(
                    np.min(0.5 * self._amax / qd_peak),
                    np.min(_RAMP_JERK_SHARE_ACCEL * self._jmax / (3 * qdd_peak)),
                ),
                0.2,
                50.0,
            )
        )
        j_r = cfg.rate_jerk_per_s3 or float(
            np.clip(np.min(_RAMP_JERK_SHARE_JERK * self._jmax / qd_peak), 1.0, 500.0)
        )
        return a_r, j_r

    def _ramp_rate(self, rate: float) -> None:
        """Start a playback-rate ramp to ``rate`` with the limits of the stretch ahead."""
        a_r, j_r = self._rate_limits_at(self._scaler.tau)
        self._scaler.inp.max_acceleration = [a_r]
        self._scaler.inp.max_jerk = [j_r]
        self._scaler.target(rate)

    @classmethod
    def for_plan(
        cls,
        endpoint: EgmEndpoint,
        plan,
        settings,
        config: ExecutorConfig | None = None,
        *,
        on_progress: Callable[[ProgressEvent], None] | None = None,
    ) -> MotionExecutor:
        """An executor for a :class:`~cellctl.planning.ScanPlan` with the envelope and the limits of
        ``settings`` (:class:`~cellctl.planning.PlannerSettings`)."""
        config = config or ExecutorConfig.from_settings(settings)
        envelope = SafetyEnvelope(EnvelopeLimits.from_settings(settings, cycle_s=config.cycle_s))
        return cls(
            endpoint,
            plan.trajectory,
            envelope,
            config,
            segment_labels=[s.label for s in plan.segments],
            segment_kinds=[s.kind for s in plan.segments],
            on_progress=on_progress,
        )

    # ---- control (call from the event loop) -------------------------------------------------------

    def pause(self) -> None:
        """Slow down and hold (jerk-limited): along the path, or in joint space during the move to the
        plan's start (resume then continues that move); a no-op when stopping or stopped."""
        self._requests.append("pause")

    def resume(self) -> None:
        """Continue from where the pause stopped, ramping the rate back up (jerk-limited)."""
        self._requests.append("resume")

    def abort(self) -> None:
        """Stop smoothly along the path and end the execution (ABORTED)."""
        self._requests.append("abort")

    def fault_stop(self, reason: str) -> None:
        """Stop smoothly (joint-space, jerk-limited) and end the execution (FAULTED)."""
        self._requests.append("fault:" + reason)

    async def events(self) -> AsyncIterator[ProgressEvent]:
        """Progress events until the execution ends (the last one carries the terminal state)."""
        while True:
            ev = await self._queue.get()
            if ev is None:
                return
            yield ev

    # ---- the loop -----------------------------------------------------------------------------

    async def run(self) -> ExecutionResult:
        """Execute the trajectory in this process: the per-cycle work runs on the endpoint's reply
        path as its cycle hook (each reference computed for the packet it answers), this coroutine
        waits for the end and watches for a silent controller. Returns when FINISHED, ABORTED or
        FAULTED (never raises for faults). The motion process (:mod:`cellctl.motion.process`) drives
        the same methods from its own real-time thread.

        Raises:
            ExecutorError: called twice.
        """
        if self._started:
            raise ExecutorError("an executor runs once; create a new one")
        self._started = True
        loop = asyncio.get_running_loop()
        done = asyncio.Event()
        if self.sink is None:
            self.sink = lambda ev: loop.call_soon_threadsafe(self._deliver, ev)
        self._ended_cb = lambda: loop.call_soon_threadsafe(done.set)
        try:
            first = await self._wait_commandable()
        except ExecutorError as exc:
            self._enter_fault(str(exc), hold=False)
            return self._finish()
        if not self.begin(self._axes(first), first.t_host_ns):
            return self._finish()
        self.endpoint.set_cycle_hook(self.on_cycle)
        try:
            poll_s = max(self.config.feedback_timeout_s / 4.0, 0.005)
            while self.state not in _TERMINAL:
                try:
                    async with asyncio.timeout(poll_s):
                        await done.wait()
                except TimeoutError:
                    self.check_silence(time.monotonic_ns())
        finally:
            self.endpoint.set_cycle_hook(None)
        await asyncio.sleep(0)  # the last progress events handed over to the loop arrive first
        return self._finish()

    def _deliver(self, ev: ProgressEvent | None) -> None:
        """A progress event on the event loop (the in-process run()): queue and callback."""
        if ev is None:
            return
        if self._queue.full():
            self._queue.get_nowait()  # the newest progress matters more than the oldest
        self._queue.put_nowait(ev)
        if self._on_progress is not None:
            try:
                self._on_progress(ev)
            except Exception:
                log.exception("executor_progress_callback_failed")

    # ---- the per-cycle work (any thread; the motion process's real-time one) ------------------

    def begin(self, q_fb: np.ndarray, t_rx_ns: int) -> bool:
        """Start from the arm's axes ``q_fb`` (a commandable feedback received at ``t_rx_ns``): the
        move to the plan's start is checked and set up, or the plan starts where the arm is. Nothing
        is sent; the cycles (:meth:`on_cycle`) do that. False when the execution ended here (the move
        would leave the envelope); :meth:`result` says how."""
        cfg = self.config
        q0 = self.trajectory.q_deg[0]
        q_fb = np.asarray(q_fb, dtype=np.float64)
        with self._lock:
            self._started = True
            self._last_rx_ns = t_rx_ns
            self._ref_q, self._ref_qd = q_fb.copy(), np.zeros(self._n)
            self._inp.current_position = q_fb.tolist()
            self._inp.current_velocity = [0.0] * self._n
            self._inp.current_acceleration = [0.0] * self._n
            self.envelope.reset(q_fb)
            self._real_move = bool(np.max(np.abs(q_fb - q0)) > cfg.start_tolerance_deg)
            if self._real_move:
                try:  # where the move goes is known before it starts: refused then, not stopped mid-way
                    self.envelope.check_path(start_path(q_fb, q0))
                except EnvelopeViolation as exc:
                    self._enter_fault(
                        f"the move to the plan's start would leave the envelope, nothing moved: {exc}",
                        hold=False,
                    )
                    return False
            # at the start already, the plan still waits for start_not_before_s (the sensor's settle)
            # with the arm at rest: a move of length zero
            self._set_state(ExecState.MOVING_TO_START)
            self._approach = True
            self._set_start_limits(q_fb, q0)
            self._scaler.set_tau(0.0)
            self._synced = False
            self._pkt_key = None
            self._ref_cycle = self._pkt_cycle = 0
        return True

    def on_cycle(self, msg: RobotMessage, t_rx_ns: int, phase: str = "now") -> None:
        """One controller packet: the EGM endpoint's cycle hook (see
        :meth:`~drivers.abb_egm.endpoint.EgmEndpoint.set_cycle_hook`).

        ``"next"`` (after the reply): check the controller's state, handle pause / resume / abort,
        monitor the tracking, and prepare the next packet's reference, one cycle on (envelope-checked
        before it is handed over). ``"now"`` (before the reply, when no prepared reference fits this
        packet: the first one, a lost packet, a jump in the controller's clock): advance by the
        controller's cycles to this packet's and set its reference."""
        with self._lock:
            if self.state in _TERMINAL:
                return
            self._last_rx_ns = t_rx_ns
            if phase == "now":
                c = self._packet_cycle(msg)
                if c is not None:
                    self._step_to(c, t_rx_ns, None)
                return
            if not ok_to_command(msg.motor_state, msg.mci_state, msg.rapid_exec_state):
                # A real stop (motors off, RAPID stopped, e-stop) persists; one packet alone may be a
                # corrupted datagram that still decoded. The next packet (one cycle) confirms it.
                self._not_ok += 1
                if self._not_ok >= 2:
                    self._enter_fault(
                        f"controller stopped EGM (motors {_name(msg.motor_state)}, EGM {_name(msg.mci_state)}, "
                        f"RAPID {_name(msg.rapid_exec_state)})",
                        hold=True,
                    )
                    self._ended()
                return
            self._not_ok = 0
            axes = axes_of(msg, self._n - 6)
            c = self._packet_cycle(msg)
            if c is None or axes.shape[0] < self._n:
                return  # an incomplete feedback: the next packet gets its reference on the spot
            self._handle_requests()
            self._fb_count += 1
            if self._fb_count % 4 == 0:  # a monitor: 16 ms of latency costs nothing, the CPU does
                self._monitor_tracking(axes)
            t_next = None if msg.feedback_time_us is None else msg.feedback_time_us + self._cycle_us
            s_next = None if msg.seqno is None else (msg.seqno + 1) % _U32
            self._step_to(c + 1, t_rx_ns + self._cycle_ns, (t_next, s_next))
            self._maybe_progress()
            if self.state in _TERMINAL:
                self._ended()

    def _packet_cycle(self, msg: RobotMessage) -> int | None:
        """The controller cycle of ``msg``, counted from the first packet after :meth:`begin` (1),
        by the controller's clock (else its sequence number); once per packet."""
        key = (msg.seqno, msg.feedback_time_us)
        if key == self._pkt_key:
            return self._pkt_cycle
        if msg.feedback_q_deg is None:
            return None
        if not self._synced:
            self._synced = True
            self._last_seqno, self._last_t_ctrl_us = msg.seqno, msg.feedback_time_us
            self._pkt_cycle = self._ref_cycle + 1
        else:
            self._pkt_cycle += self._cycles_since(msg.seqno, msg.feedback_time_us)
        self._pkt_key = key
        return self._pkt_cycle

    def _step_to(self, target: int, t_host_ns: int, prepare: tuple[int | None, int | None] | None) -> None:
        """Advance the generators to controller cycle ``target`` and hand its reference over: set now
        (``prepare`` None) or prepared for the packet ``prepare`` = (controller time us, seqno)."""
        n = target - self._ref_cycle
        for _ in range(max(n, 0)):
            self._advance()
            if self.state in _TERMINAL:
                break
        if n > 0:
            self._ref_cycle = target
            self._cycle = target
        if self._held:
            return
        if n > 0:
            self._send(t_host_ns, n, prepare)
        elif prepare is None and self._sent_q is not None:
            # this packet's reference was prepared but the packet did not match it (its clock moved
            # by a fraction of a cycle): the same reference, set now
            self.endpoint.command_joints(self._sent_q, self._sent_ff)

    def check_silence(self, now_ns: int) -> bool:
        """Called when no packet came for a while: a controller silent for ``feedback_timeout_s`` and
        a grace of half that (this process itself may not have been scheduled) has stalled. The
        reference stays where the plan was, without speed feed-forward, so the arm settles there
        when the controller keeps its last reference. True when the execution ended here."""
        cfg = self.config
        with self._lock:
            if self.state in _TERMINAL or not self._started:
                return self.state in _TERMINAL
            quiet_s = (now_ns - self._last_rx_ns) / 1e9
            if quiet_s < cfg.feedback_timeout_s + max(0.02, 0.5 * cfg.feedback_timeout_s):
                return False
            reason = f"controller stalled: no feedback for {cfg.feedback_timeout_s} s"
            self.endpoint.command_joints(self._ref_q, np.zeros(self._n) if cfg.feedforward else None)
            self.fault = reason
            log.warning(
                "executor_fault", reason=reason, state=self.state.value, t_traj_s=round(self._scaler.tau, 3),
                quiet_s=round(quiet_s, 3),
            )  # fmt: skip
            self._set_state(ExecState.FAULTED)
            self._ended()
            return True

    def _ended(self) -> None:
        cb = self._ended_cb
        if cb is not None:
            cb()

    @property
    def done(self) -> bool:
        """True once the execution reached FINISHED, ABORTED or FAULTED."""
        return self.state in _TERMINAL

    @property
    def playback_s(self) -> float:
        """The plan's playback time of the last reference, s."""
        return self._scaler.tau

    @property
    def cycles(self) -> int:
        """References sent so far."""
        return self._rec.n

    @property
    def lost_cycles(self) -> int:
        """Controller cycles with no packet (its clock or sequence number jumped past them)."""
        return self._lost

    @property
    def max_tracking_error_mm(self) -> float:
        """The worst monitored TCP tracking error so far, mm."""
        return self._max_track

    @property
    def max_tracking_t_traj_s(self) -> float:
        """The playback time (s on the plan) at which :attr:`max_tracking_error_mm` was seen."""
        return self._max_track_tau

    def fail(self, reason: str) -> None:
        """End before any motion (nothing was sent): FAULTED with ``reason``."""
        with self._lock:
            self._started = True
            self._enter_fault(reason, hold=False)

    async def _wait_commandable(self):
        deadline = time.monotonic() + self.config.start_timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise ExecutorError(
                    f"no commandable feedback from the controller within {self.config.start_timeout_s} s"
                )
            try:
                fb = await self.endpoint.wait_for_feedback(min(left, 1.0))
            except TimeoutError:
                continue
            if fb.ok_to_command and fb.q_deg.shape[0] >= 6 and fb.axes_mm_deg.shape[0] >= self._n:
                return fb

    def _axes(self, fb) -> np.ndarray:
        """The feedback of the commanded axes: ``q_deg`` (6,), or ``axes_mm_deg`` (7,) with a track."""
        return np.asarray(fb.axes_mm_deg[: self._n], dtype=np.float64)

    def _cycles_since(self, seqno: int | None, t_ctrl_us: int | None) -> int:
        """EGM cycles since the previous feedback: from the controller's clock when it sends one
        (it also counts cycles the controller ran late and integrated at once), else the seqno."""
        prev_seq, prev_t = self._last_seqno, self._last_t_ctrl_us
        self._last_seqno, self._last_t_ctrl_us = seqno, t_ctrl_us
        if t_ctrl_us is not None and prev_t is not None:
            diff = round((t_ctrl_us - prev_t) / (self.config.cycle_s * 1e6))
        elif seqno is not None and prev_seq is not None:
            diff = (seqno - prev_seq) % _U32
        else:
            return 1
        if diff <= 0 or diff > 250:  # duplicate, reordered or a new session: one cycle
            return 1
        self._lost += diff - 1
        return int(diff)

    def _set_limits(self, fraction: float) -> None:
        self._inp.max_velocity = (self._vmax * fraction).tolist()
        self._inp.max_acceleration = self._amax.tolist()
        self._inp.max_jerk = self._jmax.tolist()

    def _set_start_limits(self, q_from: np.ndarray, q_to: np.ndarray) -> None:
        """Limits for the move to the plan's start: a straight line in joint space (phase-synchronised)
        slow enough that the TCP stays well under the envelope's speed cap."""
        dq = q_to - q_from
        path = start_path(q_from, q_to)
        lim = self.envelope.limits
        p = fk_batch(path, lim.T_flange_tcp, track=lim.track)[:, :3, 3]
        dp_du = float(np.max(np.linalg.norm(np.diff(p, axis=0), axis=1)) * (len(path) - 1))
        u_dot = np.min(self.config.move_to_start_speed_fraction * self._vmax / np.maximum(np.abs(dq), 1e-9))
        if dp_du > 0:
            u_dot = min(u_dot, _START_TCP_FRACTION * self.envelope.limits.tcp_speed_max_mm_s / dp_du)
        self._inp.max_velocity = np.maximum(np.abs(dq) * u_dot, 1e-3).tolist()
        self._inp.max_acceleration = self._amax.tolist()
        self._inp.max_jerk = self._jmax.tolist()
        self._inp.synchronization = Synchronization.Phase

    def _set_state(self, state: ExecState) -> None:
        if state != self.state:
            log.info(
                "executor_state",
                state=state.value,
                previous=self.state.value,
                t_traj_s=round(self._scaler.tau, 3),
            )
            self.state = state
            self._emit(force=True)

    def _handle_requests(self) -> None:
        while self._requests:
            req = self._requests.popleft()
            s = self.state
            if req.startswith("fault:"):
                self._begin_fault_stop(req[6:])
            elif self._approach and req in ("pause", "resume", "abort"):
                self._handle_approach_request(req, s)
            elif req == "pause" and s in (ExecState.RUNNING, ExecState.RESUMING):
                self._ramp_rate(0.0)
                self._set_state(ExecState.PAUSING)
            elif req == "resume" and s in (ExecState.PAUSED, ExecState.PAUSING):
                self._ramp_rate(1.0)
                self._set_state(ExecState.RESUMING)
            elif req == "abort":
                if s == ExecState.PAUSED:
                    self._set_state(ExecState.ABORTED)
                elif s in (ExecState.RUNNING, ExecState.PAUSING, ExecState.RESUMING):
                    self._ramp_rate(0.0)
                    self._set_state(ExecState.ABORTING)
            else:
                log.info("executor_request_ignored", request=req, state=s.value)

    def _handle_approach_request(self, req: str, s: ExecState) -> None:
        """pause / resume / abort before the arm reached the plan's start (a joint-space move)."""
        if req == "pause" and s == ExecState.MOVING_TO_START:
            self._inp.control_interface = ControlInterface.Velocity
            self._inp.target_velocity = [0.0] * self._n
            self._inp.target_acceleration = [0.0] * self._n
            self._inp.synchronization = Synchronization.No
            self._set_state(ExecState.PAUSING)
        elif req == "resume" and s in (ExecState.PAUSING, ExecState.PAUSED):
            self._set_start_limits(self._ref_q, self.trajectory.q_deg[0])
            self._set_state(ExecState.MOVING_TO_START)
        elif req == "abort" and s == ExecState.PAUSED:
            self._set_state(ExecState.ABORTED)
        elif req == "abort":
            self._begin_joint_stop(ExecState.ABORTING)
        else:
            log.info("executor_request_ignored", request=req, state=s.value, approach=True)

    def _begin_joint_stop(self, state: ExecState) -> None:
        self._inp.control_interface = ControlInterface.Velocity
        self._inp.target_velocity = [0.0] * self._n
        self._inp.target_acceleration = [0.0] * self._n
        self._inp.synchronization = Synchronization.No
        self._set_limits(1.0)
        self._joint_stop = True
        self._set_state(state)

    def _begin_fault_stop(self, reason: str) -> None:
        if self.state in _TERMINAL or self.state == ExecState.FAULT_STOPPING:
            return
        self.fault = reason
        log.warning(
            "executor_fault", reason=reason, state=self.state.value, t_traj_s=round(self._scaler.tau, 3)
        )
        self._begin_joint_stop(ExecState.FAULT_STOPPING)

    def _enter_fault(self, reason: str, *, hold: bool) -> None:
        self.fault = self.fault or reason
        log.warning(
            "executor_fault", reason=reason, state=self.state.value, t_traj_s=round(self._scaler.tau, 3)
        )
        if hold and self.endpoint.latest is not None:
            self.endpoint.hold()
            self._held = True
        self._set_state(ExecState.FAULTED)

    def _advance(self) -> None:
        """One cycle of the generators; updates the reference state."""
        s = self.state
        inp, _out = self._inp, self._out
        traj = self.trajectory
        if s == ExecState.FAULT_STOPPING or (s == ExecState.ABORTING and self._joint_stop):
            res = self._otg_update()
            if res == Result.Finished or np.all(np.abs(self._ref_qd) < 1e-9):
                self._set_state(ExecState.FAULTED if s == ExecState.FAULT_STOPPING else ExecState.ABORTED)
            return
        if s == ExecState.MOVING_TO_START:
            inp.control_interface = ControlInterface.Position
            inp.target_position = traj.q_deg[0].tolist()
            inp.target_velocity = [0.0] * self._n
            inp.target_acceleration = [0.0] * self._n
            res = self._otg_update()
            if self._real_move:
                self._start_cycles += 1
                self._settle_cycles += res == Result.Finished
            fb = self.endpoint.latest
            at_start = (
                res == Result.Finished
                and fb is not None
                and np.max(np.abs(self._axes(fb) - traj.q_deg[0])) <= self.config.start_settle_tolerance_deg
                and time.monotonic() >= self.start_not_before_s
            )
            if at_start:
                self._approach = False
                self._set_limits(1.0)
                self._inp.synchronization = Synchronization.No
                self._set_state(ExecState.RUNNING)
            return
        if self._approach:  # paused on the way to the start: a jerk-limited joint stop, then hold
            if s == ExecState.PAUSING:
                res = self._otg_update()
                if res == Result.Finished or np.all(np.abs(self._ref_qd) < 1e-9):
                    self._set_state(ExecState.PAUSED)
            return
        if s == ExecState.PAUSED:
            return
        # on the path: advance the playback time and send the time-scaled plan state. The plan's
        # time law is jerk-limited (ruckig, offline) and the playback rate ramps are jerk-limited
        # (ruckig, online), so the reference needs no further filtering; an online replan towards
        # a moving target would lag and then overshoot the speed.
        self._scaler.step()
        tau, rate, rate_dot = self._scaler.tau, self._scaler.rate, self._scaler.rate_dot
        T = traj.duration_s
        if tau >= T:
            self._scaler.set_tau(T)
            tau = T
        q, qd, qdd, _ = traj.sample(tau)
        self._ref_q = q
        self._ref_qd = qd * rate
        lead_s = self.config.feedforward_lead_s
        # the controller low-pass filters its speed command: the speed reference is the plan's
        # speed one filter time constant ahead, so the arm does not overshoot where the plan slows
        # down; ahead in the playback rate too (its ramp is known: rate + lead * rate_dot), or at
        # the end of a pause's ramp the arm runs 0.4-0.5 mm past the point where the reference stood
        # (measured on the sail: every pause's worst tracking 5-13 cycles before the hold)
        if lead_s > 0:
            rate_ahead = max(0.0, rate + lead_s * rate_dot)
            self._ff_qd = traj.sample(min(tau + lead_s * rate, T))[1] * rate_ahead
        else:
            self._ff_qd = self._ref_qd
        # keep the stop generator's state on the reference, so a fault stop starts from here
        inp.current_position = q.tolist()
        inp.current_velocity = self._ref_qd.tolist()
        inp.current_acceleration = np.clip(
            qdd * rate * rate + qd * rate_dot, -self._amax, self._amax
        ).tolist()
        moving = float(np.max(np.abs(self._ref_qd))) >= 1e-6
        if s == ExecState.PAUSING and self._scaler.settled:
            self._set_state(ExecState.PAUSED)
        elif s == ExecState.RESUMING and self._scaler.settled:
            self._set_state(ExecState.RUNNING)
        elif s == ExecState.ABORTING and self._scaler.settled and not moving:
            self._set_state(ExecState.ABORTED)
        elif tau >= T:
            self._set_state(ExecState.FINISHED)

    def _otg_update(self) -> Result:
        inp, out = self._inp, self._out
        try:
            res = self._otg.update(inp, out)
        except Exception as exc:  # ruckig raises RuckigError on invalid input in some builds
            res = Result.Error
            log.warning("executor_ruckig_error", error=str(exc))
        if res not in (Result.Working, Result.Finished) and not self._joint_stop:
            # a target acceleration the limits cannot meet: track the velocity only
            inp.target_acceleration = [0.0] * self._n
            try:
                res = self._otg.update(inp, out)
            except Exception:
                res = Result.Error
        if res not in (Result.Working, Result.Finished):
            self._begin_fault_stop(f"trajectory generator failed ({res})")
            if self._otg_stop_failed():
                return Result.Finished
            return Result.Working
        out.pass_to_input(inp)
        self._ref_q = np.asarray(out.new_position, dtype=np.float64)
        self._ref_qd = np.asarray(out.new_velocity, dtype=np.float64)
        return res

    def _otg_stop_failed(self) -> bool:
        try:
            res = self._otg.update(self._inp, self._out)
        except Exception:
            res = Result.Error
        if res in (Result.Working, Result.Finished):
            self._out.pass_to_input(self._inp)
            self._ref_q = np.asarray(self._out.new_position, dtype=np.float64)
            self._ref_qd = np.asarray(self._out.new_velocity, dtype=np.float64)
            return False
        self._enter_fault("the stop generator failed; holding the last reference", hold=False)
        return True

    def _send(
        self, t_host_ns: int, cycles: int, prepare: tuple[int | None, int | None] | None = None
    ) -> None:
        q, qd = self._ref_q, self._ref_qd
        try:
            p = self.envelope.check(q, cycles)
        except EnvelopeViolation as exc:
            last = self.envelope.last_q_deg
            if self.state == ExecState.FAULT_STOPPING or last is None:
                # the stop itself left the envelope: hold the last accepted reference
                if last is not None:
                    self.endpoint.command_joints(last, np.zeros(self._n) if self.config.feedforward else None)
                self._enter_fault(f"envelope violated during the stop: {exc}", hold=False)
                return
            # fall back to the last accepted state and stop smoothly from it
            self._inp.current_position = last.tolist()
            self._inp.current_velocity = self._last_sent_qd.tolist()
            self._inp.current_acceleration = [0.0] * self._n
            self._ref_q, self._ref_qd = last, self._last_sent_qd.copy()
            self._begin_fault_stop(f"envelope: {exc}")
            self.endpoint.command_joints(last, self._last_sent_qd if self.config.feedforward else None)
            return
        ff = self._ff_qd if self._ff_qd is not None else qd
        ff = ff if self.config.feedforward else None
        if prepare is None:
            self.endpoint.command_joints(q, ff)
        else:
            self.endpoint.prepare_joints(q, ff, for_t_ctrl_us=prepare[0], for_seqno=prepare[1])
        self._sent_q, self._sent_ff = q, ff
        self._ff_qd = None
        self._last_sent_qd = np.array(qd, dtype=np.float64)
        self._tcp_hist.append(self.envelope.world_mm(q, p))
        self._rec.add(t_host_ns / 1e9, q, qd, self._scaler.tau, self._cycle, self._track_now)
        self._track_now = float("nan")

    def _monitor_tracking(self, q_fb: np.ndarray) -> None:
        if len(self._tcp_hist) < 2 or self.state in _TERMINAL:
            return
        q_fb = np.asarray(q_fb, dtype=np.float64)
        p_fb = self.envelope.world_mm(q_fb, self.envelope.tcp_mm(q_fb))
        hist = np.asarray(self._tcp_hist)
        # distance to the commanded polyline of the last window (the controller lags the reference)
        a, b = hist[:-1], hist[1:]
        ab = b - a
        u = np.clip(np.sum((p_fb - a) * ab, axis=1) / np.maximum(np.sum(ab * ab, axis=1), 1e-12), 0.0, 1.0)
        raw = float(np.min(np.linalg.norm(a + u[:, None] * ab - p_fb, axis=1)))
        # An error counts once two successive checks (16 ms apart) see it: a real tracking error
        # changes little in 16 ms, one corrupted feedback datagram that still decoded is gone by then.
        err = min(raw, self._last_track)
        self._last_track = raw
        self._track_now = raw
        if err > self._max_track:
            self._max_track, self._max_track_tau = err, self._scaler.tau
        if err > self.config.tracking_error_max_mm and self.state != ExecState.FAULT_STOPPING:
            self._begin_fault_stop(
                f"tracking error {err:.2f} mm above {self.config.tracking_error_max_mm} mm"
            )

    # ---- progress -----------------------------------------------------------------------------

    def progress(self) -> ProgressEvent:
        """The current progress (state, pass i of n, percent, time left)."""
        traj = self.trajectory
        tau = self._scaler.tau
        T = traj.duration_s
        _, _, _, seg = traj.sample(tau)
        return ProgressEvent(
            state=self.state.value,
            segment=self.segment_labels[seg] if seg < len(self.segment_labels) else str(seg),
            pass_index=int(self._pass_of_segment[seg]) if seg < len(self._pass_of_segment) else 0,
            pass_count=self._pass_count,
            percent=round(100.0 * tau / T, 3) if T > 0 else 100.0,
            time_left_s=round(max(0.0, T - tau), 3),
            t_traj_s=round(tau, 4),
            fault=self.fault,
        )

    def _emit(self, force: bool = False) -> None:
        now = time.monotonic()
        if not force and now - self._last_progress_t < self.config.progress_interval_s:
            return
        self._last_progress_t = now
        ev = self.progress()
        self._events.append(ev)
        sink = self.sink
        if sink is None:
            self._deliver(ev)
            return
        try:
            sink(ev)
        except Exception:  # a closed loop or channel: progress is for people, the motion goes on
            log.exception("executor_progress_sink_failed")

    def _maybe_progress(self) -> None:
        self._emit(force=False)

    def _finish(self) -> ExecutionResult:
        if self.state not in _TERMINAL:
            self._set_state(ExecState.FAULTED)
        if self._queue.full():
            self._queue.get_nowait()
        self._queue.put_nowait(None)
        return self.result()

    def result(self) -> ExecutionResult:
        """How the execution ended, with the record of what was commanded."""
        rec = self._rec
        n = rec.n
        log.info(
            "executor_done",
            state=self.state.value,
            fault=self.fault,
            cycles=n,
            lost_cycles=self._lost,
            max_tracking_error_mm=round(self._max_track, 4),
        )
        return ExecutionResult(
            state=self.state,
            fault=self.fault,
            cycles=n,
            max_tracking_error_mm=self._max_track,
            t_host_s=rec.t[:n].copy(),
            q_ref_deg=rec.q[:n].copy(),
            qd_ref_deg_s=rec.qd[:n].copy(),
            t_traj_s=rec.tau[:n].copy(),
            cycle=rec.cycle[:n].copy(),
            lost_cycles=self._lost,
            events=list(self._events),
            move_to_start_s=self._start_cycles * self.config.cycle_s,
            start_settle_s=self._settle_cycles * self.config.cycle_s,
            max_tracking_t_traj_s=self._max_track_tau,
            track_mm=rec.track[:n].copy(),
        )


class _Record:
    """The per-cycle record (host time, reference, speed, playback time, cycle) in arrays that
    double when full: a cycle writes into memory that exists."""

    def __init__(self, capacity: int, n_axes: int) -> None:
        self.n = 0
        self.t = np.zeros(capacity)
        self.q = np.zeros((capacity, n_axes))
        self.qd = np.zeros((capacity, n_axes))
        self.tau = np.zeros(capacity)
        self.cycle = np.zeros(capacity, dtype=np.int64)
        self.track = np.full(capacity, np.nan, dtype=np.float32)

    def add(self, t: float, q: np.ndarray, qd: np.ndarray, tau: float, cycle: int, track_mm: float) -> None:
        i = self.n
        if i == self.t.shape[0]:
            for name in ("t", "q", "qd", "tau", "cycle", "track"):
                a = getattr(self, name)
                setattr(self, name, np.concatenate([a, np.full_like(a, np.nan if name == "track" else 0)]))
        self.t[i] = t
        self.q[i] = q
        self.qd[i] = qd
        self.tau[i] = tau
        self.cycle[i] = cycle
        self.track[i] = track_mm
        self.n = i + 1


def _name(value) -> str | None:
    return None if value is None else getattr(value, "name", str(value))
