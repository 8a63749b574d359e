"""The scan planner's pipeline: design surface -> passes -> joint path -> timing -> envelope ->
predicted coverage.

Reads like the issue: :func:`plan_scan` takes the design (plate frame), the nominal placement and
the settings, and returns a :class:`~cellctl.planning.plan.ScanPlan` or raises
:class:`~cellctl.planning.plan.PlanRefused` with the pass, the point and the limit. Every plan it
returns has passed the safety envelope at the EGM cycle. Planning takes seconds of CPU: call it
from a worker thread or process, never on the event loop.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np
import structlog

from analysis.contracts.placement import placement_transform
from analysis.design.mesh import TriMesh
from cellctl.motion.envelope import EnvelopeLimits, EnvelopeViolation, SafetyEnvelope
from cellctl.motion.trajectory import TimedTrajectory
from cellctl.planning.coverage import (
    JOINT_LINK_MIN_TURN_DEG,
    build_segments,
    design_surface,
    predict_coverage,
)
from cellctl.planning.joint_path import (
    REACH_MM,
    TRACK_LEADS_MM,
    JointPathResult,
    check_reach,
    first_configuration,
    hold_position_mm,
    in_base_frame,
    sensor_kinematics,
    solve_joint_path,
    track_positions,
    wrist_distances_mm,
)
from cellctl.planning.plan import (
    PASS_AXES,
    CoverageReport,
    Placement,
    PlanInputError,
    PlanRefused,
    ScanPlan,
    Segment,
    pose_matrix,
    rotation_angle_deg,
)
from cellctl.planning.settings import PlannerSettings
from cellctl.planning.timing import TimingResult, rest_to_rest_s, time_segments
from drivers.abb_egm.kinematics import fk_batch
from drivers.abb_egm.limits import EGM_CYCLE_S

__all__ = [
    "check_plan_envelope",
    "estimate_s",
    "lower_bound_s",
    "plan_scan",
    "positions_at",
    "start_corner_near",
]

log = structlog.get_logger(__name__)


#: samples :func:`positions_at` takes at once
_POSITIONS_BLOCK = 32_768


def positions_at(trajectory: TimedTrajectory, t_s: np.ndarray) -> np.ndarray:
    """The positions (m, n_axes) of :meth:`TimedTrajectory.sample_many` at times ``t_s`` (m,) s, the
    same numbers (its quintic Hermite's position term, written as it is), without the speeds and
    accelerations the envelope check does not read (they were 2/3 of the sampling's cost)."""
    t_s = np.asarray(t_s, dtype=np.float64)
    if t_s.size > _POSITIONS_BLOCK:
        # in blocks (the same numbers, row by row): no single array operation of a 6 m plate's 431 k
        # samples, which would hold the interpreter for tens of ms beside a daemon's event loop
        return np.concatenate(
            [
                positions_at(trajectory, t_s[k : k + _POSITIONS_BLOCK])
                for k in range(0, t_s.size, _POSITIONS_BLOCK)
            ]
        )
    ts = trajectory.t_s
    t = np.clip(t_s, ts[0], ts[-1])
    i = np.clip(np.searchsorted(ts, t, side="right") - 1, 0, ts.size - 2)
    h = ts[i + 1] - ts[i]
    hs = np.where(h > 0, h, 1.0)
    u = np.where(h > 0, (t - ts[i]) / hs, 0.0)[:, None]
    hs = hs[:, None]
    v0, v1 = trajectory.qd_deg_s[i] * hs, trajectory.qd_deg_s[i + 1] * hs
    a0, a1 = trajectory.qdd_deg_s2[i] * (hs * hs), trajectory.qdd_deg_s2[i + 1] * (hs * hs)
    u2, u3, u4, u5 = u * u, u**3, u**4, u**5
    return (
        (1 - 10 * u3 + 15 * u4 - 6 * u5) * trajectory.q_deg[i]
        + (u - 6 * u3 + 8 * u4 - 3 * u5) * v0
        + (0.5 * u2 - 1.5 * u3 + 1.5 * u4 - 0.5 * u5) * a0
        + (0.5 * u3 - u4 + 0.5 * u5) * a1
        + (-4 * u3 + 7 * u4 - 3 * u5) * v1
        + (10 * u3 - 15 * u4 + 6 * u5) * trajectory.q_deg[i + 1]
    )


def check_plan_envelope(
    trajectory: TimedTrajectory, segments: list, settings: PlannerSettings, cycle_s: float = EGM_CYCLE_S
) -> None:
    """Sample ``trajectory`` at the EGM cycle and check every sample against the safety envelope.

    Raises:
        PlanRefused: naming the segment and the envelope rule that the plan would break.
    """
    envelope = SafetyEnvelope(EnvelopeLimits.from_settings(settings, cycle_s=cycle_s))
    t = np.arange(0.0, trajectory.duration_s, cycle_s)
    t = np.append(t, trajectory.duration_s) if t[-1] < trajectory.duration_s else t
    q = positions_at(trajectory, t)
    try:
        envelope.check_trajectory(t, q)
    except EnvelopeViolation as exc:
        k = exc.sample if exc.sample is not None else 0
        seg = segments[trajectory.sample(t[k])[3]]
        raise PlanRefused(
            f"the timed plan leaves the safety envelope at t = {t[k]:.3f} s: {exc}",
            pass_label=seg.label,
            limit=f"envelope {exc.rule}",
        ) from exc


#: an edge pass whose wrist centres come nearer the arm's full stretch than this is tilted less
EDGE_REACH_MARGIN_MM = 40.0
#: its tilt is lowered in these steps, down to the least that still lights the thickness face
#: (predict_edge_face_coverage on the sail: every face piece seen from 20 deg, none at 17.5 deg,
#: where the rays reaching the face meet it beyond the 80 deg incidence limit;
#: tests/planning/test_long_plate.py)
EDGE_TILT_STEP_DEG = 5.0
EDGE_TILT_MIN_DEG = 20.0


def _in_base_frame_only(
    segments: list[Segment], settings: PlannerSettings, which, *, hold_mm: float | None = None
) -> list[Segment]:
    """:func:`in_base_frame` (lead 0, or the carriage held at ``hold_mm``) of the segments for which
    ``which(index, segment)`` is true, in order: the track's positions come from all of them, the
    copies are made of these alone."""
    s = track_positions(segments, settings, 0.0, hold_mm)
    if s is None:
        return [seg for k, seg in enumerate(segments) if which(k, seg)]
    return [
        replace(seg, pos_mm=seg.pos_mm - settings.track.base_pos_mm(s[k]))
        for k, seg in enumerate(segments)
        if which(k, seg)
    ]


def _lower_edge_tilts(segments: list, settings: PlannerSettings, tilts: dict[str, float]) -> bool:
    """Lower the tilt (in ``tilts``, by label) of every edge pass whose wrist centres come within
    ``EDGE_REACH_MARGIN_MM`` of the arm's reach, with the carriage following the passes; True when
    one was lowered (the segments must then be built again)."""
    if not settings.edge_passes:
        return False
    lowered = False
    for seg in _in_base_frame_only(segments, settings, lambda _, s: s.kind == "edge"):
        if wrist_distances_mm([seg], settings)[0].max() <= REACH_MM - EDGE_REACH_MARGIN_MM:
            continue
        tilt = tilts.get(seg.label, settings.edge_tilt_deg)
        if tilt > EDGE_TILT_MIN_DEG:
            tilts[seg.label] = max(EDGE_TILT_MIN_DEG, tilt - EDGE_TILT_STEP_DEG)
            lowered = True
    return lowered


def _build(
    surface,
    placement: Placement,
    settings: PlannerSettings,
    sign: float,
    *,
    axis: str,
    edge_reverse: bool,
    raster_cache: dict,
) -> tuple[list, float, dict[str, float]]:
    """The segments (:func:`build_segments`), the margin, and the edge passes' tilts lowered to keep
    them in reach (by label; empty when none was)."""
    tilts: dict[str, float] = {}
    kwargs = {"sign": sign, "axis": axis, "edge_reverse": edge_reverse, "raster_cache": raster_cache}
    segments, margin = build_segments(surface, placement, settings, **kwargs)
    while _lower_edge_tilts(segments, settings, tilts):
        segments, margin = build_segments(surface, placement, settings, edge_tilts_deg=tilts, **kwargs)
    return segments, margin, tilts


#: a link flown as a line in joint space may come this much closer to the design surface (the
#: sensor origin's height over it) than the lower of its two ends
JOINT_LINK_CLEARANCE_TOL_MM = 5.0
#: how far (mm) the sensor may be lifted at a joint-space link's middle to keep that clearance
JOINT_LINK_MAX_LIFT_MM = 150.0


def _position_jacobian(q: np.ndarray, settings: PlannerSettings, step_deg: float = 1e-3) -> np.ndarray:
    """(3, n) d(sensor origin, mm) / d(axis) at ``q`` (n,), by central differences; the track's
    column (with a track) is zero: a lift is made by the arm alone."""
    n = q.shape[0]
    dq = np.eye(n) * step_deg
    p = fk_batch(np.vstack([q + dq, q - dq]), settings.T_flange_sensor, track=settings.track)[:, :3, 3]
    J = ((p[:n] - p[n:]) / (2.0 * step_deg)).T
    if n == 7:
        J[:, 0] = 0.0
    return J


def _kept(seg: Segment, reason: str) -> None:
    log.debug("joint_space_link_refused", link=seg.label, reason=reason)


def _joint_space_link(seg: Segment, settings: PlannerSettings, clearance) -> Segment | None:
    """``seg`` (a link at rest at both ends, joints solved) as a line in joint space between its
    end configurations, lifted by the arm at its middle (``sin(pi u)``) as far as needed to stay
    no lower over the design than its lower end less :data:`JOINT_LINK_CLEARANCE_TOL_MM`; None
    where that line would leave the joint margins, come near the wrist singularity, jump between
    waypoints, leave the workspace box, or need more than :data:`JOINT_LINK_MAX_LIFT_MM` of lift.
    ``clearance(q)``: (n,) heights of the sensor origin over the design surface, mm."""
    q0, q1 = seg.q_deg[0], seg.q_deg[-1]
    u = np.linspace(0.0, 1.0, len(seg.q_deg))
    bump = np.sin(np.pi * u)
    line = q0[None] + u[:, None] * (q1 - q0)[None]
    ends = clearance(np.vstack([q0, q1]))
    floor = float(ends.min()) - JOINT_LINK_CLEARANCE_TOL_MM
    J = _position_jacobian(0.5 * (q0 + q1), settings)
    up_dq = np.linalg.pinv(J) @ np.array([0.0, 0.0, 1.0])  # the axes' change per mm of lift
    lift = 0.0
    for _ in range(20):
        q = line + np.outer(bump * lift, up_dq)
        c = clearance(q)
        short = floor - float(c.min())
        if short <= 0.0:
            break
        # aimed 0.5 mm above the floor: the lift converges from below, this ends it in a few rounds
        lift += (short + 0.5) / max(float(bump[int(np.argmin(c))]), 0.2)
        if lift > JOINT_LINK_MAX_LIFT_MM:
            return _kept(seg, f"more than {JOINT_LINK_MAX_LIFT_MM:.0f} mm of lift needed")
    else:
        return _kept(seg, "no lift keeps the clearance")
    arm = q[:, -6:]
    if (arm < settings.q_min_deg).any() or (arm > settings.q_max_deg).any():
        return _kept(seg, "beyond the joint margins")
    if float(np.abs(arm[:, 4]).min()) < settings.wrist_margin_deg:
        return _kept(seg, "near the wrist singularity")
    if float(np.abs(np.diff(q[:, -6:], axis=0)).max()) > settings.max_waypoint_joint_step_deg:
        return _kept(seg, "a joint step between waypoints beyond the continuity limit")
    T = fk_batch(q, settings.T_flange_sensor, track=settings.track)
    pos = T[:, :3, 3]
    lo, hi = np.asarray(settings.workspace_min_mm), np.asarray(settings.workspace_max_mm)
    if np.any((pos < lo) | (pos > hi)):
        return _kept(seg, "outside the workspace box")
    return Segment(
        kind=seg.kind, label=seg.label, pos_mm=pos, R_base_sensor=T[:, :3, :3], q_deg=q, joint_line=True
    )


def joint_space_links(
    segments: list[Segment], settings: PlannerSettings, surface, placement: Placement
) -> dict[str, float]:
    """Replace, in ``segments`` (joints solved), every link at rest at both ends (the edge passes'
    corners) by its line in joint space (:func:`_joint_space_link`) where that is faster: the
    Cartesian hump through a corner turns the sensor on a geodesic, and the wrist's joints 4 and 6
    then turn unevenly along it (on the sail, up to 104 deg on joint 6 with its peak rate several
    times its mean), which a rest-to-rest law at one rate must take at the peak's pace. Returns
    the seconds saved, by link label. Every sample of the timed plan still passes the envelope.
    Only links that turn the sensor by at least :data:`JOINT_LINK_MIN_TURN_DEG` (a link between
    neighbouring raster passes keeps its hump: without flying turnarounds it is the stop-and-go
    plan). With a track only where the carriage stands still on the link (held): following the
    passes, it keeps its lead on the sensor along every segment, which a line in joint space would
    break."""
    T_world_plate = placement_transform(placement)
    T_plate_world = np.linalg.inv(T_world_plate)

    def clearance(q: np.ndarray) -> np.ndarray:
        p = fk_batch(q, settings.T_flange_sensor, track=settings.track)[:, :3, 3]
        pp = p @ T_plate_world[:3, :3].T + T_plate_world[:3, 3]
        return pp[:, 2] - surface.height_and_gradient(pp[:, 0], pp[:, 1])[0]

    saved: dict[str, float] = {}
    for k, seg in enumerate(segments):
        if seg.kind != "link" or seg.flying or seg.q_deg is None or len(seg.q_deg) < 3:
            continue
        if rotation_angle_deg(seg.R_base_sensor[0], seg.R_base_sensor[-1]) < JOINT_LINK_MIN_TURN_DEG:
            continue
        if seg.q_deg.shape[1] == 7 and float(np.ptp(seg.q_deg[:, 0])) > 1e-9:
            continue  # the carriage follows the passes on this link
        line = _joint_space_link(seg, settings, clearance)
        if line is None:
            continue
        try:
            before, after = rest_to_rest_s(seg, settings), rest_to_rest_s(line, settings)
        except PlanRefused:
            continue
        if after < before:
            segments[k] = line
            saved[seg.label] = round(before - after, 3)
    return saved


def _wrist_wound(exc: PlanRefused) -> bool:
    """The refusal is joint 4 or 6 at a limit on an edge pass or a link (the wrist's turns used up)."""
    return (exc.pass_label or "").startswith(("edge", "link")) and (exc.limit or "").startswith(
        ("joint_4", "joint_6")
    )


def _by_wrist_roll(built: list[tuple], settings: PlannerSettings, kin, hold_mm: float | None) -> list[tuple]:
    """The pass orientations (sign, segments, margin, edge tilts) in the order the wrist likes them:
    least roll on joints 4 and 6 at the first sweep's first pose (unreachable last), with the
    carriage held at ``hold_mm`` (None: following the passes abreast)."""
    costs = []
    for option in built:
        sweep = _in_base_frame_only(option[1], settings, lambda k, _: k == 1, hold_mm=hold_mm)[0]
        q0 = first_configuration(kin, pose_matrix(sweep.pos_mm[:1], sweep.R_base_sensor[:1])[0], settings)
        costs.append((np.inf if q0 is None else abs(q0[3]) + abs(q0[5]), option))
    costs.sort(key=lambda c: c[0])
    return [c[1] for c in costs]


def lower_bound_s(segments: list[Segment], settings: PlannerSettings) -> float:
    """No timing of these segments is shorter: the sweeps at the scan speed, everything else at the
    TCP speed cap (which the envelope holds every set-point to), s."""
    return float(
        sum(
            s.length_mm / (settings.scan_speed_mm_s if s.is_sweep else settings.tcp_speed_max_mm_s)
            for s in segments
        )
    )


def estimate_s(segments: list[Segment], timed: list[Segment], settings: PlannerSettings) -> float:
    """The scan time of ``segments`` (not yet solved) as :func:`lower_bound_s` plus, for each of
    their links, turnarounds, approach and retract, the mean time a timed plan's (``timed``, the same
    plate along its other axis) took above its own bound: its sweeps at the scan speed (optimistic:
    a pass slowed by a limit along one axis may not be along the other), its turnarounds as slow as
    the other axis' (the same pass step, loops and speeds), s."""
    others = [s for s in timed if not s.is_sweep]
    excess = sum(s.duration_s - s.length_mm / settings.tcp_speed_max_mm_s for s in others) / max(
        len(others), 1
    )
    n_other = sum(1 for s in segments if not s.is_sweep)
    return lower_bound_s(segments, settings) + n_other * max(excess, 0.0)


def _orientations(
    surface, placement: Placement, settings: PlannerSettings, axis: str, raster_cache: dict
) -> list[tuple]:
    """The passes along ``axis`` with the sensor looking either way round: (sign, segments, margin,
    edge tilts) for sign +1 and -1, their raster passes computed once per sign into ``raster_cache``
    (one per axis).

    Raises:
        PlanRefused: out of reach (either way round: the carriage following the passes gives the arm
            the most room, said before any inverse kinematics), or out of the depth range.
    """
    built = []
    for sign in (1.0, -1.0):
        segments, margin, tilts = _build(
            surface, placement, settings, sign, axis=axis, edge_reverse=False, raster_cache=raster_cache
        )
        if sign > 0:
            check_reach(in_base_frame(segments, settings)[0], settings)
        built.append((sign, segments, margin, tilts))
    return built


@dataclass
class _Solved:
    """One axis's plan before the coverage prediction: its joint path, segments, timing, choices."""

    axis: str
    path: JointPathResult
    segments: list[Segment]
    margin: float
    timing: TimingResult
    choices: dict


def _solve(
    surface,
    placement: Placement,
    settings: PlannerSettings,
    kin,
    axis: str,
    built: list[tuple],
    raster_cache: dict,
) -> _Solved:
    """The joint path and timing of the passes along ``axis`` (:func:`_orientations`' ``built``, its
    ``raster_cache``).

    The sensor may look along the pass either way round; the one the wrist likes better (less roll on
    joints 4 and 6) is tried first, the other when the first is refused. With a track: first hold the
    carriage where the plate's footprint centre is abreast of the base (a plate within the fixed
    arm's reach then gets the rail-less cell's plan), then follow the passes at a few along-rail
    offsets of the sensor from the base.

    Raises:
        PlanRefused: no orientation, carriage mode or edge order is within the limits (the reason
            given is the carriage following the passes': it gives the arm the most room).
    """
    if settings.track is None:
        modes: list[tuple[float | None, float]] = [(None, 0.0)]
    else:
        centre = placement_transform(placement) @ np.array(
            [
                0.5 * (surface.x_min_mm + surface.x_max_mm),
                0.5 * (surface.y_min_mm + surface.y_max_mm),
                0.0,
                1.0,
            ]
        )
        follow: list[tuple[float | None, float]] = [(None, lead) for lead in TRACK_LEADS_MM]
        modes = ([(hold_position_mm(centre[:3], settings), 0.0)] if settings.track_hold else []) + follow
    refusals: dict[bool, PlanRefused] = {}  # the first refusal when following / holding
    reversed_built: dict[float, tuple] = {}
    path = None
    for hold, lead in modes:
        for option in _by_wrist_roll(built, settings, kin, hold):
            sign = option[0]
            try:
                path = solve_joint_path(option[1], settings, kin, track_lead_mm=lead, track_hold_mm=hold)
                _, segments, margin, edge_tilts = option
                edge_reverse = False
                break
            except PlanRefused as exc:
                log.info(
                    "plan_orientation_refused",
                    axis=axis,
                    sign=sign,
                    track_hold_mm=hold,
                    track_lead_mm=lead,
                    reason=str(exc),
                )
                refusals.setdefault(hold is None, exc)
                if not _wrist_wound(exc):
                    continue
            # the wrist ran out of turns on joint 4 or 6 going round the edges: go round the other way
            if sign not in reversed_built:
                reversed_built[sign] = (
                    sign,
                    *_build(
                        surface,
                        placement,
                        settings,
                        sign,
                        axis=axis,
                        edge_reverse=True,
                        raster_cache=raster_cache,
                    ),
                )
            try:
                # the raster passes are the same: their joints carry over from the attempt just refused
                path = solve_joint_path(
                    reversed_built[sign][1],
                    settings,
                    kin,
                    track_lead_mm=lead,
                    track_hold_mm=hold,
                    solved=option[1],
                )
                _, segments, margin, edge_tilts = reversed_built[sign]
                edge_reverse = True
                break
            except PlanRefused as exc:
                log.info(
                    "plan_orientation_refused", axis=axis, sign=sign, track_hold_mm=hold, track_lead_mm=lead,
                    edge_reverse=True, reason=str(exc),
                )  # fmt: skip
        if path is not None:
            break
    else:
        raise refusals.get(True) or refusals[False]
    choices: dict = {}
    if settings.track is not None:
        choices["track"] = (
            {"mode": "hold", "hold_mm": hold} if hold is not None else {"mode": "follow", "lead_mm": lead}
        )
    if edge_tilts:
        choices["edge_tilt_deg"] = dict(edge_tilts)
    if edge_reverse:
        choices["edge_order"] = "reversed"
    saved = joint_space_links(segments, settings, surface, placement)
    if saved:
        choices["joint_space_links_saved_s"] = saved
    return _Solved(axis, path, segments, margin, time_segments(segments, settings), choices)


def start_corner_near(
    design: TriMesh, placement: Placement, settings: PlannerSettings, axes_mm_deg: np.ndarray
) -> tuple[int, int]:
    """The footprint's corner nearest the sensor at the arm's configuration ``axes_mm_deg`` ((6,)
    joints in deg, or (7,) the track in mm then the joints with ``settings.track``), as
    ``settings.start_corner`` takes it: ``(sx, sy)``, the sides of the plate frame's x and y (the
    sides of the footprint's centre the sensor is on). The serpentine started there leaves the
    shortest move to the plan's start (on the sail from the simulator's home, 1.20 m instead of
    1.38 m of the sensor's path)."""
    q = np.asarray(axes_mm_deg, dtype=np.float64)
    if q.shape != (settings.n_axes,) or not np.all(np.isfinite(q)):
        raise PlanInputError(f"start_corner_near: the arm's axes must be ({settings.n_axes},) finite values")
    p_world = fk_batch(q[None], settings.T_flange_sensor, track=settings.track)[0, :3, 3]
    T = placement_transform(placement)
    p_plate = T[:3, :3].T @ (p_world - T[:3, 3])
    xy = np.asarray(design.vertices_mm, dtype=np.float64)[:, :2]
    centre = 0.5 * (xy.min(axis=0) + xy.max(axis=0))
    return (1 if p_plate[0] >= centre[0] else -1, 1 if p_plate[1] >= centre[1] else -1)


def plan_scan(
    design: TriMesh,
    placement: Placement,
    settings: PlannerSettings | None = None,
    *,
    with_coverage: bool = True,
    cycle_s: float = EGM_CYCLE_S,
) -> ScanPlan:
    """Plan a coverage scan of ``design`` lying at ``placement``.

    Args:
        design: the design top surface, plate frame, mm.
        placement: the plate frame's nominal pose on the bed (base frame; the world frame with a
            track, whose positions the planner chooses along each pass).
        settings: sensor, scan and robot numbers (defaults: the cell.toml defaults).
        with_coverage: run the ray-cast coverage prediction (the plan's ``coverage`` is zero otherwise).
        cycle_s: EGM cycle the plan is checked against the safety envelope at.

    Raises:
        PlanInputError: unusable design or settings.
        PlanRefused: the plate cannot be scanned with these limits; names the pass, point and limit
            (with ``pass_axis`` "fastest", the passes along the longer axis' reason).

    ``pass_axis`` "fastest": the passes along each footprint axis are built, and the axis whose
    :func:`lower_bound_s` is smaller is solved and timed first (the inverse kinematics and timing
    are most of the planning time); the other is solved only when its :func:`estimate_s` (its bound
    plus its turnarounds as slow as the first's) is below that plan's scan time, or when the first
    is refused, and the faster plan is kept. The plan's ``choices["pass_axis"]`` says which axis,
    and for each its bound, estimate and scan time, or why it was skipped or refused.
    """
    settings = settings or PlannerSettings()
    if not isinstance(design, TriMesh):
        raise PlanInputError(f"design: expected a TriMesh, got {type(design).__name__}")
    if not placement.flat:
        raise PlanInputError(f"placement.rpy_deg: plates lie flat on the bed, got {placement.rpy_deg}")
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    surface = design_surface(design)
    kin = sensor_kinematics(settings)
    timings["surface_s"] = time.perf_counter() - t0

    # The passes run along the footprint's longer or shorter axis (pass_axis; "fastest": the one
    # whose timed scan is shorter, the other where one is refused). An axis whose passes cannot be
    # timed shorter than the plan already in hand (lower_bound_s) is not solved at all.
    axes = PASS_AXES if settings.pass_axis == "fastest" else (settings.pass_axis,)
    t1 = time.perf_counter()
    options: dict[str, list[tuple] | PlanRefused] = {}
    caches: dict[str, dict] = {axis: {} for axis in axes}
    for axis in axes:
        try:
            options[axis] = _orientations(surface, placement, settings, axis, caches[axis])
        except PlanRefused as exc:
            options[axis] = exc
    timings["passes_s"] = time.perf_counter() - t1
    bounds = {a: lower_bound_s(o[0][1], settings) for a, o in options.items() if isinstance(o, list)}

    t2 = time.perf_counter()
    best: _Solved | None = None
    refusals = {a: o for a, o in options.items() if isinstance(o, PlanRefused)}
    considered: dict[str, dict] = {a: {"refused": str(o)} for a, o in refusals.items()}
    for axis in sorted(bounds, key=bounds.get):
        considered[axis] = {"lower_bound_s": round(bounds[axis], 2)}
        if best is not None:
            guess = estimate_s(options[axis][0][1], best.segments, settings)
            considered[axis]["estimate_s"] = round(guess, 2)
            if guess >= best.timing.scan_time_s:
                considered[axis]["skipped"] = f"estimated {guess:.1f} s, not below {best.axis}'s"
                continue
        try:
            solved = _solve(surface, placement, settings, kin, axis, options[axis], caches[axis])
        except PlanRefused as exc:
            considered[axis]["refused"] = str(exc)
            refusals[axis] = exc
            continue
        considered[axis]["scan_time_s"] = round(solved.timing.scan_time_s, 2)
        if best is None or solved.timing.scan_time_s < best.timing.scan_time_s:
            best = solved
    timings["joint_path_s"] = time.perf_counter() - t2
    if best is None:
        # refused along every axis: the reason given is the passes along the longer one's
        raise refusals.get("longer") or next(iter(refusals.values()))
    path, segments, margin, timing = best.path, best.segments, best.margin, best.timing
    choices = dict(best.choices)
    if len(axes) > 1:
        choices["pass_axis"] = {"axis": best.axis, "considered": considered}
    if settings.start_corner is not None:
        choices["start_corner"] = list(settings.start_corner)

    # the plan must pass the same envelope every executed set-point passes, at the EGM cycle
    t_env = time.perf_counter()
    check_plan_envelope(timing.trajectory, segments, settings, cycle_s)
    timings["envelope_s"] = time.perf_counter() - t_env

    t4 = time.perf_counter()
    if with_coverage:
        coverage = predict_coverage(segments, design, surface, placement, settings)
    else:
        coverage = CoverageReport(0.0, 0.0, 0, 0, settings.coverage_cell_mm, 0, 0)
    timings["coverage_s"] = time.perf_counter() - t4
    timings["total_s"] = time.perf_counter() - t0

    plan = ScanPlan(
        placement=placement,
        footprint_mm=(surface.x_min_mm, surface.x_max_mm, surface.y_min_mm, surface.y_max_mm),
        segments=segments,
        trajectory=timing.trajectory,
        coverage=coverage,
        scan_speed_mm_s=settings.scan_speed_mm_s,
        sweep_length_mm=timing.sweep_length_mm,
        sweep_time_s=timing.sweep_time_s,
        scan_time_s=timing.scan_time_s,
        sweep_ratio=timing.sweep_ratio,
        margin_mm=margin,
        scan_speed_deviation=timing.scan_speed_deviation,
        toppra_time_s=timing.toppra_time_s,
        timings_s=timings,
        choices=choices,
    )
    log.info(
        "scan_planned",
        passes=sum(1 for s in segments if s.kind == "scan"),
        edges=sum(1 for s in segments if s.kind == "edge"),
        coverage=round(coverage.fraction, 4),
        scan_time_s=round(timing.scan_time_s, 2),
        sweep_ratio=round(timing.sweep_ratio, 4),
        min_wrist_deg=round(path.min_wrist_deg, 2),
        min_limit_margin_deg=round(path.min_limit_margin_deg, 2),
        plan_s=round(timings["total_s"], 3),
    )
    return plan
