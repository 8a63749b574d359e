"""Test harness: the acquisition against the simulators in one process, driven through their protocols.

Used by the acquisition and calibration tests and ``benchmarks/acquisition_accuracy.py`` (the
product's simulated cell, ``cellctl sim``, is :mod:`cellctl.simcell`). One process, one event loop, loopback sockets only:

* :class:`drivers.abb_egm.sim.egm.EgmControllerSim` (the controller, UDP client) talks EGM to our
  :class:`drivers.abb_egm.endpoint.EgmEndpoint`; we stream joint references, it moves the simulated
  arm by the controller's control law and records the arm's true trajectory;
* :class:`drivers.laser.sim.sensor.LaserSimulator` serves HD8 profiles over TCP to our
  :class:`drivers.laser.client.HD8Client`; it ray-casts the scene at the arm's **true** sensor pose at
  every exposure (true trajectory and the *true* hand-eye), stamps with its own clock (offset, drift,
  32-bit ms counter) and adds depth noise;
* :class:`cellctl.acquisition.pipeline.Acquisition` gets the endpoint's feedback history (measured
  joints, controller clock) and the client's batches, exactly as the daemon would, and writes the
  job's raw files.

Ground truth (plate surface: :mod:`cellctl.simcell.truth`; true poses) is known, so accuracy is
measurable. Motions here are
simple rasters and stop-and-shoot poses generated in joint space through IK; the real scan planner
lives in ``cellctl.planning``.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import structlog

from cellctl.acquisition.pipeline import Acquisition, AcquisitionSettings
from cellctl.acquisition.poses import T_from_pos_rpy
from cellctl.jobstore.rawstore import RawWriter
from cellctl.simcell.truth import PlateTruth
from drivers.abb_egm.endpoint import EgmEndpoint, EgmEndpointConfig
from drivers.abb_egm.kinematics import RobotKinematics, fk_batch
from drivers.abb_egm.sim.egm import EgmControllerSim, EgmSimConfig
from drivers.laser.client import HD8Client
from drivers.laser.sim.scene import Scene
from drivers.laser.sim.sensor import LaserSimulator, SimConfig

__all__ = [
    "JointPath",
    "PathError",
    "SimCell",
    "SimCellConfig",
    "joint_path",
    "raster_poses",
    "segment_profile",
    "sphere_scene",
    "stop_and_shoot_path",
]

log = structlog.get_logger(__name__)

#: sensor looking straight down with its line (x) along the world y axis
#: the share of a run's frames a truth check may leave out because they were rendered at an
#: extrapolated pose (the controller simulator's cycle fell behind the sensor's). A machine busy with
#: other work puts about 1 % of a scan's frames a few milliseconds past the controller's newest
#: sample (measured: 21 of 2044, up to 5.8 ms, beside a CI run); five times that is a starved
#: simulator, whose truth check would stand on too few frames
MAX_EXTRAPOLATED_SHARE = 0.05
#: the longest a pose may be continued past the controller simulator's newest sample: a platform
#: stall (up to ~40 ms measured, docs/operations.md) is one, longer is a starved simulator
MAX_EXTRAPOLATION_S = 0.05


class SimulatorStarved(AssertionError):
    """The machine starved a simulator during the run: checks against the truth cannot hold."""


R_DOWN_LINE_Y = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
Q_SEED_DEG = np.array([0.0, 15.67, 28.77, 0.0, 45.56, 90.0])


class PathError(ValueError):
    """A motion cannot be generated (unreachable pose, IK failure, limits)."""


@dataclass(frozen=True)
class SimCellConfig:
    """The simulated hardware (the truth the cell does not know).

    Attributes:
        rate_hz, exposure_ns: sensor acquisition.
        noise_sigma_mm, outlier_probability: sensor depth noise and outliers.
        sensor_offset_ms: the sensor clock runs this far ahead of the host clock at start ...
        sensor_drift_ppm: ... and drifts at this rate (cell.toml ``[sim.clocks]``).
        counter_start_ms: the HD8 32-bit ms counter at start (near 2**32 to wrap mid-scan).
        true_sensor_in_flange_pos_mm, true_sensor_in_flange_rpy_deg: the real mounting.
        egm_cycle_s: EGM cycle.
        ctrl_clock_offset_s: the controller clock minus the true (host monotonic) clock.
        seed: noise seed.
    """

    rate_hz: float = 200.0
    exposure_ns: int = 500_000
    noise_sigma_mm: float = 0.02
    outlier_probability: float = 0.0
    sensor_offset_ms: float = 30.0
    sensor_drift_ppm: float = 50.0
    counter_start_ms: int = 0
    true_sensor_in_flange_pos_mm: tuple[float, float, float] = (0.0, 0.0, 150.0)
    true_sensor_in_flange_rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    egm_cycle_s: float = 0.004032
    ctrl_clock_offset_s: float = 1000.0
    seed: int = 0

    @property
    def T_flange_sensor(self) -> np.ndarray:
        """(4, 4) true hand-eye, mm."""
        return T_from_pos_rpy(self.true_sensor_in_flange_pos_mm, self.true_sensor_in_flange_rpy_deg)


# ---------------------------------------------------------------------------------------------
# motions


def segment_profile(distance_mm: float, speed_mm_s: float, accel_mm_s2: float, dt_s: float) -> np.ndarray:
    """Arc length (k,) mm at ``dt_s`` steps of a rest-to-rest move with cosine (jerk-limited) ramps."""
    if distance_mm <= 0:
        return np.zeros(1)
    t_ramp = 1.5 * speed_mm_s / accel_mm_s2  # a cosine ramp peaks at 1.5x the mean acceleration
    d_ramp = 0.5 * speed_mm_s * t_ramp
    if 2 * d_ramp > distance_mm:  # short move: lower the top speed
        speed_mm_s = math.sqrt(distance_mm * accel_mm_s2 / 1.5)
        t_ramp = 1.5 * speed_mm_s / accel_mm_s2
        d_ramp = 0.5 * speed_mm_s * t_ramp
    t_flat = (distance_mm - 2 * d_ramp) / speed_mm_s
    total = 2 * t_ramp + t_flat
    t = np.append(np.arange(0.0, total, dt_s), total)
    v = np.full_like(t, speed_mm_s)
    up, down = t < t_ramp, t > t_ramp + t_flat
    v[up] = 0.5 * speed_mm_s * (1 - np.cos(np.pi * t[up] / t_ramp))
    v[down] = 0.5 * speed_mm_s * (1 - np.cos(np.pi * (total - t[down]) / t_ramp))
    s = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * np.diff(t))])
    return s * (distance_mm / s[-1])


@dataclass(frozen=True)
class JointPath:
    """A timed joint trajectory to stream over EGM.

    Attributes:
        t_s: (m,) seconds from the start, uniform ``dt_s``.
        q_deg: (m, 6) joints.
        qd_deg_s: (m, 6) joint speeds (feed-forward).
        passes: ``(pass_id, t_start_s, t_end_s)`` of the scanning segments.
        stops: ``(t_start_s, t_end_s)`` of dwells (stop-and-shoot captures).
    """

    t_s: np.ndarray
    q_deg: np.ndarray
    qd_deg_s: np.ndarray
    passes: list[tuple[int, float, float]] = field(default_factory=list)
    stops: list[tuple[float, float]] = field(default_factory=list)

    @property
    def duration_s(self) -> float:
        """Length of the path, s."""
        return float(self.t_s[-1])

    def at(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Joint reference and speed at ``t_s`` (held at the ends)."""
        t = min(max(t_s, 0.0), self.duration_s)
        i = min(int(np.searchsorted(self.t_s, t, side="right")) - 1, len(self.t_s) - 2)
        w = (t - self.t_s[i]) / (self.t_s[i + 1] - self.t_s[i])
        return self.q_deg[i] * (1 - w) + self.q_deg[i + 1] * w, self.qd_deg_s[i]


