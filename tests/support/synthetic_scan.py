"""Synthetic acquisition inputs with known truth (no network): robot samples and profile batches.

The robot sweeps joint 1 back and forth with the sensor looking down on a tilted plane, so a timing
error moves points along the slope and shows as a height error. Clocks: the controller clock is
true time plus an offset; the sensor clock is true time plus ``sensor_offset_ms`` with
``drift_ppm``; host receive times add a minimum latency, exponential jitter and rare spikes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cellctl.acquisition.poses import T_from_pos_rpy
from drivers.abb_egm.kinematics import fk_batch
from drivers.laser.sim.optics import LaserOptics, render_uniform
from drivers.laser.sim.scene import Scene, SceneRaycaster
from drivers.laser.source import ProfileBatch

Q_CENTER_DEG = np.array([0.0, 15.67, 28.77, 0.0, 45.56, 180.0])
T_FLANGE_SENSOR = T_from_pos_rpy([0.0, 0.0, 150.0], [0.0, 0.0, 0.0])
PLANE_SLOPE_Y = 0.3
PLANE_Z0_MM = 400.0  # plane height at y = 0; the sensor sits about 100 mm above it


def q_true_deg(t_s: np.ndarray, amp_deg: float = 3.0, period_s: float = 5.0) -> np.ndarray:
    """(n, 6) true joints: joint 1 sweeps +-amp (about +-80 mm at the sensor, up to ~100 mm/s)."""
    t = np.asarray(t_s, dtype=np.float64)
    q = np.broadcast_to(Q_CENTER_DEG, (len(t), 6)).copy()
    q[:, 0] += amp_deg * np.sin(2 * np.pi * t / period_s)
    q[:, 1] += 0.5 * np.sin(2 * np.pi * t / (1.7 * period_s))
    return q


def plane_height_mm(x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
    """True surface z(x, y) of the tilted plane, base frame, mm."""
    return PLANE_Z0_MM + PLANE_SLOPE_Y * np.asarray(y_mm)


def tilted_plane_scene() -> Scene:
    """The tilted plane as two triangles, 1.2 m square around (1500, 0)."""
    xs, ys = np.array([900.0, 2100.0]), np.array([-600.0, 600.0])
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    v = np.column_stack([X.ravel(), Y.ravel(), plane_height_mm(X.ravel(), Y.ravel())])
    return Scene(v, np.array([[0, 2, 3], [0, 3, 1]]))


@dataclass
class SyntheticRun:
    """Inputs in arrival order plus the truth."""

    events: list[tuple[str, object]]  # ("robot", (t_host_ns, t_ctrl_us, q)) or ("profiles", batch)
    epoch_ns: int
    sensor_offset_ms: float
    drift_ppm: float


def make_run(
    duration_s: float = 6.0,
    *,
    rate_hz: float = 200.0,
    sensor_offset_ms: float = 30.0,
    drift_ppm: float = 50.0,
    jitter_ms: float = 0.3,
    spike_fraction: float = 0.02,
    sensor_min_latency_ms: float = 1.0,
    robot_min_latency_ms: float = 0.2,
    counter_start_ms: int = 0,
    profiles_per_batch: int = 2,
    noise_mm: float = 0.02,
    seed: int = 3,
    width: int = 200,
    x_pitch_mm: float = 0.25,
) -> SyntheticRun:
    """Build a run: robot samples every 4.032 ms, profiles at ``rate_hz``, merged by host arrival."""
    rng = np.random.default_rng(seed)
    epoch_ns = 5_000_000_000_000  # an arbitrary host monotonic origin
    # robot
    t_r = np.arange(0.0, duration_s + 0.2, 0.004032)
    q_r = q_true_deg(t_r)
    t_ctrl_us = np.rint((t_r + 1234.5) * 1e6).astype(np.int64)
    lat_r = robot_min_latency_ms * 1e-3 + rng.exponential(jitter_ms * 1e-3 / 3, len(t_r))
    host_r = epoch_ns + np.rint((t_r + lat_r) * 1e9).astype(np.int64)
    # profiles (mid-exposure true times), starting a little after the robot
    t_p = np.arange(0.05, duration_s, 1.0 / rate_hz)
    optics = LaserOptics(width=width, x_pitch_mm=x_pitch_mm, noise_sigma_mm=noise_mm, outlier_probability=0.0)
    poses = fk_batch(q_true_deg(t_p), T_FLANGE_SENSOR)
    render = render_uniform(SceneRaycaster(tilted_plane_scene()), poses, optics, rng)
    # sensor clock: believed set to the host's, actually 30 ms off and drifting
    sensor_us = (t_p * (1 + drift_ppm * 1e-6) + sensor_offset_ms * 1e-3) * 1e6 + epoch_ns / 1000
    sensor_time_us = np.floor(sensor_us).astype(np.uint64)
    hd8 = (
        np.floor(sensor_us / 1000).astype(np.int64) - int(epoch_ns // 1_000_000) + counter_start_ms
    ) % 2**32
    n = len(t_p)
    nb = int(np.ceil(n / profiles_per_batch))
    events: list[tuple[int, int, str, object]] = []
    last_host_ns = 0
    for b in range(nb):
        sl = slice(b * profiles_per_batch, min(n, (b + 1) * profiles_per_batch))
        t_last = t_p[sl][-1]
        lat = sensor_min_latency_ms * 1e-3 + rng.exponential(jitter_ms * 1e-3 / 3)
        if rng.random() < spike_fraction:
            lat += rng.uniform(0.005, 0.05)
        # one TCP stream: a late group delays the ones behind it, order is kept
        host_ns = max(epoch_ns + round((t_last + lat) * 1e9), last_host_ns + 1000)
        last_host_ns = host_ns
        k = sl.stop - sl.start
        batch = ProfileBatch(
            frame_index=np.arange(sl.start, sl.stop, dtype=np.uint64),
            sensor_time_us=sensor_time_us[sl],
            hd8_ms=hd8[sl].astype(np.uint32),
            encoder=np.zeros(k, np.int64),
            status=np.zeros(k, np.uint32),
            exposure_ns=np.full(k, 500_000, np.uint32),
            x_mm=render.x_mm[sl],
            z_mm=render.z_mm[sl],
            valid=render.valid[sl],
            host_recv_ns=np.full(k, host_ns, np.int64),
        )
        events.append((host_ns, 1, "profiles", batch))
    # robot samples arrive one by one; group them per 4 like an endpoint poll would
    for i in range(0, len(t_r), 4):
        sl = slice(i, i + 4)
        events.append((int(host_r[sl][-1]), 0, "robot", (host_r[sl], t_ctrl_us[sl], q_r[sl])))
    events.sort(key=lambda e: (e[0], e[1]))
    return SyntheticRun(
        [(kind, payload) for _, _, kind, payload in events], epoch_ns, sensor_offset_ms, drift_ppm
    )


def feed(acq, run: SyntheticRun) -> None:
    """Feed a run's events into an Acquisition in arrival order, then finish it."""
    for kind, payload in run.events:
        if kind == "robot":
            acq.feed_robot(*payload)
        else:
            acq.feed_profiles(payload)
    acq.finish()


def plane_errors_mm(xyz_mm: np.ndarray) -> np.ndarray:
    """Perpendicular distance of points (k, 3) to the tilted plane, mm (signed)."""
    x, y, z = (
        xyz_mm[:, 0].astype(np.float64),
        xyz_mm[:, 1].astype(np.float64),
        xyz_mm[:, 2].astype(np.float64),
    )
    return (z - plane_height_mm(x, y)) / np.sqrt(1 + PLANE_SLOPE_Y**2)
