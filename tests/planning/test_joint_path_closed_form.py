"""The joint path's closed-form IK: every waypoint gets the configuration the damped solver,
warm-started from the waypoint before, converges to (the plans are the same as before it), and a
pose it cannot take still refuses the plan with the damped solver's reason."""

from __future__ import annotations

import numpy as np
import pytest

from cellctl.planning.joint_path import sensor_kinematics, solve_joint_path
from cellctl.planning.plan import PlanRefused, Segment, pose_matrix
from tests.support.plans import SMALL_SETTINGS


@pytest.mark.parametrize("plan_name", ["small_plan", "sail_plan"])
def test_every_waypoint_is_where_the_damped_solver_from_its_predecessor_converges(plan_name, request):
    plan = request.getfixturevalue(plan_name)
    kin = sensor_kinematics(SMALL_SETTINGS)  # the same sensor frame as PlannerSettings()
    q_prev = plan.segments[0].q_deg[0]
    worst = 0.0
    for seg in plan.segments:
        for T, q in zip(pose_matrix(seg.pos_mm, seg.R_base_sensor), seg.q_deg, strict=True):
            r = kin.ik(T, q_prev, frame="sensor", max_iterations=60, max_step_deg=5.0)
            assert r.converged
            worst = max(worst, float(np.abs(r.q_deg - q).max()))
            q_prev = q
    assert worst < 1e-3  # the damped solver's own tolerance (1e-4 deg, 1e-3 mm)


def test_a_pose_beyond_a_joint_limit_still_refuses_the_plan_naming_the_joint_or_the_pose():
    kin = sensor_kinematics(SMALL_SETTINGS)
    # joint 3 from 40 to 90 deg (its limit is 75, 73 with the margin): the sensor's path is reachable
    # in reach, but only with the elbow beyond its limit
    q = np.tile(np.array([0.0, 20.0, 40.0, 0.0, 60.0, 0.0]), (60, 1))
    q[:, 2] = np.linspace(40.0, 90.0, 60)
    T = kin.fk_batch(q, "sensor")
    seg = Segment(kind="scan", label="pass 1", pos_mm=T[:, :3, 3], R_base_sensor=T[:, :3, :3])
    with pytest.raises(PlanRefused) as exc:
        solve_joint_path([seg], SMALL_SETTINGS, kin, q_start_deg=q[0])
    assert exc.value.pass_label == "pass 1"
    assert "joint_3" in str(exc.value) or "unreachable" in str(exc.value)
    # the waypoints before the refusal are the ones below the limit with its margin
    assert (
        q[exc.value.point_index, 2]
        > SMALL_SETTINGS.joint_upper_deg[2] - SMALL_SETTINGS.joint_margin_deg - 1.0
    )
