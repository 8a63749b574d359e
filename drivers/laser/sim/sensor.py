"""HD8 sensor simulator: speaks the HD8 profile protocol over TCP and ray-casts a scene.

It is part of the product (commissioning, training, CI), not a test fake: the client cannot tell it
from a real sensor-side shim, because both sides share :mod:`drivers.laser.protocol`.

What it models (see docs/hd8-protocol.md for which parts are documented HD8 behaviour):

* acquisition at the configured rate; each frame's mid-exposure true time ``t_true_s`` is fed to
  ``pose_at`` for the sensor pose ``T_world_sensor``, then the laser fan is ray-cast onto the scene
  (:mod:`drivers.laser.sim.optics`): depth noise, missing returns at grazing incidence and out of range,
  sparse outliers;
* the sensor's own clock: ``sensor_time_us = offset + (t_true - t_epoch) * (1 + drift_ppm * 1e-6)``
  and the HD8's 32-bit millisecond counter derived from it (configurable start, so it can wrap);
* a ring buffer of recent frames, replayed on a SUBSCRIBE with a start frame (no loss on reconnect);
* fault knobs at run time: disconnect after N frames, corrupt frames (framing intact or broken),
  stall, timestamp jump, dropped frames.

Run stand-alone with ``python -m drivers.laser.sim`` (a static plane or step under a fixed pose).
"""

from __future__ import annotations

import argparse
import asyncio
import collections
import concurrent.futures
import contextlib
import dataclasses
import json
import math
import multiprocessing
import signal
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import structlog
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from drivers.laser import protocol as P
from drivers.laser.sim.optics import LaserOptics, render_points, render_uniform
from drivers.laser.sim.scene import Scene, SceneRaycaster, plane_scene, step_scene
from drivers.runtime import RateLimitedLog
from drivers.sim.fault_channel import start_fault_server

__all__ = ["LaserSimulator", "PoseFn", "SimConfig", "SimFaults", "SimStats", "fixed_pose", "main"]

log = structlog.get_logger(__name__)

#: spacing of the jitter-delayed sends that would otherwise share one time (keeps their order)
_SEND_ORDER_STEP_S = 1e-6

#: ``pose_at(t_true_s (n,) float64 s) -> (n, 4, 4) T_world_sensor in mm``. Called in the event loop.
PoseFn = Callable[[np.ndarray], np.ndarray]


class SimConfig(BaseModel):
    """Configuration of the simulated HD8 (defaults: HD8-0050W-like, see docs/hd8-protocol.md)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    model: str = "HD8-0050W-SIM"
    serial: str = "SIM-0000001"
    width: int = Field(500, gt=1, le=P.MAX_WIDTH)
    x_pitch_mm: float = Field(0.1, gt=0)
    z_min_mm: float = Field(70.0, gt=0)
    z_max_mm: float = Field(130.0, gt=0)
    rate_hz: float = Field(200.0, gt=0)
    max_rate_hz: float = Field(1000.0, gt=0)
    exposure_ns: int = Field(500_000, gt=0)
    min_exposure_ns: int = 100_000
    max_exposure_ns: int = 3_000_000
    profile_format: Literal["uniform", "points"] = "uniform"
    noise_sigma_mm: float = Field(0.02, ge=0)
    outlier_probability: float = Field(1e-4, ge=0, le=1)
    max_incidence_deg: float = Field(80.0, gt=0, le=90)
    #: sensor clock reading at the simulator's construction, us
    clock_offset_us: int = Field(1_000_000, ge=0)
    clock_drift_ppm: float = 0.0
    #: HD8 millisecond counter at construction (set near 2**32 to test the wrap)
    hd8_counter_start_ms: int = Field(0, ge=0, lt=2**32)
    #: stamp sensor_time_us from the 1 ms counter (what a shim around the real HD8 can do)
    sensor_time_from_ms_counter: bool = False
    #: delay from end of exposure to the frame being ready to send
    processing_latency_s: float = Field(0.0005, ge=0)
    #: extra send delay per group, |N(0, sigma)| seconds (order is kept), to make host stamps realistic
    network_jitter_s: float = Field(0.0, ge=0)
    #: frames are sent in groups at most this often (at 200 Hz that is one frame per group)
    group_period_s: float = Field(0.005, gt=0)
    max_group_profiles: int = Field(64, gt=0, le=P.MAX_PROFILES_PER_MESSAGE)
    #: frames kept for replay after a reconnect
    ring_buffer_frames: int = Field(8192, ge=0)
    #: if the producer falls behind by more than this, frames are skipped (status OVERRUN)
    max_backlog_s: float = Field(0.5, gt=0)
    #: per-client send queue; a slower client loses frames beyond it (it sees a frame-index gap)
    client_queue_frames: int = Field(20_000, gt=0)
    z_scale_nm: int = Field(2000, gt=0)
    x_scale_nm_points: int = Field(2000, gt=0)
    #: render in a separate (spawned) process instead of a thread. open3d's ray casting holds the GIL,
    #: so a render thread delays the other coroutines and threads of this process by up to a group's
    #: cast time (about 0.1 ms per profile); a process isolates them, at the cost of 1-2 s start-up.
    #: As with any spawn-based pool, the program's main module must be import-safe
    #: (``if __name__ == "__main__":``).
    render_process: bool = False
    seed: int | None = 0

    @model_validator(mode="after")
    def _consistent(self) -> SimConfig:
        if not self.z_min_mm < self.z_max_mm:
            raise ValueError(f"z_min_mm ({self.z_min_mm}) must be below z_max_mm ({self.z_max_mm})")
        if self.rate_hz > self.max_rate_hz:
            raise ValueError(f"rate_hz ({self.rate_hz}) exceeds max_rate_hz ({self.max_rate_hz})")
        if self.exposure_ns >= 1e9 / self.rate_hz:
            raise ValueError(
                f"exposure_ns ({self.exposure_ns}) does not fit in one period at {self.rate_hz} Hz"
            )
        return self

    def optics(self) -> LaserOptics:
        return LaserOptics(
            width=self.width,
            x_pitch_mm=self.x_pitch_mm,
            z_min_mm=self.z_min_mm,
            z_max_mm=self.z_max_mm,
            noise_sigma_mm=self.noise_sigma_mm,
            outlier_probability=self.outlier_probability,
            max_incidence_deg=self.max_incidence_deg,
        )


@dataclass
class SimFaults:
    """Run-time fault knobs; change them directly or through the simulator's helper methods.

    Attributes:
        disconnect_after_frames: abort every data connection once this many more frames were sent.
        corrupt_groups: corrupt the next this-many frame groups on the wire (the ring keeps them intact).
        corrupt_probability: each frame group is corrupted with this probability.
        corrupt_mode: ``payload`` breaks the profile count (framing intact: the client skips the group);
            ``framing`` breaks the size field (the client must reconnect and resume).
        drop_frames: the next this-many frames are acquired but never sent (a frame-index gap).
        drop_probability: each frame is dropped with this probability.
        stall_until_s: true time until which nothing is sent.
        stall_acquire: during a stall, keep acquiring into the ring buffer (sent afterwards) instead of
            losing the frames.
    """

    disconnect_after_frames: int | None = None
    corrupt_groups: int = 0
    corrupt_probability: float = 0.0
    corrupt_mode: Literal["payload", "framing"] = "payload"
    drop_frames: int = 0
    drop_probability: float = 0.0
    stall_until_s: float = 0.0
    stall_acquire: bool = True


class LaserFaultKnobs(BaseModel):
    """The HD8 simulator's fault knobs on its fault channel; a knob left out stays as it is.

    ``disconnect_after_frames`` (0 disarms), ``corrupt_groups`` (the next groups, in
    ``corrupt_mode``), ``corrupt_probability``, ``drop_frames``, ``drop_probability``, ``stall_s``
    (with ``stall_acquire``), ``clock_jump_us``: see :class:`SimFaults` and the helper methods.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    disconnect_after_frames: int | None = Field(None, ge=0, le=10**9)
    corrupt_groups: int | None = Field(None, ge=0, le=10**9)
    corrupt_mode: Literal["payload", "framing"] = "payload"
    corrupt_probability: float | None = Field(None, ge=0.0, le=1.0)
    drop_frames: int | None = Field(None, ge=0, le=10**9)
    drop_probability: float | None = Field(None, ge=0.0, le=1.0)
    stall_s: float | None = Field(None, ge=0.0, le=600.0, allow_inf_nan=False)
    stall_acquire: bool = True
    clock_jump_us: float | None = Field(None, ge=-1e12, le=1e12, allow_inf_nan=False)


