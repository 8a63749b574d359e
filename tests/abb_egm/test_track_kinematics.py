"""Kinematics on a linear track: a prismatic first joint carries the arm, poses are in the world frame."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.abb_egm.kinematics import KinematicsError, RobotKinematics, fk_batch
from drivers.abb_egm.limits import Q_MAX_DEG, Q_MIN_DEG, LinearTrack

TRACK = LinearTrack(
    origin_mm=[250.0, -3000.0, 100.0], direction=[0.0, 2.0, 0.0], travel_min_mm=0.0, travel_max_mm=6000.0,
    speed_max_mm_s=1000.0,
)  # fmt: skip
T_FLANGE_SENSOR = np.eye(4)
T_FLANGE_SENSOR[:3, 3] = [0.0, 0.0, 150.0]


def test_direction_is_normalised_and_bad_tracks_are_refused():
    np.testing.assert_allclose(TRACK.direction, [0.0, 1.0, 0.0])
    with pytest.raises(KinematicsError, match="zero vector"):
        LinearTrack(
            origin_mm=[0, 0, 0], direction=[0, 0, 0], travel_min_mm=0, travel_max_mm=1, speed_max_mm_s=1
        )
    with pytest.raises(KinematicsError, match="below travel_max_mm"):
        LinearTrack(
            origin_mm=[0, 0, 0], direction=[1, 0, 0], travel_min_mm=5, travel_max_mm=5, speed_max_mm_s=1
        )


def test_the_model_has_seven_axes_with_the_track_first():
    kin = RobotKinematics(track=TRACK)
    assert kin.n_axes == 7 and kin.model.nq == 7 and kin.model.names[1] == "track"
    assert kin.q_min_deg[0] == 0.0 and kin.q_max_deg[0] == 6000.0 and kin.qd_max_deg_s[0] == 1000.0
    with pytest.raises(KinematicsError, match=r"axes_mm_deg must have shape \(7,\)"):
        kin.fk(np.zeros(6))


@settings(max_examples=40, deadline=None)
@given(
    track_mm=st.floats(0.0, 6000.0, allow_nan=False),
    u=st.lists(st.floats(0.05, 0.95), min_size=6, max_size=6),
)
def test_world_pose_is_the_base_pose_carried_along_the_track(track_mm: float, u: list[float]):
    q = Q_MIN_DEG + np.asarray(u) * (Q_MAX_DEG - Q_MIN_DEG)
    axes = np.concatenate([[track_mm], q])
    kin = RobotKinematics(tools={"sensor": T_FLANGE_SENSOR}, track=TRACK)
    fixed = RobotKinematics(tools={"sensor": T_FLANGE_SENSOR})
    T_world = kin.fk(axes, "sensor").T_base_frame
    T_base = fixed.fk(q, "sensor").T_base_frame
    expected = TRACK.T_world_base(track_mm) @ T_base
    np.testing.assert_allclose(T_world, expected, atol=1e-9)
    np.testing.assert_allclose(fk_batch(axes[None], T_FLANGE_SENSOR, track=TRACK)[0], expected, atol=1e-9)
    np.testing.assert_allclose(kin.fk_batch(axes[None], "sensor")[0], expected, atol=1e-9)


def test_jacobian_track_column_is_the_direction_and_matches_finite_differences():
    kin = RobotKinematics(tools={"sensor": T_FLANGE_SENSOR}, track=TRACK)
    axes = np.array([1500.0, 10.0, 30.0, -20.0, 15.0, 40.0, -30.0])
    J = kin.jacobian(axes, "sensor")
    assert J.shape == (6, 7)
    np.testing.assert_allclose(J[:, 0], [0.0, 1.0, 0.0, 0.0, 0.0, 0.0], atol=1e-12)
    h = 1e-5
    for i in range(7):
        d = np.zeros(7)
        d[i] = h
        dp = (kin.fk(axes + d, "sensor").pos_mm - kin.fk(axes - d, "sensor").pos_mm) / (2 * h)
        np.testing.assert_allclose(dp, J[:3, i], rtol=1e-5, atol=1e-5)


def test_ik_holds_the_track_unless_told_to_move_it():
    kin = RobotKinematics(tools={"sensor": T_FLANGE_SENSOR}, track=TRACK)
    goal = np.array([2500.0, 5.0, 25.0, -10.0, 5.0, 45.0, 10.0])
    T = kin.fk(goal, "sensor").T_base_frame
    seed = goal + np.array([0.0, 3.0, -3.0, 2.0, 2.0, -3.0, 3.0])
    held = kin.ik(T, seed, "sensor")
    assert held.converged and held.q_deg[0] == 2500.0
    # a target 800 mm further along the track: the free solver reaches it by moving the carriage
    far = T.copy()
    far[:3, 3] += 800.0 * TRACK.direction
    free = kin.ik(far, goal, "sensor", move_track=True, max_iterations=400)
    assert free.converged and free.q_deg[0] > 2500.0
    np.testing.assert_allclose(kin.fk(free.q_deg, "sensor").T_base_frame, far, atol=1e-3)
