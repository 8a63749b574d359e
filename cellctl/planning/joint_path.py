"""Joint path: inverse kinematics along the planned sensor poses, with continuity and margins.

The first waypoint is solved from a few elbow-up seeds and the solution with the most room (wrist
away from its singularity, joints away from their limits, little wrist roll) is kept; every later
waypoint takes the closed-form solution (:func:`~drivers.abb_egm.kinematics.ik_branches`, a whole
segment's waypoints at once) nearest its predecessor's, so the configuration cannot flip between
neighbours; where none lies within a waypoint's step, the damped solver warm-started from the
predecessor decides (and names the reason when the pose cannot be reached). Each waypoint is checked against the configured joint limits shrunk by the margin, the
wrist-singularity margin (|q5|), the joint jump between neighbours and the sensor workspace box; the
first violation refuses the plan with the pass, the point and the limit.

With a linear track (``settings.track``) the planner first chooses the track's position at every
waypoint (:func:`track_positions`). When one carriage position lets the arm reach the whole plan
the carriage holds there (``hold_mm``, :func:`hold_position_mm`: the plate's footprint centre abreast
of the base, where a rail-less cell has the plate), and the plan is the rail-less cell's. Otherwise
the carriage follows the sensor's along-rail coordinate, so the arm works at the same reach along
the rail on every pass, where the waypoints' base-frame poses are those of the plate beside a fixed
robot. The arm's joints are then solved in the base frame at those track positions exactly as
without a track; a segment's configurations are ``axes_mm_deg``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from cellctl.planning.plan import PlanRefused, Segment, pose_matrix, slerp_frames
from cellctl.planning.settings import PlannerSettings
from drivers.abb_egm.kinematics import RobotKinematics, nearest_branch
from drivers.abb_egm.limits import JOINT_NAMES

__all__ = [
    "REACH_MM",
    "JointPathResult",
    "check_reach",
    "first_configuration",
    "hold_position_mm",
    "in_base_frame",
    "sensor_kinematics",
    "solve_joint_path",
    "split_waypoints",
    "track_positions",
    "wrist_distances_mm",
]

#: IK must reach the pose this closely, or the point counts as unreachable
_POS_TOL_MM = 0.05
_ROT_TOL_DEG = 0.05
#: elbow-up seeds (q2, q3, q5) for the first waypoint; q1 points at the target, q4 and q6 vary
_SEEDS_235 = (
    (30.0, 0.0, 60.0),
    (10.0, 20.0, 60.0),
    (50.0, -20.0, 60.0),
    (0.0, 40.0, 50.0),
    (60.0, 0.0, 30.0),
)
_SEEDS_46 = ((0.0, 0.0), (0.0, 90.0), (0.0, -90.0), (0.0, 180.0), (180.0, 0.0), (-180.0, 0.0))


@dataclass(frozen=True)
class JointPathResult:
    """What the joint path found: the worst margins along the whole plan.

    min_wrist_deg: smallest |q5| (distance from the wrist singularity), deg.
    min_limit_margin_deg: smallest distance of any joint to its hard limit, deg.
    max_step_deg: largest joint change between neighbouring waypoints, deg.
    waypoints: how many poses were solved.
    """

    min_wrist_deg: float
    min_limit_margin_deg: float
    max_step_deg: float
    waypoints: int


def sensor_kinematics(settings: PlannerSettings) -> RobotKinematics:
    """Robot kinematics with the laser sensor frame registered as tool ``"sensor"``."""
    return RobotKinematics(tools={"sensor": np.asarray(settings.T_flange_sensor, dtype=np.float64)})


#: the sensor's along-rail offsets from the base the planner tries, in order: abreast first, then a
#: little ahead or behind (where a joint limit or the wrist margin refuses the plan abreast)
TRACK_LEADS_MM = (0.0, -200.0, 200.0, -400.0, 400.0)


def hold_position_mm(centre_world_mm: np.ndarray, settings: PlannerSettings) -> float | None:
    """The carriage position that puts ``centre_world_mm`` (the plate's footprint centre, world
    frame) abreast of the robot base, clipped to the usable travel; None without a track.

    Held for a whole scan it gives the arm the plate where a rail-less cell has it (the track's
    along-rail axis through the base), so a plate within the fixed arm's reach gets the same plan."""
    track = settings.track
    if track is None:
        return None
    along = float((np.asarray(centre_world_mm, dtype=np.float64) - track.origin_mm) @ track.direction)
    return float(np.clip(along, track.travel_min_mm, track.travel_max_mm))


