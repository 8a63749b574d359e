"""The locate run's plans and verdicts (cellctl/daemon/locate.py), the trigger without a placement,
and the job record that keeps none until the plate is found."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from analysis.contracts.placement import Placement
from analysis.design.plates import design_height_mm, design_mesh, plate_spec
from analysis.register.locate import LocateResult
from cellctl.api.models import TriggerRequest
from cellctl.config import CellConfig, LocateSection, load_config
from cellctl.daemon.locate import (
    across_plans,
    face_down_refusal,
    given_placement_refusal,
    locate_height_mm,
    locate_plans,
    locate_settings,
    needs_across,
    next_locate_plans,
)
from cellctl.jobstore.jobs import JobRecord, _checked
from drivers.abb_egm.kinematics import fk_batch

REPO = Path(__file__).resolve().parents[2]

SAIL = design_mesh(plate_spec("sail", length_mm=1200.0, width_mm=800.0), pitch_mm=20.0)


def _found(
    x: float, y: float, yaw: float, *, constrained: bool = True, face_down: bool = False
) -> LocateResult:
    return LocateResult(
        placement=Placement.on_bed(x, y, yaw, z_mm=300.0), face_down=face_down, rms_mm=0.5, height_rms_mm=0.3,
        coverage=0.3, boundary_points=900, inliers=880, plate_points=10_000, ambiguous=True,
        resolved_by="convention", score_mm=0.6, alternative_score_mm=0.6, iterations=9,
        constraint_points=300.0 if constrained else 2.0, constrained=constrained,
    )  # fmt: skip


def test_the_passes_fly_flat_over_the_bed_along_it_and_across_it_at_the_locate_height():
    cfg = CellConfig()
    h = locate_height_mm(cfg, SAIL)
    # the sail's highest edge (its corners) is 72 mm above its centre: 75 mm above that
    assert h == pytest.approx(cfg.scan.placement_z_mm + 71.67 + 75.0, abs=0.5)
    along, across = locate_plans(cfg, SAIL)
    for lp in (along, across):
        for seg in lp.plan.passes:
            assert np.allclose(seg.pos_mm[:, 2], h, atol=1e-6)  # flat, at the locate height
            assert np.allclose(seg.R_base_sensor[:, :, 2], [0.0, 0.0, -1.0], atol=1e-6)  # looking down
    d_along = along.plan.passes[0].pos_mm[-1] - along.plan.passes[0].pos_mm[0]
    d_across = across.plan.passes[0].pos_mm[-1] - across.plan.passes[0].pos_mm[0]
    assert abs(d_along[1]) < 1e-6 and abs(d_across[0]) < 1e-6  # along x, then along y
    lo, hi = np.asarray(cfg.locate.bed_min_xy_mm), np.asarray(cfg.locate.bed_max_xy_mm)
    xy = np.concatenate([s.pos_mm[:, :2] for s in along.plan.passes])
    assert np.all(xy >= lo - 1e-6) and np.all(xy <= hi + 1e-6)
    # the passes' spacing is the configured one
    ys = sorted({round(float(s.pos_mm[0, 1]), 3) for s in along.plan.passes})
    assert np.allclose(np.diff(ys), np.diff(ys)[0]) and np.diff(ys)[0] <= cfg.locate.pass_spacing_mm + 1e-6
    st = locate_settings(cfg, SAIL, 12.0)
    assert st.range_z_mm == pytest.approx((h - cfg.laser.depth_max_mm, h - cfg.laser.depth_min_mm))
    assert st.yaw_hint_deg == 12.0


def test_a_given_placement_off_by_more_than_the_bound_is_refused_saying_by_how_much():
    cfg = CellConfig()
    found = _found(1500.0, 0.0, 3.0)
    assert given_placement_refusal(cfg, found, Placement.on_bed(1510.0, 5.0, 3.5, z_mm=300.0)) is None
    why = given_placement_refusal(cfg, found, Placement.on_bed(1600.0, 0.0, 3.0, z_mm=300.0))
    assert why is not None and "100.0 mm and 0.00 deg" in why and "allows 20 mm / 1 deg" in why
    why = given_placement_refusal(cfg, found, Placement.on_bed(1500.0, 0.0, 5.0, z_mm=300.0))
    assert why is not None and "2.00 deg" in why
    assert face_down_refusal(found) is None
    assert "face down" in face_down_refusal(_found(1500.0, 0.0, 3.0, face_down=True))


def test_the_passes_across_run_when_the_first_leave_the_fit_sliding_or_meet_the_edges_square_on():
    cfg = CellConfig()
    assert needs_across(cfg, _found(1500.0, 0.0, 40.0, constrained=False))
    assert needs_across(cfg, _found(1500.0, 0.0, 3.0))
    assert needs_across(cfg, _found(1500.0, 0.0, -86.0))
    assert not needs_across(cfg, _found(1500.0, 0.0, 25.0))
    assert not needs_across(cfg, _found(1500.0, 0.0, -70.0))


def test_a_trigger_may_leave_out_the_placement_and_the_record_keeps_none_until_found():
    req = TriggerRequest.model_validate({"plate_id": "P1", "design": "plate.ply"})
    assert req.placement is None
    rec = JobRecord(job_id="j", plate_id="P1", design="plate.ply", design_path="/d/plate.ply", placement=None)
    assert _checked(rec) is rec
    with pytest.raises(ValueError, match="placement"):
        _checked(
            JobRecord(job_id="j", plate_id="P1", design="p.ply", design_path="/d/p.ply", placement={"x": 1})
        )


def test_a_bed_without_extent_is_refused():
    with pytest.raises(ValidationError, match="bed_min_xy_mm"):
        LocateSection(bed_min_xy_mm=[1000.0, 0.0], bed_max_xy_mm=[900.0, 100.0])


def test_how_the_placement_was_found_travels_to_the_report_inputs():
    from analysis.contracts.job import AnalysisJob, ReportInputs
    from cellctl.analysis_job import analysis_job

    finding = {
        "source": "located",
        "given": None,
        "rms_mm": 0.7,
        "coverage": 0.3,
        "resolved_by": "convention",
    }
    job = analysis_job(
        CellConfig(), job_id="j", plate_id="P", design="/d/p.ply", placement=None, out_dir=Path("/tmp/x"),
        placement_found=finding,
    )  # fmt: skip
    again = AnalysisJob.model_validate_json(job.model_dump_json())
    assert again.placement_found is not None and again.placement_found.source == "located"
    inputs = ReportInputs.model_validate({"points": 10, "placement_found": again.placement_found})
    assert inputs.model_dump(mode="json")["placement_found"]["rms_mm"] == 0.7
    with pytest.raises(ValidationError):
        analysis_job(
            CellConfig(), job_id="j", plate_id="P", design="/d/p.ply", placement=None, out_dir=Path("/tmp/x"),
            placement_found={"source": "guessed"},
        )  # fmt: skip


def test_the_passes_across_a_deep_plate_fly_at_the_height_of_the_edges_they_cross():
    """The long cell's 6000 x 2000 sail: its long edges fall from 275 mm (corners) to 50 mm (their
    middles) above its centre, and one height above its highest edge sees down to 60 mm below it.
    Planned from a first fit that has the yaw and the place along the bed, each pass across runs
    over the bed's whole width and its depth range holds the long edges where it crosses them; the
    second starts where the first ended, and the move between them stays in the workspace box."""
    cfg = load_config(REPO / "docs" / "examples" / "cell-track.toml")
    spec = plate_spec("sail", length_mm=6000.0, width_mm=2000.0, radius_x_mm=20000.0, radius_y_mm=10000.0)
    design = design_mesh(spec, pitch_mm=50.0)
    truth = Placement.on_bed(
        1250.0, 300.0, 90.0, z_mm=cfg.scan.placement_z_mm
    )  # long side along the rail (y)
    # a first fit: yaw and y right, x slid 400 mm across the bed (the passes along cannot tell)
    found = _found(850.0, 300.0, 90.0, constrained=False)
    along_end = np.array([375.0, -3325.9])  # where the passes along end: the near side, the -y end
    plans = across_plans(cfg, design, found, along_end)
    assert [lp.name for lp in plans] == ["locate across 1", "locate across 2"] and all(
        lp.across for lp in plans
    )
    one_height = locate_settings(cfg, design, None).range_z_mm
    lo, hi = cfg.locate.bed_min_xy_mm, cfg.locate.bed_max_xy_mm
    margin = 3.0  # analysis.register.locate's range_margin_mm
    ys = []
    for lp in plans:
        (seg,) = lp.plan.passes
        y_pass = float(seg.pos_mm[0, 1])
        ys.append(y_pass)
        assert np.allclose(seg.pos_mm[:, 1], y_pass, atol=1e-6)  # across the rail, at one place along it
        assert np.allclose(seg.pos_mm[:, 2], seg.pos_mm[0, 2], atol=1e-6)  # flat
        # the laser line (the sensor leans along the pass) sweeps the bed's whole width
        line_x = seg.pos_mm[:, 0] + lp.settings.standoff_mm * seg.R_base_sensor[:, 0, 2]
        assert line_x.min() < lo[0] + 1.0 and line_x.max() > hi[0] - 1.0
        # where the truth's long edges cross it (design x = pass's place along the plate, y = +-1000)
        edge_z = truth.z_mm + float(design_height_mm(spec, np.array(y_pass - truth.y_mm), np.array(1000.0)))
        assert lp.range_z_mm[0] + margin < edge_z < lp.range_z_mm[1] - margin, (lp.range_z_mm, edge_z)
        assert not one_height[0] < edge_z  # the passes along, above the highest edge, cannot see it
    # at 20 and 80 % of the plate's extent along the rail, the nearer one first
    assert ys == pytest.approx([300.0 - 1800.0, 300.0 + 1800.0], abs=1.0)
    first, second = (lp.plan.passes[0].pos_mm for lp in plans)
    assert abs(first[0, 0] - along_end[0]) < abs(first[-1, 0] - along_end[0])  # from the near side
    assert abs(second[0, 0] - first[-1, 0]) < 1.0  # the second from where the first ended
    # the move to the second's start: a straight line in joint space, the TCP inside the box

    q_a, q_b = plans[0].plan.trajectory.q_deg[-1], plans[1].plan.trajectory.q_deg[0]
    u = np.linspace(0.0, 1.0, 257)[:, None]
    tcp = fk_batch((q_a + u * (q_b - q_a))[:, -6:], plans[1].settings.T_flange_sensor)[:, :3, 3]
    assert np.all(tcp >= np.asarray(cfg.robot.workspace_min_mm)) and np.all(tcp <= cfg.robot.workspace_max_mm)


def test_the_locate_run_goes_along_then_across_as_the_fit_asks():
    cfg = CellConfig()
    (along,) = next_locate_plans(cfg, SAIL, [], None)
    assert along.name == "locate along" and not along.across
    h = locate_height_mm(cfg, SAIL)
    assert along.range_z_mm == pytest.approx((h - cfg.laser.depth_max_mm, h - cfg.laser.depth_min_mm))
    assert next_locate_plans(cfg, SAIL, [along], _found(1500.0, 0.0, 25.0)) == []  # constrained, not square
    # sliding: passes across planned from the fit, at 20 and 80 % of the plate's 1200 mm along x
    planned = next_locate_plans(cfg, SAIL, [along], _found(1500.0, 0.0, 0.0, constrained=False))
    assert [lp.name for lp in planned] == ["locate across 1", "locate across 2"]
    xs = [float(lp.plan.passes[0].pos_mm[0, 0]) for lp in planned]
    assert xs == pytest.approx([1500.0 - 360.0, 1500.0 + 360.0], abs=1.0)
    # no fit: the square family over the bed's middle, at the locate height
    (square,) = next_locate_plans(cfg, SAIL, [along], None)
    assert square.name == "locate across" and square.across and len(square.plan.passes) > 1
    assert next_locate_plans(cfg, SAIL, [along, *planned], None) == []  # nothing after passes across


def test_the_passes_along_the_bed_start_at_its_corner_nearest_the_arm():
    """As the scan's serpentine does: the arm where the default run ends (its far corner) gets a run
    that starts there; where the default starts, the default."""
    cfg = CellConfig()
    (default,) = next_locate_plans(cfg, SAIL, [], None)
    T = default.settings.T_flange_sensor
    ends = np.array([seg.pos_mm[k, :2] for seg in default.plan.passes for k in (0, -1)])
    for q_arm in (default.plan.trajectory.q_deg[-1], default.plan.trajectory.q_deg[0]):
        arm_xy = fk_batch(q_arm[None], T)[0, :2, 3]
        (lp,) = next_locate_plans(cfg, SAIL, [], None, start_axes=q_arm)
        first = lp.plan.passes[0].pos_mm[0, :2]
        assert np.linalg.norm(first - arm_xy) == pytest.approx(
            np.linalg.norm(ends - arm_xy, axis=1).min(), abs=1.0
        )
        assert len(lp.plan.passes) == len(default.plan.passes)
    (far,) = next_locate_plans(cfg, SAIL, [], None, start_axes=default.plan.trajectory.q_deg[-1])
    assert np.linalg.norm(far.plan.passes[0].pos_mm[0, :2] - default.plan.passes[0].pos_mm[0, :2]) > 500.0
    # an arm the planner cannot place (non-finite axes): the default corner, no error
    (unknown,) = next_locate_plans(cfg, SAIL, [], None, start_axes=np.full(6, np.nan))
    assert np.allclose(unknown.plan.passes[0].pos_mm[0], default.plan.passes[0].pos_mm[0])
