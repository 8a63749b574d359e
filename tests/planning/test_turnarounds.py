"""Flying turnarounds (issue 22): neighbouring raster passes joined at speed outside the plate,
timed with the passes as one path; the plan stays inside the envelope and covers the same."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import settings as hyp_settings
from hypothesis import strategies as st

from analysis.design.plates import design_mesh, plate_spec
from cellctl.planning import PlannerSettings, ScanPlan, plan_scan
from cellctl.planning.timing import tcp_speed_mm_s
from drivers.abb_egm.kinematics import fk_batch
from tests.support.plans import SMALL_PLACEMENT, SMALL_SETTINGS

CYCLE_S = 0.004032


@pytest.fixture(scope="module")
def design():
    return design_mesh(plate_spec("sail", length_mm=300.0, width_mm=200.0), pitch_mm=5.0)


@pytest.fixture(scope="module")
def plans(design) -> tuple[ScanPlan, ScanPlan]:
    flying = plan_scan(design, SMALL_PLACEMENT, SMALL_SETTINGS)
    stop_and_go = plan_scan(design, SMALL_PLACEMENT, SMALL_SETTINGS.with_(flying_turns=False))
    return flying, stop_and_go


def _speed_in(plan: ScanPlan, k: int) -> np.ndarray:
    tr = plan.trajectory
    m = tr.segment == k
    return tcp_speed_mm_s(tr.q_deg[m], tr.qd_deg_s[m], SMALL_SETTINGS.T_flange_sensor)


def test_neighbouring_raster_passes_are_joined_by_turnarounds_flown_at_speed(plans):
    flying, _ = plans
    segs = flying.segments
    turns = [k for k, s in enumerate(segs) if s.flying]
    raster_links = [
        k for k in range(1, len(segs) - 1) if segs[k - 1].kind == "scan" and segs[k + 1].kind == "scan"
    ]
    assert raster_links and set(raster_links) <= set(turns)
    for k in turns:
        v = _speed_in(flying, k)
        # never at rest on the turnaround or at its joins with the passes
        assert v.min() > 0.3 * flying.scan_speed_mm_s, (segs[k].label, v.min())
        # outside the plate: beyond where the pass before it ends, along that pass
        d = segs[k - 1].pos_mm[-1] - segs[k - 1].pos_mm[-2]
        d /= np.linalg.norm(d)
        ahead = (segs[k].pos_mm - segs[k - 1].pos_mm[-1]) @ d
        assert ahead.max() > 5.0 and ahead.min() >= min(0.0, float(ahead[-1])) - 1e-6


def test_the_joins_are_continuous_in_joint_speed_and_acceleration(plans):
    flying, _ = plans
    tr = flying.trajectory
    t = np.arange(0.0, tr.duration_s, CYCLE_S)
    _, qd, qdd, _ = tr.sample_many(t)
    # per cycle, the speed changes no more than the acceleration limit allows, the acceleration no
    # more than the jerk limit: at the joins as everywhere
    dv = np.abs(np.diff(qd, axis=0)) / CYCLE_S
    assert np.all(dv <= 1.02 * np.asarray(SMALL_SETTINGS.joint_accel_max_deg_s2))
    da = np.abs(np.diff(qdd, axis=0)) / CYCLE_S
    assert np.all(da <= 1.05 * np.asarray(SMALL_SETTINGS.joint_jerk_max_deg_s3))


def test_flying_turnarounds_are_faster_cover_the_same_and_keep_the_scan_speed(plans):
    flying, stop_and_go = plans
    # 0.2 s saved per turnaround between raster passes (the last pass's link to the first edge pass
    # is a line in joint space when not flown, about as fast: planner.joint_space_links)
    segs = flying.segments
    raster_turns = sum(
        1
        for k in range(1, len(segs) - 1)
        if segs[k].flying and segs[k - 1].kind == segs[k + 1].kind == "scan"
    )
    assert raster_turns >= 4
    assert flying.scan_time_s < stop_and_go.scan_time_s - 0.2 * raster_turns
    assert flying.time_parts_s()["sweep_s"] < stop_and_go.time_parts_s()["sweep_s"]  # fewer speed ramps
    assert flying.sweep_length_mm == pytest.approx(stop_and_go.sweep_length_mm)
    assert flying.coverage.fraction == pytest.approx(stop_and_go.coverage.fraction, abs=1e-3)
    assert flying.coverage.fraction >= 0.99
    assert flying.scan_speed_deviation <= max(stop_and_go.scan_speed_deviation, 0.05) + 1e-6
    # the parts still add up, and every pass reports the time from the previous one
    parts = flying.time_parts_s()
    assert sum(parts.values()) == pytest.approx(flying.scan_time_s, abs=len(flying.segments) * 0.02)
    assert all(p["transition_s"] > 0 for p in flying.pass_times()[1:])


def test_a_turnaround_keeps_its_height_above_the_surface(plans):
    flying, _ = plans
    for k, s in enumerate(flying.segments):
        if s.flying:
            lowest_end = min(flying.segments[k - 1].pos_mm[-1, 2], flying.segments[k + 1].pos_mm[0, 2])
            assert s.pos_mm[:, 2].min() >= lowest_end - 5.0 - 1e-6


def test_the_flying_flag_survives_the_json_round_trip(plans):
    flying, _ = plans
    back = ScanPlan.from_json(flying.to_json())
    assert [s.flying for s in back.segments] == [s.flying for s in flying.segments]


def test_the_sensor_path_stays_on_the_passes_at_the_joins(plans):
    """The chain's one spline through all waypoints must not bend the passes near their ends."""
    flying, _ = plans
    tr = flying.trajectory
    for k, s in enumerate(flying.segments):
        if s.kind != "scan":
            continue
        m = tr.segment == k
        p = fk_batch(tr.q_deg[m], SMALL_SETTINGS.T_flange_sensor)[:, :3, 3]
        a, b = s.pos_mm[0], s.pos_mm[-1]
        d = (b - a) / np.linalg.norm(b - a)
        off = p - a
        lateral = np.linalg.norm(off - (off @ d)[:, None] * d[None], axis=1)
        # the raster line itself bends with the surface (a few mm over the plate); no more than that
        ref = s.pos_mm - a
        ref_lateral = np.linalg.norm(ref - (ref @ d)[:, None] * d[None], axis=1)
        assert lateral.max() <= ref_lateral.max() + 0.5, (s.label, lateral.max(), ref_lateral.max())


