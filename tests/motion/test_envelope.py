"""The safety envelope: every rule rejects, nothing is clamped, the last accepted set-point stays."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cellctl.motion import EnvelopeLimits, EnvelopeViolation, SafetyEnvelope
from cellctl.planning import PlannerSettings
from drivers.abb_egm.kinematics import fk_batch

CYCLE_S = 0.004032
Q_HOME = np.array([0.0, 20.0, 20.0, 0.0, 50.0, 0.0])
LIMITS = EnvelopeLimits.from_settings(PlannerSettings(), CYCLE_S)


def fresh() -> SafetyEnvelope:
    env = SafetyEnvelope(LIMITS)
    env.reset(Q_HOME)
    return env


def test_a_small_step_inside_every_limit_is_accepted_and_returns_the_tcp():
    env = fresh()
    q = Q_HOME + np.array([0.002, -0.002, 0.001, 0.0, 0.002, 0.2])
    p = env.check(q)
    np.testing.assert_allclose(p, fk_batch(q[None], LIMITS.T_flange_tcp)[0, :3, 3], atol=1e-6)
    np.testing.assert_array_equal(env.last_q_deg, q)


def test_joint_beyond_its_limit_with_margin_is_a_violation_not_a_clamp():
    env = SafetyEnvelope(LIMITS)
    q = Q_HOME.copy()
    q[2] = LIMITS.q_max_deg[2] + 0.01
    env.reset(q - np.array([0, 0, 0.05, 0, 0, 0]))
    before = env.last_q_deg
    with pytest.raises(EnvelopeViolation) as info:
        env.check(q)
    assert info.value.rule == "joint_limit" and info.value.joint == 2
    assert "joint_3" in str(info.value)
    np.testing.assert_array_equal(env.last_q_deg, before)  # the rejected set-point was not taken
    assert env.violations == 1


def test_tcp_outside_the_workspace_box_is_a_violation():
    limits = EnvelopeLimits.from_settings(
        PlannerSettings(workspace_min_mm=(-500.0, -2000.0, 1500.0)), CYCLE_S
    )
    env = SafetyEnvelope(limits)
    with pytest.raises(EnvelopeViolation) as info:
        env.check(Q_HOME)
    assert info.value.rule == "workspace" and "z" in str(info.value)


def test_joint_step_above_the_speed_limit_per_cycle_is_a_violation():
    env = fresh()
    q = Q_HOME.copy()
    # joint 6 turns the sensor about its own axis: the TCP does not move, only the step rule can trip
    q[5] += LIMITS.joint_speed_max_deg_s[5] * CYCLE_S * 1.5
    with pytest.raises(EnvelopeViolation) as info:
        env.check(q)
    assert info.value.rule == "joint_step" and info.value.joint == 5
    # the same step spread over two cycles (a lost packet) is allowed
    env2 = fresh()
    env2.check(q, cycles=2)


def test_tcp_faster_than_the_cap_is_a_violation_even_with_each_joint_within_its_speed():
    env = fresh()
    # joint 2 at 80 % of its speed swings the sensor at about 1.7 m: far above 250 mm/s
    q = Q_HOME.copy()
    q[1] += 0.8 * LIMITS.joint_speed_max_deg_s[1] * CYCLE_S
    with pytest.raises(EnvelopeViolation) as info:
        env.check(q)
    assert info.value.rule == "tcp_speed" and info.value.value > LIMITS.tcp_speed_max_mm_s


def test_non_finite_set_point_is_rejected_with_its_own_rule():
    env = fresh()
    with pytest.raises(EnvelopeViolation) as info:
        env.check(np.array([0.0, np.nan, 0, 0, 0, 0]))
    assert info.value.rule == "input"


def test_trajectory_check_names_the_first_offending_sample():
    t = np.arange(50) * CYCLE_S
    q = np.repeat(Q_HOME[None], 50, axis=0)
    q[30:, 4] = LIMITS.q_max_deg[4] + 1.0
    with pytest.raises(EnvelopeViolation) as info:
        SafetyEnvelope(LIMITS).check_trajectory(t, q)
    assert info.value.rule == "joint_limit" and info.value.sample == 30 and info.value.joint == 4


def test_a_path_without_a_time_law_is_checked_on_positions_only_and_names_its_first_bad_row():
    """The move to the plan's start (a joint-space line, its time law made cycle by cycle) is
    checked before it starts: joint limits and the workspace box, not the speed rules."""
    env = SafetyEnvelope(LIMITS)
    far = Q_HOME + np.array([40.0, -10.0, 15.0, 30.0, -20.0, 60.0])  # one row apart: no speed rule
    env.check_path(np.vstack([Q_HOME, far]))
    assert env.last_q_deg is None and env.accepted == 0  # a check, not a set-point
    line = Q_HOME[None] + np.linspace(0.0, 1.0, 41)[:, None] * np.array([0, 0, 0, 0, 80.0, 0])[None]
    with pytest.raises(EnvelopeViolation) as info:
        env.check_path(line)
    first = int(np.argmax(line[:, 4] > LIMITS.q_max_deg[4]))
    assert info.value.rule == "joint_limit" and info.value.joint == 4 and info.value.sample == first
    z = fk_batch(line, LIMITS.T_flange_tcp)[:, 2, 3]
    boxed = EnvelopeLimits.from_settings(
        PlannerSettings(workspace_max_mm=(2600.0, 2000.0, float(np.median(z)))), CYCLE_S
    )
    inside = np.nonzero(line[:, 4] <= LIMITS.q_max_deg[4])[0]
    with pytest.raises(EnvelopeViolation) as info:
        SafetyEnvelope(boxed).check_path(line[inside])
    assert info.value.rule == "workspace" and "z" in str(info.value)
    assert info.value.sample == int(np.argmax(z[inside] > np.median(z)))
    with pytest.raises(EnvelopeViolation) as info:
        env.check_path(np.array([Q_HOME, [np.nan] * 6]))
    assert info.value.rule == "input"


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.floats(-1.0, 1.0), min_size=6, max_size=6),
    st.floats(0.0, 3.0),
)
def test_any_set_point_is_either_accepted_within_every_limit_or_rejected_with_a_rule(delta, scale):
    env = fresh()
    q = Q_HOME + np.asarray(delta) * scale
    try:
        p = env.check(q)
    except EnvelopeViolation as exc:
        assert exc.rule in ("joint_limit", "workspace", "tcp_speed", "joint_step")
        assert str(exc)
        np.testing.assert_array_equal(env.last_q_deg, Q_HOME)
        return
    # accepted: every rule holds
    assert np.all(q >= LIMITS.q_min_deg) and np.all(q <= LIMITS.q_max_deg)
    assert np.all(np.abs(q - Q_HOME) <= LIMITS.joint_speed_max_deg_s * CYCLE_S * 1.001)
    p0 = fk_batch(Q_HOME[None], LIMITS.T_flange_tcp)[0, :3, 3]
    assert np.linalg.norm(p - p0) / CYCLE_S <= LIMITS.tcp_speed_max_mm_s * 1.001


def test_executor_and_envelope_take_their_limits_from_cell_toml(repo_root):
    from cellctl.config import load_config
    from cellctl.motion import ExecutorConfig

    cfg = load_config(repo_root / "cell.toml")
    ex = ExecutorConfig.from_config(cfg)
    assert ex.tracking_error_max_mm == cfg.robot.tracking_error_max_mm
    assert ex.feedback_timeout_s == cfg.robot.egm_watchdog_s
    assert ex.joint_jerk_max_deg_s3 == tuple(cfg.robot.joint_jerk_max_deg_s3)
    limits = EnvelopeLimits.from_settings(PlannerSettings.from_config(cfg), CYCLE_S)
    np.testing.assert_allclose(
        limits.q_max_deg, np.asarray(cfg.robot.joint_upper_deg) - cfg.robot.joint_margin_deg
    )
    assert limits.tcp_speed_max_mm_s == cfg.robot.tcp_speed_max_mm_s