#: a carriage following the passes stays this far inside its usable travel
TRACK_END_MARGIN_MM = 1.0


def track_positions(
    segments: list[Segment], settings: PlannerSettings, lead_mm: float = 0.0, hold_mm: float | None = None
) -> list[np.ndarray] | None:
    """The track's position (n,) mm at every waypoint of every segment, or None without a track.

    ``hold_mm`` (not None): the carriage holds that position for the whole plan.

    The carriage follows the sensor's along-rail coordinate ``a = (p - origin) . direction`` at one
    lead for the whole plan, ``s = a - lead``: the arm's reach along the rail is the same on every
    pass, and the track's path is as smooth as the sensor's (sweeps along the rail move it at the
    scan speed, sweeps across hold it). The lead is the one nearest ``lead_mm`` (0: the sensor
    abreast of the base, where the arm reaches as it would for a plate in front of a fixed robot)
    that keeps every waypoint inside the usable travel (less :data:`TRACK_END_MARGIN_MM` at either
    end: the timed path through a waypoint at the very end can overshoot it); a plan longer than
    the travel is clipped there, where the arm then reaches along the rail (or the joint path
    refuses it).
    """
    track = settings.track
    if track is None:
        return None
    if hold_mm is not None:
        return [np.full(seg.pos_mm.shape[0], float(hold_mm)) for seg in segments]
    along = [(seg.pos_mm - track.origin_mm) @ track.direction for seg in segments]
    a = np.concatenate(along)
    # kept off the travel's very ends: the timed path through waypoints at an end can overshoot it
    lo, hi = track.travel_min_mm + TRACK_END_MARGIN_MM, track.travel_max_mm - TRACK_END_MARGIN_MM
    lead_lo = float(a.max()) - hi
    lead_hi = float(a.min()) - lo
    lead = float(np.clip(lead_mm, lead_lo, lead_hi)) if lead_lo <= lead_hi else 0.5 * (lead_lo + lead_hi)
    return [np.clip(x - lead, lo, hi) for x in along]


def in_base_frame(
    segments: list[Segment], settings: PlannerSettings, lead_mm: float = 0.0, hold_mm: float | None = None
) -> tuple[list[Segment], list[np.ndarray] | None]:
    """The segments' sensor poses in the robot base frame at the chosen track positions (copies;
    the segments themselves stay in the world frame), and those track positions (None: no track,
    the segments are returned as they are)."""
    s = track_positions(segments, settings, lead_mm, hold_mm)
    if s is None:
        return segments, None
    track = settings.track
    # the base keeps the world's orientation: only the carriage's translation comes off
    base = [
        replace(seg, pos_mm=seg.pos_mm - track.base_pos_mm(si)) for seg, si in zip(segments, s, strict=True)
    ]
    return base, s


def _unreachable(kin: RobotKinematics, q: np.ndarray, pos_err_mm: float, rot_err_deg: float) -> str:
    at_lo = np.isclose(q, kin.q_min_deg, atol=0.05)
    at_hi = np.isclose(q, kin.q_max_deg, atol=0.05)
    for j in range(6):
        if at_lo[j]:
            return f"{JOINT_NAMES[j]} lower {kin.q_min_deg[j]:.1f} deg"
        if at_hi[j]:
            return f"{JOINT_NAMES[j]} upper {kin.q_max_deg[j]:.1f} deg"
    return f"reach (IK residual {pos_err_mm:.2f} mm, {rot_err_deg:.2f} deg)"


