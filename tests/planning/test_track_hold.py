"""With a track, a plate within the fixed arm's reach gets the rail-less cell's plan: the carriage
holds where the plate's footprint centre is abreast of the base for the whole scan (issue 20)."""

from __future__ import annotations

import numpy as np

from analysis.contracts.placement import Placement
from analysis.design.plates import design_mesh, plate_spec
from cellctl.planning import PlannerSettings, plan_scan
from cellctl.planning.joint_path import hold_position_mm, track_positions
from cellctl.planning.plan import Segment
from drivers.abb_egm.limits import LinearTrack

EGM_CYCLE_S = 0.004032
#: a 6 m track along +y with the base at mid-travel where the rail-less cell's base is
TRACK = LinearTrack(
    origin_mm=[0.0, -3000.0, 0.0],
    direction=[0.0, 1.0, 0.0],
    travel_min_mm=10.0,
    travel_max_mm=5990.0,
    speed_max_mm_s=1000.0,
    accel_max_mm_s2=2000.0,
    jerk_max_mm_s3=20000.0,
)


def test_the_sail_plate_on_the_track_holds_the_carriage_and_keeps_the_railless_plan():
    sail = design_mesh(plate_spec("sail"), pitch_mm=10.0)
    free = plan_scan(
        sail, Placement.on_bed(1500.0, 0.0, 3.0, z_mm=300.0), PlannerSettings(), with_coverage=False
    )
    # laid 1 m further along the rail: the carriage holds 1 m further on, the arm sees the same plate
    shifted = Placement.on_bed(1500.0, 1000.0, 3.0, z_mm=300.0)
    railed = plan_scan(sail, shifted, PlannerSettings(track=TRACK), with_coverage=False)

    assert abs(railed.scan_time_s - free.scan_time_s) <= EGM_CYCLE_S
    assert abs(railed.sweep_time_s - free.sweep_time_s) <= EGM_CYCLE_S
    carriage = railed.trajectory.q_deg[:, 0]
    assert np.all(carriage == 4000.0)
    assert len(railed.segments) == len(free.segments)
    for a, b in zip(railed.segments, free.segments, strict=True):
        assert a.label == b.label
        assert np.all(a.q_deg[:, 0] == 4000.0)
        np.testing.assert_allclose(a.q_deg[:, 1:], b.q_deg, atol=1e-6)
        np.testing.assert_allclose(a.pos_mm - [0.0, 1000.0, 0.0], b.pos_mm, atol=1e-6)


def test_the_hold_position_puts_the_centre_abreast_of_the_base_within_the_travel():
    s = PlannerSettings(track=TRACK)
    assert hold_position_mm(np.array([1500.0, 250.0, 300.0]), s) == 3250.0
    assert hold_position_mm(np.array([1500.0, 4000.0, 300.0]), s) == 5990.0  # clipped to the travel
    assert hold_position_mm(np.array([1500.0, -9000.0, 300.0]), s) == 10.0
    assert hold_position_mm(np.array([1500.0, 0.0, 300.0]), PlannerSettings()) is None


def test_a_held_carriage_stays_put_on_every_waypoint_and_a_following_one_moves_along_the_pass():
    s = PlannerSettings(track=TRACK)
    pos = np.column_stack([np.full(11, 1500.0), np.linspace(-500.0, 500.0, 11), np.full(11, 400.0)])
    seg = Segment("scan", "scan 1", pos, np.broadcast_to(np.eye(3), (11, 3, 3)).copy())
    held = track_positions([seg], s, hold_mm=2800.0)
    assert np.all(held[0] == 2800.0)
    following = track_positions([seg], s)
    np.testing.assert_allclose(following[0], pos[:, 1] + 3000.0)


def test_track_hold_off_makes_the_carriage_follow_the_passes_even_within_reach():
    """``[robot.track] hold = false``: the commissioning engineer's way to see the carriage scan."""
    demo = design_mesh(plate_spec("sail", length_mm=600.0, width_mm=400.0), pitch_mm=10.0)
    placement = Placement.on_bed(1500.0, 0.0, 0.0, z_mm=300.0)
    held = plan_scan(demo, placement, PlannerSettings(track=TRACK), with_coverage=False)
    followed = plan_scan(demo, placement, PlannerSettings(track=TRACK, track_hold=False), with_coverage=False)
    assert held.choices["track"]["mode"] == "hold"
    assert followed.choices["track"]["mode"] == "follow"
    carriage = np.concatenate([s.q_deg[:, 0] for s in followed.segments if s.kind == "scan"])
    assert float(np.ptp(carriage)) > 100.0  # the carriage moves from pass to pass across the plate
    assert float(np.ptp(np.concatenate([s.q_deg[:, 0] for s in held.segments]))) == 0.0


def test_track_hold_is_read_from_cell_toml():
    from pathlib import Path

    from cellctl.config import load_config

    cfg = load_config(Path(__file__).resolve().parents[2] / "docs/examples/cell-track.toml")
    assert PlannerSettings.from_config(cfg).track_hold is True
    data = cfg.model_dump()
    data["robot"]["track"]["hold"] = False
    assert PlannerSettings.from_config(type(cfg).model_validate(data)).track_hold is False