def joint_path(
    T_base_sensor: np.ndarray,
    dt_s: float,
    T_flange_sensor: np.ndarray,
    *,
    q_seed_deg: np.ndarray = Q_SEED_DEG,
    passes: list[tuple[int, float, float]] | None = None,
    stops: list[tuple[float, float]] | None = None,
    kinematics: RobotKinematics | None = None,
) -> JointPath:
    """IK of a dense sensor-pose timeline (one pose per ``dt_s``), warm-started along the path.

    Raises:
        PathError: a pose that IK cannot reach to 1 um / 1e-3 deg within the joint limits.
    """
    kin = kinematics or RobotKinematics()
    T_sf = np.linalg.inv(T_flange_sensor)
    q = np.asarray(q_seed_deg, dtype=np.float64)
    out = np.empty((len(T_base_sensor), 6))
    for i, T in enumerate(T_base_sensor):  # IK is sequential: each solution seeds the next
        r = kin.ik(T @ T_sf, q, tol_mm=1e-3, tol_deg=1e-3)
        if not r.converged:
            raise PathError(
                f"pose {i} at {T[:3, 3].round(1)} mm unreachable (IK error {r.pos_err_mm:.3f} mm)"
            )
        q = r.q_deg
        out[i] = q
    qd = np.gradient(out, dt_s, axis=0)
    return JointPath(
        t_s=np.arange(len(out)) * dt_s, q_deg=out, qd_deg_s=qd, passes=passes or [], stops=stops or []
    )


