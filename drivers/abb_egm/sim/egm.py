"""Controller simulator, EGM side: the UDP client that an IRC5 / OmniCore is, and the arm it moves.

Every cycle (4.032 ms by default, scheduled on absolute deadlines with ``loop.call_at`` so it does
not drift) the simulator does what the EGM manual (p.26) describes for the controller:

1. sample the joint feedback and record it in the true trajectory (:class:`TrajectoryRecorder`);
2. send one ``EgmRobot`` (seqno from 0 per session, ``tm`` in ms, feedback joints / cartesian / time,
   planned, motor / EGM / RAPID states, convergence, utilisation) to the sensor;
3. take the newest ``EgmSensor`` that arrived (or hold the last reference when none came) and move
   the joints by the controller's law ``v = k (ref - q) + speed_ref`` with ``k = PosCorrGain x 5``,
   low-pass filtered (20 Hz) and clamped to the axis speeds.

A reference beyond the joint limits, the position-deviation or the speed-deviation limit puts EGM
in error and ends the session; no sensor message for the communication timeout ends it with event
41822. With a :class:`~drivers.abb_egm.sim.model.ControllerModel` attached, motors, RAPID
state and the EGM arguments come from the model (RWS drives them) and session ends are reported to
it; without one the simulator runs standalone (``motors_on`` / ``egm_enabled`` attributes).

A linear track (``EgmSimConfig.track``) is a seventh axis in the robot's motion group: its position
(mm) goes out in ``feedBack.externalJoints`` / ``planned.externalJoints`` and its reference comes in
``EgmSensor.planned.externalJoints`` (speed feed-forward in ``speedRef.externalJoints``, mm/s). It
moves by the same law, filter and limits as the joints (its travel and speed from the track); the
state vector is then ``axes_mm_deg`` (track first), the true trajectory records it, and the
cartesian feedback is the flange in the world frame. A joint reference without the track's value
is ignored, as one without six joints is.

Fault knobs (:class:`EgmFaults`) act on the wire: loss (random and bursts), delay and jitter,
duplicates, reordering, corrupted bytes, stop sending, and loss of the sensor's replies.
"""

from __future__ import annotations

import asyncio
import dataclasses
import fcntl
import math
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import structlog

from drivers.abb_egm.codec import (
    EgmDecodeError,
    MciState,
    MessageType,
    MotorState,
    RapidState,
    RobotMessage,
    SensorMessage,
    decode_sensor,
    encode_robot,
)
from drivers.abb_egm.kinematics import RobotKinematics, fk_batch
from drivers.abb_egm.limits import EGM_CYCLE_S, LinearTrack
from drivers.abb_egm.rapid_values import EXTAX_UNUSED
from drivers.abb_egm.ring import ring_indices, ring_search, ring_start

__all__ = [
    "EVENT_EGM_COMM_TIMEOUT",
    "EVENT_EGM_JOINT_LIMIT",
    "EVENT_EGM_POS_DEVIATION",
    "EVENT_EGM_SPEED_DEVIATION",
    "EgmControllerSim",
    "EgmFaults",
    "EgmSimConfig",
    "FaultError",
    "TrajectoryRangeError",
    "TrajectoryRecorder",
]

log = structlog.get_logger(__name__)

_U32 = 2**32
#: "No data from the UdpUc device" (EGM manual; abb_libegm #132)
EVENT_EGM_COMM_TIMEOUT = 41822
# The public sources name no event codes for these guidance errors; the simulator uses its own
# numbers in the EGM range so that tests and operators can tell them apart. UNVERIFIED on hardware.
EVENT_EGM_JOINT_LIMIT = 41890
EVENT_EGM_SPEED_DEVIATION = 41891
EVENT_EGM_POS_DEVIATION = 41892
EVENT_EGM_POSE_UNREACHABLE = 41893
#: Linux ioctl: the kernel's receive time (CLOCK_REALTIME, struct timespec) of the last datagram read
_SIOCGSTAMPNS = 0x8907


class FaultError(ValueError):
    """An unknown fault knob or a value out of its range (names the knob)."""


class TrajectoryRangeError(ValueError):
    """A trajectory query outside the recorded time span."""


# ---------------------------------------------------------------------------------------------
# configuration


@dataclass(frozen=True)
class EgmSimConfig:
    """Settings of the simulated controller's EGM side (cell.toml ``[sim]``).

    Addresses: the controller sends to ``sensor_host:sensor_port`` from ``local_host:local_port``
    (0: any free port). ``cycle_s`` is the EGM sample time (4.032 ms on a real robot).

    The EGM arguments below are used when no ControllerModel is attached, or the model has none
    (outside its EGM phase); with a model in its EGM phase the RAPID variables win.

    ``track``: the linear track the robot rides on (None: a fixed base); ``track_start_mm`` its
    position at start. With a track, ``MaxPosDeviation`` applies to it in mm.
    """

    sensor_host: str = "127.0.0.1"
    sensor_port: int = 6511
    local_host: str = "127.0.0.1"
    local_port: int = 0
    cycle_s: float = EGM_CYCLE_S
    q_start_deg: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 30.0, 0.0)
    guidance_mode: str = "joint"  # "joint" (EGMRunJoint) or "pose" (EGMRunPose, flange in base frame)
    comm_timeout_s: float = 1.0
    pos_corr_gain: float = 1.0
    default_gain: float = 5.0  # system parameter "Default Proportional Position Gain"
    lp_filter_hz: float = 20.0
    max_speed_deviation_deg_s: float = 1000.0
    max_pos_deviation_deg: float = 1000.0
    convergence_deg: float = 0.5
    cond_time_s: float = 1e6
    ramp_in_time_s: float = 0.0
    stream_when_idle: bool = True  # keep sending EgmRobot outside a session (EGMStreamStart)
    ctrl_clock_offset_s: float | None = None  # controller clock - true clock; None: the wall clock
    history_capacity: int = 2**17  # true-trajectory samples kept (about 528 s at 4.032 ms)
    latency_capacity: int = 2**16  # reply latency samples kept
    seed: int | None = None
    track: LinearTrack | None = None
    track_start_mm: float = 0.0


