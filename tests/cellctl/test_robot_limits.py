"""The robot's limits and the EGM cycle have one home (drivers/abb_egm/limits.py): the configuration,
the planner, the executor, the endpoint and the simulator default to it, and reading a configuration
does not load the kinematics model (pinocchio)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cellctl.config import SimSection, parse_config
from cellctl.motion.envelope import EnvelopeLimits
from cellctl.motion.executor import ExecutorConfig
from cellctl.planning.settings import PlannerSettings
from drivers.abb_egm.endpoint import EgmEndpointConfig
from drivers.abb_egm.kinematics import RobotKinematics
from drivers.abb_egm.limits import EGM_CYCLE_S, Q_MAX_DEG, Q_MIN_DEG, QD_MAX_DEG_S, RobotLimits
from drivers.abb_egm.sim.egm import EgmSimConfig

REPO_ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.process
def test_reading_the_configuration_does_not_load_pinocchio() -> None:
    probe = "import sys, cellctl.config, drivers.abb_egm.limits; print('pinocchio' in sys.modules)"
    out = subprocess.run(
        [sys.executable, "-c", probe], cwd=REPO_ROOT, capture_output=True, text=True, check=True, timeout=60
    )
    assert out.stdout.strip() == "False", out.stderr


def test_every_default_cycle_is_the_egm_cycle() -> None:
    assert EGM_CYCLE_S == 0.004032
    assert ExecutorConfig().cycle_s == EGM_CYCLE_S
    assert EgmSimConfig().cycle_s == EGM_CYCLE_S
    assert EgmEndpointConfig().cycle_s == EGM_CYCLE_S
    assert SimSection().egm_cycle_ms * 1e-3 == EGM_CYCLE_S
    assert EnvelopeLimits.from_settings(PlannerSettings()).cycle_s == EGM_CYCLE_S


def test_the_default_limits_are_the_arms_range_and_rated_speeds() -> None:
    limits = RobotLimits()
    np.testing.assert_array_equal(limits.joint_lower_deg, Q_MIN_DEG)
    np.testing.assert_array_equal(limits.joint_upper_deg, Q_MAX_DEG)
    np.testing.assert_array_equal(limits.joint_speed_max_deg_s, QD_MAX_DEG_S)
    np.testing.assert_array_equal(limits.q_min_deg, Q_MIN_DEG + limits.joint_margin_deg)
    np.testing.assert_array_equal(limits.q_max_deg, Q_MAX_DEG - limits.joint_margin_deg)
    kin = RobotKinematics()
    np.testing.assert_array_equal(kin.q_min_deg, Q_MIN_DEG)
    np.testing.assert_array_equal(kin.qd_max_deg_s, QD_MAX_DEG_S)


def test_configuration_planner_and_executor_default_to_one_robot_limits() -> None:
    limits = RobotLimits()
    cfg = parse_config({})
    assert cfg.robot.limits() == limits
    assert PlannerSettings().limits == limits
    assert PlannerSettings.from_config(cfg).limits == limits
    executor = ExecutorConfig()
    assert executor.joint_speed_max_deg_s == limits.joint_speed_max_deg_s
    assert executor.joint_accel_max_deg_s2 == limits.joint_accel_max_deg_s2
    assert executor.joint_jerk_max_deg_s3 == limits.joint_jerk_max_deg_s3


def test_configured_limits_reach_planner_and_executor_as_one_value() -> None:
    cfg = parse_config(
        {
            "robot": {
                "joint_margin_deg": 3.0,
                "joint_speed_max_deg_s": [100.0, 110.0, 120.0, 130.0, 140.0, 150.0],
                "joint_accel_max_deg_s2": [200.0] * 6,
                "joint_jerk_max_deg_s3": [2000.0] * 6,
            }
        }
    )
    limits = cfg.robot.limits()
    assert limits.joint_margin_deg == 3.0
    assert limits.joint_speed_max_deg_s == (100.0, 110.0, 120.0, 130.0, 140.0, 150.0)
    assert PlannerSettings.from_config(cfg).limits == limits
    executor = ExecutorConfig.from_config(cfg)
    assert executor.joint_speed_max_deg_s == limits.joint_speed_max_deg_s
    assert executor.joint_accel_max_deg_s2 == limits.joint_accel_max_deg_s2
    assert executor.joint_jerk_max_deg_s3 == limits.joint_jerk_max_deg_s3
    from_settings = ExecutorConfig.from_settings(PlannerSettings.from_config(cfg))
    assert from_settings.joint_speed_max_deg_s == limits.joint_speed_max_deg_s
    assert from_settings.joint_jerk_max_deg_s3 == limits.joint_jerk_max_deg_s3


def test_robot_limits_refuse_a_wrong_number_of_joints() -> None:
    with pytest.raises(ValueError, match=r"RobotLimits.joint_speed_max_deg_s: needs 6 values, got 5"):
        RobotLimits(joint_speed_max_deg_s=(1.0,) * 5)