def _margin_violation(q: np.ndarray, settings: PlannerSettings) -> str | None:
    """The first joint outside its limits with margin, or the wrist singularity margin, or None."""
    lo, hi = settings.q_min_deg, settings.q_max_deg
    for j in range(6):
        if q[j] < lo[j]:
            return f"{JOINT_NAMES[j]} lower {lo[j]:.1f} deg (at {q[j]:.1f} deg, margin {settings.joint_margin_deg} deg)"
        if q[j] > hi[j]:
            return f"{JOINT_NAMES[j]} upper {hi[j]:.1f} deg (at {q[j]:.1f} deg, margin {settings.joint_margin_deg} deg)"
    if abs(q[4]) < settings.wrist_margin_deg:
        return f"wrist singularity margin |joint_5| >= {settings.wrist_margin_deg} deg (at {q[4]:.1f} deg)"
    return None


def _score(q: np.ndarray, settings: PlannerSettings) -> float:
    room = np.minimum(q - settings.q_min_deg, settings.q_max_deg - q).min()
    return min(abs(q[4]) - settings.wrist_margin_deg, 30.0) + min(room, 30.0) - 0.05 * (abs(q[3]) + abs(q[5]))


def first_configuration(
    kin: RobotKinematics, T_base_sensor: np.ndarray, settings: PlannerSettings
) -> np.ndarray | None:
    """The best IK solution for the first pose among those nearest the elbow-up seeds (each seed's
    nearest closed-form solution inside the joint limits), or None if none lies inside the margins."""
    p = T_base_sensor[:3, 3]
    q1 = float(np.rad2deg(np.arctan2(p[1], p[0])))
    branches = kin.ik_branches(T_base_sensor[None], frame="sensor")[0]
    best: tuple[float, np.ndarray] | None = None
    for q2, q3, q5 in _SEEDS_235:
        for q4, q6 in _SEEDS_46:
            seed = np.array([q1, q2, q3, q4, q5, q6])
            q = nearest_branch(branches, seed, kin.q_min_deg, kin.q_max_deg)
            if q is None or np.any(q < settings.q_min_deg) or np.any(q > settings.q_max_deg):
                continue
            s = _score(q, settings)
            if best is None or s > best[0]:
                best = (s, q)
    return None if best is None else best[1]


#: shoulder (joint 2 axis) offset and height, and the longest shoulder -> wrist-centre distance, mm
_SHOULDER_X_MM, _SHOULDER_Z_MM = 175.0, 495.0
REACH_MM = 1095.0 + float(np.hypot(1270.0, 175.0))
_WRIST_TO_FLANGE_MM = 135.0


def wrist_distances_mm(segments: list[Segment], settings: PlannerSettings) -> list[np.ndarray]:
    """Per segment, (n,) distances of the wrist centre from the shoulder (joint 2 axis), mm, for
    base-frame sensor poses; the arm reaches no further than ``REACH_MM``.

    The wrist centre sits 135 mm behind the flange along the flange's z axis."""
    T_sensor_flange = np.linalg.inv(np.asarray(settings.T_flange_sensor, dtype=np.float64))
    out = []
    for seg in segments:
        T = pose_matrix(seg.pos_mm, seg.R_base_sensor) @ T_sensor_flange
        wrist = T[:, :3, 3] - _WRIST_TO_FLANGE_MM * T[:, :3, 2]
        r_xy = np.hypot(wrist[:, 0], wrist[:, 1])
        out.append(np.hypot(r_xy - _SHOULDER_X_MM, wrist[:, 2] - _SHOULDER_Z_MM))
    return out


def check_reach(segments: list[Segment], settings: PlannerSettings) -> None:
    """Refuse early, with the share of the sweeps in reach, when wrist centres lie beyond the arm.

    The wrist centre must lie within upper arm + forearm of the shoulder (:func:`wrist_distances_mm`).
    This is a necessary condition only (IK checks the rest), but it names the reason plainly for a
    plate too large for a rail-less cell.
    """
    dist_all = list(zip(segments, wrist_distances_mm(segments, settings), strict=True))
    sweep_d = np.concatenate([d for seg, d in dist_all if seg.is_sweep] or [np.zeros(0)])
    for seg, dist in dist_all:
        far = dist > REACH_MM
        if far.any():
            i = int(np.argmax(far))
            share = float(np.mean(sweep_d <= REACH_MM)) if sweep_d.size else 0.0
            advice = (
                "lay the plate closer to the track (the track carries the arm along it, not across)"
                if settings.track is not None
                else "split the plate into several placements or add a rail"
            )
            raise PlanRefused(
                f"the wrist centre would be {dist[i]:.0f} mm from the shoulder, beyond the arm's "
                f"{REACH_MM:.0f} mm; {share:.0%} of the sweep waypoints are in reach: {advice}",
                pass_label=seg.label,
                point_index=i,
                limit=f"reach {REACH_MM:.0f} mm",
                pos_mm=seg.pos_mm[i],
            )