@dataclass(frozen=True)
class EgmFaults:
    """Wire faults of the simulated controller, all off by default.

    ``loss_fraction``: the fraction of ``EgmRobot`` lost; with ``burst_ms`` > 0 the losses come in
    bursts of that length (every packet inside a burst is lost; bursts start with the probability
    that loses ``loss_fraction`` of the packets overall, so "5 % loss in 50 ms bursts" loses 5 %). ``delay_ms`` + uniform(0, ``jitter_ms``)
    delays each packet (jitter also reorders). ``duplicate_fraction`` sends a packet twice,
    ``reorder_fraction`` holds a packet back behind the next one, ``corrupt_fraction`` flips bytes.
    ``stop_sending`` silences the controller. ``rx_loss_fraction`` drops the sensor's replies.
    """

    loss_fraction: float = 0.0
    burst_ms: float = 0.0
    delay_ms: float = 0.0
    jitter_ms: float = 0.0
    duplicate_fraction: float = 0.0
    reorder_fraction: float = 0.0
    corrupt_fraction: float = 0.0
    stop_sending: bool = False
    rx_loss_fraction: float = 0.0

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.name == "stop_sending":
                if not isinstance(value, bool):
                    raise FaultError(f"fault {f.name} must be a bool, got {value!r}")
                continue
            if not isinstance(value, int | float) or not math.isfinite(value) or value < 0:
                raise FaultError(f"fault {f.name} must be a finite number >= 0, got {value!r}")
            if f.name.endswith("_fraction") and value > 1:
                raise FaultError(f"fault {f.name} must be within [0, 1], got {value!r}")


class ControllerModelLike(Protocol):
    """What the simulator uses of :class:`drivers.abb_egm.sim.model.ControllerModel`."""

    @property
    def ctrl_state(self) -> str: ...
    @property
    def rapid_state(self) -> str: ...
    @property
    def egm_wanted(self) -> bool: ...
    @property
    def egm_params(self) -> Any: ...
    def egm_session_ended(self, reason: str, event_code: int | None) -> None: ...
    def set_position_source(self, fn: Callable[[], tuple[np.ndarray, np.ndarray, np.ndarray]]) -> None: ...
    def set_external_axes_source(self, fn: Callable[[], np.ndarray]) -> None: ...


# ---------------------------------------------------------------------------------------------
# the true trajectory


