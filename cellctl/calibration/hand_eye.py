"""Hand-eye calibration of the line laser: the sensor frame in the flange frame, from a sphere.

A precision sphere of known radius ``R`` is scanned *stop-and-shoot* from many robot poses
(line-laser-and-sync.md section 4): at each stop the arm is still, so timing does not matter (a time
offset would bias a calibration made while moving). Each profile is an arc of the sphere in the laser
plane. With ``T_i`` the flange pose of stop ``i`` (forward kinematics of the measured joints) and
``s_ij`` the profile points in the sensor frame, every point must lie on the sphere:

    || T_i X s_ij - c || = R

Nonlinear least squares over ``X`` (6 parameters: a rotation vector applied to the nominal rotation
and the translation) and the sphere centre ``c`` (3), started from the configured hand-eye and an
algebraic sphere fit. The result comes with its residual report (RMS, max, per stop) and the
parameters' standard deviations from the Jacobian, and is written to ``[robot.sensor_in_flange]``.

Poses must vary in orientation around at least two axes and cut the sphere off-centre at both
sides, or some parameters are not observable; :func:`sphere_capture_poses` generates such a set.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from cellctl.acquisition.pipeline import (
    KIND_PASS_BEGIN,
    KIND_PASS_END,
    KIND_PROFILES,
    KIND_ROBOT,
    AcquisitionSettings,
    batch_from_arrays,
)
from cellctl.acquisition.poses import T_from_pos_rpy, interpolate_joints, pos_rpy_from_T
from cellctl.acquisition.reassemble import final_fits
from cellctl.jobstore.rawstore import RawReader
from drivers.abb_egm.kinematics import fk_batch

__all__ = [
    "HandEyeError",
    "HandEyeResult",
    "StopCapture",
    "calibrate_hand_eye",
    "captures_from_job",
    "fit_sphere",
    "solve_hand_eye",
    "sphere_capture_poses",
]


class HandEyeError(ValueError):
    """The captures cannot determine the hand-eye transform (too few stops or points, no convergence)."""


@dataclass(frozen=True)
class StopCapture:
    """One stop: the profile points ``s_mm`` (k, 3) in the sensor frame (y = 0) and the flange pose of
    each point's profile, ``T_base_flange`` (k, 4, 4) mm (or one (4, 4) pose for all)."""

    T_base_flange: np.ndarray
    s_mm: np.ndarray


@dataclass(frozen=True)
class HandEyeResult:
    """The calibrated ``T_flange_sensor`` with its residual report.

    Attributes:
        T_flange_sensor: (4, 4) mm.
        pos_mm, rpy_deg: the same as cell.toml writes it.
        sphere_center_mm: (3,) fitted sphere centre, base frame.
        rms_mm, max_mm: point-to-sphere residuals after the fit.
        per_stop_rms_mm: (n_stops,) RMS per stop.
        std_pos_mm, std_rpy_deg: 1-sigma of the parameters (from the Jacobian at the optimum).
        delta_pos_mm, delta_angle_deg: change from the starting (configured) hand-eye.
        n_points, n_stops: data used.
    """

    T_flange_sensor: np.ndarray
    pos_mm: np.ndarray
    rpy_deg: np.ndarray
    sphere_center_mm: np.ndarray
    rms_mm: float
    max_mm: float
    per_stop_rms_mm: np.ndarray
    std_pos_mm: np.ndarray
    std_rpy_deg: np.ndarray
    delta_pos_mm: float
    delta_angle_deg: float
    n_points: int
    n_stops: int
    extra: dict = field(default_factory=dict)

    def report(self) -> dict:
        """Plain numbers for the console and the calibration record."""
        return {
            "pos_mm": [round(float(v), 4) for v in self.pos_mm],
            "rpy_deg": [round(float(v), 5) for v in self.rpy_deg],
            "sphere_center_mm": [round(float(v), 4) for v in self.sphere_center_mm],
            "rms_mm": self.rms_mm,
            "max_mm": self.max_mm,
            "worst_stop_rms_mm": float(self.per_stop_rms_mm.max()),
            "std_pos_mm": [float(v) for v in self.std_pos_mm],
            "std_rpy_deg": [float(v) for v in self.std_rpy_deg],
            "delta_pos_mm": self.delta_pos_mm,
            "delta_angle_deg": self.delta_angle_deg,
            "n_points": self.n_points,
            "n_stops": self.n_stops,
        }


def fit_sphere(p_mm: np.ndarray) -> tuple[np.ndarray, float]:
    """Algebraic least-squares sphere through points (k, 3): ``(center (3,), radius)``."""
    A = np.column_stack([2 * p_mm, np.ones(len(p_mm))])
    b = np.sum(p_mm**2, axis=1)
    sol, *_ = np.linalg.lstsq(A, b, rcond=None)
    c = sol[:3]
    return c, float(np.sqrt(sol[3] + c @ c))


