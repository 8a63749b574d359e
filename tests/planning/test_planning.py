"""Coverage planning, joint path, timing and the plan object, on the project's design surfaces."""

from __future__ import annotations

import itertools
import json
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from analysis.contracts.placement import Placement, placement_transform
from analysis.design.mesh import TriMesh, save_mesh
from analysis.design.plates import design_mesh, plate_spec
from cellctl.motion import EnvelopeLimits, SafetyEnvelope
from cellctl.planning import PlanInputError, PlannerSettings, PlanRefused, ScanPlan, plan_scan
from cellctl.planning.coverage import design_surface
from cellctl.planning.timing import RAMP_ALLOWANCE_MM, tcp_speed_mm_s
from drivers.abb_egm.kinematics import fk_batch
from tests.support.plans import SAIL_PLACEMENT

CYCLE_S = 0.004032


def test_sail_plate_plan_sees_the_whole_top_surface_and_meets_the_sweep_ratio(sail_plan):
    assert sail_plan.coverage.fraction >= 0.99
    assert sail_plan.coverage.worst_fraction >= 0.99  # also at the corners of the placement uncertainty
    assert sail_plan.sweep_ratio <= 1.2
    assert sail_plan.scan_speed_mm_s == pytest.approx(100.0)  # 0.5 mm profile spacing x 200 Hz
    assert sail_plan.scan_speed_deviation <= 0.02
    kinds = [s.kind for s in sail_plan.segments]
    assert kinds[0] == "approach" and kinds[-1] == "retract"
    assert kinds.count("edge") == 4
    # links between every two sweeps
    assert all(
        a.is_sweep != b.is_sweep
        for a, b in zip(sail_plan.segments[1:-2], sail_plan.segments[2:-1], strict=True)
    )


def test_raster_passes_keep_the_line_across_the_pass_and_the_sensor_on_the_normal_at_the_standoff(sail_plan):
    settings = PlannerSettings()
    surface = design_surface(design_mesh(plate_spec("sail"), pitch_mm=10.0))
    T_plate_base = np.linalg.inv(placement_transform(SAIL_PLACEMENT))
    checked = 0
    for seg in (s for s in sail_plan.segments if s.kind == "scan"):
        R = T_plate_base[:3, :3] @ seg.R_base_sensor
        p = seg.pos_mm @ T_plate_base[:3, :3].T + T_plate_base[:3, 3]
        travel = np.diff(p, axis=0)
        travel /= np.linalg.norm(travel, axis=1, keepdims=True)
        # laser line (sensor x) perpendicular to the direction of the pass
        assert np.max(np.abs(np.einsum("ij,ij->i", R[:-1, :, 0], travel))) < 0.02
        # the point the sensor looks at, one standoff along its axis, lies on the surface, and the
        # axis is along minus the surface normal there
        s = p + settings.standoff_mm * R[:, :, 2]
        h, gx, gy = surface.height_and_gradient(s[:, 0], s[:, 1])
        normal = np.column_stack([-gx, -gy, np.ones_like(gx)])
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        inside = surface.inside(s[:, 0], s[:, 1])  # the outermost passes look just beyond the edges
        checked += int(inside.sum())
        assert np.all(np.abs(s[inside, 2] - h[inside]) < 0.5)
        assert np.all(np.einsum("ij,ij->i", R[:, :, 2], -normal)[inside] > np.cos(np.deg2rad(1.0)))
    assert checked > 1000


def test_tcp_speed_is_constant_on_every_sweep_outside_the_ramps(sail_plan):
    settings = PlannerSettings()
    tr = sail_plan.trajectory
    for seg in sail_plan.segments:
        if not seg.is_sweep:
            continue
        t = np.arange(seg.t_start_s, seg.t_start_s + seg.duration_s, CYCLE_S)
        q, qd, _, _ = tr.sample_many(t)
        p = fk_batch(q, settings.T_flange_sensor)[:, :3, 3]
        travelled = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])
        mid = (travelled > RAMP_ALLOWANCE_MM) & (travelled < travelled[-1] - RAMP_ALLOWANCE_MM)
        v = tcp_speed_mm_s(q[mid], qd[mid], settings.T_flange_sensor)
        assert np.all(np.abs(v / sail_plan.scan_speed_mm_s - 1.0) <= 0.02), seg.label


def test_every_timed_sample_of_the_sail_plan_passes_the_safety_envelope(sail_plan):
    settings = PlannerSettings()
    t = np.arange(0.0, sail_plan.trajectory.duration_s, CYCLE_S)
    q = sail_plan.trajectory.sample_many(t)[0]
    SafetyEnvelope(EnvelopeLimits.from_settings(settings, CYCLE_S)).check_trajectory(t, q)


