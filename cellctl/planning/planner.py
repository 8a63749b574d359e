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

import numpy as np
import structlog

from analysis.mesh import TriMesh
from cellctl.motion.envelope import EnvelopeLimits, EnvelopeViolation, SafetyEnvelope
from cellctl.motion.trajectory import TimedTrajectory
from cellctl.planning.coverage import build_segments, design_surface, predict_coverage
from cellctl.planning.joint_path import (
    TRACK_LEADS_MM,
    check_reach,
    first_configuration,
    in_base_frame,
    sensor_kinematics,
    solve_joint_path,
)
from cellctl.planning.plan import (
    CoverageReport,
    Placement,
    PlanInputError,
    PlanRefused,
    ScanPlan,
    pose_matrix,
)
from cellctl.planning.settings import PlannerSettings
from cellctl.planning.timing import time_segments

__all__ = ["check_plan_envelope", "plan_scan"]

log = structlog.get_logger(__name__)


def check_plan_envelope(
    trajectory: TimedTrajectory, segments: list, settings: PlannerSettings, cycle_s: float = 0.004032
) -> None:
    """Sample ``trajectory`` at the EGM cycle and check every sample against the safety envelope.

    Raises:
        PlanRefused: naming the segment and the envelope rule that the plan would break.
    """
    envelope = SafetyEnvelope(EnvelopeLimits.from_settings(settings, cycle_s=cycle_s))
    t = np.arange(0.0, trajectory.duration_s, cycle_s)
    t = np.append(t, trajectory.duration_s) if t[-1] < trajectory.duration_s else t
    q = trajectory.sample_many(t)[0]
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


def plan_scan(
    design: TriMesh,
    placement: Placement,
    settings: PlannerSettings | None = None,
    *,
    with_coverage: bool = True,
    cycle_s: float = 0.004032,
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
        PlanRefused: the plate cannot be scanned with these limits; names the pass, point and limit.
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

    # The sensor may look along the pass either way round; take the one the wrist likes better
    # (less roll on joints 4 and 6), and fall back to the other when the first is refused.
    t1 = time.perf_counter()
    candidates = []
    for sign in (1.0, -1.0):
        segments, margin = build_segments(surface, placement, settings, sign=sign)
        # with a track: the poses the arm reaches, relative to its base at the track's positions
        base_segments, _ = in_base_frame(segments, settings)
        if sign > 0:
            # out of reach is out of reach either way round: say so before any inverse kinematics
            check_reach(base_segments, settings)
        sweep = base_segments[1]
        q0 = first_configuration(kin, pose_matrix(sweep.pos_mm[:1], sweep.R_base_sensor[:1])[0], settings)
        cost = np.inf if q0 is None else abs(q0[3]) + abs(q0[5])
        candidates.append((cost, sign, segments, margin))
    candidates.sort(key=lambda c: c[0])
    timings["passes_s"] = time.perf_counter() - t1

    t2 = time.perf_counter()
    refusal: PlanRefused | None = None
    # with a track, each orientation is tried at a few along-rail offsets of the sensor from the base
    leads = TRACK_LEADS_MM if settings.track is not None else (0.0,)
    path = None
    for _, sign, segs_try, margin_try in candidates:
        for lead in leads:
            try:
                path = solve_joint_path(segs_try, settings, kin, track_lead_mm=lead)
                segments, margin = segs_try, margin_try
                break
            except PlanRefused as exc:
                log.info("plan_orientation_refused", sign=sign, track_lead_mm=lead, reason=str(exc))
                refusal = refusal or exc
        if path is not None:
            break
    else:
        assert refusal is not None
        raise refusal
    timings["joint_path_s"] = time.perf_counter() - t2

    t3 = time.perf_counter()
    timing = time_segments(segments, settings)
    timings["timing_s"] = time.perf_counter() - t3

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