def _same_waypoints(done: Segment, seg: Segment, track_mm: np.ndarray | None) -> bool:
    """``done`` (solved) has the same waypoints as ``seg`` and, with a track, the same track positions."""
    if done.q_deg is None or done.label != seg.label or done.pos_mm.shape != seg.pos_mm.shape:
        return False
    if not (
        np.array_equal(done.pos_mm, seg.pos_mm) and np.array_equal(done.R_base_sensor, seg.R_base_sensor)
    ):
        return False
    return track_mm is None or np.array_equal(done.q_deg[:, 0], track_mm)


#: a segment flown in the air (not a sweep) whose joints would step beyond the continuity limit
#: between two waypoints has its waypoints split this many times at most before the plan is refused
_MAX_SPLITS = 2
#: ... into pieces this large at most, as a share of the continuity limit
_SPLIT_STEP_SHARE = 0.5
#: ... and each interval into no more than this many pieces
_MAX_SPLIT_FACTOR = 8


class _JointJump(PlanRefused):
    """A configuration jump between waypoints ``point_index - 1`` and ``point_index`` of segment
    ``segment_index``, ``step_deg`` on one joint."""

    def __init__(self, reason: str, *, segment_index: int, step_deg: float, **where) -> None:
        super().__init__(reason, **where)
        self.segment_index = segment_index
        self.step_deg = step_deg


def split_waypoints(seg: Segment, factor: int) -> Segment:
    """``seg`` with every interval between neighbouring waypoints split into ``factor`` pieces: the
    positions on the chord between the two, the orientations on the geodesic between them (joints
    not solved). A link's hump deviates from its chords by lift * (pi / n)^2 / 8: 0.06 mm for a
    50 mm lift over 32 waypoints."""
    if factor < 2:
        return replace(seg, q_deg=None)
    u = np.arange(factor) / factor
    steps = np.diff(seg.pos_mm, axis=0)
    pos = (seg.pos_mm[:-1, None, :] + u[None, :, None] * steps[:, None, :]).reshape(-1, 3)
    R = [slerp_frames(seg.R_base_sensor[i], seg.R_base_sensor[i + 1], u) for i in range(len(steps))]
    return replace(
        seg,
        pos_mm=np.vstack([pos, seg.pos_mm[-1:]]),
        R_base_sensor=np.concatenate([*R, seg.R_base_sensor[-1:]]),
        q_deg=None,
        length_mm=seg.length_mm,
    )


#: waypoints checked at once by :func:`_same_branch_run` (a run stops at the first that needs a look)
_RUN_CHUNK = 512


