"""Pose at exposure time: joint interpolation, forward kinematics, hand-eye, profile transform."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cellctl.acquisition.poses import (
    PoseTimeError,
    T_from_pos_rpy,
    interpolate_joints,
    interpolate_poses,
    pos_rpy_from_T,
    sensor_poses,
    transform_profiles,
)
from drivers.abb_egm.kinematics import RobotKinematics, fk_batch
from tests.support.synthetic_scan import T_FLANGE_SENSOR, q_true_deg

EPOCH = 1_000_000_000_000


def test_pose_at_profile_times_matches_fk_of_the_true_joints_within_a_micrometre():
    t_s = np.arange(0.0, 3.0, 0.004032)
    ts_ns = EPOCH + np.rint(t_s * 1e9).astype(np.int64)
    tq_s = np.random.default_rng(0).uniform(0.01, 2.9, 500)
    tq_ns = EPOCH + np.rint(tq_s * 1e9).astype(np.int64)
    got = sensor_poses(ts_ns, q_true_deg(t_s), tq_ns, T_FLANGE_SENSOR, EPOCH)
    want = fk_batch(q_true_deg(tq_s), T_FLANGE_SENSOR)
    assert got.inside.all()
    assert np.max(np.abs(got.T_base_sensor[:, :3, 3] - want[:, :3, 3])) < 1e-3


def test_hand_eye_transform_moves_the_sensor_along_the_flange_axis():
    q = np.array([[0.0, 15.67, 28.77, 0.0, 45.56, 180.0]] * 2)
    ts = np.array([EPOCH, EPOCH + 4_000_000])
    p = sensor_poses(ts, q, ts[:1], T_FLANGE_SENSOR, EPOCH).T_base_sensor[0]
    flange = RobotKinematics().fk(q[0]).T_base_frame
    np.testing.assert_allclose(p[:3, 3], flange[:3, 3] + 150.0 * flange[:3, 2], atol=1e-9)


def test_times_outside_the_history_are_flagged_not_extrapolated():
    ts = EPOCH + np.array([0, 4_000_000, 8_000_000])
    q = np.arange(18.0).reshape(3, 6)
    qi, inside = interpolate_joints(ts, q, np.array([EPOCH - 1, EPOCH + 2_000_000, EPOCH + 9_000_000]), EPOCH)
    assert inside.tolist() == [False, True, False]
    np.testing.assert_allclose(qi[1], (q[0] + q[1]) / 2)
    np.testing.assert_allclose(qi[2], q[2])  # held, not extrapolated


def test_interpolation_rejects_unsorted_history():
    with pytest.raises(PoseTimeError, match="strictly increasing"):
        interpolate_joints(np.array([2, 1]), np.zeros((2, 6)), np.array([1]), 0)


@settings(max_examples=40, deadline=None)
@given(
    pos=st.lists(st.floats(-2000, 2000), min_size=3, max_size=3),
    rpy=st.tuples(st.floats(-179, 179), st.floats(-89, 89), st.floats(-179, 179)),
)
def test_pos_rpy_round_trips_through_the_matrix(pos, rpy):
    T = T_from_pos_rpy(pos, rpy)
    p, r = pos_rpy_from_T(T)
    np.testing.assert_allclose(T_from_pos_rpy(p, r), T, atol=1e-9)


def test_profile_transform_equals_the_matrix_product_per_point():
    rng = np.random.default_rng(4)
    T = fk_batch(q_true_deg(rng.uniform(0, 5, 7)), T_FLANGE_SENSOR)
    x = rng.uniform(-25, 25, (7, 11))
    z = rng.uniform(70, 130, (7, 11))
    got = transform_profiles(T, x, z)
    pts = np.stack([x, np.zeros_like(x), z, np.ones_like(x)], axis=-1)
    want = np.einsum("nij,nwj->nwi", T, pts)[..., :3]
    np.testing.assert_allclose(got, want, atol=2e-4)  # float32 arithmetic


def test_blending_sample_poses_agrees_with_joint_interpolation_and_fk_below_a_micrometre():
    t_s = np.arange(0.0, 5.0, 0.004032)
    ts_ns = EPOCH + np.rint(t_s * 1e9).astype(np.int64)
    tq_ns = EPOCH + np.rint(np.random.default_rng(1).uniform(0.01, 4.9, 2000) * 1e9).astype(np.int64)
    exact = sensor_poses(ts_ns, q_true_deg(t_s), tq_ns, T_FLANGE_SENSOR, EPOCH).T_base_sensor
    T, inside = interpolate_poses(ts_ns, fk_batch(q_true_deg(t_s), T_FLANGE_SENSOR)[:, :3], tq_ns, EPOCH)
    assert inside.all()
    x, z = np.full((len(tq_ns), 2), [-25.0, 25.0]), np.full((len(tq_ns), 2), 130.0)
    p_exact = transform_profiles(exact, x, z).astype(np.float64)
    p_fast = transform_profiles(T, x, z).astype(np.float64)
    assert np.max(np.abs(p_exact - p_fast)) < 1e-3


def test_a_feedback_gap_longer_than_allowed_gives_no_pose():
    ts = EPOCH + np.array([0, 4_000_000, 60_000_000, 64_000_000])
    q = np.zeros((4, 6))
    _, inside = interpolate_joints(
        ts, q, EPOCH + np.array([2_000_000, 30_000_000, 62_000_000]), EPOCH, 25_000_000
    )
    assert inside.tolist() == [True, False, True]


@pytest.mark.parametrize("gap_ms", [20.0, 52.0, 100.0])
def test_a_burst_of_lost_feedback_is_bridged_by_a_cubic_far_closer_than_the_chord(gap_ms):
    """EGM packets lost in a burst leave a gap in the joint samples. The cubic Hermite across it, with
    the slopes of the sample intervals beside it, stays within a few micrometres of the true sensor
    pose on the synthetic scan motion where the chord is off by far more during accelerations."""
    t_s = np.arange(0.0, 3.0, 0.004032)
    keep = ~((t_s > 1.2) & (t_s < 1.2 + gap_ms / 1000.0))  # the burst
    ts_ns = EPOCH + np.rint(t_s[keep] * 1e9).astype(np.int64)
    q = q_true_deg(t_s[keep])
    tq_s = np.linspace(1.2, 1.2 + gap_ms / 1000.0, 50)
    tq_ns = EPOCH + np.rint(tq_s * 1e9).astype(np.int64)
    want = fk_batch(q_true_deg(tq_s), T_FLANGE_SENSOR)[:, :3, 3]
    q_cubic, inside = interpolate_joints(ts_ns, q, tq_ns, EPOCH, max_gap_ns=120_000_000)
    q_chord, _ = interpolate_joints(ts_ns, q, tq_ns, EPOCH, cubic_gap_ns=None)
    err_cubic = np.linalg.norm(fk_batch(q_cubic, T_FLANGE_SENSOR)[:, :3, 3] - want, axis=1).max()
    err_chord = np.linalg.norm(fk_batch(q_chord, T_FLANGE_SENSOR)[:, :3, 3] - want, axis=1).max()
    assert inside.all()
    assert err_cubic < 0.01 and err_cubic < 0.2 * err_chord, (err_cubic, err_chord)
    # the pose fast path (blended sample poses) bridges the same way
    T_samples = fk_batch(q, T_FLANGE_SENSOR)[:, :3, :]
    T, _ = interpolate_poses(ts_ns, T_samples, tq_ns, EPOCH, 120_000_000)
    assert np.linalg.norm(T[:, :3, 3] - want, axis=1).max() < 0.01


def test_samples_one_cycle_apart_are_interpolated_linearly_as_before():
    t_s = np.arange(0.0, 1.0, 0.004032)
    ts_ns = EPOCH + np.rint(t_s * 1e9).astype(np.int64)
    q = q_true_deg(t_s)
    tq_ns = EPOCH + np.rint(np.random.default_rng(1).uniform(0.01, 0.99, 300) * 1e9).astype(np.int64)
    a, _ = interpolate_joints(ts_ns, q, tq_ns, EPOCH)
    b, _ = interpolate_joints(ts_ns, q, tq_ns, EPOCH, cubic_gap_ns=None)
    np.testing.assert_array_equal(a, b)
