"""Shared plans for the planning and motion tests: the placements and settings they plan with, and
the sail and small plans as session fixtures (each planned once per process, whichever folder's
conftest asks first: ``tests/planning/conftest.py`` and ``tests/motion/conftest.py`` both use them).
"""

from __future__ import annotations

import functools

import pytest

from analysis.contracts.placement import Placement
from analysis.design.plates import design_mesh, plate_spec
from cellctl.planning import PlannerSettings, ScanPlan, plan_scan

SAIL_PLACEMENT = Placement.on_bed(1500.0, 0.0, 3.0, z_mm=300.0)
#: a small plate and fast sweeps keep the executions short; the geometry is the real planner's
SMALL_SETTINGS = PlannerSettings(
    speed_mm_s=200.0, placement_uncertainty_mm=5.0, placement_uncertainty_deg=0.5
)
SMALL_PLACEMENT = Placement.on_bed(1600.0, 100.0, 3.0, z_mm=300.0)


@functools.cache
def _sail_plan() -> ScanPlan:
    return plan_scan(design_mesh(plate_spec("sail"), pitch_mm=10.0), SAIL_PLACEMENT, PlannerSettings())


@functools.cache
def _small_plan() -> ScanPlan:
    mesh = design_mesh(plate_spec("sail", length_mm=200.0, width_mm=150.0), pitch_mm=5.0)
    return plan_scan(mesh, SMALL_PLACEMENT, SMALL_SETTINGS)


@pytest.fixture(scope="session")
def sail_plan() -> ScanPlan:
    """The 1200 x 800 sail plate at the default placement with the cell.toml defaults."""
    return _sail_plan()


@pytest.fixture(scope="session")
def small_plan() -> ScanPlan:
    """A 200 x 150 sail-shaped plate: a full plan (approach, raster, edges, retract) of a few seconds."""
    return _small_plan()