def _same_branch_run(
    branches: np.ndarray, q_prev: np.ndarray, kin: RobotKinematics, settings: PlannerSettings
) -> np.ndarray:
    """The leading waypoints of ``branches`` ((m, 8, 6), :func:`ik_branches`) that the one-at-a-time
    walk (:func:`nearest_branch` from each predecessor, starting at ``q_prev``) would solve on the
    branch it picks for the first, inside the joint margins and the wrist margin, each within
    ``max_waypoint_joint_step_deg`` of its predecessor: their configurations (k, 6), k >= 0.

    The same numbers as the walk: each joint is turned by whole turns to lie nearest its
    predecessor's (the walk's rounding, accumulated), and every waypoint's choice is checked against
    all eight branches as :func:`nearest_branch` makes it; the run stops before the first waypoint
    where it would differ (the caller solves that one alone)."""
    cand = branches[:_RUN_CHUNK]
    m = cand.shape[0]
    lo_k, hi_k = kin.q_min_deg, kin.q_max_deg
    first = nearest_branch(cand[0], q_prev, lo_k, hi_k)
    if first is None:
        return np.zeros((0, 6))
    unwrapped0 = cand[0] + 360.0 * np.round((q_prev - cand[0]) / 360.0)
    d0 = np.sum((unwrapped0 - first) ** 2, axis=1)
    b = int(np.argmin(np.where(np.isnan(d0), np.inf, d0)))  # a branch without a solution is NaN
    cb = cand[:, b]
    if np.isnan(cb).any():
        m = int(np.argmax(np.isnan(cb).any(axis=1)))
        cb = cb[:m]
    if m == 0:
        return np.zeros((0, 6))
    # the walk's whole turns, accumulated along the branch
    turns = np.empty((m, 6))
    turns[0] = np.round((q_prev - cb[0]) / 360.0)
    if m > 1:
        turns[1:] = turns[0] + np.cumsum(np.round((cb[:-1] - cb[1:]) / 360.0), axis=0)
    q = cb + 360.0 * turns
    prev = np.vstack([q_prev[None], q[:-1]])
    # the walk's choice at every waypoint from the predecessor found here
    allq = cand[:m] + 360.0 * np.round((prev[:, None, :] - cand[:m]) / 360.0)
    inside = np.all((allq >= lo_k - 1e-9) & (allq <= hi_k + 1e-9), axis=2)
    dist = np.where(inside, np.sum((allq - prev[:, None, :]) ** 2, axis=2), np.inf)
    same = (np.argmin(dist, axis=1) == b) & inside[:, b] & np.all(allq[:, b] == q, axis=1)
    good = (
        same
        & (np.abs(q - prev).max(axis=1) <= settings.max_waypoint_joint_step_deg)
        & np.all((q >= settings.q_min_deg) & (q <= settings.q_max_deg), axis=1)
        & (np.abs(q[:, 4]) >= settings.wrist_margin_deg)
    )
    k = m if good.all() else int(np.argmin(good))
    return q[:k]


def solve_joint_path(
    segments: list[Segment],
    settings: PlannerSettings,
    kin: RobotKinematics | None = None,
    q_start_deg: np.ndarray | None = None,
    track_lead_mm: float = 0.0,
    track_hold_mm: float | None = None,
    solved: list[Segment] | None = None,
) -> JointPathResult:
    """Fill ``segment.q_deg`` for every segment, in order, with continuity.

    A segment flown in the air (a link, the approach, the retract) on which a joint would step
    beyond the continuity limit between two waypoints is sampled finer there (the wrist near its
    singularity turns joints 4 and 6 many times faster than the sensor turns: 15 deg per waypoint
    for 3 deg of the sensor at joint 5 = 8 deg), and the plan goes on from there; a jump that stays
    as large on the finer samples is a configuration flip, and refuses the plan. Such a segment is
    replaced in ``segments`` by its finer one (:func:`split_waypoints`). Sweeps are never split:
    their waypoints are the scan's.

    Args:
        segments: the plan's segments (base frame sensor poses; world frame with a track).
        settings: limits and margins (and the track).
        kin: kinematics with the ``"sensor"`` tool (built from the settings when None), of the arm
            alone: with a track the joints are solved in the base frame at the track's positions.
        q_start_deg: (6,) seed for the first waypoint; chosen from elbow-up seeds when None.
        track_lead_mm: with a track, the preferred along-rail offset of the sensor from the base
            (:func:`track_positions`).
        track_hold_mm: with a track, hold the carriage at this position for the whole plan instead
            (None: follow the passes).
        solved: the segments of an earlier attempt (another list): its leading segments with the same
            waypoints and track positions as these keep their joints (the solve is deterministic),
            and the solve goes on from there.

    Raises:
        PlanRefused: a waypoint is unreachable, outside the joint margins, too close to the wrist
            singularity, outside the workspace box, or would need a configuration jump.
    """
    kin = kin or sensor_kinematics(settings)
    splits: dict[int, int] = {}
    while True:
        try:
            return _solve_once(segments, settings, kin, q_start_deg, track_lead_mm, track_hold_mm, solved)
        except _JointJump as exc:
            k, seg = exc.segment_index, segments[exc.segment_index]
            if seg.is_sweep or exc.point_index == 0 or splits.get(k, 0) >= _MAX_SPLITS:
                raise
            factor = int(
                np.clip(
                    np.ceil(exc.step_deg / (_SPLIT_STEP_SHARE * settings.max_waypoint_joint_step_deg)),
                    2,
                    _MAX_SPLIT_FACTOR,
                )
            )
            splits[k] = splits.get(k, 0) + 1
            # the segments before keep the joints this attempt gave them (the solve is deterministic)
            solved = [replace(s) for s in segments[:k]]
            segments[k] = split_waypoints(seg, factor)


