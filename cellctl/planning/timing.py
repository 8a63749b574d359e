"""Timing: toppra for feasibility and the time-optimal bound, a jerk-limited time law for execution.

Each segment is timed on its own, rest to rest, along a cubic spline of its joint waypoints
parameterised by the sensor's arc length (plus a small rotation term so pure reorientations advance
too), so the parameter's rate is the TCP speed.

1. toppra (joint velocity and acceleration limits plus a first-order TCP-speed constraint,
   :class:`TcpSpeedConstraint`) decides whether the segment can be timed at all and gives the
   time-optimal duration.
2. toppra's optimum has piecewise-constant acceleration (unbounded jerk): a jerk-limited tracker
   follows it with lag and then overshoots the speed. The executed time law is therefore a
   jerk-limited cruise (ruckig, offline, one axis, no intermediate waypoints) at the largest
   *constant* rate the joint velocity, acceleration and jerk limits and the TCP speed allow on
   every point of the path. On sweeps that rate is the scan speed, so the TCP speed is constant
   outside the short ramps at the ends of each pass.

Joint limits are used with safety factors (toppra checks them on a grid only; the tracker needs
room). Units: joint angles in deg (deg/s, deg/s^2, deg/s^3), positions in mm, time in s.

With a linear track the path is seven-dimensional (``axes_mm_deg``: the track in mm, then the
joints): toppra and the time law time track and arm together, under the track's speed,
acceleration and jerk limits beside the joints', and the TCP speed is the world frame's.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import toppra as ta
import toppra.algorithm as ta_algo
import toppra.constraint as ta_constraint
from ruckig import InputParameter, Result, Ruckig, Trajectory

from cellctl.motion.trajectory import TimedTrajectory
from cellctl.planning.plan import PlanRefused, Segment
from cellctl.planning.settings import PlannerSettings
from drivers.abb_egm.kinematics import LinearTrack, fk_batch

__all__ = ["RAMP_ALLOWANCE_MM", "TcpSpeedConstraint", "TimingResult", "tcp_speed_mm_s", "time_segments"]

logging.getLogger("toppra").setLevel(logging.WARNING)

_VEL_FACTOR = 0.95
_ACC_FACTOR = 0.9
_JERK_FACTOR = 0.6
#: weight of rotation in the path parameter (mm per rad), so pure reorientations still advance s
_ROT_WEIGHT_MM_PER_RAD = 100.0
_GRID_STEP_MM = 4.0
#: the sweep's ends where the speed may ramp (the passes reach this far beyond what they must cover)
RAMP_ALLOWANCE_MM = 25.0
#: planned transit speeds stay at or below this share of the envelope's TCP speed cap
TCP_CAP_FRACTION = 0.9


class TcpSpeedConstraint(ta_constraint.LinearConstraint):
    """toppra first-order constraint: speed of the tool point ``|dp/ds| * sdot <= v_max_mm_s``.

    ``T_flange_tool`` (4, 4) mm selects the tool point (the laser sensor's origin). ``dp/ds`` is a
    central difference of the vectorised forward kinematics along ``q'(s)``.
    """

    def __init__(
        self, v_max_mm_s: float, T_flange_tool: np.ndarray, track: LinearTrack | None = None
    ) -> None:
        super().__init__()
        self.v_max_mm_s = float(v_max_mm_s)
        self.T_flange_tool = np.asarray(T_flange_tool, dtype=np.float64)
        self.track = track
        self.dof = 6 + (track is not None)
        self._format_string = f"    TCP speed limit: {self.v_max_mm_s} mm/s\n"

    def compute_constraint_params(self, path, gridpoints):
        """toppra hook: ``(a, b, c, F, g, ubound, xbound)`` with only ``xbound`` set (x = sdot^2)."""
        dpds = _tool_velocity(path(gridpoints), path(gridpoints, 1), self.T_flange_tool, self.track)
        speed = np.maximum(np.linalg.norm(dpds, axis=1), 1e-9)
        xbound = np.zeros((len(gridpoints), 2))
        xbound[:, 1] = (self.v_max_mm_s / speed) ** 2
        return None, None, None, None, None, None, xbound


def _tool_velocity(
    q_deg: np.ndarray, qd: np.ndarray, T_flange_tool: np.ndarray, track: LinearTrack | None = None
) -> np.ndarray:
    """Tool point velocity (n, 3) for joint rates ``qd`` (n, 6) at ``q_deg`` (n, 6), per unit of qd
    (``axes_mm_deg`` (n, 7) with a track: the world frame's velocity, carriage included)."""
    scale = np.maximum(np.abs(qd).max(axis=1, keepdims=True), 1e-12)
    h = 1e-3 / scale  # a 1e-3 deg probe along the direction of motion
    p_plus = fk_batch(q_deg + h * qd, T_flange_tool, track=track)[:, :3, 3]
    p_minus = fk_batch(q_deg - h * qd, T_flange_tool, track=track)[:, :3, 3]
    return (p_plus - p_minus) / (2 * h)


def tcp_speed_mm_s(
    q_deg: np.ndarray, qd_deg_s: np.ndarray, T_flange_tool: np.ndarray, track: LinearTrack | None = None
) -> np.ndarray:
    """Speed (n,) mm/s of the tool point for states ``q_deg`` (n, 6) deg and ``qd_deg_s`` (n, 6) deg/s
    (``axes_mm_deg`` (n, 7) and mm/s first with a track)."""
    return np.linalg.norm(_tool_velocity(q_deg, qd_deg_s, T_flange_tool, track), axis=1)


@dataclass(frozen=True)
class TimingResult:
    """The timed trajectory and its figures.

    scan_time_s: total duration. sweep_length_mm: total sweep length. sweep_time_s: sweep length /
    scan speed. sweep_ratio: scan time / sweep time. scan_speed_deviation: max relative deviation of
    the sensor speed from the scan speed on the sweeps, outside the ramps at their ends.
    toppra_time_s: the time-optimal (jerk-unbounded) duration toppra found, for comparison.
    """

    trajectory: TimedTrajectory
    scan_time_s: float
    sweep_length_mm: float
    sweep_time_s: float
    sweep_ratio: float
    scan_speed_deviation: float
    toppra_time_s: float


def _path_parameter(seg: Segment) -> np.ndarray:
    dp = np.linalg.norm(np.diff(seg.pos_mm, axis=0), axis=1)
    R = seg.R_base_sensor
    tr = np.einsum("nij,nij->n", R[:-1], R[1:])  # trace(R_a^T R_b)
    dth = np.arccos(np.clip((tr - 1) / 2, -1.0, 1.0))
    ds = np.maximum(np.hypot(dp, _ROT_WEIGHT_MM_PER_RAD * dth), 1e-6)
    return np.concatenate([[0.0], np.cumsum(ds)])


def _time_law(path, v_tcp: float, settings: PlannerSettings, grid: np.ndarray) -> tuple[float, float, float]:
    """Cruise rate V, acceleration A and jerk J of the path parameter that keep the joint limits and
    the TCP speed everywhere on the path.

    With |sdot| <= V, |sddot| <= A, |sdddot| <= J the joint velocity is dq/ds * sdot, the acceleration
    d2q/ds2 * sdot^2 + dq/ds * sddot and the jerk d3q/ds3 * sdot^3 + 3 d2q/ds2 * sdot * sddot +
    dq/ds * sdddot; V, A, J are chosen so each stays under its limit on every joint.
    """
    vmax = _VEL_FACTOR * settings.axis_speed_max
    amax = _ACC_FACTOR * settings.axis_accel_max
    jmax = _JERK_FACTOR * settings.axis_jerk_max
    d1 = path(grid, 1)
    d2 = path(grid, 2)
    d3 = np.abs(np.diff(d2, axis=0)) / np.maximum(np.diff(grid), 1e-9)[:, None]
    m1 = np.maximum(np.abs(d1).max(axis=0), 1e-9)
    m2 = np.abs(d2).max(axis=0)
    m3 = d3.max(axis=0) if d3.size else np.zeros(settings.n_axes)
    dpds = np.linalg.norm(_tool_velocity(path(grid), d1, settings.T_flange_sensor, settings.track), axis=1)
    v = min(v_tcp / max(float(dpds.max()), 1e-9), float(np.min(vmax / m1)))
    # the centripetal term may use at most half of the acceleration budget
    v0 = min(v, float(np.min(np.sqrt(0.5 * amax / np.maximum(m2, 1e-12)))))
    # The acceleration budget and the jerk budget compete (3 q'' V A); a small grid search over the
    # cruise rate and the share of acceleration used picks the fastest feasible rest-to-rest law.
    length = float(grid[-1])
    best: tuple[float, float, float, float] | None = None
    for v in v0 * 0.85 ** np.arange(25):
        a_max = float(np.min((amax - m2 * v * v) / m1))
        if a_max <= 0:
            continue
        for frac in (1.0, 0.5, 0.25, 0.1, 0.05, 0.02):
            a = a_max * frac
            j = float(np.min((jmax - m3 * v**3 - 3 * m2 * v * a) / m1))
            if j <= 0:
                continue
            duration = length / v + v / a + a / j  # rest to rest, a close upper estimate
            if best is None or duration < best[0]:
                best = (duration, float(v), a, j)
    if best is None:
        raise PlanRefused(
            "no jerk-limited timing fits the joint limits", limit="joint acceleration / jerk limits"
        )
    return best[1], best[2], best[3]


def _time_one(seg: Segment, v_tcp: float, settings: PlannerSettings, dt_s: float):
    s = _path_parameter(seg)
    path = ta.SplineInterpolator(s, seg.q_deg)
    vlim = _VEL_FACTOR * settings.axis_speed_max
    alim = _ACC_FACTOR * settings.axis_accel_max
    constraints = [
        ta_constraint.JointVelocityConstraint(vlim),
        ta_constraint.JointAccelerationConstraint(
            alim, discretization_scheme=ta_constraint.DiscretizationType.Interpolation
        ),
        TcpSpeedConstraint(v_tcp, settings.T_flange_sensor, settings.track),
    ]
    n_grid = int(np.clip(np.ceil(s[-1] / _GRID_STEP_MM), 20, 1500)) + 1
    grid = np.linspace(0.0, s[-1], n_grid)
    optimal = ta_algo.TOPPRA(constraints, path, gridpoints=grid, parametrizer="ParametrizeConstAccel")
    optimal = optimal.compute_trajectory(0.0, 0.0)
    if optimal is None:
        raise PlanRefused(
            "toppra found no feasible timing for this segment",
            pass_label=seg.label,
            limit="joint velocity / acceleration limits",
        )
    try:
        v, a, j = _time_law(path, v_tcp, settings, grid)
    except PlanRefused as exc:
        raise PlanRefused(exc.reason, pass_label=seg.label, limit=exc.limit) from None
    otg = Ruckig(1)
    inp = InputParameter(1)
    inp.current_position, inp.target_position = [0.0], [float(s[-1])]
    inp.max_velocity, inp.max_acceleration, inp.max_jerk = [v], [a], [j]
    law = Trajectory(1)
    res = otg.calculate(inp, law)
    if res not in (Result.Working, Result.Finished):
        raise PlanRefused(f"the time law could not be computed ({res})", pass_label=seg.label)
    T = float(law.duration)
    n = max(2, int(np.ceil(T / dt_s)) + 1)
    t = np.linspace(0.0, T, n)
    sv = np.array([np.ravel(law.at_time(float(x))) for x in t]).reshape(n, 3)  # s, sdot, sddot
    ss = np.clip(sv[:, 0], 0.0, s[-1])
    d1 = path(ss, 1)
    q = path(ss)
    qd = d1 * sv[:, 1:2]
    qdd = path(ss, 2) * sv[:, 1:2] ** 2 + d1 * sv[:, 2:3]
    return t, q, qd, qdd, float(optimal.duration)


def time_segments(segments: list[Segment], settings: PlannerSettings, *, dt_s: float = 0.02) -> TimingResult:
    """Time every segment and concatenate them into one sampled trajectory.

    Args:
        segments: with ``q_deg`` filled by the joint path; ``t_start_s`` / ``duration_s`` are set here.
        settings: joint limits, scan / transit speeds, the sensor transform.
        dt_s: sample interval of the stored trajectory (the executor interpolates between samples
            with quintic Hermite polynomials, continuous in acceleration).

    Raises:
        PlanRefused: a segment cannot be timed within the limits.
    """
    v_scan = settings.scan_speed_mm_s
    # headroom under the envelope's cap: the executor's tracker may briefly run a little faster
    v_transit = min(settings.transit_speed_mm_s, TCP_CAP_FRACTION * settings.tcp_speed_max_mm_s)
    ts, qs, qds, qdds, segidx = [], [], [], [], []
    t0 = 0.0
    worst_dev = 0.0
    sweep_len = 0.0
    optimal_s = 0.0
    for k, seg in enumerate(segments):
        if seg.q_deg is None:
            raise PlanRefused("the segment has no joint path", pass_label=seg.label)
        v = v_scan if seg.is_sweep else max(v_transit, v_scan)
        t, q, qd, qdd, t_opt = _time_one(seg, v, settings, dt_s)
        optimal_s += t_opt
        seg.t_start_s, seg.duration_s = t0, float(t[-1])
        if seg.is_sweep:
            sweep_len += seg.length_mm
            p = fk_batch(q, settings.T_flange_sensor, track=settings.track)[:, :3, 3]
            travelled = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
            interior = (travelled > RAMP_ALLOWANCE_MM) & (travelled < travelled[-1] - RAMP_ALLOWANCE_MM)
            if interior.any():
                speed = tcp_speed_mm_s(q[interior], qd[interior], settings.T_flange_sensor, settings.track)
                worst_dev = max(worst_dev, float(np.max(np.abs(speed / v_scan - 1.0))))
            else:
                worst_dev = max(worst_dev, 1.0)  # a pass too short to reach the scan speed
        first = 0 if k == 0 else 1  # the joint between segments is one sample (both at rest)
        ts.append(t[first:] + t0)
        qs.append(q[first:])
        qds.append(qd[first:])
        qdds.append(qdd[first:])
        segidx.append(np.full(t.size - first, k, dtype=np.int64))
        t0 += float(t[-1])
    traj = TimedTrajectory(
        t_s=np.concatenate(ts),
        q_deg=np.concatenate(qs),
        qd_deg_s=np.concatenate(qds),
        qdd_deg_s2=np.concatenate(qdds),
        segment=np.concatenate(segidx),
    )
    sweep_time = sweep_len / v_scan if sweep_len > 0 else 0.0
    return TimingResult(
        trajectory=traj,
        scan_time_s=traj.duration_s,
        sweep_length_mm=sweep_len,
        sweep_time_s=sweep_time,
        sweep_ratio=traj.duration_s / sweep_time if sweep_time > 0 else float("inf"),
        scan_speed_deviation=worst_dev,
        toppra_time_s=optimal_s,
    )