def raster_poses(
    truth: PlateTruth,
    pass_y_mm: Sequence[float],
    *,
    speed_mm_s: float | Sequence[float] = 100.0,
    standoff_mm: float = 100.0,
    margin_mm: float = 30.0,
    x_range_mm: tuple[float, float] | None = None,
    accel_mm_s2: float = 500.0,
    dt_s: float = 0.004032,
    follow_surface: bool = False,
) -> tuple[np.ndarray, list[tuple[int, float, float]]]:
    """Sensor poses of a boustrophedon raster along the plate's length, looking straight down.

    Passes run along plate x at the given plate-frame ``y``: straight lines at a constant height,
    ``standoff_mm`` above the pass's mean surface height (as a planner working on the design would
    do), or with ``follow_surface`` at ``standoff_mm`` above the true surface. Note that a path
    parallel to the surface hides timing errors (a late pose is still at the right standoff), so
    the accuracy tests use straight passes, where a timing error moves points along the slope.

    ``speed_mm_s`` is one speed or one per pass (several speeds for the time-offset calibration).

    Returns:
        ``(T_base_sensor (m, 4, 4), passes)`` with one pose per ``dt_s``; ``passes`` holds
        ``(pass_id, t_start_s, t_end_s)``.
    """
    speeds = np.broadcast_to(np.asarray(speed_mm_s, dtype=np.float64), (len(pass_y_mm),))
    L = truth.spec.length_mm
    x0, x1 = x_range_mm if x_range_mm is not None else (-L / 2 - margin_mm, L / 2 + margin_mm)
    segs: list[np.ndarray] = []
    passes: list[tuple[int, float, float]] = []
    n = 0  # points so far; point i is at t = i * dt_s
    for k, y in enumerate(pass_y_mm):
        a, b = (x0, x1) if k % 2 == 0 else (x1, x0)
        if segs:  # move across to the next pass start
            last = segs[-1][-1]
            s = segment_profile(abs(y - last[1]), float(speeds[k]), accel_mm_s2, dt_s)[1:]
            segs.append(np.column_stack([np.full_like(s, last[0]), last[1] + np.sign(y - last[1]) * s]))
            n += len(s)
        s = segment_profile(abs(b - a), float(speeds[k]), accel_mm_s2, dt_s)
        if segs:
            s = s[1:]
        xy = np.column_stack([a + np.sign(b - a) * s, np.full_like(s, y)])
        passes.append((k, max(n - 1, 0) * dt_s, (n + len(s) - 1) * dt_s))
        segs.append(xy)
        n += len(s)
    xy = np.concatenate(segs)
    # follow the surface (clamped to the plate so the margins keep the edge height)
    hx = np.clip(xy[:, 0], -L / 2, L / 2)
    hy = np.clip(xy[:, 1], -truth.spec.width_mm / 2, truth.spec.width_mm / 2)
    h = truth.height_mm(hx, hy)[0]
    if not follow_surface:
        # each pass at its mean height; moves between passes blend linearly from one to the next
        y_pass = np.asarray(pass_y_mm, dtype=np.float64)
        h_pass = np.array(
            [
                truth.height_mm(np.linspace(max(x0, -L / 2), min(x1, L / 2), 64), np.full(64, y))[0].mean()
                for y in y_pass
            ]
        )
        order = np.argsort(y_pass)
        h = np.interp(xy[:, 1], y_pass[order], h_pass[order])
    z = h + standoff_mm
    T = np.tile(np.eye(4), (len(xy), 1, 1))
    T[:, :3, :3] = truth.T_base_plate[:3, :3] @ R_DOWN_LINE_Y
    T[:, :3, 3] = truth.to_base(np.column_stack([xy, z]))
    return T, passes