def _solve_once(
    segments: list[Segment],
    settings: PlannerSettings,
    kin: RobotKinematics,
    q_start_deg: np.ndarray | None,
    track_lead_mm: float,
    track_hold_mm: float | None,
    solved: list[Segment] | None,
) -> JointPathResult:
    """One pass of :func:`solve_joint_path` over ``segments``; a jump raises :class:`_JointJump`."""
    world_segments = segments
    segments, track_mm = in_base_frame(world_segments, settings, track_lead_mm, track_hold_mm)
    check_reach(segments, settings)
    ws_lo, ws_hi = np.asarray(settings.workspace_min_mm), np.asarray(settings.workspace_max_mm)
    lo, hi = settings.q_min_deg, settings.q_max_deg
    q_prev: np.ndarray | None = None
    min_wrist, min_room, max_step, count = np.inf, np.inf, 0.0, 0
    for seg in world_segments:
        seg.q_deg = None  # a refused attempt leaves joints only on the segments it solved
    reuse = 0
    while solved is not None and reuse < min(len(solved), len(segments)):
        if not _same_waypoints(
            solved[reuse], world_segments[reuse], None if track_mm is None else track_mm[reuse]
        ):
            break
        reuse += 1
    for k, seg in enumerate(segments):
        if k < reuse:
            q_all = solved[k].q_deg.copy()
            q = q_all[:, -6:]
            steps = np.abs(np.diff(q, axis=0) if q_prev is None else np.diff(np.vstack([q_prev, q]), axis=0))
            max_step = max(max_step, float(steps.max(initial=0.0)))
            min_wrist = min(min_wrist, float(np.abs(q[:, 4]).min()))
            room = np.minimum(
                q - np.asarray(settings.joint_lower_deg), np.asarray(settings.joint_upper_deg) - q
            )
            min_room = min(min_room, float(room.min()))
            count += q.shape[0]
            q_prev = q[-1]
            world_segments[k].q_deg = q_all
            continue
        out = np.zeros((seg.pos_mm.shape[0], 6))
        Ts = pose_matrix(seg.pos_mm, seg.R_base_sensor)
        outside = np.any((seg.pos_mm < ws_lo) | (seg.pos_mm > ws_hi), axis=1)
        if outside.any():
            i = int(np.argmax(outside))
            raise PlanRefused(
                f"sensor position {np.round(seg.pos_mm[i], 1).tolist()} mm is outside the workspace box",
                pass_label=seg.label,
                point_index=i,
                limit=f"workspace box {ws_lo.tolist()} .. {ws_hi.tolist()} mm",
                pos_mm=seg.pos_mm[i],
            )
        branches = kin.ik_branches(Ts, frame="sensor")  # every closed-form solution, all at once
        i = 0
        while i < len(Ts):
            if q_prev is not None:
                # the waypoints from i on that stay on one branch within every limit, all at once
                run = _same_branch_run(branches[i:], q_prev, kin, settings)
                if run.shape[0]:
                    steps = np.abs(np.diff(np.vstack([q_prev[None], run]), axis=0)).max(axis=1)
                    out[i : i + run.shape[0]] = run
                    max_step = max(max_step, float(steps.max()))
                    min_wrist = min(min_wrist, float(np.abs(run[:, 4]).min()))
                    room = np.minimum(
                        run - np.asarray(settings.joint_lower_deg), np.asarray(settings.joint_upper_deg) - run
                    )
                    min_room = min(min_room, float(room.min()))
                    count += run.shape[0]
                    q_prev = run[-1]
                    i += run.shape[0]
                    continue
            # one waypoint at a time where the branch changes, a limit is hit or the step is large
            T = Ts[i]
            if q_prev is None:
                q0 = q_start_deg if q_start_deg is not None else first_configuration(kin, T, settings)
                if q0 is None:
                    r = kin.ik(
                        T,
                        np.array([np.rad2deg(np.arctan2(T[1, 3], T[0, 3])), 30, 0, 0, 60, 0]),
                        frame="sensor",
                    )
                    if r.pos_err_mm <= _POS_TOL_MM and r.rot_err_deg <= _ROT_TOL_DEG:
                        limit = _margin_violation(r.q_deg, settings) or "joint margins"
                    else:
                        limit = _unreachable(kin, r.q_deg, r.pos_err_mm, r.rot_err_deg)
                    raise PlanRefused(
                        "the first pose cannot be reached inside the joint margins",
                        pass_label=seg.label,
                        point_index=i,
                        limit=limit,
                        pos_mm=T[:3, 3],
                    )
                q_prev = np.asarray(q0, dtype=np.float64)
            q = nearest_branch(branches[i], q_prev, kin.q_min_deg, kin.q_max_deg)
            if q is None or float(np.max(np.abs(q - q_prev))) > settings.max_waypoint_joint_step_deg:
                # no closed-form solution within a waypoint's step of the last one: the damped
                # solver from it finds where it leads, or says why there is none (the pose out of
                # reach, a joint held at its limit)
                r = kin.ik(T, q_prev, frame="sensor", max_iterations=60, max_step_deg=5.0)
                q = r.q_deg
                if r.pos_err_mm > _POS_TOL_MM or r.rot_err_deg > _ROT_TOL_DEG:
                    raise PlanRefused(
                        "the pose is unreachable",
                        pass_label=seg.label,
                        point_index=i,
                        limit=_unreachable(kin, q, r.pos_err_mm, r.rot_err_deg),
                        pos_mm=T[:3, 3],
                    )
            below, above = q < lo, q > hi
            if below.any() or above.any():
                j = int(np.argmax(below | above))
                side, lim = ("lower", lo[j]) if below[j] else ("upper", hi[j])
                raise PlanRefused(
                    f"{JOINT_NAMES[j]} would be at {q[j]:.2f} deg, beyond its {side} limit with margin",
                    pass_label=seg.label,
                    point_index=i,
                    limit=f"{JOINT_NAMES[j]} {side} {lim:.1f} deg (limit {settings.joint_margin_deg} deg inside)",
                    pos_mm=T[:3, 3],
                )
            if abs(q[4]) < settings.wrist_margin_deg:
                raise PlanRefused(
                    f"the wrist would pass near its singularity (joint_5 at {q[4]:.2f} deg)",
                    pass_label=seg.label,
                    point_index=i,
                    limit=f"wrist singularity margin |joint_5| >= {settings.wrist_margin_deg} deg",
                    pos_mm=T[:3, 3],
                )
            step = float(np.max(np.abs(q - q_prev)))
            if step > settings.max_waypoint_joint_step_deg:
                j = int(np.argmax(np.abs(q - q_prev)))
                raise _JointJump(
                    f"configuration jump of {step:.1f} deg on {JOINT_NAMES[j]} between neighbouring waypoints",
                    segment_index=k,
                    step_deg=step,
                    pass_label=seg.label,
                    point_index=i,
                    limit=f"continuity {settings.max_waypoint_joint_step_deg} deg per waypoint",
                    pos_mm=T[:3, 3],
                )
            out[i] = q
            q_prev = q
            max_step = max(max_step, step)
            min_wrist = min(min_wrist, abs(q[4]))
            room = float(
                np.minimum(
                    q - np.asarray(settings.joint_lower_deg), np.asarray(settings.joint_upper_deg) - q
                ).min()
            )
            min_room = min(min_room, room)
            count += 1
            i += 1
        world_segments[k].q_deg = out if track_mm is None else np.column_stack([track_mm[k], out])
    return JointPathResult(float(min_wrist), float(min_room), float(max_step), count)
