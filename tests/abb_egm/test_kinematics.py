"""IRB 4600-40/2.55 kinematics: known pose, FK/IK round trips, limits, Jacobian, batch FK, the
closed-form IK's branches against FK and against the damped solver."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from drivers.abb_egm.kinematics import (
    KinematicsError,
    RobotKinematics,
    fk_batch,
    ik_branches,
    matrix_from_quat_wxyz,
    nearest_branch,
    quat_wxyz_from_matrix,
)
from drivers.abb_egm.limits import Q_MAX_DEG, Q_MIN_DEG, LinearTrack

KIN = RobotKinematics()
# a sensor 150 mm out along the flange z axis, tilted 10 deg about the flange y axis
_c, _s = np.cos(np.deg2rad(10)), np.sin(np.deg2rad(10))
T_FLANGE_SENSOR = np.array([[_c, 0, _s, 20.0], [0, 1, 0, -5.0], [-_s, 0, _c, 150.0], [0, 0, 0, 1]])


def test_all_joints_zero_puts_the_flange_at_1580_0_1765_mm():
    pose = KIN.fk(np.zeros(6))
    np.testing.assert_allclose(pose.pos_mm, [1580.0, 0.0, 1765.0], atol=1e-9)
    # tool0 z points along base x at home (rpy (0, pi/2, 0))
    np.testing.assert_allclose(pose.T_base_frame[:3, 2], [1.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(pose.quat_wxyz, [np.sqrt(0.5), 0, np.sqrt(0.5), 0], atol=1e-12)


def test_joint_1_rotates_the_flange_about_base_z():
    pose = KIN.fk(np.array([90.0, 0, 0, 0, 0, 0]))
    np.testing.assert_allclose(pose.pos_mm, [0.0, 1580.0, 1765.0], atol=1e-9)


def test_tool_frame_is_the_flange_pose_composed_with_the_tool_transform():
    kin = RobotKinematics(tools={"sensor": T_FLANGE_SENSOR})
    q = np.array([10.0, 20.0, -30.0, 40.0, 50.0, 60.0])
    T_flange = kin.fk(q).T_base_frame
    np.testing.assert_allclose(kin.fk(q, "sensor").T_base_frame, T_flange @ T_FLANGE_SENSOR, atol=1e-9)
    np.testing.assert_allclose(kin.fk_batch(q[None], "sensor")[0], T_flange @ T_FLANGE_SENSOR, atol=1e-9)


def test_unknown_frame_and_bad_shapes_raise_kinematics_error():
    with pytest.raises(KinematicsError, match="unknown frame"):
        KIN.fk(np.zeros(6), "laser")
    with pytest.raises(KinematicsError, match=r"shape \(6,\)"):
        KIN.fk(np.zeros(5))
    with pytest.raises(KinematicsError, match="non-finite"):
        KIN.fk(np.array([0, 0, np.nan, 0, 0, 0]))
    with pytest.raises(KinematicsError, match="rotation"):
        KIN.add_tool("bad", np.diag([2.0, 1, 1, 1]))


def test_batch_fk_agrees_with_pinocchio_over_random_configurations():
    rng = np.random.default_rng(1)
    q = rng.uniform(Q_MIN_DEG, Q_MAX_DEG, size=(300, 6))
    expected = np.array([KIN.fk(qi).T_base_frame for qi in q])
    np.testing.assert_allclose(fk_batch(q), expected, atol=1e-9)


def test_jacobian_matches_finite_differences_in_mm_and_deg():
    q = np.array([15.0, 10.0, -20.0, 30.0, 40.0, 50.0])
    J = KIN.jacobian(q)
    h = 1e-4
    for i in range(6):
        dq = np.zeros(6)
        dq[i] = h
        dp = (KIN.fk(q + dq).pos_mm - KIN.fk(q - dq).pos_mm) / (2 * h)
        np.testing.assert_allclose(J[:3, i], dp, rtol=1e-5, atol=1e-6)
        R0, R1 = KIN.fk(q - dq).T_base_frame[:3, :3], KIN.fk(q + dq).T_base_frame[:3, :3]
        dR = R1 @ R0.T
        w_deg = np.rad2deg(np.array([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]]) / 2)
        np.testing.assert_allclose(J[3:, i], w_deg / (2 * h), rtol=1e-4, atol=1e-6)


_inner = st.tuples(*[st.floats(lo * 0.85, hi * 0.85) for lo, hi in zip(Q_MIN_DEG, Q_MAX_DEG, strict=True)])
_offset = st.tuples(*[st.floats(-8.0, 8.0)] * 6)


@settings(max_examples=80, deadline=None)
@given(q=_inner, offset=_offset)
def test_ik_recovers_a_reachable_pose_from_a_nearby_seed(q, offset):
    q = np.array(q)
    # Keep farther from the three singularities than the seed offset (8 deg): across one, the pose has a
    # second solution as close to the seed, and either is correct. Wrist: q5 = 0.
    if abs(q[4]) < 10.0:
        q[4] = 10.0 if q[4] >= 0 else -10.0
    # Elbow: forearm (wrist centre) in line with the upper arm.
    q3_stretched = -90.0 + np.rad2deg(np.arctan2(0.175, 1.270))
    if abs(q[2] - q3_stretched) < 12.0:
        q[2] = q3_stretched + (12.0 if q[2] >= q3_stretched else -12.0)
    target = KIN.fk(q, "flange").T_base_frame
    # Shoulder: the wrist centre (135 mm behind the flange along its z) on the axis of joint 1.
    wrist_centre = target[:3, 3] - 135.0 * target[:3, 2]
    assume(np.hypot(wrist_centre[0], wrist_centre[1]) > 100.0)
    result = KIN.ik(target, q + np.array(offset))
    assert result.converged, result
    assert result.pos_err_mm < 1e-3 and result.rot_err_deg < 1e-3
    np.testing.assert_allclose(KIN.fk(result.q_deg).T_base_frame[:3, 3], target[:3, 3], atol=2e-3)
    assert KIN.within_limits(result.q_deg)
    # the DLS solver stays on the seed's branch (joint space is ill-conditioned near q5 = 0: 0.05 deg)
    np.testing.assert_allclose(result.q_deg, q, atol=5e-2)


def test_ik_for_a_tool_frame_round_trips():
    kin = RobotKinematics(tools={"sensor": T_FLANGE_SENSOR})
    q = np.array([-20.0, 30.0, -10.0, 15.0, 60.0, -30.0])
    result = kin.ik(kin.fk(q, "sensor").T_base_frame, q + 5.0, "sensor")
    assert result.converged
    np.testing.assert_allclose(result.q_deg, q, atol=1e-2)


def test_ik_never_leaves_the_joint_limits_even_for_an_unreachable_target():
    target = KIN.fk(np.zeros(6)).T_base_frame.copy()
    target[:3, 3] = [5000.0, 0.0, 1000.0]  # 5 m away: outside the 2.55 m reach
    result = KIN.ik(target, np.zeros(6), max_iterations=100)
    assert not result.converged
    assert KIN.within_limits(result.q_deg)
    assert result.pos_err_mm > 1000.0


def test_ik_respects_a_limit_that_the_unconstrained_solution_would_cross():
    # joint 3 upper limit is +75 deg: a pose whose only nearby solution needs q3 = 80 stays clipped
    q_beyond = np.array([0.0, 0.0, 80.0, 0.0, 30.0, 0.0])
    target = KIN.fk(q_beyond).T_base_frame
    result = KIN.ik(target, np.array([0.0, 0.0, 70.0, 0.0, 30.0, 0.0]))
    assert result.q_deg[2] <= Q_MAX_DEG[2] + 1e-9
    assert KIN.within_limits(result.q_deg)


@settings(max_examples=50, deadline=None)
@given(q=st.tuples(*[st.floats(-1.0, 1.0)] * 4).filter(lambda v: np.linalg.norm(v) > 1e-3))
def test_quaternion_matrix_conversions_round_trip(q):
    quat = np.array(q) / np.linalg.norm(q)
    quat = -quat if quat[0] < 0 else quat
    back = quat_wxyz_from_matrix(matrix_from_quat_wxyz(quat))
    assert np.allclose(back, quat, atol=1e-9) or np.allclose(back, -quat, atol=1e-9)


_anywhere = st.tuples(
    *[st.floats(lo, hi) for lo, hi in zip(Q_MIN_DEG, Q_MAX_DEG, strict=True)]
)  # joints 4 and 6 over their whole +-400 deg


@settings(max_examples=200, deadline=None)
@given(q=_anywhere)
def test_the_closed_form_branches_hold_the_configuration_and_all_reproduce_its_pose(q):
    q = np.array(q)
    assume(abs(q[4]) > 0.5)  # off the wrist singularity, where joints 4 and 6 are one rotation
    # and off the elbow's stretched singularity, where the two elbow branches meet: there a seed 3 deg
    # away can be nearer the other branch (hypothesis found q = (0, 0, -83, 0, 1, 0))
    q3_stretched = -90.0 + np.rad2deg(np.arctan2(0.175, 1.270))
    assume(abs(q[2] - q3_stretched) > 6.0)
    T = fk_batch(q[None])
    branches = ik_branches(T)[0]
    valid = ~np.isnan(branches[:, 0])
    assert valid[:4].all()  # the shoulder facing the wrist centre reaches it, both elbows
    # every branch puts the flange exactly there
    np.testing.assert_allclose(fk_batch(branches[valid]), np.repeat(T, valid.sum(), axis=0), atol=1e-7)
    # one branch is the configuration itself, up to whole turns of a joint
    turns = (branches[valid] - q + 180.0) % 360.0 - 180.0
    assert np.min(np.max(np.abs(turns), axis=1)) < 1e-6
    # and from a seed near it, the nearest in the joint limits is exactly it (turns of 4 and 6 too)
    got = nearest_branch(branches, q + 3.0 * np.sign(np.sin(np.arange(6.0) + 1.0)), Q_MIN_DEG, Q_MAX_DEG)
    np.testing.assert_allclose(got, q, atol=1e-6)


@settings(max_examples=60, deadline=None)
@given(q=_inner, offset=_offset)
def test_the_nearest_closed_form_branch_is_where_the_damped_solver_converges(q, offset):
    q = np.array(q)
    assume(abs(q[4]) > 10.0)
    q3_stretched = -90.0 + np.rad2deg(np.arctan2(0.175, 1.270))
    assume(abs(q[2] - q3_stretched) > 12.0)
    kin = RobotKinematics(tools={"sensor": T_FLANGE_SENSOR})
    target = kin.fk(q, "sensor").T_base_frame
    wrist_centre = kin.fk(q).T_base_frame[:3, 3] - 135.0 * kin.fk(q).T_base_frame[:3, 2]
    assume(np.hypot(wrist_centre[0], wrist_centre[1]) > 100.0)
    seed = q + np.array(offset)
    damped = kin.ik(target, seed, "sensor")
    assert damped.converged
    closed = nearest_branch(kin.ik_branches(target[None], "sensor")[0], seed, kin.q_min_deg, kin.q_max_deg)
    np.testing.assert_allclose(closed, damped.q_deg, atol=1e-3)


def test_a_pose_out_of_reach_has_no_branch_and_one_beyond_the_limits_no_nearest():
    target = KIN.fk(np.zeros(6)).T_base_frame.copy()
    target[:3, 3] = [5000.0, 0.0, 1000.0]
    assert np.isnan(ik_branches(target[None])).all()
    # joint 3 at 80 deg (limit 75): the branch exists, but no solution inside narrowed limits
    T = fk_batch(np.array([[0.0, 0.0, 80.0, 0.0, 30.0, 0.0]]))
    branches = ik_branches(T)[0]
    lo, hi = Q_MIN_DEG.copy(), Q_MAX_DEG.copy()
    hi[2] = 75.0
    got = nearest_branch(branches, np.array([0.0, 0.0, 70.0, 0.0, 30.0, 0.0]), lo, hi)
    assert got is None or abs(got[2] - 80.0) > 1.0  # never the configuration beyond the limit


def test_the_closed_form_refuses_a_model_on_a_track_and_bad_shapes():
    track = LinearTrack(np.zeros(3), np.array([0.0, 1.0, 0.0]), 0.0, 6000.0, 1000.0)
    with pytest.raises(KinematicsError, match="arm alone"):
        RobotKinematics(track=track).ik_branches(np.eye(4)[None])
    with pytest.raises(KinematicsError, match="shape"):
        KIN.ik_branches(np.eye(4))
