"""The safety envelope with a linear track: the track's travel, speed and acceleration are checked
like the arm's joints, refused with a reason, never clamped; the TCP speed cap counts the carriage."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cellctl.config import parse_config
from cellctl.motion import EnvelopeLimits, EnvelopeViolation, SafetyEnvelope
from cellctl.planning import PlannerSettings
from drivers.abb_egm.limits import LinearTrack

CYCLE_S = 0.004032
TRACK = LinearTrack(
    origin_mm=[0.0, 0.0, 0.0], direction=[1.0, 0.0, 0.0], travel_min_mm=0.0, travel_max_mm=4000.0,
    speed_max_mm_s=500.0, accel_max_mm_s2=1000.0,
)  # fmt: skip
Q_HOME = np.array([0.0, 20.0, 20.0, 0.0, 50.0, 0.0])
#: the TCP cap above the track's speed, so the track's own rules are what trips
LIMITS = EnvelopeLimits.from_settings(PlannerSettings(track=TRACK, tcp_speed_max_mm_s=1000.0), CYCLE_S)


def axes(track_mm: float, q_deg=Q_HOME) -> np.ndarray:
    return np.concatenate([[track_mm], q_deg])


def fresh(track_mm: float = 2000.0) -> SafetyEnvelope:
    env = SafetyEnvelope(LIMITS)
    env.reset(axes(track_mm))
    return env


def test_track_limits_come_from_cell_toml_shrunk_by_the_margin():
    cfg = parse_config({"robot": {"egm_max_pos_deviation_deg": 6000.0, "track": {"travel_min_mm": -100.0, "travel_max_mm": 5000.0, "margin_mm": 25.0,
                                            "speed_max_mm_s": 800.0, "accel_max_mm_s2": 1500.0}}})  # fmt: skip
    limits = EnvelopeLimits.from_settings(PlannerSettings.from_config(cfg), CYCLE_S)
    assert limits.n_axes == 7
    assert (limits.track.travel_min_mm, limits.track.travel_max_mm) == (-75.0, 4975.0)
    assert (limits.track.speed_max_mm_s, limits.track.accel_max_mm_s2) == (800.0, 1500.0)
    assert EnvelopeLimits.from_settings(PlannerSettings.from_config(parse_config({})), CYCLE_S).track is None


def test_a_six_value_set_point_is_refused_when_the_cell_has_a_track():
    env = fresh()
    with pytest.raises(EnvelopeViolation) as info:
        env.check(Q_HOME)
    assert info.value.rule == "input" and "7 finite values" in str(info.value)


def test_track_beyond_its_travel_is_refused_with_the_limit_and_not_clamped():
    env = fresh(3999.0)
    before = env.last_q_deg
    with pytest.raises(EnvelopeViolation) as info:
        env.check(axes(4000.5))
    assert info.value.rule == "track_travel" and info.value.limit == 4000.0
    assert "upper travel limit 4000.00 mm" in str(info.value)
    np.testing.assert_array_equal(env.last_q_deg, before)


def test_track_step_above_its_speed_is_refused():
    env = fresh()
    # accelerate within the limits to just below the speed cap, then one step too fast
    v, s = 0.0, 2000.0
    while v < 495.0:
        v = min(v + 1000.0 * CYCLE_S * 0.99, 495.0)
        s += v * CYCLE_S
        env.check(axes(s))
    with pytest.raises(EnvelopeViolation) as info:
        env.check(axes(s + 503.0 * CYCLE_S))
    assert info.value.rule == "track_speed" and "above its limit 500.0 mm/s" in str(info.value)


def test_track_jump_from_rest_is_refused_on_acceleration():
    env = fresh()
    # 0.1 mm in one cycle from rest: 25 mm/s, far below the speed cap, but 6200 mm/s^2
    with pytest.raises(EnvelopeViolation) as info:
        env.check(axes(2000.1))
    assert info.value.rule == "track_accel" and info.value.limit == 1000.0


def test_a_path_is_checked_on_the_track_travel_too():
    env = SafetyEnvelope(LIMITS)
    path = np.vstack([axes(2000.0), axes(3000.0), axes(LIMITS.track.travel_max_mm + 5.0)])
    with pytest.raises(EnvelopeViolation) as info:
        env.check_path(path)
    assert info.value.rule == "track_travel" and info.value.sample == 2
    env.check_path(path[:2])  # 1000 mm in one row: a path has no speed


def test_arm_rules_still_apply_with_a_track():
    env = fresh()
    q = Q_HOME.copy()
    q[2] = LIMITS.q_max_deg[2] + 0.01
    env.reset(axes(2000.0, q - np.array([0, 0, 0.05, 0, 0, 0])))
    with pytest.raises(EnvelopeViolation) as info:
        env.check(axes(2000.0, q))
    assert info.value.rule == "joint_limit" and info.value.joint == 2


def test_tcp_speed_cap_counts_the_carriage():
    limits = EnvelopeLimits.from_settings(PlannerSettings(track=TRACK, tcp_speed_max_mm_s=100.0), CYCLE_S)
    env = SafetyEnvelope(limits)
    env.reset(axes(2000.0))
    # the arm does not move: the TCP moves with the carriage, 120 mm/s in the world frame
    v = 0.0
    s = 2000.0
    with pytest.raises(EnvelopeViolation) as info:
        for _ in range(1000):
            v = min(v + 1000.0 * CYCLE_S * 0.99, 120.0)
            s += v * CYCLE_S
            env.check(axes(s))
    assert info.value.rule == "tcp_speed"


def _ramp(v_peak: float, accel: float, dist_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """A trapezoidal track move of ``dist_mm`` sampled at the EGM cycle, from rest to rest (a short
    move is a triangle: it never reaches ``v_peak``)."""
    v_peak = min(v_peak, float(np.sqrt(accel * dist_mm)))
    t_acc = v_peak / accel
    d_acc = 0.5 * accel * t_acc**2
    t_cruise = max(0.0, (dist_mm - 2 * d_acc) / v_peak)
    total = 2 * t_acc + t_cruise
    t = np.arange(0.0, total + CYCLE_S, CYCLE_S)
    t[-1] = max(t[-1], total)
    s = np.where(t < t_acc, 0.5 * accel * t**2, d_acc + v_peak * (t - t_acc))
    dec = t > t_acc + t_cruise
    td = np.clip(total - t, 0.0, None)
    s = np.where(dec, 2 * d_acc + v_peak * t_cruise - 0.5 * accel * td**2, s)
    return t, s


def test_trajectory_within_the_track_limits_passes_and_beyond_is_refused():
    env = SafetyEnvelope(LIMITS)
    t, s = _ramp(450.0, 900.0, 1500.0)
    q = np.column_stack([500.0 + s, np.tile(Q_HOME, (s.size, 1))])
    env.check_trajectory(t, q)
    t, s = _ramp(450.0, 1300.0, 1500.0)
    q = np.column_stack([500.0 + s, np.tile(Q_HOME, (s.size, 1))])
    with pytest.raises(EnvelopeViolation) as info:
        env.check_trajectory(t, q)
    assert info.value.rule == "track_accel" and info.value.sample is not None
    t, s = _ramp(600.0, 900.0, 1500.0)
    q = np.column_stack([500.0 + s, np.tile(Q_HOME, (s.size, 1))])
    with pytest.raises(EnvelopeViolation) as info:
        env.check_trajectory(t, q)
    assert info.value.rule == "track_speed"


@settings(max_examples=60, deadline=None)
@given(track_mm=st.floats(-5000.0, 9000.0, allow_nan=False))
def test_track_positions_pass_exactly_when_inside_the_travel(track_mm: float):
    env = SafetyEnvelope(LIMITS)
    env.reset(axes(track_mm))  # a reset places the last set-point; the check then decides
    inside = TRACK.travel_min_mm <= track_mm <= TRACK.travel_max_mm
    if inside:
        env.check(axes(track_mm))
    else:
        with pytest.raises(EnvelopeViolation) as info:
            env.check(axes(track_mm))
        assert info.value.rule == "track_travel"


@settings(max_examples=60, deadline=None)
@given(v_peak=st.floats(50.0, 900.0, allow_nan=False), accel=st.floats(100.0, 2500.0, allow_nan=False))
def test_trapezoidal_track_moves_are_judged_by_their_speed_and_acceleration(v_peak: float, accel: float):
    env = SafetyEnvelope(LIMITS)
    t, s = _ramp(v_peak, accel, 1200.0)
    q = np.column_stack([1000.0 + s, np.tile(Q_HOME, (s.size, 1))])
    # the sampled profile's true peak speed/acceleration (a short move may never reach v_peak)
    v = np.diff(s) / np.diff(t)
    a = np.abs(np.diff(np.concatenate([[0.0], v, [0.0]]))) / CYCLE_S
    ok_speed = np.abs(v).max() <= TRACK.speed_max_mm_s * (1 + 1e-3)
    ok_accel = a.max() <= TRACK.accel_max_mm_s2 * (1 + 2e-2)
    if ok_speed and ok_accel:
        env.check_trajectory(t, q)
    else:
        with pytest.raises(EnvelopeViolation) as info:
            env.check_trajectory(t, q)
        assert info.value.rule == ("track_speed" if not ok_speed else "track_accel")


def test_steps_of_several_cycles_after_lost_packets_are_judged_on_the_same_acceleration():
    # a constant 900 mm/s^2 (within the limit) sent with irregular gaps: 1, 5, 1, 3, 1 cycles. Each
    # speed is a mean over its step, so the change between a 5-cycle and a 1-cycle step spans three
    # cycles, not one: the rule must not see 2.7 times the acceleration it is
    env = fresh(1000.0)
    accel, t, k = 900.0, 0.0, 0
    for gap in [1, 5, 1, 3, 1, 1, 4, 1, 2, 1] * 3:
        k += gap
        t = k * CYCLE_S
        env.check(axes(1000.0 + 0.5 * accel * t * t), cycles=gap)
    # and a true step change of the speed in a multi-cycle gap is still refused
    s_now = 1000.0 + 0.5 * accel * t * t
    v_now = accel * t
    with pytest.raises(EnvelopeViolation) as info:
        env.check(axes(s_now + (v_now + 40.0) * 3 * CYCLE_S), cycles=3)
    assert info.value.rule == "track_accel"
