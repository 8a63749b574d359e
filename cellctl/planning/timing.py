"""Timing: toppra for feasibility and the time-optimal bound, a jerk-limited time law for execution.

Each segment is timed on its own, rest to rest (but see the flying turnarounds below), along a
cubic spline of its joint waypoints parameterised by the sensor's arc length (plus a small rotation
term so pure reorientations advance too), so the parameter's rate is the TCP speed.

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

Segments joined by a *flying* turnaround (``Segment.flying``: the raster's neighbouring passes) are
timed as one path instead (:func:`_time_chain`): one spline through all their waypoints, each
segment's own cruise rate, and the rate at a join the lower of its two sides', so the arm does not
stop between the passes; on the turnaround itself the rate is the largest its curvature allows
under the joint acceleration and jerk limits (:func:`_flying_rate`).

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

from cellctl.motion.trajectory import PLAN_JERK_SHARE, TimedTrajectory
from cellctl.planning.plan import PlanRefused, Segment
from cellctl.planning.settings import PlannerSettings
from drivers.abb_egm.kinematics import fk_batch
from drivers.abb_egm.limits import LinearTrack

__all__ = [
    "RAMP_ALLOWANCE_MM",
    "TcpSpeedConstraint",
    "TimingResult",
    "rest_to_rest_s",
    "tcp_speed_mm_s",
    "time_segments",
    "transit_speed_mm_s",
]

logging.getLogger("toppra").setLevel(logging.WARNING)

_VEL_FACTOR = 0.95
_ACC_FACTOR = 0.9
#: weight of rotation in the path parameter (mm per rad), so pure reorientations still advance s
_ROT_WEIGHT_MM_PER_RAD = 100.0
_GRID_STEP_MM = 4.0
_TURN_GRID_STEP_MM = 0.5
#: toppra's feasibility check and time-optimal bound take every other point of that grid (and the
#: segments' ends): the sail's bound moves by 0.06 % (180.76 s against 180.65 s on every point),
#: its cost (most of a cold plan's timing) halves
_TOPPRA_GRID_STRIDE = 2
#: ... and on a sweep (a straight pass at the scan speed, the rate its TCP cap sets) every this-many-th,
#: but within _TOPPRA_END_MM of its ends, where it speeds up and slows down (the timing's cost halves
#: on the 6 m plate; its executed time law keeps every point)
_TOPPRA_SWEEP_STRIDE = 10
_TOPPRA_END_MM = 50.0  # twice RAMP_ALLOWANCE_MM


def _toppra_grid(seg: Segment, grid: np.ndarray) -> np.ndarray:
    """The points of ``seg``'s timing grid toppra checks: every other one (:data:`_TOPPRA_GRID_STRIDE`);
    on a sweep every :data:`_TOPPRA_SWEEP_STRIDE`-th away from its ends."""
    if not seg.is_sweep:
        return grid[::_TOPPRA_GRID_STRIDE]
    near_end = (grid - grid[0] <= _TOPPRA_END_MM) | (grid[-1] - grid <= _TOPPRA_END_MM)
    k = np.arange(grid.size)
    return grid[(near_end & (k % _TOPPRA_GRID_STRIDE == 0)) | (k % _TOPPRA_SWEEP_STRIDE == 0)]


#: a turnaround is flown at this share of the largest rate its limits allow (the rest: its joins)
_FLYING_SHARE = 0.95
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
        self,
        v_max_mm_s: float,
        T_flange_tool: np.ndarray,
        track: LinearTrack | None = None,
        v_max_at=None,
    ) -> None:
        super().__init__()
        self.v_max_mm_s = float(v_max_mm_s)
        #: optional ``v_max_at(s) -> (n,) mm/s`` per path parameter (a chain: passes and turnarounds)
        self.v_max_at = v_max_at
        self.T_flange_tool = np.asarray(T_flange_tool, dtype=np.float64)
        self.track = track
        self.dof = 6 + (track is not None)
        self._format_string = f"    TCP speed limit: {self.v_max_mm_s} mm/s\n"

    def compute_constraint_params(self, path, gridpoints):
        """toppra hook: ``(a, b, c, F, g, ubound, xbound)`` with only ``xbound`` set (x = sdot^2)."""
        dpds = _tool_velocity(path(gridpoints), path(gridpoints, 1), self.T_flange_tool, self.track)
        speed = np.maximum(np.linalg.norm(dpds, axis=1), 1e-9)
        xbound = np.zeros((len(gridpoints), 2))
        v_max = self.v_max_mm_s if self.v_max_at is None else self.v_max_at(np.asarray(gridpoints))
        xbound[:, 1] = (v_max / speed) ** 2
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


def _path_parameter(seg: Segment, settings: PlannerSettings) -> np.ndarray:
    """The path parameter (n,) mm of ``seg``'s waypoints: the sensor's arc length with rotation
    weighted in (:func:`_arc_parameter`); on a line in joint space (``seg.joint_line``) the joints'
    progress along it instead (the axes in units of their speed limits), scaled to the same total, so
    the joints are nearly linear in it and its time law reaches the slowest axis's limits."""
    arc = _arc_parameter(seg.pos_mm, seg.R_base_sensor)
    if not seg.joint_line or seg.q_deg is None:
        return arc
    step = np.linalg.norm(np.diff(seg.q_deg, axis=0) / np.asarray(settings.axis_speed_max)[None], axis=1)
    progress = np.concatenate([[0.0], np.cumsum(np.maximum(step, 1e-9))])
    return progress * (arc[-1] / progress[-1])