def sphere_scene(
    center_mm: Sequence[float], radius_mm: float, *, n_lat: int = 160, n_lon: int = 320
) -> Scene:
    """A calibration sphere (UV mesh, outward normals) on the bed: base frame, mm.

    160 x 320 facets on a 20 mm radius keep the faceting error (sagitta) below 2 um.
    """
    c = np.asarray(center_mm, dtype=np.float64)
    th = np.linspace(0.0, np.pi, n_lat + 1)[1:-1]
    ph = np.linspace(0.0, 2 * np.pi, n_lon, endpoint=False)
    T, P = np.meshgrid(th, ph, indexing="ij")
    ring = np.column_stack(
        [np.sin(T).ravel() * np.cos(P).ravel(), np.sin(T).ravel() * np.sin(P).ravel(), np.cos(T).ravel()]
    )
    v = np.concatenate([[[0.0, 0.0, 1.0]], ring, [[0.0, 0.0, -1.0]]]) * radius_mm + c
    n_r = n_lat - 1
    idx = 1 + np.arange(n_r * n_lon).reshape(n_r, n_lon)
    nxt = np.roll(idx, -1, axis=1)
    tris = [np.column_stack([np.zeros(n_lon, int), idx[0], nxt[0]])]
    a, b, cc, d = idx[:-1], nxt[:-1], nxt[1:], idx[1:]
    tris += [
        np.column_stack([a.ravel(), d.ravel(), cc.ravel()]),
        np.column_stack([a.ravel(), cc.ravel(), b.ravel()]),
    ]
    last = len(v) - 1
    tris.append(np.column_stack([np.full(n_lon, last), nxt[-1], idx[-1]]))
    return Scene(v, np.concatenate(tris))


def stop_and_shoot_path(
    q_stops_deg: np.ndarray, *, move_s: float = 0.6, dwell_s: float = 0.4, dt_s: float = 0.004032
) -> JointPath:
    """Joint path visiting each stop (smooth cosine moves in joint space), dwelling ``dwell_s`` at each.

    Each dwell is marked as a pass (pass id = stop index) so the captures can be told apart later.
    """
    q_stops = np.asarray(q_stops_deg, dtype=np.float64)
    qs: list[np.ndarray] = [q_stops[:1]]
    passes: list[tuple[int, float, float]] = []
    n = 1
    n_move = max(round(move_s / dt_s), 2)
    n_dwell = max(round(dwell_s / dt_s), 2)
    for i, q in enumerate(q_stops):
        if i > 0:
            u = 0.5 - 0.5 * np.cos(np.pi * np.arange(1, n_move + 1) / n_move)
            qs.append(q_stops[i - 1] + u[:, None] * (q - q_stops[i - 1]))
            n += n_move
        passes.append((i, (n - 1) * dt_s, (n - 1 + n_dwell) * dt_s))
        qs.append(np.repeat(q[None], n_dwell, axis=0))
        n += n_dwell
    q = np.concatenate(qs)
    return JointPath(
        t_s=np.arange(len(q)) * dt_s, q_deg=q, qd_deg_s=np.gradient(q, dt_s, axis=0), passes=passes
    )