def _X(params: np.ndarray, R0: np.ndarray) -> np.ndarray:
    X = np.eye(4)
    X[:3, :3] = Rotation.from_rotvec(params[:3]).as_matrix() @ R0
    X[:3, 3] = params[3:6]
    return X


def solve_hand_eye(
    captures: list[StopCapture],
    radius_mm: float,
    T_flange_sensor_start: np.ndarray,
    *,
    max_points_per_stop: int = 2000,
    seed: int = 0,
) -> HandEyeResult:
    """Least-squares hand-eye from stop-and-shoot sphere captures (see the module docstring).

    Raises:
        HandEyeError: fewer than 6 stops, too few points, or no convergence.
    """
    if len(captures) < 6:
        raise HandEyeError(f"{len(captures)} stops; at least 6 varied stops are needed")
    rng = np.random.default_rng(seed)
    Ts, Ss, stop_of = [], [], []
    for i, cap in enumerate(captures):
        s = cap.s_mm
        Tc = np.asarray(cap.T_base_flange, dtype=np.float64)
        if Tc.ndim == 3:
            Tc = Tc if len(Tc) == len(cap.s_mm) else None
            if Tc is None:
                raise HandEyeError(f"stop {i}: {len(cap.T_base_flange)} poses for {len(cap.s_mm)} points")
        if len(cap.s_mm) > max_points_per_stop:
            pick = rng.choice(len(cap.s_mm), max_points_per_stop, replace=False)
            s = cap.s_mm[pick]
            Tc = Tc[pick] if Tc.ndim == 3 else Tc
        Ts.append(np.broadcast_to(Tc, (len(s), 4, 4)))
        Ss.append(s)
        stop_of.append(np.full(len(s), i))
    T = np.concatenate(Ts)
    S = np.concatenate(Ss)
    stop_of = np.concatenate(stop_of)
    if len(S) < 100:
        raise HandEyeError(f"only {len(S)} sphere points in the captures")
    R0 = np.asarray(T_flange_sensor_start, dtype=np.float64)[:3, :3]
    t0 = np.asarray(T_flange_sensor_start, dtype=np.float64)[:3, 3]
    RT, tT = T[:, :3, :3], T[:, :3, 3]

    def points(params: np.ndarray) -> np.ndarray:
        X = _X(params, R0)
        q = S @ X[:3, :3].T + X[:3, 3]
        return np.einsum("nij,nj->ni", RT, q) + tT

    x0 = np.concatenate([np.zeros(3), t0])
    c0, _ = fit_sphere(points(x0))

    def resid(z: np.ndarray) -> np.ndarray:
        return np.linalg.norm(points(z[:6]) - z[6:9], axis=1) - radius_mm

    sol = least_squares(resid, np.concatenate([x0, c0]), method="lm", x_scale="jac")
    if not sol.success:
        raise HandEyeError(f"least squares did not converge: {sol.message}")
    r = sol.fun
    X = _X(sol.x[:6], R0)
    pos, rpy = pos_rpy_from_T(X)
    # parameter covariance: sigma^2 (J^T J)^-1
    J = sol.jac
    dof = max(len(r) - 9, 1)
    try:
        cov = np.linalg.inv(J.T @ J) * (r @ r) / dof
        std = np.sqrt(np.clip(np.diag(cov), 0, None))
    except np.linalg.LinAlgError:
        std = np.full(9, np.inf)
    d_ang = np.rad2deg(np.linalg.norm(Rotation.from_matrix(X[:3, :3] @ R0.T).as_rotvec()))
    per_stop = np.sqrt(np.bincount(stop_of, r**2) / np.bincount(stop_of))
    return HandEyeResult(
        T_flange_sensor=X,
        pos_mm=pos,
        rpy_deg=rpy,
        sphere_center_mm=sol.x[6:9].copy(),
        rms_mm=float(np.sqrt(np.mean(r**2))),
        max_mm=float(np.max(np.abs(r))),
        per_stop_rms_mm=per_stop,
        std_pos_mm=std[3:6],
        std_rpy_deg=np.rad2deg(std[:3]),
        delta_pos_mm=float(np.linalg.norm(X[:3, 3] - t0)),
        delta_angle_deg=float(d_ang),
        n_points=len(S),
        n_stops=len(captures),
    )


