"""The edge passes' corner links flown as lines in joint space (issue 22, item 1): faster than the
Cartesian hump, clear of the plate, inside every margin; refused where the line cannot keep them."""

from __future__ import annotations

import numpy as np
import pytest

from analysis.contracts.placement import placement_transform
from analysis.design.plates import design_mesh, plate_spec
from cellctl.planning import plan_scan
from cellctl.planning.coverage import design_surface
from cellctl.planning.planner import (
    JOINT_LINK_CLEARANCE_TOL_MM,
    _joint_space_link,
    joint_space_links,
)
from cellctl.planning.timing import rest_to_rest_s
from drivers.abb_egm.kinematics import fk_batch
from tests.support.plans import SMALL_PLACEMENT, SMALL_SETTINGS


@pytest.fixture(scope="module")
def design():
    return design_mesh(plate_spec("sail", length_mm=300.0, width_mm=200.0), pitch_mm=5.0)


@pytest.fixture(scope="module")
def plan(design):
    return plan_scan(design, SMALL_PLACEMENT, SMALL_SETTINGS)


def _clearance(design):
    surface = design_surface(design)
    T_plate_world = np.linalg.inv(placement_transform(SMALL_PLACEMENT))

    def clearance(q: np.ndarray) -> np.ndarray:
        p = fk_batch(q, SMALL_SETTINGS.T_flange_sensor)[:, :3, 3]
        pp = p @ T_plate_world[:3, :3].T + T_plate_world[:3, 3]
        return pp[:, 2] - surface.height_and_gradient(pp[:, 0], pp[:, 1])[0]

    return clearance


def test_the_corner_links_are_lifted_joint_lines_that_keep_their_clearance_and_margins(plan, design):
    saved = plan.choices["joint_space_links_saved_s"]
    corners = [s for s in plan.segments if s.label in saved]
    assert len(corners) >= 2 and all(v > 0.1 for v in saved.values())
    assert all(s.kind == "link" and not s.flying for s in corners)
    clearance = _clearance(design)
    for seg in corners:
        q = seg.q_deg
        u = np.linspace(0.0, 1.0, len(q))
        off = q - (q[0] + u[:, None] * (q[-1] - q[0]))
        # the line plus one joint-space direction scaled by sin(pi u): the lift at the middle
        mid = off[len(q) // 2] / np.sin(np.pi * u[len(q) // 2])
        np.testing.assert_allclose(off, np.outer(np.sin(np.pi * u), mid), atol=1e-9)
        c = clearance(q)
        assert c.min() >= min(c[0], c[-1]) - JOINT_LINK_CLEARANCE_TOL_MM - 1e-6
        assert np.all(q >= SMALL_SETTINGS.q_min_deg) and np.all(q <= SMALL_SETTINGS.q_max_deg)
        assert np.abs(q[:, 4]).min() >= SMALL_SETTINGS.wrist_margin_deg
        # the stored poses are the joints' (the timing's path parameter and the TCP speed use them)
        np.testing.assert_allclose(
            fk_batch(q, SMALL_SETTINGS.T_flange_sensor)[:, :3, 3], seg.pos_mm, atol=1e-9
        )


def test_a_link_is_kept_where_the_line_would_need_more_lift_than_allowed(plan):
    seg = next(s for s in plan.segments if s.label in plan.choices["joint_space_links_saved_s"])

    # a clearance the lift cannot change: high at the ends, far too low between them
    def sunk(q: np.ndarray) -> np.ndarray:
        c = np.full(len(q), -500.0)
        c[[0, -1]] = 100.0
        return c

    assert _joint_space_link(seg, SMALL_SETTINGS, sunk) is None


def test_a_link_is_replaced_only_where_the_line_is_faster_so_a_second_pass_changes_nothing(plan, design):
    segments = list(plan.segments)
    before = [s.q_deg.copy() for s in segments]
    # the plan's links are already lines where that was faster: a second pass changes nothing
    assert joint_space_links(segments, SMALL_SETTINGS, design_surface(design), SMALL_PLACEMENT) == {}
    for s, q in zip(segments, before, strict=True):
        np.testing.assert_array_equal(s.q_deg, q)
    corner = next(s for s in plan.segments if s.label in plan.choices["joint_space_links_saved_s"])
    assert rest_to_rest_s(corner, SMALL_SETTINGS) == pytest.approx(corner.duration_s, abs=0.03)


def test_a_joint_line_is_timed_along_the_line_at_its_slowest_axis_limits(plan):
    """A joint-space link is timed over the joints' progress along it (``Segment.joint_line``), so its
    time law is the line's own: never slower than the same link timed over the sensor's arc length
    (there the wrist turns unevenly and the law must take its peak rate everywhere), and at an edge
    corner, where the wrist's joint 6 turns most, within a few per cent of that joint's own
    jerk-limited rest-to-rest move (a link that swings the sensor fast is held by the TCP cap)."""
    import dataclasses

    from ruckig import InputParameter, Ruckig, Trajectory

    from cellctl.motion.trajectory import PLAN_JERK_SHARE
    from cellctl.planning import timing

    def axis_alone(travel: float, k: int) -> float:
        inp = InputParameter(1)
        inp.current_position, inp.target_position = [0.0], [travel]
        inp.max_velocity = [timing._VEL_FACTOR * SMALL_SETTINGS.axis_speed_max[k]]
        inp.max_acceleration = [timing._ACC_FACTOR * SMALL_SETTINGS.axis_accel_max[k]]
        inp.max_jerk = [PLAN_JERK_SHARE * SMALL_SETTINGS.axis_jerk_max[k]]
        law = Trajectory(1)
        Ruckig(1).calculate(inp, law)
        return float(law.duration)

    lines = [s for s in plan.segments if s.joint_line]
    corners = [s for s in lines if abs(s.q_deg[-1, 5] - s.q_deg[0, 5]) > 45.0]
    assert lines and corners
    for seg in lines:
        over_arc = rest_to_rest_s(dataclasses.replace(seg, joint_line=False), SMALL_SETTINGS)
        assert seg.duration_s <= over_arc + 1e-9, (seg.label, seg.duration_s, over_arc)
    for seg in corners:
        travel = np.abs(seg.q_deg[-1] - seg.q_deg[0])
        bound = max(axis_alone(float(d), k) for k, d in enumerate(travel) if d > 1e-6)
        assert bound - 1e-6 <= seg.duration_s <= 1.05 * bound, (seg.label, seg.duration_s, bound)