# ---------------------------------------------------------------------------------------------
# the simulated cell


class SimCell:
    """Controller simulator + EGM endpoint + sensor simulator + HD8 client + acquisition, on loopback.

    Args:
        scene: what the sensor sees (base frame, mm).
        config: the simulated hardware.
        settings: what the cell believes (hand-eye, latency, clock handling); ``epoch_ns`` is set here.
        job_dir: where the raw files go (None: no raw files).
        q_start_deg: where the arm starts (the first point of the path to run).

    Use ``async with SimCell(...) as cell: await cell.run(path)``; then ``cell.acq.cloud()``.
    """

    def __init__(
        self,
        scene: Scene,
        config: SimCellConfig,
        settings: AcquisitionSettings,
        job_dir: str | Path | None,
        q_start_deg: np.ndarray,
    ) -> None:
        self.scene = scene
        self.config = config
        self.settings = settings
        self.job_dir = None if job_dir is None else Path(job_dir)
        self.q_start_deg = np.asarray(q_start_deg, dtype=np.float64)
        self.endpoint: EgmEndpoint | None = None
        self.controller: EgmControllerSim | None = None
        self.sensor: LaserSimulator | None = None
        self.client: HD8Client | None = None
        self.writer: RawWriter | None = None
        self.acq: Acquisition | None = None
        self._consumer: asyncio.Task | None = None
        self._last_robot_ns = -1
        #: sensor exposures the controller simulator had not reached yet (machine overload), see pose_at
        self.poses_extrapolated = 0
        self.max_extrapolation_s = 0.0
        self.extrapolated_t_s: list[float] = []
        self._profile_stamps: list[tuple[np.ndarray, np.ndarray]] = []

    async def __aenter__(self) -> SimCell:
        await self.start()
        return self

    async def __aexit__(self, *exc) -> None:
        await self.stop()

    async def start(self) -> None:
        """Start both simulators, connect to them, and start acquiring (the arm at rest)."""
        cfg = self.config
        self.endpoint = EgmEndpoint(EgmEndpointConfig(host="127.0.0.1", port=0))
        _, port = await self.endpoint.start()
        self.controller = EgmControllerSim(
            EgmSimConfig(
                sensor_port=port,
                q_start_deg=tuple(self.q_start_deg),
                cycle_s=cfg.egm_cycle_s,
                ctrl_clock_offset_s=cfg.ctrl_clock_offset_s,
                seed=cfg.seed,
            )
        )
        await self.controller.start()
        await self.endpoint.wait_for_feedback(2.0)
        self.endpoint.command_joints(self.q_start_deg)
        T_fs_true = cfg.T_flange_sensor
        trajectory = self.controller.trajectory

        def pose_at(t_true_s: np.ndarray) -> np.ndarray:
            # The controller simulator's cycle fell behind the sensor's (a loaded machine): the arm's
            # last joint velocity continues for those few milliseconds, counted, never a crash.
            q, late = trajectory.q_deg_continued(t_true_s)
            if late.any():
                t = np.atleast_1d(np.asarray(t_true_s, dtype=np.float64))
                self.poses_extrapolated += int(late.sum())
                self.extrapolated_t_s.extend(t[late].tolist())
                t_newest = float(trajectory.newest(1)[0][-1])
                self.max_extrapolation_s = max(self.max_extrapolation_s, float(t.max() - t_newest))
            return fk_batch(q, T_fs_true)

        # the HD8 counter counts the sensor clock's ms from the config's clock_offset_us (default 1 s):
        # choose its base so that it reads counter_start_ms now (near 2**32 it wraps mid-scan)
        sensor_ms_now = (
            time.monotonic() * 1e6 + cfg.sensor_offset_ms * 1e3 - SimConfig().clock_offset_us
        ) // 1000
        counter_base = int(cfg.counter_start_ms - sensor_ms_now) % 2**32
        self.sensor = LaserSimulator(
            self.scene,
            pose_at,
            config=SimConfig(
                rate_hz=cfg.rate_hz,
                exposure_ns=cfg.exposure_ns,
                noise_sigma_mm=cfg.noise_sigma_mm,
                outlier_probability=cfg.outlier_probability,
                clock_drift_ppm=cfg.sensor_drift_ppm,
                hd8_counter_start_ms=counter_base,
                seed=cfg.seed,
            ),
        )
        # The sensor clock was once set to the host's; now it is sensor_offset_ms ahead (and drifts).
        # Set after construction: building the scene's ray-casting structure takes a while.
        now = time.monotonic()
        self.sensor.jump_timestamp(
            now * 1e6 + cfg.sensor_offset_ms * 1e3 - float(self.sensor.sensor_time_us(now))
        )
        ctl_port, data_port = await self.sensor.start()
        self.client = HD8Client("127.0.0.1", ctl_port, data_port)
        await self.client.connect()
        await self.client.configure(rate_hz=cfg.rate_hz, exposure_ns=cfg.exposure_ns)
        epoch_ns = time.monotonic_ns()
        self.settings = AcquisitionSettings(**{**self.settings.__dict__, "epoch_ns": epoch_ns})
        if self.job_dir is not None:
            self.writer = RawWriter(
                self.job_dir,
                {"acquisition": self.settings.to_json(), "simulated": True, "truth": _truth_meta(cfg)},
            )
        self.acq = Acquisition(self.settings, self.writer)
        self._consumer = asyncio.create_task(self._consume(), name="simcell-acquisition")
        await self.client.start()

    def _feed_robot(self) -> None:
        a = self.endpoint.history.since(self._last_robot_ns)
        if len(a):
            self.acq.feed_robot(a.t_host_ns, a.t_ctrl_us, a.q_deg)
            self._last_robot_ns = int(a.t_host_ns[-1])

    async def _consume(self) -> None:
        async for batch in self.client:
            self._feed_robot()
            self.acq.feed_profiles(batch)
            self._profile_stamps.append(
                (batch.frame_index.astype(np.int64), batch.sensor_time_us.astype(np.int64))
            )

    async def run(self, path: JointPath, *, settle_s: float = 1.0, lead_s: float | None = None) -> None:
        """Stream ``path`` as joint references (speed feed-forward), marking its passes; dwell first.

        ``settle_s`` lets the clock fits gather pairs before the arm moves.
        """
        ep = self.endpoint
        lead = self.config.egm_cycle_s if lead_s is None else lead_s
        ep.command_joints(path.q_deg[0])
        await asyncio.sleep(settle_s)
        t0_ns = time.monotonic_ns()
        # at equal times a pass ends before the next begins
        marks = sorted(
            [(s, 1, pid) for pid, s, _ in path.passes] + [(e, 0, pid) for pid, _, e in path.passes]
        )
        mi = 0
        while True:
            await ep.wait_for_feedback(1.0)
            t = (time.monotonic_ns() - t0_ns) * 1e-9
            while mi < len(marks) and marks[mi][0] <= t:
                ts, kind, pid = marks[mi]
                t_mark = t0_ns + round(ts * 1e9)
                if kind == 1:
                    self.acq.begin_pass(pid, t_mark)
                else:
                    self.acq.end_pass(t_mark)
                mi += 1
            if t > path.duration_s + 0.2:
                break
            q, qd = path.at(t + lead)
            ep.command_joints(q, speed_deg_s=qd if t + lead < path.duration_s else None)

    async def stop(self) -> None:
        """Stop acquiring, assemble what is left, close everything (raw files flushed)."""
        with contextlib.suppress(Exception):
            if self.client is not None:
                await self.client.stop()
                await asyncio.sleep(0.05)
        if self.client is not None:
            await self.client.close()
        if self._consumer is not None:
            with contextlib.suppress(asyncio.CancelledError):
                await asyncio.wait_for(self._consumer, 5.0)
        if self.acq is not None:
            self._feed_robot()
            self.acq.finish()
        if self.writer is not None:
            self.writer.close()
        if self.sensor is not None:
            await self.sensor.stop()
        if self.controller is not None:
            await self.controller.stop()
        if self.endpoint is not None:
            await self.endpoint.close()

    def exposure_true_s(self, frame_index: np.ndarray) -> np.ndarray:
        """True mid-exposure time (s, host monotonic clock) of frames of the run."""
        return self.sensor.exposure_mid_true_s(np.asarray(frame_index, dtype=np.float64))

    def truth_reliable(
        self, frame_index: np.ndarray, max_share: float = MAX_EXTRAPOLATED_SHARE
    ) -> np.ndarray:
        """(n,) bool: False for frames rendered at an extrapolated pose (the simulator fell behind).

        A check against the truth may leave those frames out, but only a few: more than
        ``max_share`` of them (or any pose continued for longer than MAX_EXTRAPOLATION_S) means the
        machine starved the controller simulator, and :class:`SimulatorStarved` says so with the
        counts instead of a check that quietly stands on what is left (a caller may take it as a
        counted fallback: ``pytest.skip("fallback: simulators starved (...)")``).
        """
        n = len(frame_index)
        if not self.extrapolated_t_s:
            return np.ones(n, dtype=bool)
        t_us = np.rint(self.exposure_true_s(frame_index) * 1e6).astype(np.int64)
        late_us = np.rint(np.asarray(self.extrapolated_t_s) * 1e6).astype(np.int64)
        ok = ~np.isin(t_us, late_us)
        dropped = int(n - np.count_nonzero(ok))
        if dropped > max_share * n or self.max_extrapolation_s > MAX_EXTRAPOLATION_S:
            raise SimulatorStarved(
                f"{dropped} of {n} frames were rendered at an extrapolated pose (at most {max_share:.1%} may "
                f"be left out), continued up to {self.max_extrapolation_s * 1e3:.1f} ms past the controller "
                f"simulator's newest sample (at most {MAX_EXTRAPOLATION_S * 1e3:.0f} ms): the machine starved "
                "the simulator, so the truth check would stand on too few frames"
            )
        return ok

    def true_time_offset_ms(self, fits: dict) -> float:
        """The latency the cell should configure, from the truth: how much later than the true
        exposure the sensor fit places profiles, minus how much later than the true sampling the
        controller fit places joint samples (both with ``latency_ms = 0``).

        Args:
            fits: ``{"sensor": ClockFit, "robot": ClockFit}`` used for the cloud (e.g. the final fits).
        """
        a = self.endpoint.history.arrays()
        t_true_robot_ns = np.rint((a.t_ctrl_us * 1e-6 - self.config.ctrl_clock_offset_s) * 1e9)
        robot_late_ns = np.median(fits["robot"].to_host_ns(a.t_ctrl_us) - t_true_robot_ns)
        recs = self._profile_stamps
        f = np.concatenate([r[0] for r in recs])
        src = np.concatenate([r[1] for r in recs])
        t_true_ns = np.rint(self.exposure_true_s(f) * 1e9)
        sensor_late_ns = np.median(fits["sensor"].to_host_ns(src) - t_true_ns)
        return float(sensor_late_ns - robot_late_ns) * 1e-6

    def true_sensor_pose(self, t_host_ns: np.ndarray) -> np.ndarray:
        """(n, 4, 4) true sensor pose at host times (the simulators' true clock is the host's)."""
        return self.controller.trajectory.T_base_frame_at(
            np.asarray(t_host_ns) * 1e-9, self.config.T_flange_sensor
        )


def _truth_meta(cfg: SimCellConfig) -> dict:
    return {
        "sensor_offset_ms": cfg.sensor_offset_ms,
        "sensor_drift_ppm": cfg.sensor_drift_ppm,
        "sensor_in_flange_pos_mm": list(cfg.true_sensor_in_flange_pos_mm),
        "sensor_in_flange_rpy_deg": list(cfg.true_sensor_in_flange_rpy_deg),
    }
