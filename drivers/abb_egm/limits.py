"""The robot's limits and timing, in one place and without pinocchio: the IRB 4600-40/2.55's joint
ranges and rated speeds, the EGM cycle, the cell's default dynamic limits (:class:`RobotLimits`) and
the linear track's (:class:`LinearTrack`).

Everything that checks or plans against a limit (the kinematics model, the EGM simulator, the
configuration's bounds, the planner's and the executor's settings, the safety envelope) reads its
numbers from here, so a limit is written once. Only numpy is imported: ``cellctl.config`` validates
``[robot]`` against these without loading the kinematics model.

Units are the controller's: degrees, millimetres, seconds.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "EGM_CYCLE_S",
    "JOINT_NAMES",
    "N_ARM_JOINTS",
    "QD_MAX_DEG_S",
    "Q_MAX_DEG",
    "Q_MIN_DEG",
    "KinematicsError",
    "LinearTrack",
    "RobotLimits",
]

#: the EGM sample time of an IRB 4600's controller, s (EGM's "4 ms" is 4.032 ms on the robot)
EGM_CYCLE_S = 0.004032

JOINT_NAMES = ("joint_1", "joint_2", "joint_3", "joint_4", "joint_5", "joint_6")
N_ARM_JOINTS = 6
# The IRB 4600-40/2.55's axis ranges and rated speeds (its product specification, as in the public
# ros-industrial description: docs/reference/abb-egm-rws.md section 4). Read-only: shared arrays.
#: (6,) lower joint range, deg
Q_MIN_DEG = np.array([-180.0, -90.0, -180.0, -400.0, -125.0, -400.0])
#: (6,) upper joint range, deg
Q_MAX_DEG = np.array([180.0, 150.0, 75.0, 400.0, 120.0, 400.0])
#: (6,) rated joint speeds, deg/s
QD_MAX_DEG_S = np.array([175.0, 175.0, 175.0, 250.0, 250.0, 360.0])
for _a in (Q_MIN_DEG, Q_MAX_DEG, QD_MAX_DEG_S):
    _a.flags.writeable = False


def _floats(values: np.ndarray) -> tuple[float, ...]:
    return tuple(float(v) for v in values)


@dataclass(frozen=True)
class RobotLimits:
    """The joint limits a cell plans and commands within (deg, deg/s, deg/s^2, deg/s^3).

    ``joint_lower_deg`` / ``joint_upper_deg`` (6,): the configured range (by default the arm's whole
    range, :data:`Q_MIN_DEG` / :data:`Q_MAX_DEG`); ``joint_margin_deg``: how far inside it a plan
    stays. ``joint_speed_max_deg_s`` (6,): by default the rated speeds (:data:`QD_MAX_DEG_S`);
    ``joint_accel_max_deg_s2`` / ``joint_jerk_max_deg_s3`` (6,): the cell's dynamic limits.
    The defaults are ``cell.toml [robot]``'s; :meth:`cellctl.config.RobotSection.limits` gives a
    configured cell's.
    """

    joint_lower_deg: tuple[float, ...] = field(default_factory=lambda: _floats(Q_MIN_DEG))
    joint_upper_deg: tuple[float, ...] = field(default_factory=lambda: _floats(Q_MAX_DEG))
    joint_margin_deg: float = 2.0
    joint_speed_max_deg_s: tuple[float, ...] = field(default_factory=lambda: _floats(QD_MAX_DEG_S))
    joint_accel_max_deg_s2: tuple[float, ...] = (300.0, 300.0, 300.0, 600.0, 600.0, 800.0)
    joint_jerk_max_deg_s3: tuple[float, ...] = (3000.0, 3000.0, 3000.0, 6000.0, 6000.0, 8000.0)

    def __post_init__(self) -> None:
        for name in (
            "joint_lower_deg",
            "joint_upper_deg",
            "joint_speed_max_deg_s",
            "joint_accel_max_deg_s2",
            "joint_jerk_max_deg_s3",
        ):
            values = tuple(float(v) for v in getattr(self, name))
            if len(values) != N_ARM_JOINTS:
                raise ValueError(f"RobotLimits.{name}: needs {N_ARM_JOINTS} values, got {len(values)}")
            object.__setattr__(self, name, values)

    @property
    def q_min_deg(self) -> np.ndarray:
        """(6,) lower joint limits shrunk by the margin, deg."""
        return np.asarray(self.joint_lower_deg) + self.joint_margin_deg

    @property
    def q_max_deg(self) -> np.ndarray:
        """(6,) upper joint limits shrunk by the margin, deg."""
        return np.asarray(self.joint_upper_deg) - self.joint_margin_deg


class KinematicsError(ValueError):
    """Bad input to a kinematics function (wrong shape, unknown frame, non-finite values)."""


@dataclass(frozen=True, slots=True)
class LinearTrack:
    """A linear track carrying the robot base: the first, prismatic joint of a seven-axis chain.

    ``origin_mm`` (3,): the robot base origin in the world frame at track position 0.
    ``direction`` (3,): the world direction of + travel (normalised here).
    ``travel_min_mm`` / ``travel_max_mm``: the track's travel; ``speed_max_mm_s`` /
    ``accel_max_mm_s2`` / ``jerk_max_mm_s3`` its speed, acceleration and jerk limits.
    The base keeps the world's orientation: ``T_world_base(s) = [I | origin_mm + s * direction]``.
    """

    origin_mm: np.ndarray
    direction: np.ndarray
    travel_min_mm: float
    travel_max_mm: float
    speed_max_mm_s: float
    accel_max_mm_s2: float = 2000.0
    jerk_max_mm_s3: float = 20000.0

    def __post_init__(self) -> None:
        origin = np.asarray(self.origin_mm, dtype=np.float64)
        d = np.asarray(self.direction, dtype=np.float64)
        if (
            origin.shape != (3,)
            or d.shape != (3,)
            or not (np.all(np.isfinite(origin)) and np.all(np.isfinite(d)))
        ):
            raise KinematicsError("LinearTrack: origin_mm and direction must be 3 finite values each")
        norm = float(np.linalg.norm(d))
        if norm < 1e-9:
            raise KinematicsError("LinearTrack: direction must not be the zero vector")
        if not (np.isfinite(self.travel_min_mm) and np.isfinite(self.travel_max_mm)):
            raise KinematicsError("LinearTrack: travel limits must be finite")
        if not self.travel_min_mm < self.travel_max_mm:
            raise KinematicsError(
                f"LinearTrack: travel_min_mm ({self.travel_min_mm}) must be below travel_max_mm ({self.travel_max_mm})"
            )
        if not (self.speed_max_mm_s > 0 and self.accel_max_mm_s2 > 0 and self.jerk_max_mm_s3 > 0):
            raise KinematicsError("LinearTrack: speed, acceleration and jerk limits must be positive")
        origin.flags.writeable = False
        d = d / norm
        d.flags.writeable = False
        object.__setattr__(self, "origin_mm", origin)
        object.__setattr__(self, "direction", d)

    def base_pos_mm(self, track_mm) -> np.ndarray:
        """World position of the robot base origin at track position(s) ``track_mm`` (scalar or (n,)):
        (3,) or (n, 3) mm."""
        s = np.asarray(track_mm, dtype=np.float64)
        return self.origin_mm + s[..., None] * self.direction

    def T_world_base(self, track_mm: float) -> np.ndarray:
        """(4, 4) robot base in the world frame at track position ``track_mm``, mm."""
        T = np.eye(4)
        T[:3, 3] = self.base_pos_mm(float(track_mm))
        return T
