"""Links sampled finer where the wrist turns fast: near its singularity joints 4 and 6 turn many times
faster than the sensor, and a link's waypoints 3 deg of sensor turn apart can be 15 deg of joint 6
apart. The joint path splits such a link's waypoints and goes on; a sweep is never split, and a jump
on it still refuses the plan."""

from __future__ import annotations

import numpy as np
import pytest

import cellctl.planning.joint_path as joint_path
from analysis.contracts.placement import Placement
from analysis.design.plates import design_mesh, plate_spec
from cellctl.config import load_config
from cellctl.planning import PlannerSettings, plan_scan
from cellctl.planning.joint_path import sensor_kinematics, solve_joint_path, split_waypoints
from cellctl.planning.plan import PlanRefused, Segment, rotation_angle_deg, slerp_frames
from tests.support.e2e_cell import tiny_cell_config
from tests.support.plans import SMALL_PLACEMENT, SMALL_SETTINGS

#: where the locate e2e (seed 17939) found its plate: the corner link from the third edge to the
#: fourth passes joint 5 at 7.7 deg, and its Cartesian waypoints stepped joint 6 by 15.2 deg
LOCATED = Placement.on_bed(1437.6, 62.8, -5.03, z_mm=301.0)


@pytest.fixture(scope="module")
def tiny():
    """The e2e cells' 300 x 200 sail plate."""
    return design_mesh(plate_spec("sail", length_mm=300.0, width_mm=200.0), pitch_mm=5.0)


def _tiny_settings(tmp_path) -> PlannerSettings:
    return PlannerSettings.from_config(load_config(tiny_cell_config(tmp_path)))


def test_a_link_past_the_wrist_singularity_is_split_and_the_plate_is_planned(tiny, tmp_path, monkeypatch):
    settings = _tiny_settings(tmp_path)
    plan = plan_scan(tiny, LOCATED, settings, with_coverage=False)
    for seg in plan.segments:
        q = seg.q_deg[:, -6:]
        assert float(np.abs(np.diff(q, axis=0)).max(initial=0.0)) <= settings.max_waypoint_joint_step_deg
    # without the split the same plate is refused on that link
    monkeypatch.setattr(joint_path, "_MAX_SPLITS", 0)
    with pytest.raises(PlanRefused, match="configuration jump") as exc:
        plan_scan(tiny, LOCATED, settings, with_coverage=False)
    assert exc.value.pass_label.startswith("link")


def test_split_waypoints_keeps_every_waypoint_and_puts_the_new_ones_between():
    R0 = np.eye(3)
    R1 = slerp_frames(
        np.eye(3), np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]), np.array([1.0])
    )[0]
    pos = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 5.0], [20.0, 4.0, 5.0]])
    R = np.stack([R0, slerp_frames(R0, R1, np.array([0.5]))[0], R1])
    seg = Segment(kind="link", label="link 1", pos_mm=pos, R_base_sensor=R, q_deg=np.zeros((3, 6)))
    fine = split_waypoints(seg, 4)
    assert fine.q_deg is None and fine.label == "link 1" and fine.kind == "link"
    assert fine.pos_mm.shape == (9, 3) and fine.R_base_sensor.shape == (9, 3, 3)
    np.testing.assert_allclose(fine.pos_mm[::4], pos, atol=1e-12)
    np.testing.assert_allclose(fine.R_base_sensor[::4], R, atol=1e-12)
    np.testing.assert_allclose(fine.pos_mm[1], [2.5, 0.0, 1.25], atol=1e-12)
    steps = [
        rotation_angle_deg(a, b) for a, b in zip(fine.R_base_sensor[:-1], fine.R_base_sensor[1:], strict=True)
    ]
    np.testing.assert_allclose(steps, 90.0 / 8, atol=1e-9)
    assert fine.length_mm == pytest.approx(seg.length_mm)


def _turned_on_the_spot(kind: str, turn_deg: float) -> list[Segment]:
    """Two waypoints of one pose of the small plan's first sweep, the second turned ``turn_deg`` about
    the sensor's view axis (one joint-6 turn of that size)."""
    first = plan_scan(
        design_mesh(plate_spec("sail", length_mm=200.0, width_mm=150.0), pitch_mm=5.0),
        SMALL_PLACEMENT,
        SMALL_SETTINGS,
        with_coverage=False,
    ).segments[1]
    R0 = first.R_base_sensor[0]
    a = np.deg2rad(turn_deg)
    Rz = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    pos = np.repeat(first.pos_mm[:1], 2, axis=0)
    return [Segment(kind=kind, label=f"{kind} 1", pos_mm=pos, R_base_sensor=np.stack([R0, R0 @ Rz]))]


def test_a_turn_too_fast_for_one_waypoint_is_split_on_a_link_and_refused_on_a_sweep():
    kin = sensor_kinematics(SMALL_SETTINGS)
    link = _turned_on_the_spot("link", 40.0)
    path = solve_joint_path(link, SMALL_SETTINGS, kin)
    assert link[0].pos_mm.shape[0] > 2  # replaced by its split
    assert path.max_step_deg <= SMALL_SETTINGS.max_waypoint_joint_step_deg
    q = link[0].q_deg
    assert abs(q[-1, 5] - q[0, 5]) == pytest.approx(40.0, abs=1.0)
    with pytest.raises(PlanRefused, match="configuration jump") as exc:
        solve_joint_path(_turned_on_the_spot("scan", 40.0), SMALL_SETTINGS, kin)
    assert exc.value.pass_label == "scan 1" and exc.value.point_index == 1