def test_default_settings_fly_the_turnarounds():
    assert PlannerSettings().flying_turns


@pytest.fixture(scope="module")
def cell_sail_plan() -> ScanPlan:
    """The 1200 x 800 sail with cell.toml's settings as shipped (200 mm/s: 1 mm at 200 Hz)."""
    from pathlib import Path

    from cellctl.config import load_config

    cfg = load_config(Path(__file__).resolve().parents[2] / "cell.toml")
    return plan_scan(
        design_mesh(plate_spec("sail"), pitch_mm=10.0),
        cfg.sim.placement.to_placement(),
        PlannerSettings.from_config(cfg),
    )


def test_turnarounds_use_the_jerk_budget_and_the_passes_keep_the_scan_speed_between_their_ramps(
    cell_sail_plan,
):
    """At 60 % of the jerk limits a turnaround came back onto its pass at ~150 mm/s and the next
    pass was still speeding up 25 mm in (the sail's pass interiors deviated 28 % from 200 mm/s,
    transitions 13.78 s); the plan now uses 80 % of them, the executor's stop ramps the rest."""
    plan = cell_sail_plan
    assert plan.scan_speed_mm_s == pytest.approx(200.0)
    assert plan.scan_speed_deviation <= 0.02
    settings = PlannerSettings()
    jmax = np.asarray(settings.joint_jerk_max_deg_s3)
    tr = plan.trajectory
    t = np.arange(0.0, tr.duration_s, CYCLE_S)
    _, _, qdd, _ = tr.sample_many(t)
    jerk = np.abs(np.diff(qdd, axis=0)) / CYCLE_S
    seg = tr.segment[np.clip(np.searchsorted(tr.t_s, t[1:], side="right") - 1, 0, tr.segment.size - 1)]
    flying = np.array([s.flying for s in plan.segments])[seg]
    assert np.all(jerk <= 0.9 * jmax)  # the stop ramps' 20 % stays free
    # a turnaround runs at the jerk its limit share allows (it is jerk-bound): above 60 % somewhere
    assert float(np.max(jerk[flying] / jmax)) > 0.6
    assert plan.time_parts_s()["transitions_s"] < 13.0