def test_scan_plan_survives_a_json_round_trip(small_plan, tmp_path):
    path = tmp_path / "plan.json"
    small_plan.to_json(path)
    back = ScanPlan.from_json(path)
    assert back.summary() == small_plan.summary()
    assert [s.label for s in back.segments] == [s.label for s in small_plan.segments]
    np.testing.assert_allclose(back.trajectory.q_deg, small_plan.trajectory.q_deg, atol=1e-6)
    q_a = back.trajectory.sample(1.234)[0]
    q_b = small_plan.trajectory.sample(1.234)[0]
    np.testing.assert_allclose(q_a, q_b, atol=1e-5)


def test_plan_file_that_is_not_a_plan_is_rejected_with_a_reason():
    with pytest.raises(PlanInputError, match="format"):
        ScanPlan.from_json(json.dumps({"format": "something else"}))
    with pytest.raises(PlanInputError, match="not a scan plan"):
        ScanPlan.from_json(json.dumps({"format": "cellctl.scan_plan/1"}))


def test_plate_beyond_the_reach_of_a_railless_cell_is_refused_naming_pass_point_and_limit():
    spec = plate_spec("sail", length_mm=6000.0, width_mm=2500.0, radius_x_mm=20000.0, radius_y_mm=10000.0)
    large = design_mesh(spec, pitch_mm=25.0)
    with pytest.raises(PlanRefused) as info:
        plan_scan(large, Placement.on_bed(2000.0, 0.0, 90.0, z_mm=300.0), with_coverage=False)
    r = info.value
    assert r.pass_label and r.point_index is not None and r.limit.startswith("reach")
    assert "split the plate" in r.reason
    assert r.to_dict()["message"] == str(r)


def test_depth_range_too_narrow_for_the_curved_surface_and_the_uncertainty_is_refused():
    settings = PlannerSettings(depth_min_mm=99.0, depth_max_mm=101.0)
    with pytest.raises(PlanRefused) as info:
        plan_scan(
            design_mesh(plate_spec("sail"), pitch_mm=10.0), SAIL_PLACEMENT, settings, with_coverage=False
        )
    assert info.value.limit.startswith("depth range") and info.value.pass_label.startswith("scan")


def test_wrist_singularity_margin_refusal_names_joint_5():
    settings = PlannerSettings(wrist_margin_deg=60.0)
    with pytest.raises(PlanRefused) as info:
        plan_scan(
            design_mesh(plate_spec("sail"), pitch_mm=10.0), SAIL_PLACEMENT, settings, with_coverage=False
        )
    assert "joint_5" in str(info.value)


def test_joint_limit_with_margin_refusal_names_the_joint_and_the_limit():
    upper = list(PlannerSettings().joint_upper_deg)
    upper[2] = 30.0  # joint 3 cannot reach the near side of the plate any more
    settings = PlannerSettings(joint_upper_deg=tuple(upper))
    with pytest.raises(PlanRefused) as info:
        plan_scan(
            design_mesh(plate_spec("sail"), pitch_mm=10.0), SAIL_PLACEMENT, settings, with_coverage=False
        )
    assert "joint_3" in info.value.limit


def test_a_vertical_wall_is_not_a_plate_design():
    wall = TriMesh(
        np.array([[0, 0, 0], [100, 0, 0], [100, 0, 100], [0, 0, 100]], float),
        np.array([[0, 1, 2], [0, 2, 3]]),
    )
    with pytest.raises(PlanInputError, match="design"):
        design_surface(wall)


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_placement_with_a_non_finite_value_names_the_field(bad):
    with pytest.raises(ValidationError, match=r"rpy_deg"):
        Placement.on_bed(1500.0, 0.0, bad, z_mm=300.0)


def test_a_tilted_placement_is_refused_by_the_planner():
    tilted = Placement(pos_mm=[1500.0, 0.0, 300.0], rpy_deg=[2.0, 0.0, 3.0])
    with pytest.raises(PlanInputError, match=r"placement\.rpy_deg"):
        plan_scan(design_mesh(plate_spec("sail"), pitch_mm=20.0), tilted, with_coverage=False)


def test_settings_with_the_standoff_outside_the_depth_range_are_rejected():
    with pytest.raises(PlanInputError, match="standoff_mm"):
        PlannerSettings(standoff_mm=150.0)


