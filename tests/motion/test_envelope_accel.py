"""The envelope's joint acceleration rule on whole trajectories: a plan, fresh or cached, whose
accelerations the arm cannot follow is refused before anything moves."""

from __future__ import annotations

import numpy as np
import pytest
from structlog.testing import capture_logs

from analysis.design.plates import design_mesh, plate_spec
from cellctl.motion import EnvelopeLimits, SafetyEnvelope
from cellctl.motion.envelope import EnvelopeViolation
from cellctl.planning.cache import PlanCache, _entry_bytes, _read_entry
from tests.support.plans import SMALL_PLACEMENT, SMALL_SETTINGS

CYCLE_S = 0.004032
LIMITS = EnvelopeLimits.from_settings(SMALL_SETTINGS, CYCLE_S)
Q_MID = np.array([0.0, 20.0, 10.0, 0.0, 45.0, 0.0])


def rest_to_rest(joint: int, accel_deg_s2: float, half_s: float = 0.2) -> tuple[np.ndarray, np.ndarray]:
    """Accelerate ``joint`` at ``accel_deg_s2`` for ``half_s``, then brake as hard: at rest at both ends."""
    t = np.arange(0.0, 2 * half_s + 1e-12, CYCLE_S)
    s = np.where(t <= half_s, 0.5 * accel_deg_s2 * t**2,
                 accel_deg_s2 * half_s**2 - 0.5 * accel_deg_s2 * (2 * half_s - t) ** 2)  # fmt: skip
    q = np.tile(Q_MID, (t.size, 1))
    q[:, joint] += s
    return t, q


def test_accelerations_within_the_limits_pass_and_twice_the_limit_is_refused_naming_the_joint():
    env = SafetyEnvelope(LIMITS)
    amax = LIMITS.joint_accel_max_deg_s2
    assert amax is not None
    t, q = rest_to_rest(3, 0.8 * amax[3], half_s=0.1)
    env.check_trajectory(t, q)
    t, q = rest_to_rest(3, 2.0 * amax[3], half_s=0.05)
    with pytest.raises(EnvelopeViolation) as exc:
        env.check_trajectory(t, q)
    assert exc.value.rule == "joint_accel" and exc.value.joint == 3
    assert exc.value.value == pytest.approx(2.0 * amax[3], rel=0.05)
    assert "joint_4" in str(exc.value) or "4" in str(exc.value)


def test_without_acceleration_limits_the_rule_is_not_applied():
    limits = EnvelopeLimits(
        q_min_deg=LIMITS.q_min_deg, q_max_deg=LIMITS.q_max_deg, workspace_min_mm=LIMITS.workspace_min_mm,
        workspace_max_mm=LIMITS.workspace_max_mm, tcp_speed_max_mm_s=LIMITS.tcp_speed_max_mm_s,
        joint_speed_max_deg_s=LIMITS.joint_speed_max_deg_s, cycle_s=CYCLE_S, T_flange_tcp=LIMITS.T_flange_tcp,
    )  # fmt: skip
    t, q = rest_to_rest(3, 2.0 * LIMITS.joint_accel_max_deg_s2[3], half_s=0.05)
    SafetyEnvelope(limits).check_trajectory(t, q)


def test_a_plan_starting_with_a_jolt_is_refused():
    """A trajectory that is not at rest at its start: its first speed is an acceleration from rest."""
    t = np.arange(0.0, 0.5, CYCLE_S)
    q = np.tile(Q_MID, (t.size, 1))
    q[:, 1] += 5.0 * t  # 5 deg/s from the first cycle: 5 / 4 ms = 1240 deg/s^2 > 300
    with pytest.raises(EnvelopeViolation) as exc:
        SafetyEnvelope(LIMITS).check_trajectory(t, q)
    assert exc.value.rule == "joint_accel" and exc.value.joint == 1


def test_a_cached_plan_edited_to_extreme_accelerations_is_refused_and_replanned(tmp_path):
    design = design_mesh(plate_spec("sail", length_mm=200.0, width_mm=150.0), pitch_mm=5.0)
    cache = PlanCache(tmp_path / "plan-cache")
    first = cache.plan(design, SMALL_PLACEMENT, SMALL_SETTINGS, with_coverage=False)
    path = cache.path(first.key)
    header, arrays = _read_entry(path.read_bytes())
    qdd = arrays["qdd_deg_s2"]
    # a valid entry, the same key, every position, speed and step inside its limits: only the stored
    # acceleration of joint 2 at one sample in the middle of a pass is five times its limit (the
    # executor interpolates the samples with their accelerations)
    sweep = [i for i, s in enumerate(first.plan.segments) if s.kind == "scan"][1]
    rows = np.flatnonzero(arrays["segment"] == sweep)
    qdd[rows[rows.size // 2], 1] = 5.0 * SMALL_SETTINGS.joint_accel_max_deg_s2[1]
    path.write_bytes(_entry_bytes(header, arrays))
    with capture_logs() as logs:
        again = cache.plan(design, SMALL_PLACEMENT, SMALL_SETTINGS, with_coverage=False)
    assert not again.hit
    reasons = [e["reason"] for e in logs if e["event"] == "plan_cache_ignored"]
    assert reasons and "joint_accel" in reasons[0], reasons
    np.testing.assert_allclose(again.plan.trajectory.q_deg, first.plan.trajectory.q_deg, atol=1e-6)
