"""Planner settings: the numbers from ``cell.toml`` the planner needs, in one flat frozen record.

Kept separate from the configuration models so the planner is callable from a notebook or a test
without a configuration file; :meth:`PlannerSettings.from_config` builds one from a ``CellConfig``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, replace
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np

from analysis.contracts.placement import T_from_pos_rpy
from cellctl.planning.plan import PASS_AXES, PlanInputError
from drivers.abb_egm.limits import LinearTrack, RobotLimits

if TYPE_CHECKING:
    from cellctl.config import CellConfig

__all__ = ["PlannerSettings"]

#: the joint limits when none are given (``cell.toml [robot]``'s defaults)
_DEFAULT_LIMITS = RobotLimits()


def _default_T_flange_sensor() -> np.ndarray:
    return T_from_pos_rpy([0.0, 0.0, 150.0], [0.0, 0.0, 0.0])


@dataclass(frozen=True)
class PlannerSettings:
    """Everything the coverage planner, the joint path and the timing need (mm, deg, s).

    Sensor: ``line_width_mm`` (laser line length at the standoff), ``depth_min_mm`` /
    ``depth_max_mm`` (measuring range along the sensor's +z), ``rate_hz`` (profiles per second).
    Scan: ``standoff_mm`` along the surface normal, ``overlap_fraction`` between neighbouring
    passes, ``speed_mm_s`` (None: as fast as the sensor rate allows at ``profile_spacing_mm``),
    ``transit_speed_mm_s`` on links, edge passes (``edge_passes``, tilted ``edge_tilt_deg`` outward so
    the thickness face is lit), ``sweep_pitch_deg`` (the sensor leaning along every pass, about its
    laser line, keeping the wrist clear of its singularity), placement uncertainty (``placement_uncertainty_mm`` shift,
    ``placement_uncertainty_deg`` rotation), ``flying_turns`` (neighbouring raster passes joined by
    a turnaround flown at speed outside the plate; off: a hump link, at rest at both ends),
    ``pass_axis``: the raster passes run along the footprint's ``"longer"`` or ``"shorter"`` axis,
    or ``"fastest"``: the one whose timed scan is shorter within the limits (the other where one is
    refused; :func:`~cellctl.planning.planner.plan_scan`), ``passes_reversed`` (the serpentine's first raster pass runs from the far end of the passes'
    axis, +x of the plate frame for a plate longer in x; the sensor's lean along that axis stays),
    ``start_corner`` (``(sx, sy)``, each -1 or +1: the serpentine starts at the footprint's corner on
    those sides of the plate frame's x and y, :func:`~cellctl.planning.planner.start_corner_near`
    picks the one nearest the arm; it sets the first pass's direction and which side the passes
    start from, overriding ``passes_reversed``; None: the first pass at the footprint's low side),
    ``link_clearance_mm`` lift on links, ``approach_mm``
    along the normal before the first and after the last pass, ``waypoint_step_mm`` spacing.
    Robot: joint limits and margin, speed / acceleration / jerk limits (:attr:`limits`, one
    :class:`~drivers.abb_egm.limits.RobotLimits`), TCP speed cap, workspace box for the
    sensor origin, ``T_flange_sensor`` (4, 4) mm, ``wrist_margin_deg`` (min |q5|),
    ``max_waypoint_joint_step_deg`` (a larger jump between neighbouring waypoints is a flip).
    Track: ``track`` (usable travel, speed and acceleration limits, frame in the world) or None
    for a fixed base; with one, configurations are ``axes_mm_deg`` (track mm, then six joints).
    ``track_hold``: hold the carriage at one position when the arm reaches the whole plan from there
    (False: the carriage always follows the passes).
    Coverage prediction: ``coverage_cell_mm``, ``coverage_profile_step_mm``, ``coverage_rays``,
    ``max_incidence_deg``.
    """

    line_width_mm: float = 50.0
    depth_min_mm: float = 70.0
    depth_max_mm: float = 130.0
    rate_hz: float = 200.0
    standoff_mm: float = 100.0
    overlap_fraction: float = 0.2
    speed_mm_s: float | None = None
    profile_spacing_mm: float = 0.5
    transit_speed_mm_s: float = 250.0
    edge_passes: bool = True
    edge_tilt_deg: float = 30.0
    flying_turns: bool = True
    pass_axis: str = "fastest"
    passes_reversed: bool = False
    start_corner: tuple[int, int] | None = None
    sweep_pitch_deg: float = 0.0
    placement_uncertainty_mm: float = 30.0
    placement_uncertainty_deg: float = 2.0
    link_clearance_mm: float = 30.0
    approach_mm: float = 100.0
    waypoint_step_mm: float = 20.0
    joint_lower_deg: tuple[float, ...] = _DEFAULT_LIMITS.joint_lower_deg
    joint_upper_deg: tuple[float, ...] = _DEFAULT_LIMITS.joint_upper_deg
    joint_margin_deg: float = _DEFAULT_LIMITS.joint_margin_deg
    joint_speed_max_deg_s: tuple[float, ...] = _DEFAULT_LIMITS.joint_speed_max_deg_s
    joint_accel_max_deg_s2: tuple[float, ...] = _DEFAULT_LIMITS.joint_accel_max_deg_s2
    joint_jerk_max_deg_s3: tuple[float, ...] = _DEFAULT_LIMITS.joint_jerk_max_deg_s3
    tcp_speed_max_mm_s: float = 250.0
    workspace_min_mm: tuple[float, ...] = (-500.0, -2000.0, 100.0)
    workspace_max_mm: tuple[float, ...] = (2600.0, 2000.0, 2400.0)
    T_flange_sensor: np.ndarray = field(default_factory=_default_T_flange_sensor)
    wrist_margin_deg: float = 5.0
    max_waypoint_joint_step_deg: float = 15.0
    coverage_cell_mm: float = 5.0
    coverage_profile_step_mm: float = 3.0
    coverage_rays: int = 21
    max_incidence_deg: float = 80.0
    track: LinearTrack | None = None
    track_hold: bool = True

    def __post_init__(self) -> None:
        for f in fields(self):
            if f.name in ("track", "track_hold", "pass_axis", "start_corner"):  # LinearTrack / a bool / below
                continue
            v = getattr(self, f.name)
            arr = np.asarray(v, dtype=np.float64) if f.name != "speed_mm_s" or v is not None else None
            if arr is not None and not np.all(np.isfinite(arr)):
                raise PlanInputError(f"settings.{f.name}: must be finite, got {v!r}")
        positive = [
            "line_width_mm",
            "depth_min_mm",
            "depth_max_mm",
            "rate_hz",
            "standoff_mm",
            "profile_spacing_mm",
            "transit_speed_mm_s",
            "tcp_speed_max_mm_s",
            "waypoint_step_mm",
            "coverage_cell_mm",
            "coverage_profile_step_mm",
            "approach_mm",
        ]
        for name in positive:
            if not getattr(self, name) > 0:
                raise PlanInputError(f"settings.{name}: must be positive, got {getattr(self, name)!r}")
        if self.speed_mm_s is not None and not self.speed_mm_s > 0:
            raise PlanInputError(
                f"settings.speed_mm_s: must be positive or None (auto), got {self.speed_mm_s!r}"
            )
        if not 0 <= self.overlap_fraction < 0.9:
            raise PlanInputError(
                f"settings.overlap_fraction: must be in [0, 0.9), got {self.overlap_fraction!r}"
            )
        if not self.depth_min_mm < self.standoff_mm < self.depth_max_mm:
            raise PlanInputError(
                f"settings.standoff_mm: {self.standoff_mm} is outside the depth range "
                f"[{self.depth_min_mm}, {self.depth_max_mm}]"
            )
        if not 0 <= self.edge_tilt_deg < 80:
            raise PlanInputError(f"settings.edge_tilt_deg: must be in [0, 80), got {self.edge_tilt_deg!r}")
        if not 0 <= self.sweep_pitch_deg < 45:
            raise PlanInputError(
                f"settings.sweep_pitch_deg: must be in [0, 45), got {self.sweep_pitch_deg!r}"
            )
        if self.placement_uncertainty_mm < 0 or not 0 <= self.placement_uncertainty_deg < 45:
            raise PlanInputError("settings.placement_uncertainty_mm/_deg: must be >= 0 (and deg < 45)")
        if self.coverage_rays < 2:
            raise PlanInputError(f"settings.coverage_rays: must be >= 2, got {self.coverage_rays}")
        T = np.asarray(self.T_flange_sensor, dtype=np.float64)
        if T.shape != (4, 4):
            raise PlanInputError(f"settings.T_flange_sensor: must be (4, 4), got {T.shape}")
        if self.start_corner is not None and (
            len(self.start_corner) != 2 or any(c not in (-1, 1) for c in self.start_corner)
        ):
            raise PlanInputError(
                f"settings.start_corner: must be None or two of -1 / +1, got {self.start_corner!r}"
            )
        if self.pass_axis not in (*PASS_AXES, "fastest"):
            raise PlanInputError(
                f"settings.pass_axis: {self.pass_axis!r} is not one of {(*PASS_AXES, 'fastest')}"
            )
        for name in ("joint_lower_deg", "joint_upper_deg", "joint_speed_max_deg_s", "joint_accel_max_deg_s2"):
            if len(getattr(self, name)) != 6:
                raise PlanInputError(f"settings.{name}: needs 6 values")

    @property
    def scan_speed_mm_s(self) -> float:
        """TCP speed on sweeps: the configured speed, or profile spacing x sensor rate ("auto"),
        never above 90 % of the TCP speed cap (headroom for the executor's tracking)."""
        v = self.speed_mm_s if self.speed_mm_s is not None else self.profile_spacing_mm * self.rate_hz
        return float(min(v, 0.9 * self.tcp_speed_max_mm_s))

    @property
    def pass_step_mm(self) -> float:
        """Largest distance between neighbouring raster passes."""
        return self.line_width_mm * (1.0 - self.overlap_fraction)

    @property
    def n_axes(self) -> int:
        """Axes in a configuration: 6 joints, or the track (mm) and 6 joints (``axes_mm_deg``)."""
        return 6 + (self.track is not None)

    @property
    def axis_speed_max(self) -> np.ndarray:
        """(n_axes,) speed limits: the track's (mm/s) first when there is one, then the joints' (deg/s)."""
        return self._with_track(self.joint_speed_max_deg_s, "speed_max_mm_s")

    @property
    def axis_accel_max(self) -> np.ndarray:
        """(n_axes,) acceleration limits, the track's (mm/s^2) first when there is one."""
        return self._with_track(self.joint_accel_max_deg_s2, "accel_max_mm_s2")

    @property
    def axis_jerk_max(self) -> np.ndarray:
        """(n_axes,) jerk limits, the track's (mm/s^3) first when there is one."""
        return self._with_track(self.joint_jerk_max_deg_s3, "jerk_max_mm_s3")

    def _with_track(self, joints: tuple[float, ...], track_field: str) -> np.ndarray:
        arm = np.asarray(joints, dtype=np.float64)
        if self.track is None:
            return arm
        return np.concatenate([[float(getattr(self.track, track_field))], arm])

    @property
    def q_min_deg(self) -> np.ndarray:
        """(6,) lower joint limits shrunk by the margin, deg."""
        return self.limits.q_min_deg

    @property
    def q_max_deg(self) -> np.ndarray:
        """(6,) upper joint limits shrunk by the margin, deg."""
        return self.limits.q_max_deg

    @cached_property
    def limits(self) -> RobotLimits:
        """The joint limits as the one value motion and the configuration also speak (the fields of
        :class:`~drivers.abb_egm.limits.RobotLimits`, which these settings carry flat)."""
        return RobotLimits(**{f.name: getattr(self, f.name) for f in fields(RobotLimits)})

    def with_(self, **changes) -> PlannerSettings:
        """A copy with some fields changed."""
        return replace(self, **changes)

    @classmethod
    def from_config(cls, cfg: CellConfig) -> PlannerSettings:
        """Settings from a :class:`cellctl.config.CellConfig` (``[robot]``, ``[laser]``, ``[scan]``)."""
        r, laser, s = cfg.robot, cfg.laser, cfg.scan
        return cls(
            line_width_mm=laser.line_width_mm,
            depth_min_mm=laser.depth_min_mm,
            depth_max_mm=laser.depth_max_mm,
            rate_hz=laser.rate_hz,
            standoff_mm=s.standoff_mm,
            overlap_fraction=s.overlap_fraction,
            speed_mm_s=None if s.speed_mm_s == "auto" else float(s.speed_mm_s),
            profile_spacing_mm=s.profile_spacing_mm,
            transit_speed_mm_s=s.transit_speed_mm_s,
            edge_passes=s.edge_passes,
            pass_axis=s.pass_axis,
            placement_uncertainty_mm=s.placement_uncertainty_mm,
            placement_uncertainty_deg=s.placement_uncertainty_deg,
            **asdict(r.limits()),
            tcp_speed_max_mm_s=r.tcp_speed_max_mm_s,
            workspace_min_mm=tuple(r.workspace_min_mm),
            workspace_max_mm=tuple(r.workspace_max_mm),
            T_flange_sensor=T_from_pos_rpy(r.sensor_in_flange.pos_mm, r.sensor_in_flange.rpy_deg),
            wrist_margin_deg=r.wrist_margin_deg,
            edge_tilt_deg=s.edge_tilt_deg,
            sweep_pitch_deg=s.sweep_pitch_deg,
            link_clearance_mm=s.link_clearance_mm,
            approach_mm=s.approach_mm,
            track=None if r.track is None else r.track.linear_track(),
            track_hold=True if r.track is None else r.track.hold,
        )