def _arc_parameter(pos_mm: np.ndarray, R: np.ndarray) -> np.ndarray:
    """The path parameter (n,) mm at waypoints ``pos_mm`` (n, 3) with orientations ``R`` (n, 3, 3):
    arc length, with rotation weighted in, so pure reorientations advance too."""
    dp = np.linalg.norm(np.diff(pos_mm, axis=0), axis=1)
    tr = np.einsum("nij,nij->n", R[:-1], R[1:])  # trace(R_a^T R_b)
    dth = np.arccos(np.clip((tr - 1) / 2, -1.0, 1.0))
    ds = np.maximum(np.hypot(dp, _ROT_WEIGHT_MM_PER_RAD * dth), 1e-6)
    return np.concatenate([[0.0], np.cumsum(ds)])


def _path_peaks(path, settings: PlannerSettings, grid: np.ndarray):
    """Peaks over ``grid`` per axis of the path's first, second and third derivatives (the third
    from differences of the second), and the largest tool speed per unit of the path parameter."""
    d1 = path(grid, 1)
    d2 = path(grid, 2)
    d3 = np.abs(np.diff(d2, axis=0)) / np.maximum(np.diff(grid), 1e-9)[:, None]
    m1 = np.maximum(np.abs(d1).max(axis=0), 1e-9)
    m2 = np.abs(d2).max(axis=0)
    m3 = d3.max(axis=0) if d3.size else np.zeros(settings.n_axes)
    dpds = np.linalg.norm(_tool_velocity(path(grid), d1, settings.T_flange_sensor, settings.track), axis=1)
    return m1, m2, m3, float(dpds.max())


def _law_states(law: Trajectory, t: np.ndarray) -> np.ndarray:
    """(n, 3) position, velocity and acceleration of a 1-axis ruckig law at times ``t`` (n,) in
    ``[0, duration]``: its seven constant-jerk phases integrated as ruckig's ``at_time`` does, for
    all times at once (``at_time`` one by one where the law has a brake or acceleration pre-phase)."""
    prof = law.profiles[0][0]
    if prof.brake.duration > 0 or prof.accel.duration > 0:
        return np.array([np.ravel(law.at_time(float(x))) for x in t]).reshape(len(t), 3)
    t_sum = np.cumsum(prof.t)
    k = np.minimum(np.searchsorted(t_sum, t, side="right"), len(t_sum) - 1)
    dt = t - np.concatenate([[0.0], t_sum])[k]
    p, v, a, j = (np.asarray(x, dtype=np.float64)[k] for x in (prof.p, prof.v, prof.a, prof.j))
    return np.column_stack([p + dt * (v + dt * (a / 2 + dt * j / 6)), v + dt * (a + dt * j / 2), a + dt * j])