def captures_from_job(job_dir: str | Path, *, max_joint_speed_deg_s: float = 0.5) -> list[StopCapture]:
    """Stops of a stop-and-shoot job: each pass marker pair is one stop.

    Every profile of a stop gets its own flange pose, interpolated from the measured joints at its
    exposure time (the job's whole-scan clock fits, its configured latency), and only profiles taken
    while the joints move slower than ``max_joint_speed_deg_s`` count: an arm still settling at the
    start of a stop is then harmless (and a residual timing error of milliseconds moves nothing).
    """
    reader = RawReader(job_dir)
    recs = reader.records()
    settings = AcquisitionSettings.from_json(reader.meta["acquisition"])
    fits = final_fits(recs, settings)
    if "sensor" not in fits or "robot" not in fits:
        raise HandEyeError(f"{job_dir}: too little data for clock fits")
    stops: list[list[int]] = []
    for r in recs:
        if r.kind == KIND_PASS_BEGIN:
            stops.append([int(r.arrays["t_ns"]), -1])
        elif r.kind == KIND_PASS_END and stops:
            stops[-1][1] = int(r.arrays["t_ns"])
    robot = [r.arrays for r in recs if r.kind == KIND_ROBOT]
    if not robot or not stops:
        raise HandEyeError(f"{job_dir}: no robot samples or no stops (pass markers) in the raw files")
    rt = fits["robot"].to_host_ns(np.concatenate([a["t_ctrl_us"] for a in robot]))
    rq = np.concatenate([a["q_deg"] for a in robot])
    keep = np.concatenate([[True], np.diff(rt) > 0])
    rt, rq = rt[keep], rq[keep]
    speed = np.zeros(len(rt))
    speed[1:] = np.abs(np.diff(rq, axis=0)).max(axis=1) / (np.diff(rt) * 1e-9)
    batches = [batch_from_arrays(r.arrays) for r in recs if r.kind == KIND_PROFILES]
    pt = fits["sensor"].to_host_ns(np.concatenate([b.sensor_time_us for b in batches]).astype(np.int64))
    pt = pt - round(settings.latency_ms * 1e6)
    x = np.concatenate([b.x_mm for b in batches])
    z = np.concatenate([b.z_mm for b in batches])
    valid = np.concatenate([b.valid for b in batches])
    q_p, inside = interpolate_joints(rt, rq, pt, int(rt[0]))
    i_next = np.clip(np.searchsorted(rt, pt), 1, len(rt) - 1)
    slow = inside & (speed[i_next] < max_joint_speed_deg_s) & (speed[i_next - 1] < max_joint_speed_deg_s)
    out = []
    for t0, t1 in stops:
        if t1 < 0:
            continue
        mp = slow & (pt >= t0) & (pt <= t1 + 300_000_000)
        if not mp.any():
            continue
        T_prof = fk_batch(q_p[mp])
        v = valid[mp]
        rows = np.nonzero(v)[0]
        s = np.column_stack([x[mp][v], np.zeros(len(rows)), z[mp][v]]).astype(np.float64)
        out.append(StopCapture(T_base_flange=T_prof[rows], s_mm=s))
    return out


def calibrate_hand_eye(
    job_dir: str | Path, radius_mm: float, T_flange_sensor_start: np.ndarray | None = None
) -> HandEyeResult:
    """Hand-eye from a stop-and-shoot sphere job's raw files (start: the job's configured hand-eye)."""
    if T_flange_sensor_start is None:
        acq = RawReader(job_dir).meta["acquisition"]
        T_flange_sensor_start = T_from_pos_rpy(
            acq["sensor_in_flange_pos_mm"], acq["sensor_in_flange_rpy_deg"]
        )
    return solve_hand_eye(captures_from_job(job_dir), radius_mm, T_flange_sensor_start)


def sphere_capture_poses(
    center_mm: np.ndarray,
    radius_mm: float,
    *,
    n: int = 16,
    standoff_mm: tuple[float, float] = (75.0, 105.0),
    max_tilt_deg: float = 30.0,
    seed: int = 0,
) -> np.ndarray:
    """Sensor poses (n, 4, 4) for stop-and-shoot captures of a sphere: looking at it from varied tilts
    and azimuths, the line turned to varied angles, the laser plane cutting it off-centre on both
    sides, at standoffs spread over ``standoff_mm`` (sensor to sphere top). Varying the standoff
    separates a translation along the line from a rotation within the laser plane, which otherwise
    look alike (both shift the arc sideways)."""
    rng = np.random.default_rng(seed)
    c = np.asarray(center_mm, dtype=np.float64)
    out = np.empty((n, 4, 4))
    for i in range(n):
        tilt = np.deg2rad(max_tilt_deg) * np.sqrt((i + 0.5) / n)
        az = 2.39996 * i  # golden angle: spread azimuths
        d = np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)])
        z_axis = -d
        psi = rng.uniform(-np.pi / 2, np.pi / 2)
        ref = np.array([np.cos(psi), np.sin(psi), 0.0])
        x_axis = ref - (ref @ z_axis) * z_axis
        x_axis /= np.linalg.norm(x_axis)
        y_axis = np.cross(z_axis, x_axis)
        offset = radius_mm * (0.25 + 0.4 * rng.random()) * (1 if i % 2 else -1)
        T = np.eye(4)
        T[:3, :3] = np.column_stack([x_axis, y_axis, z_axis])
        standoff = standoff_mm[0] + (standoff_mm[1] - standoff_mm[0]) * ((i * 0.618034) % 1.0)
        T[:3, 3] = c + d * (radius_mm + standoff) + y_axis * offset
        out[i] = T
    return out
