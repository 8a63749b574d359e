"""Property tests: whatever the placement, plate and scan parameters, the planner either produces a plan
that passes the safety envelope, or refuses with a reason; it never fails otherwise."""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from analysis.contracts.placement import Placement
from analysis.design.plates import design_mesh, plate_spec
from cellctl.motion import EnvelopeLimits, SafetyEnvelope
from cellctl.planning import PlanInputError, PlannerSettings, PlanRefused, plan_scan

CYCLE_S = 0.004032


@st.composite
def plates(draw):
    kind = draw(st.sampled_from(["sail", "saddle", "twisted", "cylinder", "flat"]))
    length = draw(st.floats(150.0, 900.0))
    width = draw(st.floats(100.0, length))
    overrides = {"length_mm": length, "width_mm": width}
    if kind in ("sail", "saddle"):
        overrides["radius_x_mm"] = draw(st.floats(1500.0, 8000.0))
        overrides["radius_y_mm"] = draw(st.floats(1500.0, 8000.0))
    if kind == "cylinder":
        overrides["radius_x_mm"] = draw(st.floats(max(1500.0, length), 8000.0))
    return plate_spec(kind, **overrides)


placements = st.builds(
    Placement.on_bed,
    x_mm=st.floats(700.0, 2600.0),
    y_mm=st.floats(-1200.0, 1200.0),
    yaw_deg=st.floats(-180.0, 180.0),
    z_mm=st.floats(0.0, 700.0),
)

scan_settings = st.builds(
    PlannerSettings,
    overlap_fraction=st.floats(0.0, 0.6),
    speed_mm_s=st.one_of(st.none(), st.floats(20.0, 250.0)),
    edge_passes=st.booleans(),
    edge_tilt_deg=st.floats(0.0, 45.0),
    placement_uncertainty_mm=st.floats(0.0, 40.0),
    placement_uncertainty_deg=st.floats(0.0, 3.0),
    standoff_mm=st.floats(80.0, 120.0),
    line_width_mm=st.floats(30.0, 80.0),
)


@settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(spec=plates(), placement=placements, cfg=scan_settings)
def test_every_plan_passes_the_envelope_and_every_refusal_has_a_reason(spec, placement, cfg):
    mesh = design_mesh(spec, pitch_mm=max(spec.length_mm / 60.0, 5.0))
    try:
        plan = plan_scan(mesh, placement, cfg, with_coverage=False)
    except PlanRefused as exc:
        assert exc.reason and exc.pass_label and exc.limit
        assert exc.to_dict()["message"]
        return
    except PlanInputError as exc:
        assert str(exc)
        return
    t = np.arange(0.0, plan.trajectory.duration_s, CYCLE_S)
    q = plan.trajectory.sample_many(t)[0]
    SafetyEnvelope(EnvelopeLimits.from_settings(cfg, CYCLE_S)).check_trajectory(t, q)
    assert plan.scan_time_s > 0 and plan.sweep_length_mm > 0
    assert sum(1 for s in plan.segments if s.kind == "edge") == (4 if cfg.edge_passes else 0)


@settings(max_examples=3, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    dx=st.floats(-150.0, 150.0),
    dy=st.floats(-300.0, 300.0),
    angle=st.floats(-20.0, 20.0),
)
def test_plans_near_the_default_placement_cover_the_plate(dx, dy, angle):
    spec = plate_spec("sail", length_mm=400.0, width_mm=300.0)
    placement = Placement.on_bed(1600.0 + dx, dy, angle, z_mm=300.0)
    try:
        plan = plan_scan(design_mesh(spec, pitch_mm=10.0), placement, PlannerSettings())
    except PlanRefused as exc:
        assert exc.reason and exc.limit
        return
    assert plan.coverage.fraction >= 0.99