class LaserFaultRequest(BaseModel):
    """A fault-channel request: ``{"laser": {...LaserFaultKnobs...}}``; ``{}`` only reads the state."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    laser: LaserFaultKnobs = LaserFaultKnobs()


@dataclass
class SimStats:
    """Counters of the simulator."""

    frames_acquired: int = 0
    frames_sent: int = 0
    groups_sent: int = 0
    frames_dropped_fault: int = 0
    frames_dropped_slow_client: int = 0
    overrun_frames: int = 0
    malformed_commands: int = 0
    triggers_ignored: int = 0
    data_connections: int = 0
    control_connections: int = 0
    render_s: float = 0.0


@dataclass
class _Settings:
    rate_hz: float
    exposure_ns: int
    fmt: P.ProfileFormat
    trigger: P.TriggerMode = P.TriggerMode.TIME


@dataclass(eq=False)
class _DataClient:
    writer: asyncio.StreamWriter
    queue: collections.deque[tuple[int, bytes]] = field(default_factory=collections.deque)
    queued_frames: int = 0
    wake: asyncio.Event = field(default_factory=asyncio.Event)


def fixed_pose(T_world_sensor: np.ndarray) -> PoseFn:
    """A ``pose_at`` for a sensor that does not move."""
    T = np.asarray(T_world_sensor, dtype=np.float64).reshape(4, 4)

    def pose_at(t_true_s: np.ndarray) -> np.ndarray:
        return np.broadcast_to(T, (len(t_true_s), 4, 4))

    return pose_at


class LaserSimulator:
    """A simulated HD8 on two TCP ports (control and data) of ``host``.

    Args:
        scene: what the sensor looks at, world frame, mm: a :class:`drivers.laser.sim.scene.Scene` or a
            ``(vertices_mm (n, 3), triangles (m, 3))`` pair.
        pose_at: ``pose_at(t_true_s (n,)) -> (n, 4, 4)`` sensor pose ``T_world_sensor`` (mm) at each
            exposure's true mid-exposure time, in the time base of ``clock``. Called in the event loop.
        config: sensor model; see :class:`SimConfig`.
        clock: the true time base, seconds (must advance at real-time rate; asyncio sleeps on it).
        host, control_port, data_port: where to listen (port 0 = any free port).
        fault_port: serve the fault channel (:class:`LaserFaultRequest`, :mod:`drivers.sim.fault_channel`)
            on this port (0: any free port; None: off); its address is :attr:`fault_address`.
    """

    def __init__(
        self,
        scene: Scene | tuple[np.ndarray, np.ndarray],
        pose_at: PoseFn,
        *,
        config: SimConfig | None = None,
        clock: Callable[[], float] = time.monotonic,
        host: str = "127.0.0.1",
        control_port: int = 0,
        data_port: int = 0,
        fault_port: int | None = None,
    ) -> None:
        self.scene = scene if isinstance(scene, Scene) else Scene(*scene)
        self._fault_port = fault_port
        self._fault_server: asyncio.Server | None = None
        self.pose_at = pose_at
        self.config = config or SimConfig()
        self.clock = clock
        self.host = host
        self._ports = (control_port, data_port)
        self.faults = SimFaults()
        self.stats = SimStats()
        cfg = self.config
        fmt = P.ProfileFormat.UNIFORM if cfg.profile_format == "uniform" else P.ProfileFormat.POINTS
        self.settings = _Settings(rate_hz=cfg.rate_hz, exposure_ns=cfg.exposure_ns, fmt=fmt)
        self._optics = cfg.optics()
        # Two random streams: noise is drawn by the renderer, faults in the event loop.
        self._fault_rng = np.random.default_rng(np.random.SeedSequence(cfg.seed).spawn(2)[1])
        self._local: dict[str, object] = {}  # renderer state when rendering in a thread
        self._t_epoch_s = clock()
        self._offset_us = float(cfg.clock_offset_us)
        self._counter_base_ms = cfg.hd8_counter_start_ms
        self._counter_ref_us = float(cfg.clock_offset_us)
        self._next_frame = 0
        self._running = False
        self._run_t0_s = 0.0
        self._run_k0 = 0
        self._producer: asyncio.Task[None] | None = None
        self._servers: list[asyncio.AbstractServer] = []
        self._data_clients: set[_DataClient] = set()
        self._conn_tasks: set[asyncio.Task[None]] = set()
        self._writers: set[asyncio.StreamWriter] = set()
        self._ring: collections.deque[tuple[int, int, bytes]] = collections.deque()
        self._ring_frames = 0
        self._held: list[tuple[int, bytes]] = []  # groups kept back during a stall
        self._edges: collections.deque[float] = collections.deque()  # pending trigger edges, true time
        self._edge_event = asyncio.Event()
        self._last_edge_s = -math.inf
        self._last_send_at = 0.0  # loop time of the last jitter-delayed send
        self._frames_since_disconnect_arm = 0
        # Rendering runs off the event loop: in a worker process (see SimConfig.render_process) or in
        # one worker thread.
        seeds = np.random.SeedSequence(cfg.seed).spawn(2)
        self._executor: concurrent.futures.Executor
        if cfg.render_process:
            self._executor = concurrent.futures.ProcessPoolExecutor(
                max_workers=1,
                mp_context=multiprocessing.get_context("spawn"),  # no fork of a threaded process
                initializer=_worker_init,
                initargs=(self.scene.vertices_mm, self.scene.triangles, self._optics, seeds[0]),
            )
        else:
            self._executor = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="hd8sim")
            _worker_init(self.scene.vertices_mm, self.scene.triangles, self._optics, seeds[0], self._local)
        self._ratelog = RateLimitedLog(log)
        self.info = P.SensorInfo(
            model=cfg.model,
            serial=cfg.serial,
            width=cfg.width,
            x_pitch_nm=round(cfg.x_pitch_mm * 1e6),
            x_start_um=round(self._optics.x_start_mm * 1e3),
            z_min_um=round(cfg.z_min_mm * 1e3),
            z_max_um=round(cfg.z_max_mm * 1e3),
            max_rate_mhz=round(cfg.max_rate_hz * 1e3),
            min_exposure_ns=cfg.min_exposure_ns,
            max_exposure_ns=cfg.max_exposure_ns,
        )

    # ------------------------------------------------------------------------------ lifecycle

    async def start(self) -> tuple[int, int]:
        """Start the renderer, listen on the control and data ports; return ``(control_port, data_port)``."""
        # A worker process imports open3d and builds the scene now, not when the first frame is due.
        await asyncio.get_running_loop().run_in_executor(self._executor, _worker_ping)
        ctl = await asyncio.start_server(self._serve_control, self.host, self._ports[0])
        dat = await asyncio.start_server(self._serve_data, self.host, self._ports[1])
        self._servers = [ctl, dat]
        if self._fault_port is not None:
            self._fault_server = await start_fault_server(self.host, self._fault_port, self.apply_faults)
            self._servers.append(self._fault_server)
        ports = (ctl.sockets[0].getsockname()[1], dat.sockets[0].getsockname()[1])
        log.info("hd8sim_listening", host=self.host, control_port=ports[0], data_port=ports[1])
        return ports

    async def stop(self) -> None:
        """Stop acquisition, close every connection and both listeners."""
        await self._stop_acquisition()
        for srv in self._servers:
            srv.close()
        # Aborting the transports ends every connection handler through EOF; cancelling the handler
        # tasks instead makes asyncio's stream callback log spurious errors.
        for w in list(self._writers):
            w.transport.abort()
        if self._conn_tasks:
            _, pending = await asyncio.wait(set(self._conn_tasks), timeout=2.0)
            for t in pending:
                t.cancel()
        for srv in self._servers:
            await srv.wait_closed()
        self._servers = []
        await asyncio.to_thread(self._executor.shutdown, True)

    @property
    def running(self) -> bool:
        """True while acquiring."""
        return self._running

    # ---------------------------------------------------------------------------- ground truth

    def sensor_time_us(self, t_true_s: np.ndarray | float) -> np.ndarray:
        """The sensor clock (us, float) at true time(s) ``t_true_s``: offset, drift, jumps included."""
        drift = 1.0 + self.config.clock_drift_ppm * 1e-6
        return self._offset_us + (np.asarray(t_true_s, dtype=np.float64) - self._t_epoch_s) * 1e6 * drift

    def hd8_counter_ms(self, sensor_time_us: np.ndarray | float) -> np.ndarray:
        """The HD8 32-bit ms counter at the given sensor clock reading(s)."""
        ticks = np.floor((np.asarray(sensor_time_us, dtype=np.float64) - self._counter_ref_us) / 1000.0)
        return ((ticks.astype(np.int64) + self._counter_base_ms) & 0xFFFF_FFFF).astype(np.uint32)

    def exposure_mid_true_s(self, frame_index: np.ndarray | int) -> np.ndarray:
        """True mid-exposure time (s, ``clock`` base) of frames of the current run (TIME trigger mode)."""
        k = np.asarray(frame_index, dtype=np.float64)
        return (
            self._run_t0_s + (k - self._run_k0) / self.settings.rate_hz + self.settings.exposure_ns * 0.5e-9
        )

    def render_profiles(self, t_mid_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Ray cast profiles at true mid-exposure times, in the calling thread (another transport's
        device, e.g. :mod:`drivers.laser.sim.gige_device`, when this simulator's own servers are not
        running: both would share one renderer).

        Returns:
            z_mm (n, width) float32 (NaN where no return), valid (n, width) bool, and sensor_time_us
            (n,) float64: the sensor clock at each exposure (offset, drift and jumps as the HD8's).
        """
        t_mid_s = np.asarray(t_mid_s, dtype=np.float64)
        poses = np.asarray(self.pose_at(t_mid_s), dtype=np.float64)
        if poses.shape != (len(t_mid_s), 4, 4):
            raise ValueError(f"pose_at returned shape {poses.shape}, expected ({len(t_mid_s)}, 4, 4)")
        raycaster, optics, rng = self._local["raycaster"], self._local["optics"], self._local["rng"]
        assert isinstance(raycaster, SceneRaycaster) and isinstance(optics, LaserOptics)
        assert isinstance(rng, np.random.Generator)
        t0 = time.perf_counter()
        r = render_uniform(raycaster, poses, optics, rng)
        self.stats.render_s += time.perf_counter() - t0
        self.stats.frames_acquired += len(t_mid_s)
        return r.z_mm.astype(np.float32), r.valid, self.sensor_time_us(t_mid_s)

    # ------------------------------------------------------------------------------ faults

    @property
    def fault_address(self) -> tuple[str, int] | None:
        """``(host, port)`` of the fault channel once started, None when it is off."""
        if self._fault_server is None:
            return None
        return self.host, int(self._fault_server.sockets[0].getsockname()[1])

    def apply_faults(self, request: object) -> dict:
        """One fault-channel request (decoded JSON, see :class:`LaserFaultRequest`) applied; returns
        the reply: ``{"ok": true, "faults": {...in force...}, "stats": {...}}`` or ``{"ok": false,
        "error": ...}`` (then nothing changed)."""
        try:
            k = LaserFaultRequest.model_validate(request).laser
        except ValidationError as exc:
            return {"ok": False, "error": str(exc)}
        if k.disconnect_after_frames is not None:
            if k.disconnect_after_frames == 0:
                self.faults.disconnect_after_frames = None
            else:
                self.disconnect_after(k.disconnect_after_frames)
        if k.corrupt_groups is not None:
            self.corrupt_next(k.corrupt_groups, k.corrupt_mode)
        if k.corrupt_probability is not None:
            self.faults.corrupt_mode = k.corrupt_mode
            self.faults.corrupt_probability = k.corrupt_probability
        if k.drop_frames is not None:
            self.drop_next(k.drop_frames)
        if k.drop_probability is not None:
            self.faults.drop_probability = k.drop_probability
        if k.stall_s is not None:
            self.stall(k.stall_s, acquire=k.stall_acquire)
        if k.clock_jump_us is not None:
            self.jump_timestamp(k.clock_jump_us)
        faults = dataclasses.asdict(self.faults)
        faults["stall_remaining_s"] = max(0.0, faults.pop("stall_until_s") - self.clock())
        return {"ok": True, "faults": faults, "stats": dataclasses.asdict(self.stats)}

    def disconnect_after(self, n_frames: int) -> None:
        """Abort all data connections after ``n_frames`` more frames have been sent."""
        self._frames_since_disconnect_arm = 0
        self.faults.disconnect_after_frames = n_frames

    def corrupt_next(self, n_groups: int = 1, mode: Literal["payload", "framing"] = "payload") -> None:
        """Corrupt the next ``n_groups`` frame groups on the wire."""
        self.faults.corrupt_mode = mode
        self.faults.corrupt_groups = n_groups

    def drop_next(self, n_frames: int) -> None:
        """Acquire but never send the next ``n_frames`` frames."""
        self.faults.drop_frames = n_frames

    def stall(self, seconds: float, *, acquire: bool = True) -> None:
        """Send nothing for ``seconds``; with ``acquire`` the frames are sent late, otherwise lost."""
        self.faults.stall_acquire = acquire
        self.faults.stall_until_s = self.clock() + seconds

    def jump_timestamp(self, delta_us: float) -> None:
        """Step the sensor clock by ``delta_us`` (the ms counter jumps with it)."""
        self._offset_us += delta_us

    # --------------------------------------------------------------------------- acquisition

    async def _start_acquisition(self) -> None:
        if self._running:
            return
        self._running = True
        self._run_t0_s = self.clock()
        self._run_k0 = self._next_frame
        self._producer = asyncio.create_task(self._produce_loop(), name="hd8sim-producer")

    async def _stop_acquisition(self) -> None:
        self._running = False
        self._edges.clear()
        if self._producer is not None:
            self._producer.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._producer
            self._producer = None

    def _ready_count(self, now_s: float) -> int:
        """Index one past the last frame whose data is ready at ``now_s``."""
        s = self.settings
        lag = s.exposure_ns * 1e-9 + self.config.processing_latency_s
        return self._run_k0 + max(0, math.floor((now_s - self._run_t0_s - lag) * s.rate_hz) + 1)

    async def _produce_loop(self) -> None:
        cfg = self.config
        loop = asyncio.get_running_loop()
        last_group_s = -math.inf
        try:
            while self._running:
                if self.settings.trigger == P.TriggerMode.EXTERNAL:
                    await self._produce_triggered(loop)
                    continue
                now = self.clock()
                ready = self._ready_count(now)
                if ready > self._next_frame and now - last_group_s >= cfg.group_period_s * 0.999:
                    max_backlog = max(1, int(cfg.max_backlog_s * self.settings.rate_hz))
                    overrun = ready - self._next_frame > max_backlog
                    if overrun:
                        skipped = ready - max_backlog - self._next_frame
                        self.stats.overrun_frames += skipped
                        self._next_frame += skipped
                        self._ratelog.warning("hd8sim_overrun", skipped_frames=skipped)
                    k0 = self._next_frame
                    k1 = min(ready, k0 + cfg.max_group_profiles)
                    self._next_frame = k1
                    last_group_s = now
                    await self._produce(loop, k0, k1, overrun)
                    continue
                # Sleep until the next frame is ready, but batch frames into groups at high rates.
                s = self.settings
                t_ready = (
                    self._run_t0_s
                    + (self._next_frame - self._run_k0) / s.rate_hz
                    + s.exposure_ns * 1e-9
                    + cfg.processing_latency_s
                )
                wake = max(t_ready, last_group_s + cfg.group_period_s)
                await asyncio.sleep(max(0.0, wake - now))
        except asyncio.CancelledError:
            raise
        except Exception:
            # The endpoint must survive a bad pose callback or scene: log and stop acquiring.
            log.exception("hd8sim_producer_failed")
            self._running = False

    async def _produce_triggered(self, loop: asyncio.AbstractEventLoop) -> None:
        """One step of external-trigger acquisition: render the edges whose frames are ready, or wait."""
        s = self.settings
        lag = s.exposure_ns * 1e-9 + self.config.processing_latency_s
        now = self.clock()
        ready: list[float] = []
        while self._edges and self._edges[0] + lag <= now and len(ready) < self.config.max_group_profiles:
            ready.append(self._edges.popleft())
        if ready:
            k0 = self._next_frame
            self._next_frame += len(ready)
            t_mid = np.asarray(ready) + s.exposure_ns * 0.5e-9
            await self._produce(loop, k0, self._next_frame, False, t_mid)
            return
        self._edge_event.clear()
        timeout = (self._edges[0] + lag - now) if self._edges else None
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._edge_event.wait(), timeout)

    def trigger(self, t_true_s: float | None = None) -> bool:
        """A rising edge on the trigger input (external-trigger mode); call it in the event loop.

        Args:
            t_true_s: when the edge happened (``clock`` base); default now. The exposure starts there.

        Returns:
            True if the edge starts a frame; False if the sensor is not running in EXTERNAL mode or
            the edge comes sooner than ``1 / max_rate_hz`` after the previous one (such edges are
            ignored and counted in ``stats.triggers_ignored``, like a sensor still busy with a frame).
        """
        t = self.clock() if t_true_s is None else float(t_true_s)
        if not self._running or self.settings.trigger != P.TriggerMode.EXTERNAL:
            self.stats.triggers_ignored += 1
            return False
        if t - self._last_edge_s < 1.0 / self.config.max_rate_hz:
            self.stats.triggers_ignored += 1
            return False
        self._last_edge_s = t
        self._edges.append(t)
        self._edge_event.set()
        return True

    async def _produce(
        self,
        loop: asyncio.AbstractEventLoop,
        k0: int,
        k1: int,
        overrun: bool,
        t_mid: np.ndarray | None = None,
    ) -> None:
        frames = np.arange(k0, k1, dtype=np.uint64)
        n = len(frames)
        if t_mid is None:
            t_mid = self.exposure_mid_true_s(frames)
        poses = np.asarray(self.pose_at(t_mid), dtype=np.float64)
        if poses.shape != (n, 4, 4):
            raise ValueError(f"pose_at returned shape {poses.shape}, expected ({n}, 4, 4)")
        sensor_us = self.sensor_time_us(t_mid)
        hd8_ms = self.hd8_counter_ms(sensor_us)
        status = np.zeros(n, dtype=np.uint32)
        if overrun:
            status[0] |= np.uint32(P.StatusBits.OVERRUN)
        if self.config.sensor_time_from_ms_counter:
            sensor_us = np.floor(sensor_us / 1000.0) * 1000.0
            status |= np.uint32(P.StatusBits.TIME_FROM_MS_COUNTER)
        keep = self._keep_mask(n)
        self.stats.frames_acquired += n
        if not keep.any():
            return
        fmt = self.settings.fmt
        exposure = np.full(n, self.settings.exposure_ns, dtype=np.uint32)
        t0 = time.perf_counter()
        renderer = _render_in_worker if self.config.render_process else self._render_in_thread
        group = await loop.run_in_executor(
            self._executor,
            renderer,
            poses[keep],
            fmt,
            self._uniform_scale(),
            self._points_scale(),
            dict(
                frame_index=frames[keep],
                sensor_time_us=sensor_us[keep].astype(np.uint64),
                hd8_ms=hd8_ms[keep],
                encoder=np.zeros(int(keep.sum()), dtype=np.int64),
                status=status[keep],
                exposure_ns=exposure[keep],
            ),
        )
        self.stats.render_s += time.perf_counter() - t0
        self._publish(int(frames[keep][0]), int(frames[keep][-1]), group)

    def _keep_mask(self, n: int) -> np.ndarray:
        f = self.faults
        keep = np.ones(n, dtype=bool)
        if f.drop_frames > 0:
            d = min(f.drop_frames, n)
            keep[:d] = False
            f.drop_frames -= d
        if f.drop_probability > 0:
            keep &= self._fault_rng.random(n) >= f.drop_probability
        if f.stall_until_s > self.clock() and not f.stall_acquire:
            keep[:] = False
        self.stats.frames_dropped_fault += int(n - keep.sum())
        return keep

    def _render_in_thread(
        self,
        poses: np.ndarray,
        fmt: P.ProfileFormat,
        uniform: P.ProfileScale,
        points: P.ProfileScale,
        stamps: dict[str, np.ndarray],
    ) -> bytes:
        return _render_with(self._local, poses, fmt, uniform, points, stamps)

    def _points_scale(self) -> P.ProfileScale:
        return P.ProfileScale(self.config.x_scale_nm_points, self.config.z_scale_nm, 0, self._z_offset_um())

    def _z_offset_um(self) -> int:
        return round((self.config.z_min_mm + self.config.z_max_mm) * 500.0)  # range centre, um

    def _uniform_scale(self) -> P.ProfileScale:
        cfg = self.config
        return P.ProfileScale(
            x_scale_nm=round(cfg.x_pitch_mm * 1e6),
            z_scale_nm=cfg.z_scale_nm,
            x_offset_um=round(self._optics.x_start_mm * 1e3),
            z_offset_um=self._z_offset_um(),
        )

    def _publish(self, first: int, last: int, group: bytes) -> None:
        """Store a group in the ring and queue it for every data client (no await: keeps order)."""
        n = last - first + 1  # upper bound when frames inside were dropped; fine for accounting
        cap = self.config.ring_buffer_frames
        if cap:
            self._ring.append((first, last, group))
            self._ring_frames += n
            while self._ring_frames > cap and self._ring:
                f0, f1, _ = self._ring.popleft()
                self._ring_frames -= f1 - f0 + 1
        f = self.faults
        if f.stall_until_s > self.clock():
            self._held.append((n, group))
            return
        pending = [*self._held, (n, group)]
        self._held = []
        jitter = self.config.network_jitter_s
        if jitter <= 0:
            for hn, hg in pending:
                self._send_all(hn, hg)
            return
        # Delay each group by a random amount, never overtaking the group before it. The send times
        # must be strictly increasing: the event loop's timer heap does not keep insertion order
        # among equal times (the groups held by a stall, released together, came out shuffled).
        loop = asyncio.get_running_loop()
        for hn, hg in pending:
            t_jitter = loop.time() + abs(self._fault_rng.normal(0.0, jitter))
            t_send = max(self._last_send_at + _SEND_ORDER_STEP_S, t_jitter)
            self._last_send_at = t_send
            loop.call_at(t_send, self._send_all, hn, hg)

    def _send_all(self, n: int, group: bytes) -> None:
        f = self.faults
        wire = group
        random_hit = f.corrupt_probability > 0 and self._fault_rng.random() < f.corrupt_probability
        if f.corrupt_groups > 0 or random_hit:
            f.corrupt_groups = max(0, f.corrupt_groups - (not random_hit))
            wire = _corrupt(group, f.corrupt_mode)
            self._ratelog.warning("hd8sim_corrupted_group", mode=f.corrupt_mode)
        for c in self._data_clients:
            self._enqueue(c, n, wire)
        self.stats.groups_sent += 1
        self.stats.frames_sent += n
        if f.disconnect_after_frames is not None:
            self._frames_since_disconnect_arm += n
            if self._frames_since_disconnect_arm >= f.disconnect_after_frames:
                f.disconnect_after_frames = None
                log.info("hd8sim_fault_disconnect", clients=len(self._data_clients))
                for c in list(self._data_clients):
                    # Abort after the queued bytes: the client sees the stream end mid-flight.
                    c.queue.append((0, b""))
                    c.wake.set()

    def _enqueue(self, c: _DataClient, n: int, data: bytes) -> None:
        if c.queued_frames + n > self.config.client_queue_frames:
            self.stats.frames_dropped_slow_client += n
            self._ratelog.warning("hd8sim_client_too_slow", dropped_frames=n)
            return
        c.queue.append((n, data))
        c.queued_frames += n
        c.wake.set()

    # ------------------------------------------------------------------------------ data channel

    async def _serve_data(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._conn_tasks.add(task)
        self._writers.add(writer)
        self.stats.data_connections += 1
        peer = writer.get_extra_info("peername")
        client: _DataClient | None = None
        try:
            framer = P.MessageFramer(max_message_size=64)
            msgs: list[P.Message] = []
            while not msgs:
                chunk = await asyncio.wait_for(reader.read(64), timeout=5.0)
                if not chunk:
                    return
                msgs = framer.feed(chunk)
            start = P.decode_subscribe(msgs[0])
            client = _DataClient(writer)
            if start != P.LIVE:
                for f0, f1, g in self._ring:
                    if f1 >= start:
                        self._enqueue(client, f1 - f0 + 1, g)
            self._data_clients.add(client)
            log.info("hd8sim_data_client", peer=peer, start_frame=None if start == P.LIVE else start)
            await self._write_loop(reader, client)
        except (P.DecodeError, TimeoutError) as exc:
            self.stats.malformed_commands += 1
            self._ratelog.warning("hd8sim_bad_subscribe", peer=peer, error=str(exc))
        except (ConnectionError, asyncio.IncompleteReadError):
            pass
        except Exception:
            log.exception("hd8sim_data_connection_failed", peer=peer)
        finally:
            if client is not None:
                self._data_clients.discard(client)
            writer.transport.abort()
            self._writers.discard(writer)
            self._conn_tasks.discard(task)

    async def _write_loop(self, reader: asyncio.StreamReader, c: _DataClient) -> None:
        eof = asyncio.create_task(reader.read(1))  # the client never sends more; EOF = it left
        try:
            while True:
                while c.queue:
                    n, data = c.queue.popleft()
                    if not data:  # disconnect fault marker
                        await c.writer.drain()
                        return
                    c.queued_frames -= n
                    c.writer.write(data)
                    await c.writer.drain()
                if eof.done():
                    return
                c.wake.clear()
                waiter = asyncio.create_task(c.wake.wait())
                done, _ = await asyncio.wait({waiter, eof}, return_when=asyncio.FIRST_COMPLETED)
                if eof in done:
                    waiter.cancel()
                    return
        finally:
            eof.cancel()

    # --------------------------------------------------------------------------- control channel

    async def _serve_control(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._conn_tasks.add(task)
        self._writers.add(writer)
        self.stats.control_connections += 1
        peer = writer.get_extra_info("peername")
        framer = P.MessageFramer(max_message_size=4096)
        try:
            while True:
                chunk = await reader.read(4096)
                if not chunk:
                    return
                try:
                    msgs = framer.feed(chunk)
                except P.FramingError as exc:
                    self.stats.malformed_commands += 1
                    self._ratelog.warning("hd8sim_control_framing_error", peer=peer, error=str(exc))
                    return  # stream position unknown: drop this connection only
                for msg in msgs:
                    writer.write(await self._dispatch(msg, peer))
                await writer.drain()
        except (ConnectionError, asyncio.IncompleteReadError):
            pass
        except Exception:
            log.exception("hd8sim_control_connection_failed", peer=peer)
        finally:
            writer.transport.abort()
            self._writers.discard(writer)
            self._conn_tasks.discard(task)

    async def _dispatch(self, msg: P.Message, peer: object) -> bytes:
        try:
            request = P.decode_command(msg)
            cmd, payload = request.command, request.payload
        except P.DecodeError as exc:
            self.stats.malformed_commands += 1
            self._ratelog.warning("hd8sim_unknown_command", peer=peer, error=str(exc))
            return P.encode_reply(msg.type, P.Status.UNKNOWN_COMMAND, str(exc).encode()[:200])
        try:
            status, reply = await self._execute(cmd, payload)
        except P.DecodeError as exc:
            self.stats.malformed_commands += 1
            self._ratelog.warning("hd8sim_malformed_command", peer=peer, command=cmd.name, error=str(exc))
            return P.encode_reply(cmd, P.Status.MALFORMED, str(exc).encode()[:200])
        return P.encode_reply(cmd, status, reply)

    async def _execute(self, cmd: P.CommandId, payload: bytes) -> tuple[int, bytes]:
        C, S = P.CommandId, P.Status
        s = self.settings
        if cmd in (C.SET_EXPOSURE, C.SET_RATE, C.SET_TRIGGER_MODE, C.SET_PROFILE_FORMAT):
            value = P.decode_u32_param(cmd, payload)
        elif payload:
            raise P.DecodeError(
                f"{cmd.name} takes no payload, got {len(payload)} bytes", field="size", data=payload
            )
        if cmd == C.GET_INFO:
            return S.OK, self.info.to_bytes()
        if cmd == C.KEEP_ALIVE:
            return S.OK, b""
        if cmd == C.GET_TIMESTAMP:
            us = float(self.sensor_time_us(self.clock()))
            return S.OK, P.TimestampReply(int(us), int(self.hd8_counter_ms(us))).to_bytes()
        if cmd == C.RESET_TIMESTAMP:
            self._counter_ref_us = float(self.sensor_time_us(self.clock()))
            self._counter_base_ms = 0
            return S.OK, b""
        if cmd == C.GET_STATE:
            oldest = self._ring[0][0] if self._ring else self._next_frame
            state = P.SensorState.RUNNING if self._running else P.SensorState.READY
            return S.OK, P.StateReply(state, self._next_frame, oldest).to_bytes()
        if cmd == C.START:
            await self._start_acquisition()
            return S.OK, b""
        if cmd == C.STOP:
            await self._stop_acquisition()
            return S.OK, b""
        if cmd == C.SET_EXPOSURE:
            period_ns = 1e9 / s.rate_hz
            if not self.config.min_exposure_ns <= value <= self.config.max_exposure_ns:
                return S.INVALID_PARAMETER, (
                    f"exposure_ns {value} outside [{self.config.min_exposure_ns}, {self.config.max_exposure_ns}]"
                ).encode()
            if value >= period_ns:
                return S.INVALID_PARAMETER, f"exposure_ns {value} >= frame period {period_ns:.0f} ns".encode()
            s.exposure_ns = value
            return S.OK, b""
        if self._running:
            return S.INVALID_STATE, f"{cmd.name} needs the sensor stopped".encode()
        if cmd == C.SET_RATE:
            rate_hz = value / 1000.0
            if not 0 < rate_hz <= self.config.max_rate_hz:
                return (
                    S.INVALID_PARAMETER,
                    f"rate {rate_hz} Hz outside (0, {self.config.max_rate_hz}]".encode(),
                )
            if s.exposure_ns >= 1e9 / rate_hz:
                return (
                    S.INVALID_PARAMETER,
                    f"frame period at {rate_hz} Hz is shorter than the exposure".encode(),
                )
            s.rate_hz = rate_hz
            return S.OK, b""
        if cmd == C.SET_TRIGGER_MODE:
            if value not in (P.TriggerMode.TIME, P.TriggerMode.EXTERNAL):
                return (
                    S.INVALID_PARAMETER,
                    f"trigger mode {value}: the simulator has no encoder input".encode(),
                )
            s.trigger = P.TriggerMode(value)
            return S.OK, b""
        if cmd == C.SET_PROFILE_FORMAT:
            try:
                s.fmt = P.ProfileFormat(value)
            except ValueError:
                return S.INVALID_PARAMETER, f"profile format {value} unknown".encode()
            return S.OK, b""
        return S.UNKNOWN_COMMAND, b""  # pragma: no cover - every CommandId is handled above


# ------------------------------------------------------------------------------------- renderer

_WORKER_STATE: dict[str, object] = {}  # the renderer's state inside a worker process


def _worker_init(
    vertices_mm: np.ndarray,
    triangles: np.ndarray,
    optics: LaserOptics,
    seed: np.random.SeedSequence,
    state: dict[str, object] | None = None,
) -> None:
    """Build the renderer's scene and noise source (in the worker process, or in ``state``)."""
    state = _WORKER_STATE if state is None else state
    state["raycaster"] = rc = SceneRaycaster(Scene(vertices_mm, triangles))
    # Embree builds its BVH on the first cast: build it now, at start-up. Built when the first frame
    # is due, a 6 m plate's scene (about 10^6 triangles) took over a second in the renderer, which
    # inherits the simulator's real-time priority: the EGM session starved and timed out.
    rc.cast(np.zeros((1, 3)), np.array([[0.0, 0.0, -1.0]]))
    state["optics"] = optics
    state["rng"] = np.random.default_rng(seed)


def _worker_ping() -> bool:
    return True


def _render_in_worker(
    poses: np.ndarray,
    fmt: P.ProfileFormat,
    uniform: P.ProfileScale,
    points: P.ProfileScale,
    stamps: dict[str, np.ndarray],
) -> bytes:
    return _render_with(_WORKER_STATE, poses, fmt, uniform, points, stamps)


def _render_with(
    state: dict[str, object],
    poses: np.ndarray,
    fmt: P.ProfileFormat,
    uniform: P.ProfileScale,
    points: P.ProfileScale,
    stamps: dict[str, np.ndarray],
) -> bytes:
    """Ray cast, quantise and encode one frame group (runs in the renderer)."""
    raycaster = state["raycaster"]
    optics = state["optics"]
    rng = state["rng"]
    assert isinstance(raycaster, SceneRaycaster) and isinstance(optics, LaserOptics)
    assert isinstance(rng, np.random.Generator)
    if fmt == P.ProfileFormat.UNIFORM:
        r = render_uniform(raycaster, poses, optics, rng)
        z_raw = P.quantize_mm(r.z_mm, r.valid, uniform.z_scale_nm, uniform.z_offset_um)
        return P.encode_frame_group(scale=uniform, z_raw=z_raw, **stamps)
    r = render_points(raycaster, poses, optics, rng)
    x_raw = P.quantize_mm(r.x_mm, r.valid, points.x_scale_nm, points.x_offset_um)
    z_raw = P.quantize_mm(r.z_mm, r.valid, points.z_scale_nm, points.z_offset_um)
    return P.encode_frame_group(scale=points, z_raw=z_raw, x_raw=x_raw, **stamps)


def _corrupt(group: bytes, mode: str) -> bytes:
    """Break a frame group: ``payload`` changes the profile count, ``framing`` the first size field."""
    b = bytearray(group)
    if mode == "framing":
        P.HEADER.pack_into(b, 0, 3, P.MessageType.STAMP)
    else:
        stamp_size = P.HEADER.unpack_from(b, 0)[0]
        count = int.from_bytes(b[stamp_size + 8 : stamp_size + 12], "little")
        b[stamp_size + 8 : stamp_size + 12] = (count + 1).to_bytes(4, "little")
    return bytes(b)


# ---------------------------------------------------------------------------------- stand-alone


def _looking_down(standoff_mm: float) -> np.ndarray:
    """Sensor ``standoff_mm`` above the origin, laser axis (+z) pointing down, x along world x."""
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[2, 3] = standoff_mm
    return T


async def _run(args: argparse.Namespace) -> None:
    scene = plane_scene(0.0) if args.scene == "plane" else step_scene(0.0, 0.0, args.step_mm)
    cfg = SimConfig(rate_hz=args.rate, profile_format=args.format)
    sim = LaserSimulator(
        scene,
        fixed_pose(_looking_down(args.standoff)),
        config=cfg,
        host=args.host,
        control_port=args.control_port,
        data_port=args.data_port,
        fault_port=args.fault_port,
    )
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop.set)
    if args.protocol == "gige":
        from drivers.laser.sim.gige_device import GigeSimDevice

        device = GigeSimDevice(sim, address=args.host, serial=args.serial)
        await asyncio.to_thread(device.start)
        print(json.dumps({"protocol": "gige", "host": args.host, "serial": args.serial}), flush=True)
        await stop.wait()
        await asyncio.to_thread(device.stop)
        return
    ctl, dat = await sim.start()
    ready = {"control_port": ctl, "data_port": dat, "host": args.host}
    if sim.fault_address is not None:
        ready["fault_port"] = sim.fault_address[1]
    print(json.dumps(ready), flush=True)
    await stop.wait()
    await sim.stop()


def main(argv: list[str] | None = None) -> None:
    """``python -m drivers.laser.sim``: a sensor looking at a static plane or step until SIGINT/SIGTERM."""
    ap = argparse.ArgumentParser(prog="python -m drivers.laser.sim", description=main.__doc__)
    ap.add_argument("--host", default="127.0.0.1")
    ap.add_argument("--control-port", type=int, default=0)
    ap.add_argument("--data-port", type=int, default=0)
    ap.add_argument(
        "--fault-port", type=int, default=None, help="serve the fault channel here (0: any free port)"
    )
    ap.add_argument("--scene", choices=("plane", "step"), default="plane")
    ap.add_argument("--step-mm", type=float, default=10.0, help="step height for --scene step")
    ap.add_argument("--standoff", type=float, default=100.0, help="sensor height above the floor, mm")
    ap.add_argument("--rate", type=float, default=200.0, help="profile rate, Hz")
    ap.add_argument("--format", choices=("uniform", "points"), default="uniform")
    ap.add_argument(
        "--protocol",
        choices=("hd8", "gige"),
        default="hd8",
        help="hd8: the HD8 protocol on TCP; gige: a GigE Vision profiler on --host, UDP 3956 (Aravis)",
    )
    ap.add_argument("--serial", default="SIMGIGE", help="--protocol gige: the device's serial number")
    args = ap.parse_args(argv)
    if not structlog.is_configured():
        # stdout carries the one JSON line with the ports; logs go to stderr.
        structlog.configure(logger_factory=structlog.PrintLoggerFactory(sys.stderr))
    asyncio.run(_run(args))
