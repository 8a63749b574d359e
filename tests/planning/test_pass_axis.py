"""Passes along the plate's longer or shorter axis, and "fastest": the shorter timed scan is kept.

The planner's choice is checked against the plans it chose between (each planned on its own with
``pass_axis`` "longer" / "shorter"): a joint made slow where one axis' passes need it makes that
axis the slower, whichever the planner solves first.
"""

from __future__ import annotations

import numpy as np
import pytest

from analysis.contracts.placement import Placement
from analysis.design.plates import design_mesh, plate_spec
from cellctl.planning import PlanInputError, PlannerSettings, plan_scan
from cellctl.planning.planner import estimate_s, lower_bound_s

PLACEMENT = Placement.on_bed(1500.0, 0.0, 3.0, z_mm=300.0)
MESH = design_mesh(plate_spec("sail", length_mm=400.0, width_mm=300.0), pitch_mm=10.0)
#: joint 1 slow: the passes across the base's radius (the plate's y, its shorter axis) crawl
SLOW_J1 = PlannerSettings(joint_speed_max_deg_s=(3.0, 175.0, 175.0, 250.0, 250.0, 360.0))
#: joints 2 and 3 slow: the passes along the radius (the plate's x, its longer axis) crawl
SLOW_J23 = PlannerSettings(joint_speed_max_deg_s=(175.0, 4.0, 4.0, 250.0, 250.0, 360.0))


def _plans(settings: PlannerSettings) -> dict:
    return {
        axis: plan_scan(MESH, PLACEMENT, settings.with_(pass_axis=axis), with_coverage=False)
        for axis in ("longer", "shorter", "fastest")
    }


def _raster_direction(plan) -> np.ndarray:
    """The unit direction of the first raster pass in the plate frame (x, y)."""
    seg = next(s for s in plan.segments if s.kind == "scan")
    d = seg.pos_mm[-1] - seg.pos_mm[0]
    yaw = np.radians(PLACEMENT.rpy_deg[2])
    c, s = np.cos(yaw), np.sin(yaw)
    local = np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1]])
    return np.abs(local) / np.linalg.norm(local)


@pytest.mark.parametrize(
    ("settings", "faster"), [(SLOW_J1, "longer"), (SLOW_J23, "shorter")], ids=["joint1-slow", "joints23-slow"]
)
def test_fastest_keeps_the_shorter_timed_scan_of_the_two_axes(settings, faster):
    plans = _plans(settings)
    slower = "shorter" if faster == "longer" else "longer"
    # the limit made a difference the choice has to see
    assert plans[faster].scan_time_s < 0.9 * plans[slower].scan_time_s
    chosen = plans["fastest"]
    assert chosen.choices["pass_axis"]["axis"] == faster
    assert chosen.scan_time_s == pytest.approx(plans[faster].scan_time_s, rel=1e-9)
    considered = chosen.choices["pass_axis"]["considered"]
    assert considered[slower]["scan_time_s"] == pytest.approx(plans[slower].scan_time_s, abs=0.01)
    # passes along x for "longer" (the plate is 400 long in x), along y for "shorter"
    assert _raster_direction(plans["longer"])[0] > 0.99
    assert _raster_direction(plans["shorter"])[1] > 0.99
    assert _raster_direction(chosen)[0 if faster == "longer" else 1] > 0.99


def test_an_axis_that_cannot_win_is_not_solved_and_its_estimate_is_said():
    plan = plan_scan(MESH, PLACEMENT, PlannerSettings(), with_coverage=False)
    pa = plan.choices["pass_axis"]
    solved = [a for a, c in pa["considered"].items() if "scan_time_s" in c]
    skipped = [a for a, c in pa["considered"].items() if "skipped" in c]
    assert solved == [pa["axis"]] and len(skipped) == 1
    other = pa["considered"][skipped[0]]
    assert other["estimate_s"] >= plan.scan_time_s
    # the bound holds for the plan made: no timing is shorter than it
    assert lower_bound_s(plan.segments, PlannerSettings()) <= plan.scan_time_s
    # a plan's estimate from itself is its bound plus its own non-sweep time above the bound
    assert estimate_s(plan.segments, plan.segments, PlannerSettings()) == pytest.approx(
        plan.scan_time_s, rel=0.02
    )


def test_an_unknown_pass_axis_is_refused_by_name():
    with pytest.raises(PlanInputError, match="pass_axis"):
        PlannerSettings(pass_axis="diagonal")


@pytest.mark.parametrize("axis", ["longer", "shorter"])
@pytest.mark.parametrize("corner", [(-1, -1), (-1, 1), (1, -1), (1, 1)])
def test_the_serpentine_starts_at_the_corner_asked_for_and_covers_the_same_passes(axis, corner):
    """``start_corner`` (the daemon picks the one nearest the arm): the first raster pass starts on
    that corner's sides of the footprint and the passes go across from there; the passes are the
    same lines as from the default corner, only their order and directions differ."""
    from analysis.contracts.placement import placement_transform
    from cellctl.planning.coverage import build_segments, design_surface

    surface = design_surface(MESH)
    T = placement_transform(PLACEMENT)

    def raster(settings: PlannerSettings) -> list[np.ndarray]:
        segs, _ = build_segments(surface, PLACEMENT, settings, axis=axis)
        return [(s.pos_mm - T[:3, 3]) @ T[:3, :3] for s in segs if s.kind == "scan"]  # plate frame

    asked = raster(PlannerSettings(start_corner=corner))
    default = raster(PlannerSettings())
    start = asked[0][0, :2]
    assert (np.sign(start) == np.asarray(corner)).all()
    across = 1 if axis == "longer" else 0  # the plate is longer in x: "longer" passes step across y
    assert np.sign(asked[-1][-1, across]) == -corner[across]  # the last pass on the far side
    assert (np.sign(default[0][0, :2]) == -1).all()  # the default starts at the low corner
    assert sorted(float(p[:, across].mean()) for p in asked) == pytest.approx(
        sorted(float(p[:, across].mean()) for p in default)
    )
    with pytest.raises(PlanInputError, match="start_corner"):
        PlannerSettings(start_corner=(0, 1))