def test_raster_turnarounds_are_u_turns_faster_than_the_quintic_loop_and_turning_links_go_at_rest(
    cell_sail_plan,
):
    """The U-turn (coverage._UTURN_OUT) keeps the joints' jerk in the reversal lower than the quintic
    Hermite loop did (0.36-0.44 s each on this plate, transitions 12.59 s); the link from the last
    raster pass to the tilted edge passes turns the sensor 30 deg and goes at rest as a line in joint
    space, timed along that line (0.64 s: the wrist's joint 4 at its limits; flown, 1.26 s)."""
    from cellctl.planning.coverage import JOINT_LINK_MIN_TURN_DEG
    from cellctl.planning.plan import rotation_angle_deg

    segs = cell_sail_plan.segments
    raster_turns = [s for k, s in enumerate(segs[1:-1], 1) if segs[k - 1].kind == segs[k + 1].kind == "scan"]
    assert len(raster_turns) == 22 and all(s.flying for s in raster_turns)
    assert max(s.duration_s for s in raster_turns) < 0.38
    for s in segs:
        if (
            s.kind == "link"
            and rotation_angle_deg(s.R_base_sensor[0], s.R_base_sensor[-1]) >= JOINT_LINK_MIN_TURN_DEG
        ):
            assert not s.flying and s.joint_line, s.label
    assert cell_sail_plan.time_parts_s()["transitions_s"] < 11.2


def _turning_angles(pos: np.ndarray) -> np.ndarray:
    d = np.diff(pos, axis=0)
    d /= np.linalg.norm(d, axis=1)[:, None]
    return np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", d[:-1], d[1:]), -1.0, 1.0)))


@hyp_settings(max_examples=60, deadline=None)
@given(
    step=st.floats(20.0, 80.0),
    stagger=st.floats(-0.5, 0.5),
    rise=st.floats(-15.0, 15.0),
    skew_deg=st.floats(-9.0, 9.0),
    heading_deg=st.floats(0.0, 360.0),
)
def test_a_turnaround_meets_both_passes_in_position_and_direction_without_curvature(
    step, stagger, rise, skew_deg, heading_deg
):
    """Whatever the pass ends (staggered, at another height, the next pass not quite parallel), the
    turnaround starts and ends on them, leaves and arrives along them, and its curvature grows from
    zero at both ends (the joint path stays continuous in speed and acceleration at the joins)."""
    from cellctl.planning.coverage import _turn_path

    h = np.radians(heading_deg)
    t0 = np.array([np.cos(h), np.sin(h), 0.0])
    side = np.array([-np.sin(h), np.cos(h), 0.0])
    p0 = np.array([100.0, -50.0, 400.0])
    p1 = p0 + step * side + stagger * step * t0 + np.array([0.0, 0.0, rise])
    k = np.radians(skew_deg)
    t1 = -(np.cos(k) * t0 + np.sin(k) * side)
    pos = _turn_path(p0, t0, p1, t1, 0.25)  # finely sampled: the curve itself, not its waypoints
    np.testing.assert_allclose(pos[0], p0, atol=1e-9)
    np.testing.assert_allclose(pos[-1], p1, atol=1e-9)
    first, last = pos[1] - pos[0], pos[-1] - pos[-2]
    assert np.degrees(np.arccos(first @ t0 / np.linalg.norm(first))) < 1.0
    assert np.degrees(np.arccos(last @ t1 / np.linalg.norm(last))) < 1.0
    turn = _turning_angles(pos)
    assert turn[0] < 0.15 * turn.max() and turn[-1] < 0.15 * turn.max()