@pytest.mark.process
def test_cli_plan_prints_passes_coverage_and_scan_time_and_writes_json(tmp_path, repo_root):
    mesh = tmp_path / "small.ply"
    save_mesh(design_mesh(plate_spec("sail", length_mm=200.0, width_mm=150.0), pitch_mm=5.0), mesh)
    out = tmp_path / "plan.json"
    cmd = [sys.executable, "-m", "cellctl", "--log-level", "WARNING", "plan", "--design", str(mesh)]
    cmd += ["--placement", "1600,100,3", "--config", str(repo_root / "cell.toml"), "--out", str(out)]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120, cwd=repo_root)
    assert done.returncode == 0, done.stderr
    assert "coverage:" in done.stdout and "scan time:" in done.stdout and "scan 1" in done.stdout
    assert ScanPlan.from_json(out).coverage.fraction >= 0.99


def test_cli_plan_refusal_exits_2_with_the_reason_as_json(tmp_path, repo_root, capsys):
    from cellctl.commands.plan_cmd import register

    mesh = tmp_path / "small.ply"
    save_mesh(design_mesh(plate_spec("sail", length_mm=200.0, width_mm=150.0), pitch_mm=5.0), mesh)
    args = _plan_args(
        register, ["--design", str(mesh), "--placement", "4000,0,0", "--json", "--no-coverage"], repo_root
    )
    assert args.func(args) == 2
    out = [line for line in capsys.readouterr().out.splitlines() if line.startswith('{"ok"')]
    refusal = json.loads(out[-1])["refusal"]
    assert refusal["reason"] and refusal["limit"].startswith("reach") and refusal["pass"]


@pytest.mark.parametrize("placement", ["1500,zero,3", "1500,0", "1500,0,nan", "1,2,3,4,5"])
def test_cli_plan_rejects_a_malformed_placement_with_exit_2(placement, repo_root, capsys):
    from cellctl.commands.plan_cmd import register

    args = _plan_args(register, ["--design", "sim", "--placement", placement], repo_root)
    assert args.func(args) == 2
    assert "--placement" in capsys.readouterr().err


def test_cli_plan_reports_a_missing_design_file_with_exit_2(tmp_path, repo_root, capsys):
    from cellctl.commands.plan_cmd import register

    args = _plan_args(
        register, ["--design", str(tmp_path / "nope.ply"), "--placement", "1500,0,3"], repo_root
    )
    assert args.func(args) == 2
    assert "nope.ply" in capsys.readouterr().err


def _plan_args(register, argv: list[str], repo_root):
    """Parse ``cellctl plan`` arguments with the command's own parser (in process: fast)."""
    import argparse

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    return parser.parse_args(["plan", *argv, "--config", str(repo_root / "cell.toml")])


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.floats(0.0, 1.0), min_size=1, max_size=20))
def test_vectorised_and_single_trajectory_samples_agree(small_plan, fractions):
    tr = small_plan.trajectory
    t = np.asarray(fractions) * tr.duration_s
    q, qd, qdd, seg = tr.sample_many(t)
    for k, tk in enumerate(t):
        q1, qd1, qdd1, s1 = tr.sample(tk)
        np.testing.assert_allclose(q[k], q1, atol=1e-9)
        np.testing.assert_allclose(qd[k], qd1, atol=1e-9)
        np.testing.assert_allclose(qdd[k], qdd1, atol=1e-7)
        assert seg[k] == s1


def test_the_planned_time_parts_add_up_to_the_scan_time_and_name_each_transition(small_plan):
    s = small_plan.summary()
    parts = s["approach_s"] + s["sweep_s"] + s["transitions_s"] + s["retract_s"]
    assert abs(parts - small_plan.scan_time_s) <= CYCLE_S
    assert min(s["approach_s"], s["sweep_s"], s["transitions_s"], s["retract_s"]) > 0
    times = s["pass_times"]
    assert [t["label"] for t in times] == [p.label for p in small_plan.passes]
    assert times[0]["transition_s"] == 0.0
    # each transition is the gap between the previous pass's end and this pass's start
    for prev, cur in itertools.pairwise(times):
        gap = cur["t_start_s"] - (prev["t_start_s"] + prev["duration_s"])
        assert abs(cur["transition_s"] - gap) <= 0.002
    assert abs(sum(t["transition_s"] for t in times) - s["transitions_s"]) <= 0.001 * len(times)
    assert abs(sum(t["duration_s"] for t in times) - s["sweep_s"]) <= 0.001 * len(times)