class TrajectoryRecorder:
    """Bounded record of the arm's true joint trajectory on one true time base.

    ``t_s`` are seconds of the simulator's ``clock`` (``time.monotonic`` by default), one sample per
    cycle. Thread-safe: the sensor simulator may read it from another thread.
    """

    def __init__(self, capacity: int, n_axes: int = 6) -> None:
        if capacity < 2:
            raise ValueError(f"capacity must be >= 2, got {capacity}")
        self.capacity = capacity
        self._t_s = np.zeros(capacity)
        self._q_deg = np.zeros((capacity, n_axes))
        self._next = 0
        self._count = 0
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return self._count

    def append(self, t_s: float, q_deg: np.ndarray) -> None:
        """Add one sample; times must not decrease."""
        with self._lock:
            i = self._next
            self._t_s[i] = t_s
            self._q_deg[i] = q_deg
            self._next = (i + 1) % self.capacity
            self._count = min(self._count + 1, self.capacity)

    def _order(self) -> np.ndarray:
        if self._count < self.capacity:
            return np.arange(self._count)
        return (np.arange(self.capacity) + self._next) % self.capacity

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """Copies of all kept samples, oldest first: ``t_s`` (n,) s and ``q_deg`` (n, 6) deg."""
        with self._lock:
            idx = self._order()
            return self._t_s[idx], self._q_deg[idx]

    def span_s(self) -> tuple[float, float] | None:
        """(oldest, newest) sample time, or None when empty."""
        with self._lock:
            if self._count == 0:
                return None
            newest = self._t_s[(self._next - 1) % self.capacity]
            oldest = self._t_s[0 if self._count < self.capacity else self._next]
            return float(oldest), float(newest)

    def _window(self, t_lo: float, t_hi: float) -> tuple[np.ndarray, np.ndarray, float, float]:
        """Copies of the samples that bracket ``[t_lo, t_hi]`` (one more on each side when there is
        one), oldest first, and the (oldest, newest) time of the whole record. Binary search on the
        ring's two sorted runs: a query costs the window it needs, not the whole record (a copy of
        the full 2**17-sample ring took 3 ms per query, and the sensor asks ~100 times a second)."""
        cap = self.capacity
        with self._lock:
            n = self._count
            if n == 0:
                raise TrajectoryRangeError("no trajectory recorded yet")
            start = ring_start(self._next, n, cap)
            v0 = max(ring_search(self._t_s, start, n, t_lo, "right") - 1, 0)
            v1 = min(max(ring_search(self._t_s, start, n, t_hi, "left") + 1, v0 + 2), n)
            v0 = max(min(v0, v1 - 2), 0)
            idx = ring_indices(start, v0, v1, cap)
            oldest = float(self._t_s[start])
            newest = float(self._t_s[(start + n - 1) % cap])
            return self._t_s[idx], self._q_deg[idx], oldest, newest

    def q_deg_at(self, t_s: np.ndarray, *, hold_s: float = 0.01) -> np.ndarray:
        """Joint angles at times ``t_s`` (m,) s, linearly interpolated between samples -> (m, 6) deg.

        Times up to ``hold_s`` after the newest sample get the newest sample (the arm moves little
        within one cycle); earlier than the oldest or later than that raises TrajectoryRangeError.
        """
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        if t.size == 0:
            with self._lock:
                if self._count == 0:
                    raise TrajectoryRangeError("no trajectory recorded yet")
            return np.zeros((0, self._q_deg.shape[1]))
        ts, qs, oldest, newest = self._window(float(t.min()), float(t.max()))
        if t.min() < oldest or t.max() > newest + hold_s:
            raise TrajectoryRangeError(
                f"times [{t.min():.6f}, {t.max():.6f}] s outside the record [{oldest:.6f}, {newest:.6f}] s"
            )
        if ts.shape[0] == 1:
            return np.repeat(qs, t.shape[0], axis=0)
        tc = np.minimum(t, ts[-1])
        i = np.clip(np.searchsorted(ts, tc, side="right") - 1, 0, ts.shape[0] - 2)
        span = ts[i + 1] - ts[i]
        w = np.divide(tc - ts[i], span, out=np.zeros_like(tc), where=span > 0)[:, None]
        return qs[i] * (1.0 - w) + qs[i + 1] * w

    def newest(self, k: int = 2) -> tuple[np.ndarray, np.ndarray]:
        """Copies of the newest ``k`` samples (fewer when fewer are kept), oldest first."""
        with self._lock:
            n = min(k, self._count)
            idx = ring_indices(
                ring_start(self._next, self._count, self.capacity),
                self._count - n,
                self._count,
                self.capacity,
            )
            return self._t_s[idx], self._q_deg[idx]

    def q_deg_continued(self, t_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Like :meth:`q_deg_at`, but times after the newest sample continue the arm's last joint
        velocity instead of failing (the sensor simulator's clock ran ahead of a controller cycle
        that fell behind on a loaded machine). Returns (q (m, 6) deg, late (m,) bool)."""
        t = np.atleast_1d(np.asarray(t_s, dtype=np.float64))
        ts, qs = self.newest(2)
        late = t > ts[-1] if ts.shape[0] else np.zeros(t.shape, dtype=bool)
        if ts.shape[0] < 2 or not late.any():
            return self.q_deg_at(t), np.zeros(t.shape, dtype=bool)
        q = np.empty((t.shape[0], qs.shape[1]))
        if (~late).any():
            q[~late] = self.q_deg_at(t[~late])
        v = (qs[-1] - qs[-2]) / max(ts[-1] - ts[-2], 1e-6)
        q[late] = qs[-1] + v * (t[late] - ts[-1])[:, None]
        return q, late

    def T_base_frame_at(
        self, t_s: np.ndarray, T_flange_tool: np.ndarray | None = None, track: LinearTrack | None = None
    ) -> np.ndarray:
        """Poses at times ``t_s`` (m,): (m, 4, 4), mm, of the flange or of ``T_flange_tool``'s frame
        (in the world frame when the record holds ``axes_mm_deg`` of a robot on ``track``)."""
        return fk_batch(self.q_deg_at(t_s), T_flange_tool, track=track)


# ---------------------------------------------------------------------------------------------
# the simulator


@dataclass
class EgmSimStats:
    """Counters of the simulated controller."""

    cycles: int = 0
    sent: int = 0
    dropped: int = 0
    silenced: int = 0
    duplicated: int = 0
    reordered: int = 0
    corrupted: int = 0
    sensor_received: int = 0
    sensor_malformed: int = 0
    sensor_ignored: int = 0
    sensor_dropped: int = 0
    sessions: int = 0
    overruns: int = 0


class EgmControllerSim(asyncio.DatagramProtocol):
    """The simulated controller's EGM side. ``await start()`` begins the cycle; ``await stop()`` ends it.

    Args:
        config: addresses, cycle, defaults of the EGM arguments.
        faults: initial wire faults (change them at run time with :meth:`set_faults`).
        model: the shared controller state (RWS side); None runs standalone.
        clock: the true time base in seconds (``time.monotonic`` by default); trajectory samples are
            stamped with it.
        kinematics: for the cartesian feedback (a new :class:`RobotKinematics` by default).
    """

    def __init__(
        self,
        config: EgmSimConfig | None = None,
        *,
        faults: EgmFaults | None = None,
        model: ControllerModelLike | None = None,
        clock: Callable[[], float] = time.monotonic,
        kinematics: RobotKinematics | None = None,
    ) -> None:
        self.config = cfg = config or EgmSimConfig()
        if cfg.cycle_s <= 0 or not math.isfinite(cfg.cycle_s):
            raise ValueError(f"cycle_s must be > 0, got {cfg.cycle_s}")
        if cfg.guidance_mode not in ("joint", "pose"):
            raise ValueError(f"guidance_mode must be 'joint' or 'pose', got {cfg.guidance_mode!r}")
        self.faults = faults or EgmFaults()
        self.model = model
        self.clock = clock
        self.kin = kinematics or RobotKinematics(track=cfg.track)
        if self.kin.track is not cfg.track:
            raise ValueError("the kinematics must be built with the configured track")
        #: values in the state: the six joints, or the track (mm) and the six joints (``axes_mm_deg``)
        self.n_axes = self.kin.n_axes
        self._n_ext = self.n_axes - 6
        self.stats = EgmSimStats()
        self.trajectory = TrajectoryRecorder(cfg.history_capacity, self.n_axes)
        # the same limits for every axis of the motion group (a track's in mm and mm/s)
        self.q_min_deg, self.q_max_deg = self.kin.q_min_deg.copy(), self.kin.q_max_deg.copy()
        self.qd_max_deg_s = self.kin.qd_max_deg_s.copy()
        q0 = np.array(cfg.q_start_deg, dtype=np.float64)
        if q0.shape != (6,):
            raise ValueError(f"q_start_deg must have 6 values, got {q0.shape}")
        if cfg.track is not None:
            if not cfg.track.travel_min_mm <= cfg.track_start_mm <= cfg.track.travel_max_mm:
                raise ValueError(f"track_start_mm {cfg.track_start_mm} is outside the track's travel")
            q0 = np.concatenate([[cfg.track_start_mm], q0])
        self._q_deg = q0.copy()
        self._v_deg_s = np.zeros(self.n_axes)  # filtered axis speed
        self._utilization = 0.0
        self._ctrl_offset_s = 0.0
        self._clock_minus_loop_s = 0.0
        self._ref_q_deg = q0.copy()
        self._speed_ref_deg_s = np.zeros(self.n_axes)
        self._rng = np.random.default_rng(cfg.seed)
        # standalone knobs (ignored when a model is attached)
        self.motors_on = True
        self.egm_enabled = True
        # session state
        self._running = False
        self._mci = MciState.STOPPED
        self._seqno = 0
        self._cycle_count = 0
        self._move_index = 0
        self._session_t0 = 0.0
        self._session_q0 = q0.copy()
        self._last_sensor_t = 0.0
        self._converged_since: float | None = None
        self._wanted_seen_false = True  # a session only (re)starts after EGM was not wanted
        self._params: dict[str, float] = {}
        self._newest_sensor: SensorMessage | None = None
        self._malformed_logged = -1e9
        # wire
        self._transport: asyncio.DatagramTransport | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._timer: asyncio.TimerHandle | None = None
        self._deadline = 0.0
        self._burst_until = -1.0
        self._held: bytes | None = None
        self._pending: set[asyncio.TimerHandle] = set()
        # reply latency probe: send time of each seqno (monotonic; the kernel's CLOCK_REALTIME receive
        # stamps are carried onto it), latency of each matched reply in user space and kernel time
        self._send_t_ns = np.zeros(4096, dtype=np.int64)
        self._send_seq = np.full(4096, -1, dtype=np.int64)
        self._latency_us = np.zeros(cfg.latency_capacity)
        self._latency_missed = np.zeros(cfg.latency_capacity, dtype=bool)
        self._latency_kernel_us = np.full(cfg.latency_capacity, np.nan)
        self._latency_kernel_missed = np.zeros(cfg.latency_capacity, dtype=bool)
        self._latency_sent_ns = np.zeros(cfg.latency_capacity, dtype=np.int64)
        self._latency_n = 0
        self._kernel_stamps = False
        self._late_us = np.zeros(4096)
        self._late_n = 0
        self.ended_sessions: list[tuple[str, int | None]] = []
        if model is not None:
            model.set_position_source(self.position)
            if cfg.track is not None:
                model.set_external_axes_source(self.external_axes)

    # ---- lifecycle ----------------------------------------------------------------------------

    async def start(self) -> tuple[str, int]:
        """Open the UDP socket and start the cycle; returns the controller's local address."""
        if self._transport is not None:
            raise RuntimeError("simulator already started")
        loop = asyncio.get_running_loop()
        self._loop = loop
        await loop.create_datagram_endpoint(
            lambda: self, local_addr=(self.config.local_host, self.config.local_port)
        )
        self._ctrl_offset_s = (
            self.config.ctrl_clock_offset_s
            if self.config.ctrl_clock_offset_s is not None
            else time.time() - self.clock()
        )
        # One offset, measured once: the true clock must run at the rate of the loop's clock (real
        # time). Re-reading both clocks every cycle would put read jitter into the sample times.
        self._clock_minus_loop_s = self.clock() - loop.time()
        self._kernel_stamps = self._enable_kernel_rx_stamps()
        self._deadline = loop.time() + self.config.cycle_s
        self._timer = loop.call_at(self._deadline, self._tick)
        addr = self.local_address
        log.info(
            "egm_sim_started",
            host=addr[0],
            port=addr[1],
            sensor=f"{self.config.sensor_host}:{self.config.sensor_port}",
            cycle_ms=self.config.cycle_s * 1e3,
        )
        return addr

    async def stop(self) -> None:
        """Stop the cycle and close the socket (pending delayed packets are discarded)."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        for h in list(self._pending):
            h.cancel()
        self._pending.clear()
        if self._transport is not None:
            self._transport.close()
            self._transport = None
            log.info("egm_sim_stopped", **dataclasses.asdict(self.stats))

    @property
    def local_address(self) -> tuple[str, int]:
        """(host, port) the controller sends from."""
        if self._transport is None:
            raise RuntimeError("simulator not started")
        return self._transport.get_extra_info("sockname")[:2]

    # ---- knobs and state ----------------------------------------------------------------------

    def set_faults(self, **changes: Any) -> EgmFaults:
        """Change fault knobs at run time, e.g. ``set_faults(loss_fraction=0.1, burst_ms=20)``.

        Raises:
            FaultError: an unknown knob or a value out of range.
        """
        known = {f.name for f in dataclasses.fields(EgmFaults)}
        unknown = set(changes) - known
        if unknown:
            raise FaultError(f"unknown fault knob(s) {sorted(unknown)}; known: {sorted(known)}")
        self.faults = dataclasses.replace(self.faults, **changes)
        log.info("egm_sim_faults", **{k: v for k, v in dataclasses.asdict(self.faults).items() if v})
        return self.faults

    @property
    def q_deg(self) -> np.ndarray:
        """Current true joint angles (6,) deg (the arm's; the track's position is in ``axes_mm_deg``)."""
        return self._q_deg[self._n_ext :].copy()

    @property
    def axes_mm_deg(self) -> np.ndarray:
        """Current true state of every axis: (6,) deg, or (7,) track mm then joints deg."""
        return self._q_deg.copy()

    @property
    def reference_q_deg(self) -> np.ndarray:
        """The reference the controller is following, every axis ((6,) or (7,) like ``axes_mm_deg``)."""
        return self._ref_q_deg.copy()

    @property
    def mci_state(self) -> MciState:
        """EGM state as reported in ``EgmRobot.mciState``."""
        return self._mci

    @property
    def session_running(self) -> bool:
        """True while an EGM session (EGMRunJoint) is active."""
        return self._running

    def position(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(q_deg (6,), flange pos_mm (3,), quat_wxyz (4,)) for RWS position reads (the flange in the
        world frame with a track)."""
        pose = self.kin.fk(self._q_deg)
        return self._q_deg[self._n_ext :].copy(), pose.pos_mm, pose.quat_wxyz

    def external_axes(self) -> np.ndarray:
        """The six external axes for RWS position reads (``eax_a..eax_f``): the track's position (mm) in
        the first, 9E9 (unused) in the others; all unused without a track."""
        ext = np.full(6, EXTAX_UNUSED)
        ext[: self._n_ext] = self._q_deg[: self._n_ext]
        return ext

    def reply_latency(self, *, kernel: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Measured reply latencies: ``latency_us`` (n,) from our send of EgmRobot k (stamped right at the
        socket call) to the arrival of the reply with seqno k, and ``missed`` (n,) bool, True where it
        arrived after the next send.

        ``kernel=False``: arrival is when this simulator read the reply (user space, so its own wake-up
        is included). ``kernel=True``: arrival is the kernel's receive stamp of the reply's datagram
        (loopback: the moment the sensor's ``sendto`` handed it over), NaN where none was available.
        """
        n = min(self._latency_n, self._latency_us.shape[0])
        if kernel:
            return self._latency_kernel_us[:n].copy(), self._latency_kernel_missed[:n].copy()
        return self._latency_us[:n].copy(), self._latency_missed[:n].copy()

    def reply_sent_ns(self) -> np.ndarray:
        """When each of :meth:`reply_latency`'s samples was sent (the EgmRobot's send, monotonic ns)."""
        n = min(self._latency_n, self._latency_us.shape[0])
        return self._latency_sent_ns[:n].copy()

    @property
    def kernel_rx_stamps(self) -> bool:
        """True when the kernel stamps received replies (Linux), so ``reply_latency(kernel=True)`` has data."""
        return self._kernel_stamps

    def reset_reply_latency(self) -> None:
        """Forget the latency samples (e.g. after a warm-up)."""
        self._latency_n = 0

    def tick_lateness_us(self) -> np.ndarray:
        """How late the recent cycles started after their deadline, us (timer precision)."""
        n = min(self._late_n, self._late_us.shape[0])
        return self._late_us[:n].copy()

    # ---- the cycle ----------------------------------------------------------------------------

    def _inputs(self) -> tuple[bool, bool, bool, dict[str, float]]:
        """(motors_on, rapid_running, egm_wanted, EGM arguments) from the model or standalone knobs."""
        cfg = self.config
        params = {
            "comm_timeout_s": cfg.comm_timeout_s,
            "pos_corr_gain": cfg.pos_corr_gain,
            "max_speed_deviation_deg_s": cfg.max_speed_deviation_deg_s,
            "max_pos_deviation_deg": cfg.max_pos_deviation_deg,
            "cond_time_s": cfg.cond_time_s,
            "ramp_in_time_s": cfg.ramp_in_time_s,
            "lp_filter_hz": cfg.lp_filter_hz,
            "sample_rate_ms": 4.0,
        }
        m = self.model
        if m is None:
            return self.motors_on, self.egm_enabled, self.motors_on and self.egm_enabled, params
        p = m.egm_params
        if p is not None:
            params.update(
                comm_timeout_s=p.comm_timeout_s,
                pos_corr_gain=p.pos_corr_gain,
                max_speed_deviation_deg_s=p.max_speed_deviation_dps,
                max_pos_deviation_deg=p.max_pos_deviation_deg,
                cond_time_s=p.cond_time_s,
                ramp_in_time_s=p.ramp_in_time_s,
                lp_filter_hz=p.lp_filter_hz,
                sample_rate_ms=p.sample_rate_ms,
            )
        return m.ctrl_state == "motoron", m.rapid_state == "running", bool(m.egm_wanted), params

    def _tick(self) -> None:
        loop = self._loop
        if loop is None or self._transport is None:
            return
        cfg = self.config
        now_loop = loop.time()
        late_s = now_loop - self._deadline
        self._late_us[self._late_n % self._late_us.shape[0]] = late_s * 1e6
        self._late_n += 1
        # A stalled loop must not make the arm stop in time: integrate every missed cycle, send once.
        steps = 1 + max(0, int(late_s // cfg.cycle_s))
        if steps > 1:
            self.stats.overruns += steps - 1
        # The servo samples at the deadline, whenever the loop got round to it; on the true time base.
        t_true = self._deadline + (steps - 1) * cfg.cycle_s + self._clock_minus_loop_s
        try:
            self._cycle(t_true, steps)
        except Exception:  # the controller keeps its cycle whatever one step did
            log.exception("egm_sim_cycle_failed")
        self._deadline += steps * cfg.cycle_s
        self._timer = loop.call_at(self._deadline, self._tick)

    def _cycle(self, t_true: float, steps: int) -> None:
        cfg = self.config
        dt = cfg.cycle_s
        motors_on, rapid_running, wanted, params = self._inputs()
        self._params = params
        if not wanted:
            self._wanted_seen_false = True
        if self._running and not wanted:
            self._end_session("EGM no longer wanted (program stopped, motors off or end requested)", None)
        elif not self._running and wanted and self._wanted_seen_false:
            self._start_session(t_true)
        if not motors_on:
            # motors off / guard stop / e-stop: brakes, the arm stops hard
            self._v_deg_s[:] = 0.0
        # Per cycle, as the manual describes it (p.26): sample the feedback, send it, then read the
        # newest reference and move for one cycle. Only the last of several overdue cycles sends.
        # The trajectory gets the position at the end of the cycle at once: the motion over the
        # cycle is fixed when the cycle starts, and readers then rarely ask beyond the newest sample.
        if self._running and steps > 1:
            # The simulator's own stall (its process not scheduled on a loaded machine) sent no
            # feedback for those cycles, and a sensor cannot answer packets it never got: the stall
            # does not count toward the communication timeout (a real controller does not stall).
            self._last_sensor_t += (steps - 1) * dt
        send_due = False
        for k in range(steps):
            t_k = t_true - (steps - 1 - k) * dt
            if len(self.trajectory) == 0:
                self.trajectory.append(t_k, self._q_deg)
            # \SampleRate is a multiple of 4 ms: a session sends every n-th servo cycle
            every = max(1, round(params["sample_rate_ms"] / 4.0)) if self._running else 1
            self._cycle_count += 1
            send_due = send_due or self._cycle_count % every == 0
            if k == steps - 1 and (self._running or cfg.stream_when_idle) and send_due:
                self._send_robot(t_k, motors_on, rapid_running)
            if self._running:
                self._apply_newest_sensor()
                if self._running:
                    self._check_comm_timeout(t_k)
            if self._running and motors_on:
                self._integrate(dt, t_k, params)
            elif motors_on:
                # outside a session the arm settles: commanded speed 0 through the same filter
                self._filter_and_move(np.zeros(self.n_axes), dt, params["lp_filter_hz"])
            self.trajectory.append(t_k + dt, self._q_deg)
        self.stats.cycles += steps

    def _start_session(self, t: float) -> None:
        self._running = True
        self._wanted_seen_false = False
        self._mci = MciState.RUNNING
        self._seqno = 0
        self._move_index += 1
        self._cycle_count = -1  # the first cycle of a session sends
        self._session_t0 = t
        self._session_q0 = self._q_deg.copy()
        self._ref_q_deg = self._q_deg.copy()
        self._speed_ref_deg_s = np.zeros(self.n_axes)
        self._last_sensor_t = t
        self._converged_since = None
        self._newest_sensor = None
        self.stats.sessions += 1
        log.info("egm_sim_session_started", session=self.stats.sessions, q_deg=self._q_deg.round(3).tolist())

    def _end_session(self, reason: str, event_code: int | None, *, error: bool = False) -> None:
        self._running = False
        self._mci = MciState.ERROR if error else MciState.STOPPED
        self._speed_ref_deg_s = np.zeros(self.n_axes)
        self.ended_sessions.append((reason, event_code))
        log.info("egm_sim_session_ended", reason=reason, event_code=event_code, error=error)
        if event_code is not None or reason.startswith("convergence"):
            if self.model is not None:
                self.model.egm_session_ended(reason, event_code)
            else:
                self.egm_enabled = False  # standalone: the RAPID program would leave EGMRunJoint

    def _apply_newest_sensor(self) -> None:
        msg = self._newest_sensor
        if msg is None:
            return  # hold the last reference, as the controller does
        self._newest_sensor = None
        if self.config.guidance_mode == "joint":
            if msg.planned_q_deg is None or msg.planned_q_deg.shape[0] < 6:
                self.stats.sensor_ignored += 1
                return
            ref = msg.planned_q_deg[:6]
            if self._n_ext:
                ext = msg.planned_external_joints
                if ext is None or ext.shape[0] < self._n_ext:
                    self.stats.sensor_ignored += 1
                    return
                ref = np.concatenate([ext[: self._n_ext], ref])
        else:
            if msg.planned_pos_mm is None:
                self.stats.sensor_ignored += 1
                return
            ref = self._pose_to_joints(msg)
            if ref is None:
                return
        speed = (
            msg.speed_ref_q_deg_s[:6]
            if msg.speed_ref_q_deg_s is not None and msg.speed_ref_q_deg_s.shape[0] >= 6
            else np.zeros(6)
        )
        if self._n_ext:
            ext_v = msg.speed_ref_external_joints
            ok = ext_v is not None and ext_v.shape[0] >= self._n_ext
            speed = np.concatenate([ext_v[: self._n_ext] if ok else np.zeros(self._n_ext), speed])
        if np.any(ref < self.q_min_deg) or np.any(ref > self.q_max_deg):
            bad = np.flatnonzero((ref < self.q_min_deg) | (ref > self.q_max_deg))
            names = ["track" if i < self._n_ext else int(i - self._n_ext + 1) for i in bad]
            self._end_session(
                f"reference outside the axis limits on axis {names}: {ref[bad].round(3).tolist()}",
                EVENT_EGM_JOINT_LIMIT,
                error=True,
            )
            return
        dev = np.abs(ref - self._session_q0)
        if np.any(dev > self._params["max_pos_deviation_deg"]):
            self._end_session(
                f"reference deviates {dev.max():.1f} deg from the start point "
                f"(MaxPosDeviation {self._params['max_pos_deviation_deg']})",
                EVENT_EGM_POS_DEVIATION,
                error=True,
            )
            return
        self._ref_q_deg = ref.copy()
        self._speed_ref_deg_s = speed.copy()

    def _pose_to_joints(self, msg: SensorMessage) -> np.ndarray | None:
        from drivers.abb_egm.kinematics import matrix_from_quat_wxyz  # local: pose mode is rare

        # with a track the solver holds the carriage at the reference's position (the pose is the flange's)
        T = np.eye(4)
        T[:3, 3] = msg.planned_pos_mm
        if msg.planned_euler_deg is not None:  # Euler wins over the quaternion (proto comment)
            rx, ry, rz = np.deg2rad(msg.planned_euler_deg)
            cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
            T[:3, :3] = np.array(
                [
                    [cy * cz, sx * sy * cz - cx * sz, cx * sy * cz + sx * sz],
                    [cy * sz, sx * sy * sz + cx * cz, cx * sy * sz - sx * cz],
                    [-sy, sx * cy, cx * cy],
                ]
            )
        elif msg.planned_quat_wxyz is not None:
            T[:3, :3] = matrix_from_quat_wxyz(msg.planned_quat_wxyz)
        else:
            T[:3, :3] = self.kin.fk(self._ref_q_deg).T_base_frame[:3, :3]
        result = self.kin.ik(T, self._ref_q_deg, max_iterations=50)
        if not result.converged:
            self._end_session(
                f"pose reference not reachable (residual {result.pos_err_mm:.2f} mm, {result.rot_err_deg:.3f} deg)",
                EVENT_EGM_POSE_UNREACHABLE,
                error=True,
            )
            return None
        return result.q_deg

    def _check_comm_timeout(self, t: float) -> None:
        if t - self._last_sensor_t > self._params["comm_timeout_s"]:
            self._end_session(
                f"no data from the UdpUc device for {t - self._last_sensor_t:.3f} s", EVENT_EGM_COMM_TIMEOUT
            )

    def _integrate(self, dt: float, t: float, params: dict[str, float]) -> None:
        k = params["pos_corr_gain"] * self.config.default_gain
        ramp = params["ramp_in_time_s"]
        if ramp > 0:
            k *= min(1.0, (t - self._session_t0) / ramp)
        err = self._ref_q_deg - self._q_deg
        v_cmd = k * err + self._speed_ref_deg_s
        worst = float(np.max(np.abs(v_cmd)))
        if worst > params["max_speed_deviation_deg_s"]:
            axis = self._axis_name(int(np.argmax(np.abs(v_cmd))))
            self._end_session(
                f"speed deviation {worst:.1f} deg/s on {axis} above MaxSpeedDeviation "
                f"{params['max_speed_deviation_deg_s']:.1f} deg/s",
                EVENT_EGM_SPEED_DEVIATION,
                error=True,
            )
            self._filter_and_move(np.zeros(self.n_axes), dt, params["lp_filter_hz"])
            return
        self._filter_and_move(v_cmd, dt, params["lp_filter_hz"])
        if np.all(np.abs(self._ref_q_deg - self._q_deg) < self.config.convergence_deg):
            if self._converged_since is None:
                self._converged_since = t
            elif t - self._converged_since >= params["cond_time_s"]:
                self._end_session("convergence met for CondTime", None)
        else:
            self._converged_since = None

    def _filter_and_move(self, v_cmd_deg_s: np.ndarray, dt: float, lp_hz: float) -> None:
        # first-order low pass, exact discretisation of a 1/(1 + s/(2 pi f)) filter
        alpha = 1.0 - math.exp(-2.0 * math.pi * lp_hz * dt) if lp_hz > 0 else 1.0
        self._v_deg_s += alpha * (v_cmd_deg_s - self._v_deg_s)
        self._utilization = float(np.max(np.abs(self._v_deg_s) / self.qd_max_deg_s)) * 100.0
        np.clip(self._v_deg_s, -self.qd_max_deg_s, self.qd_max_deg_s, out=self._v_deg_s)
        q = self._q_deg + self._v_deg_s * dt
        # the servo stops at the axis limits; speed into a limit is dropped
        at_limit = (q <= self.q_min_deg) | (q >= self.q_max_deg)
        self._v_deg_s[at_limit] = 0.0
        self._q_deg = np.clip(q, self.q_min_deg, self.q_max_deg)

    def _axis_name(self, i: int) -> str:
        """Name of state index ``i``: ``track`` or ``axis k`` (1-based arm joint, as the controller says)."""
        return "track" if i < self._n_ext else f"axis {i - self._n_ext + 1}"

    def _send_robot(self, t_true: float, motors_on: bool, rapid_running: bool) -> None:
        pose = self.kin.fk(self._q_deg)
        n = self._n_ext
        t_ctrl_us = round((t_true + self._ctrl_offset_s) * 1e6)
        msg = RobotMessage(
            seqno=self._seqno,
            tm_ms=(t_ctrl_us // 1000) % _U32,
            mtype=MessageType.DATA,
            feedback_q_deg=self._q_deg[n:],
            feedback_pos_mm=pose.pos_mm,
            feedback_quat_wxyz=pose.quat_wxyz,
            feedback_time_us=t_ctrl_us,
            planned_q_deg=self._ref_q_deg[n:],
            planned_time_us=t_ctrl_us,
            motor_state=MotorState.ON if motors_on else MotorState.OFF,
            mci_state=self._mci,
            mci_convergence_met=self._converged_since is not None,
            rapid_exec_state=RapidState.RUNNING if rapid_running else RapidState.STOPPED,
            utilization_pct=self._utilization,
            move_index=self._move_index,
            feedback_external_joints=self._q_deg[:n] if n else None,
            planned_external_joints=self._ref_q_deg[:n] if n else None,
        )
        payload = encode_robot(msg)
        seqno = self._seqno
        self._seqno = (self._seqno + 1) % _U32
        self._emit(payload, seqno)

    # ---- wire and faults ----------------------------------------------------------------------

    def _loss_start_probability(self) -> float:
        """Per packet: the chance to start a loss (a burst of ``n`` packets when ``burst_ms`` > 0),
        chosen so that ``loss_fraction`` of the packets are lost overall: f = p n / (1 - p + p n)."""
        f = self.faults
        n = max(1.0, f.burst_ms / 1000.0 / self.config.cycle_s) if f.burst_ms > 0 else 1.0
        frac = min(f.loss_fraction, 0.999)
        return frac / (n - frac * (n - 1.0))

    def _emit(self, payload: bytes, seqno: int) -> None:
        f = self.faults
        if f.stop_sending:
            self.stats.silenced += 1
            return
        rng = self._rng
        now = self.clock()
        if now < self._burst_until:
            self.stats.dropped += 1
            return
        if f.loss_fraction > 0 and rng.random() < self._loss_start_probability():
            self.stats.dropped += 1
            if f.burst_ms > 0:
                self._burst_until = now + f.burst_ms / 1000.0
            return
        # The latency probe counts from the controller's send, before any injected network delay;
        # an undelayed first copy is stamped again right at its socket call below.
        slot = seqno % self._send_t_ns.shape[0]
        self._stamp_send(slot)
        self._send_seq[slot] = seqno
        if f.corrupt_fraction > 0 and rng.random() < f.corrupt_fraction:
            payload = self._corrupt(payload)
            self.stats.corrupted += 1
        if f.reorder_fraction > 0 and self._held is None and rng.random() < f.reorder_fraction:
            # hold this one back; it goes out right after the next packet
            self._held = payload
            self.stats.reordered += 1
            return
        copies = 1
        if f.duplicate_fraction > 0 and rng.random() < f.duplicate_fraction:
            copies = 2
            self.stats.duplicated += 1
        out = [payload] * copies
        if self._held is not None:
            out.append(self._held)
            self._held = None
        stamp: int | None = slot
        for p in out:
            delay_s = (f.delay_ms + (rng.random() * f.jitter_ms if f.jitter_ms > 0 else 0.0)) / 1000.0
            if delay_s > 0 and self._loop is not None:
                self._send_after(delay_s, p)
            else:
                self._sendto(p, stamp if p is payload else None)
            if p is payload:
                stamp = None  # a duplicate is not the send the probe measures from

    def _stamp_send(self, slot: int) -> None:
        self._send_t_ns[slot] = time.monotonic_ns()

    def _send_after(self, delay_s: float, payload: bytes) -> None:
        assert self._loop is not None
        holder: list[asyncio.TimerHandle] = []

        def fire() -> None:
            self._pending.discard(holder[0])
            self._sendto(payload)

        holder.append(self._loop.call_later(delay_s, fire))
        self._pending.add(holder[0])

    def _corrupt(self, payload: bytes) -> bytes:
        b = bytearray(payload)
        n = int(self._rng.integers(1, 5))
        for i in self._rng.integers(0, len(b), size=n):
            b[i] ^= int(self._rng.integers(1, 256))
        return bytes(b)

    def _sendto(self, payload: bytes, stamp_slot: int | None = None) -> None:
        if self._transport is None:
            return
        if stamp_slot is not None:
            self._stamp_send(stamp_slot)
        try:
            self._transport.sendto(payload, (self.config.sensor_host, self.config.sensor_port))
        except OSError as exc:
            log.warning("egm_sim_send_failed", error=str(exc))
            return
        self.stats.sent += 1

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self._transport = transport  # type: ignore[assignment]

    def error_received(self, exc: Exception) -> None:
        # ICMP "port unreachable" while no sensor listens: normal during start-up, keep cycling
        pass

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        t_rx_ns = time.monotonic_ns()
        t_krx_ns = self._kernel_rx_stamp_ns()
        f = self.faults
        if f.rx_loss_fraction > 0 and self._rng.random() < f.rx_loss_fraction:
            self.stats.sensor_dropped += 1
            return
        try:
            msg = decode_sensor(data)
        except EgmDecodeError as exc:
            self.stats.sensor_malformed += 1
            now = self.clock()
            if now - self._malformed_logged >= 1.0:
                self._malformed_logged = now
                log.warning(
                    "egm_sim_malformed_sensor_packet", error=str(exc), total=self.stats.sensor_malformed
                )
            return
        self.stats.sensor_received += 1
        self._probe_latency(msg.seqno, t_rx_ns, t_krx_ns)
        if not self._running:
            self.stats.sensor_ignored += 1
            return
        # the controller reads the newest message of the cycle; older ones are superseded
        self._newest_sensor = msg
        self._last_sensor_t = self.clock()

    def _enable_kernel_rx_stamps(self) -> bool:
        # The first SIOCGSTAMPNS switches the socket's receive stamps on (it answers ENOENT because
        # nothing was stamped yet); from then on the kernel keeps the stamp of the last datagram read.
        # The ioctl rather than SO_TIMESTAMPNS + recvmsg: the asyncio transport reads with recvfrom,
        # which drops ancillary data, and the stamp is the same skb receive time either way.
        sock = None if self._transport is None else self._transport.get_extra_info("socket")
        if sock is None:
            return False
        try:
            fcntl.ioctl(sock.fileno(), _SIOCGSTAMPNS, bytes(16))
        except FileNotFoundError:
            return True
        except OSError as exc:
            log.info("egm_sim_kernel_stamps_unavailable", error=str(exc))
            return False
        return True

    def _kernel_rx_stamp_ns(self) -> int | None:
        """The kernel's receive stamp of the datagram just read, on the monotonic clock (ns), or None.

        The kernel stamps in CLOCK_REALTIME; the send stamps and the user-space reads are monotonic.
        The stamp is carried over by the realtime-minus-monotonic offset read now, so every latency
        is a difference on one clock (a realtime clock slewed or stepped between a send and its
        reply would otherwise make a kernel latency longer than the user-space one)."""
        if not self._kernel_stamps or self._transport is None:
            return None
        sock = self._transport.get_extra_info("socket")
        try:
            sec, nsec = struct.unpack("qq", fcntl.ioctl(sock.fileno(), _SIOCGSTAMPNS, bytes(16)))
        except OSError:
            return None
        m0 = time.monotonic_ns()
        real = time.time_ns()
        m1 = time.monotonic_ns()
        return sec * 1_000_000_000 + nsec - real + (m0 + m1) // 2

    def _probe_latency(self, seqno: int | None, t_rx_ns: int, t_krx_ns: int | None = None) -> None:
        if seqno is None:
            return
        slot = seqno % self._send_t_ns.shape[0]
        if self._send_seq[slot] != seqno:
            return
        latency_us = (t_rx_ns - self._send_t_ns[slot]) / 1000.0
        i = self._latency_n % self._latency_us.shape[0]
        self._latency_us[i] = latency_us
        self._latency_sent_ns[i] = self._send_t_ns[slot]
        # missed: the next EgmRobot had already gone out when the reply came
        nxt = (seqno + 1) % self._send_t_ns.shape[0]
        next_sent = bool(self._send_seq[nxt] == (seqno + 1) % _U32)
        self._latency_missed[i] = next_sent and self._send_t_ns[nxt] <= t_rx_ns
        if t_krx_ns is None:
            self._latency_kernel_us[i] = np.nan
            self._latency_kernel_missed[i] = self._latency_missed[i]
        else:
            self._latency_kernel_us[i] = (t_krx_ns - self._send_t_ns[slot]) / 1000.0
            self._latency_kernel_missed[i] = next_sent and self._send_t_ns[nxt] <= t_krx_ns
        self._send_seq[slot] = -1  # a duplicate reply is not a second sample
        self._latency_n += 1