def _law_samples(law: Trajectory, path, s0: float, s1: float, dt_s: float):
    """A 1-axis law of the path parameter from ``s0`` sampled every ``dt_s`` or a little less:
    ``(t, q, qd, qdd)``, the parameter clipped to ``[s0, s1]``."""
    T = float(law.duration)
    n = max(2, int(np.ceil(T / dt_s)) + 1)
    t = np.linspace(0.0, T, n)
    sv = _law_states(law, t)  # s, sdot, sddot
    ss = np.clip(s0 + sv[:, 0], s0, s1)
    d1 = path(ss, 1)
    q = path(ss)
    qd = d1 * sv[:, 1:2]
    qdd = path(ss, 2) * sv[:, 1:2] ** 2 + d1 * sv[:, 2:3]
    return t, q, qd, qdd


#: the shares of the acceleration budget :func:`_time_law` tries at each cruise rate
_ACC_SHARES = np.array([1.0, 0.5, 0.25, 0.1, 0.05, 0.02])


def _time_law(path, v_tcp: float, settings: PlannerSettings, grid: np.ndarray) -> tuple[float, float, float]:
    """Cruise rate V, acceleration A and jerk J of the path parameter that keep the joint limits and
    the TCP speed everywhere on the path.

    With |sdot| <= V, |sddot| <= A, |sdddot| <= J the joint velocity is dq/ds * sdot, the acceleration
    d2q/ds2 * sdot^2 + dq/ds * sddot and the jerk d3q/ds3 * sdot^3 + 3 d2q/ds2 * sdot * sddot +
    dq/ds * sdddot; V, A, J are chosen so each stays under its limit on every joint.
    """
    vmax = _VEL_FACTOR * settings.axis_speed_max
    amax = _ACC_FACTOR * settings.axis_accel_max
    jmax = PLAN_JERK_SHARE * settings.axis_jerk_max
    m1, m2, m3, dpds = _path_peaks(path, settings, grid)
    v = min(v_tcp / max(dpds, 1e-9), float(np.min(vmax / m1)))
    # the centripetal term may use at most half of the acceleration budget
    v0 = min(v, float(np.min(np.sqrt(0.5 * amax / np.maximum(m2, 1e-12)))))
    # The acceleration budget and the jerk budget compete (3 q'' V A); a small grid search over the
    # cruise rate and the share of acceleration used picks the fastest feasible rest-to-rest law.
    # (every candidate at once: the numbers of the loop over rates and shares it replaced, the first
    # of equal durations in that order kept)
    length = float(grid[-1] - grid[0])
    v = (v0 * 0.85 ** np.arange(25))[:, None]  # (25, 1) cruise rates
    a_max = np.min((amax[None] - m2[None] * v * v) / m1[None], axis=1)[:, None]  # (25, 1)
    a = a_max * _ACC_SHARES[None]  # (25, 6)
    j = np.min((jmax - m3 * v[..., None] ** 3 - 3 * m2 * v[..., None] * a[..., None]) / m1, axis=2)
    ok = (a_max > 0) & (j > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        duration = np.where(ok, length / v + v / a + a / j, np.inf)  # rest to rest, a close upper estimate
    if not ok.any():
        raise PlanRefused(
            "no jerk-limited timing fits the joint limits", limit="joint acceleration / jerk limits"
        )
    k, f = np.unravel_index(int(np.argmin(duration)), duration.shape)
    return float(v[k, 0]), float(a[k, f]), float(j[k, f])


def _flying_rate(
    path, v_tcp: float, settings: PlannerSettings, grid: np.ndarray
) -> tuple[float, float, float]:
    """Cruise rate V, acceleration A and jerk J of the path parameter on a flying turnaround.

    It is flown at about one rate (the passes either side meet it there), so the centripetal term
    q'' V^2 may use the acceleration budget and q''' V^3 the jerk budget that a rest-to-rest law
    shares with speeding up: V is 90 % of the largest rate the joint speed, acceleration and jerk
    limits and the TCP speed allow on every point; A and J are what then remains (for a join that
    has to be slower than V), so |q'''| V^3 + 3 |q''| V A + |q'| J stays under the jerk limits.
    """
    vmax = _VEL_FACTOR * settings.axis_speed_max
    amax = _ACC_FACTOR * settings.axis_accel_max
    jmax = PLAN_JERK_SHARE * settings.axis_jerk_max
    m1, m2, m3, dpds = _path_peaks(path, settings, grid)
    m2, m3 = np.maximum(m2, 1e-12), np.maximum(m3, 1e-15)
    v = _FLYING_SHARE * min(
        v_tcp / max(dpds, 1e-9),
        float(np.min(vmax / m1)),
        float(np.min(np.sqrt(amax / m2))),
        float(np.min(np.cbrt(jmax / m3))),
    )
    jerk_left = jmax - m3 * v**3  # at least 27 % of the budget at 90 % of the bound
    a = float(np.min(np.minimum((amax - m2 * v * v) / m1, 0.5 * jerk_left / (3 * m2 * v))))
    j = float(np.min(0.5 * jerk_left / m1))
    return v, a, j


def _toppra_constraints(settings: PlannerSettings, tcp: TcpSpeedConstraint) -> list:
    """toppra's constraints of every timed path: the axes' speed and acceleration limits (with the
    planner's headroom factors) and ``tcp``, the sensor's speed cap."""
    return [
        ta_constraint.JointVelocityConstraint(_VEL_FACTOR * settings.axis_speed_max),
        ta_constraint.JointAccelerationConstraint(
            _ACC_FACTOR * settings.axis_accel_max,
            discretization_scheme=ta_constraint.DiscretizationType.Interpolation,
        ),
        tcp,
    ]


def _spline(seg: Segment, settings: PlannerSettings):
    """The spline of ``seg``'s joint waypoints over its path parameter, and its timing grid:
    ``(path, s, grid)``."""
    s = _path_parameter(seg, settings)
    path = ta.SplineInterpolator(s, seg.q_deg)
    n_grid = int(np.clip(np.ceil(s[-1] / _GRID_STEP_MM), 20, 1500)) + 1
    return path, s, np.linspace(0.0, s[-1], n_grid)


def _rest_to_rest_law(
    seg: Segment, path, s: np.ndarray, grid: np.ndarray, v_tcp: float, settings: PlannerSettings
):
    """The jerk-limited rest-to-rest time law of ``seg``'s spline (:func:`_time_law`, ruckig)."""
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
    return law


def transit_speed_mm_s(settings: PlannerSettings) -> float:
    """The TCP speed a segment off the passes (link, approach, retract) is timed at: the transit
    speed, under :data:`TCP_CAP_FRACTION` of the envelope's cap (the executor's tracker may briefly
    run a little faster), never below the scan speed."""
    v_transit = min(settings.transit_speed_mm_s, TCP_CAP_FRACTION * settings.tcp_speed_max_mm_s)
    return max(v_transit, settings.scan_speed_mm_s)


def rest_to_rest_s(seg: Segment, settings: PlannerSettings) -> float:
    """The executed duration of ``seg`` (joints filled) timed on its own, at rest at both ends, at
    the transit speed: what :func:`time_segments` gives a link that is not flown (s)."""
    path, s, grid = _spline(seg, settings)
    return float(_rest_to_rest_law(seg, path, s, grid, transit_speed_mm_s(settings), settings).duration)


def _time_one(seg: Segment, v_tcp: float, settings: PlannerSettings, dt_s: float):
    path, s, grid = _spline(seg, settings)
    constraints = _toppra_constraints(
        settings, TcpSpeedConstraint(v_tcp, settings.T_flange_sensor, settings.track)
    )
    grid_toppra = np.unique(np.concatenate([_toppra_grid(seg, grid[:-1]), grid[-1:]]))
    optimal = ta_algo.TOPPRA(constraints, path, gridpoints=grid_toppra, parametrizer="ParametrizeConstAccel")
    optimal = optimal.compute_trajectory(0.0, 0.0)
    if optimal is None:
        raise PlanRefused(
            "toppra found no feasible timing for this segment",
            pass_label=seg.label,
            limit="joint velocity / acceleration limits",
        )
    law = _rest_to_rest_law(seg, path, s, grid, v_tcp, settings)
    t, q, qd, qdd = _law_samples(law, path, 0.0, float(s[-1]), dt_s)
    return t, q, qd, qdd, float(optimal.duration)


def _chains(segments: list[Segment]) -> list[list[int]]:
    """Runs of segment indices timed as one path: a flying turnaround joins the segments either side
    (with a track, its carriage is one more axis under its speed, acceleration and jerk limits)."""
    chains: list[list[int]] = [[0]]
    for k in range(1, len(segments)):
        if segments[k].flying or segments[k - 1].flying:
            chains[-1].append(k)
        else:
            chains.append([k])
    return chains


def _flying_law(length: float, v_in: float, v_out: float, v: float, a: float, j: float) -> Trajectory | None:
    """A jerk-limited 1-axis law over ``length`` from rate ``v_in`` to ``v_out`` (no acceleration at
    either end) cruising at up to ``v``; None when it would have to run backwards or overshoot."""
    otg = Ruckig(1)
    inp = InputParameter(1)
    inp.current_position, inp.target_position = [0.0], [float(length)]
    inp.current_velocity, inp.target_velocity = [float(v_in)], [float(v_out)]
    inp.max_velocity, inp.max_acceleration, inp.max_jerk = [float(v)], [float(a)], [float(j)]
    inp.min_velocity = [0.0]
    law = Trajectory(1)
    try:
        res = otg.calculate(inp, law)
    except RuntimeError:
        return None
    if res not in (Result.Working, Result.Finished):
        return None
    ext = law.position_extrema[0]
    if ext.min < -1e-6 or ext.max > length + 1e-6:
        return None
    return law


def _time_chain(segs: list[Segment], speeds: list[float], settings: PlannerSettings, dt_s: float):
    """Time segments joined by flying turnarounds as one path that does not stop at the joins.

    One cubic spline runs through all their joint waypoints (continuous in speed and acceleration
    across the joins); each segment gets its own cruise rate, acceleration and jerk
    (:func:`_time_law` on its stretch of the path) and a jerk-limited law from the rate at its start
    to the rate at its end, no acceleration at either: the rate at a join is the lower of the two
    segments' cruise rates (a turnaround tighter than the pass's speed allows slows the pass's end
    down, within its ramp allowance), at rest at the chain's ends. Returns, per segment, the sampled
    ``(t, q, qd, qdd)`` from its own start, and toppra's time-optimal duration of the whole chain.
    """
    pos = [segs[0].pos_mm]
    rot = [segs[0].R_base_sensor]
    qs = [segs[0].q_deg]
    for seg in segs[1:]:  # each segment starts where the previous one ended: that waypoint once
        pos.append(seg.pos_mm[1:])
        rot.append(seg.R_base_sensor[1:])
        qs.append(seg.q_deg[1:])
    ends = np.cumsum([len(segs[0].q_deg)] + [len(seg.q_deg) - 1 for seg in segs[1:]]) - 1
    s = _arc_parameter(np.concatenate(pos), np.concatenate(rot))
    path = ta.SplineInterpolator(s, np.concatenate(qs))
    bounds = np.concatenate([[0.0], s[ends]])
    # a turnaround's tight curve is sampled finely: its rate comes from the peaks of q'' and q'''
    grids = [
        np.linspace(a, b, int(np.clip(np.ceil((b - a) / (_TURN_GRID_STEP_MM if seg.flying else _GRID_STEP_MM)),
                                      100 if seg.flying else 20, 1500)) + 1)
        for seg, a, b in zip(segs, bounds[:-1], bounds[1:], strict=True)
    ]  # fmt: skip
    laws = []
    for seg, v_tcp, grid in zip(segs, speeds, grids, strict=True):
        try:
            laws.append((_flying_rate if seg.flying else _time_law)(path, v_tcp, settings, grid))
        except PlanRefused as exc:
            raise PlanRefused(exc.reason, pass_label=seg.label, limit=exc.limit) from None
    constraints = _toppra_constraints(
        settings,
        TcpSpeedConstraint(
            max(speeds),
            settings.T_flange_sensor,
            settings.track,
            v_max_at=lambda x: np.asarray(speeds)[
                np.clip(np.searchsorted(bounds, x, side="right") - 1, 0, len(segs) - 1)
            ],
        ),
    )
    grid_toppra = np.unique(
        np.concatenate([_toppra_grid(seg, g) for seg, g in zip(segs, grids, strict=True)] + [bounds])
    )
    optimal = ta_algo.TOPPRA(constraints, path, gridpoints=grid_toppra, parametrizer="ParametrizeConstAccel")
    optimal = optimal.compute_trajectory(0.0, 0.0)
    if optimal is None:
        raise PlanRefused(
            "toppra found no feasible timing for these passes and turnarounds",
            pass_label=segs[0].label,
            limit="joint velocity / acceleration limits",
        )
    # the rates at the joins: the lower cruise rate of the two sides; halved where a segment's law
    # cannot reach it (too short to change speed), and at rest as the last resort
    joins = np.array([0.0] + [min(laws[k][0], laws[k + 1][0]) for k in range(len(segs) - 1)] + [0.0])
    timed: list[Trajectory | None] = [None] * len(segs)
    for attempt in range(8):
        failed = []
        for k, (v, a, j) in enumerate(laws):
            if timed[k] is None:
                timed[k] = _flying_law(bounds[k + 1] - bounds[k], joins[k], joins[k + 1], v, a, j)
                if timed[k] is None:
                    failed.append(k)
        if not failed:
            break
        for k in failed:
            for i in (k, k + 1):
                joins[i] = 0.0 if attempt >= 6 else 0.5 * joins[i]
                for n in (i - 1, i):  # both segments at a changed join are timed again
                    if 0 <= n < len(segs):
                        timed[n] = None
    else:
        raise PlanRefused("the time law could not be computed", pass_label=segs[0].label)
    out = []
    for k, law in enumerate(timed):
        assert law is not None
        out.append(_law_samples(law, path, float(bounds[k]), float(bounds[k + 1]), dt_s))
    return out, float(optimal.duration)


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
    ts, qs, qds, qdds, segidx = [], [], [], [], []
    t0 = 0.0
    worst_dev = 0.0
    sweep_len = 0.0
    optimal_s = 0.0
    for seg in segments:
        if seg.q_deg is None:
            raise PlanRefused("the segment has no joint path", pass_label=seg.label)
    timed: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
    for chain in _chains(segments):
        segs = [segments[k] for k in chain]
        speeds = [v_scan if seg.is_sweep else transit_speed_mm_s(settings) for seg in segs]
        if len(segs) == 1:
            t, q, qd, qdd, t_opt = _time_one(segs[0], speeds[0], settings, dt_s)
            timed.append((t, q, qd, qdd))
        else:
            parts, t_opt = _time_chain(segs, speeds, settings, dt_s)
            timed.extend(parts)
        optimal_s += t_opt
    for k, (seg, (t, q, qd, qdd)) in enumerate(zip(segments, timed, strict=True)):
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
        first = 0 if k == 0 else 1  # the joint between segments is one sample (the same state)
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
