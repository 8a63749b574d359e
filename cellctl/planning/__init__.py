"""Scan planning: coverage passes over a design surface, joint path, timing, the plan object.

Entry point: :func:`plan_scan`. The pieces (``coverage``, ``joint_path``, ``timing``) are plain
functions on numpy arrays and usable on their own.
"""

from cellctl.planning.plan import (
    CoverageReport,
    PlanInputError,
    PlanRefused,
    ScanPlan,
    Segment,
)
from cellctl.planning.planner import plan_scan, start_corner_near
from cellctl.planning.settings import PlannerSettings

__all__ = [
    "CoverageReport",
    "PlanInputError",
    "PlanRefused",
    "PlannerSettings",
    "ScanPlan",
    "Segment",
    "plan_scan",
    "start_corner_near",
]
