"""The planner's cheaper computations (issue 42) against the reference computations they replaced:
the same coverage as casting every ray, the same joints as the one-at-a-time IK walk, the same time
law samples as ruckig's ``at_time``, the same envelope samples as ``sample_many``, the same segments
as building every pass afresh, and the same executed trajectory whatever toppra's grid on the
sweeps. Nothing here is timed."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from ruckig import InputParameter, Ruckig, Trajectory

import cellctl.planning.coverage as coverage
import cellctl.planning.joint_path as joint_path
import cellctl.planning.planner as planner
import cellctl.planning.timing as timing
from analysis.design.mesh import TriMesh
from analysis.design.plates import design_mesh, plate_spec
from cellctl.planning import PlannerSettings, plan_scan
from cellctl.planning.coverage import _predict_coverage, build_segments, design_surface, predict_coverage
from cellctl.planning.planner import positions_at
from drivers.abb_egm.limits import LinearTrack
from tests.support.plans import SMALL_PLACEMENT, SMALL_SETTINGS


@pytest.fixture(scope="module")
def mesh():
    return design_mesh(plate_spec("sail", length_mm=200.0, width_mm=150.0), pitch_mm=5.0)


@pytest.fixture(scope="module")
def plan(mesh):
    return plan_scan(mesh, SMALL_PLACEMENT, SMALL_SETTINGS)


def test_culled_coverage_is_that_of_casting_every_ray_on_a_plan_with_a_gap(mesh, plan):
    surface = design_surface(mesh)
    # one raster pass left out: unseen cells, so the second round of rays has work to do
    gap = next(i for i, s in enumerate(plan.segments) if s.label == "scan 2")
    segments = plan.segments[:gap] + plan.segments[gap + 1 :]
    culled = predict_coverage(segments, mesh, surface, SMALL_PLACEMENT, SMALL_SETTINGS)
    every = _predict_coverage(segments, mesh, surface, SMALL_PLACEMENT, SMALL_SETTINGS, exhaustive=True)
    assert every.fraction < 0.99 and every.worst_fraction <= every.fraction
    assert culled == every
    full = predict_coverage(plan.segments, mesh, surface, SMALL_PLACEMENT, SMALL_SETTINGS)
    assert full == _predict_coverage(
        plan.segments, mesh, surface, SMALL_PLACEMENT, SMALL_SETTINGS, exhaustive=True
    )
    assert full.fraction == pytest.approx(1.0)


@pytest.mark.parametrize("max_incidence_deg", [80.0, 5.0])
def test_the_incidence_shortcut_counts_what_checking_every_rays_normal_counts(
    mesh, plan, monkeypatch, max_incidence_deg
):
    # 5 deg: below the fans' own spread, so many rays are refused on the incidence and the exact
    # check runs; 80: every ray is inside the shortcut's bound
    surface = design_surface(mesh)
    settings = SMALL_SETTINGS.with_(max_incidence_deg=max_incidence_deg)
    shortcut = _predict_coverage(plan.segments, mesh, surface, SMALL_PLACEMENT, settings, exhaustive=True)
    monkeypatch.setattr(coverage, "_steepest_facet_deg", lambda design, reach_mm: 90.0)  # no ray is sure
    every = _predict_coverage(plan.segments, mesh, surface, SMALL_PLACEMENT, settings, exhaustive=True)
    assert shortcut == every
    if max_incidence_deg < 20.0:
        assert every.fraction < 0.99  # the limit bites: the exact check did decide
    else:
        assert every.fraction == pytest.approx(1.0)


def test_the_incidence_shortcuts_bound_covers_flat_sliver_and_degenerate_facets():
    square = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [10.0, 10.0, 0.0], [0.0, 10.0, 0.0]])
    flat = TriMesh(square, np.array([[0, 1, 2], [0, 2, 3]]))
    assert coverage._steepest_facet_deg(flat, 5000.0) < 0.1  # level, and float32's error at 5 m
    sliver = TriMesh(np.vstack([square, [[5.0, 1e-4, 0.0]]]), np.array([[0, 1, 2], [0, 2, 3], [0, 4, 1]]))
    assert coverage._steepest_facet_deg(sliver, 5000.0) > 1.0  # a normal float32 cannot resolve
    degenerate = TriMesh(np.vstack([square, [[5.0, 0.0, 0.0]]]), np.array([[0, 1, 2], [0, 4, 1]]))
    assert coverage._steepest_facet_deg(degenerate, 5000.0) == 90.0


def _solve(mesh, settings, monkeypatch, walk_only: bool):
    if walk_only:  # the reference: every waypoint by the one-at-a-time walk
        monkeypatch.setattr(joint_path, "_same_branch_run", lambda *a, **k: np.zeros((0, 6)))
    else:
        monkeypatch.undo()
    return plan_scan(mesh, SMALL_PLACEMENT, settings, with_coverage=False)


@pytest.mark.parametrize("track", [False, True])
def test_branch_runs_give_the_walks_joints_bit_for_bit(mesh, monkeypatch, track):
    settings = SMALL_SETTINGS
    if track:
        settings = settings.with_(
            track=LinearTrack(
                origin_mm=[0.0, -2000.0, 0.0], direction=[0.0, 1.0, 0.0], travel_min_mm=0.0,
                travel_max_mm=4000.0, speed_max_mm_s=500.0, accel_max_mm_s2=1000.0, jerk_max_mm_s3=10000.0,
            ),
            track_hold=False,
        )  # fmt: skip
    walk = _solve(mesh, settings, monkeypatch, walk_only=True)
    fast = _solve(mesh, settings, monkeypatch, walk_only=False)
    assert [s.label for s in fast.segments] == [s.label for s in walk.segments]
    for a, b in zip(fast.segments, walk.segments, strict=True):
        assert np.array_equal(a.q_deg, b.q_deg), a.label
    assert np.array_equal(fast.trajectory.q_deg, walk.trajectory.q_deg)
    assert fast.scan_time_s == walk.scan_time_s


def test_a_run_stops_where_the_walk_would_change_branch():
    kin = joint_path.sensor_kinematics(SMALL_SETTINGS)
    q = np.array([10.0, 20.0, 10.0, 30.0, 50.0, -20.0])
    path = np.linspace(q, q + np.array([5.0, 3.0, -2.0, 40.0, 10.0, 30.0]), 9)
    T = kin.fk_batch(path, frame="sensor")
    branches = kin.ik_branches(T, frame="sensor")
    run = joint_path._same_branch_run(branches, q, kin, SMALL_SETTINGS)
    np.testing.assert_allclose(run, path, atol=1e-6)
    # branches without a solution (NaN: the shoulder turned away, out of reach) do not end a run
    b = int(np.nanargmin(np.sum((branches[0] - q) ** 2, axis=1)))
    unreachable = branches.copy()
    unreachable[:, [i for i in range(8) if i != b][:4]] = np.nan
    assert joint_path._same_branch_run(unreachable, q, kin, SMALL_SETTINGS).shape[0] == len(path)
    # a waypoint whose nearest branch is another one ends the run just before it
    swapped = branches.copy()
    swapped[5] = swapped[5][::-1]
    assert joint_path._same_branch_run(swapped, q, kin, SMALL_SETTINGS).shape[0] == 5
    # a step beyond the continuity limit too
    tight = SMALL_SETTINGS.with_(max_waypoint_joint_step_deg=4.0)
    assert joint_path._same_branch_run(branches, q, kin, tight).shape[0] == 1  # q itself, then 5 deg


@pytest.mark.parametrize(("v_in", "v_out"), [(0.0, 0.0), (3.0, 0.0), (0.0, 4.0), (5.0, 5.0), (9.9, 2.0)])
def test_vectorised_law_states_are_ruckigs_at_time(v_in, v_out):
    otg, inp, law = Ruckig(1), InputParameter(1), Trajectory(1)
    inp.current_position, inp.target_position = [0.0], [100.0]
    inp.current_velocity, inp.target_velocity = [v_in], [v_out]
    inp.max_velocity, inp.max_acceleration, inp.max_jerk = [10.0], [5.0], [20.0]
    inp.min_velocity = [0.0]
    otg.calculate(inp, law)
    t = np.linspace(0.0, law.duration, 777)
    reference = np.array([np.ravel(law.at_time(float(x))) for x in t])
    assert np.array_equal(timing._law_states(law, t), reference)


@pytest.mark.parametrize("block", [None, 1000])
def test_envelope_positions_are_sample_manys(plan, monkeypatch, block):
    if block is not None:  # taken in blocks, as a long plan's are
        monkeypatch.setattr(planner, "_POSITIONS_BLOCK", block)
    tr = plan.trajectory
    t = np.append(np.arange(0.0, tr.duration_s, 0.004032), tr.duration_s)
    assert block is None or t.size > 2 * block
    assert np.array_equal(positions_at(tr, t), tr.sample_many(t)[0])


def test_mirrored_raster_and_the_cached_head_are_the_fresh_build(mesh):
    surface = design_surface(mesh)
    settings = SMALL_SETTINGS.with_(sweep_pitch_deg=10.0)
    cache: dict = {}
    build_segments(surface, SMALL_PLACEMENT, settings, sign=1.0, raster_cache=cache)
    for sign in (-1.0, 1.0):  # -1: the mirrored raster; +1 again: the cached head
        got, _ = build_segments(surface, SMALL_PLACEMENT, settings, sign=sign, raster_cache=cache)
        fresh, _ = build_segments(surface, SMALL_PLACEMENT, settings, sign=sign)
        assert [(s.kind, s.label, s.flying) for s in got] == [(s.kind, s.label, s.flying) for s in fresh]
        for a, b in zip(got, fresh, strict=True):
            assert np.array_equal(a.pos_mm, b.pos_mm) and np.array_equal(a.R_base_sensor, b.R_base_sensor), (
                a.label
            )
    # the cache hands out fresh segments: moving one does not move the cached plan
    again, _ = build_segments(surface, SMALL_PLACEMENT, settings, sign=1.0, raster_cache=cache)
    again[1].pos_mm = again[1].pos_mm + 1.0
    third, _ = build_segments(surface, SMALL_PLACEMENT, settings, sign=1.0, raster_cache=cache)
    assert np.array_equal(third[1].pos_mm, got[1].pos_mm)


def test_toppras_sweep_grid_leaves_the_executed_trajectory_and_moves_its_bound_little(mesh, monkeypatch):
    settings = PlannerSettings()
    sail = design_mesh(plate_spec("sail", length_mm=600.0, width_mm=400.0), pitch_mm=10.0)
    coarse = plan_scan(sail, SMALL_PLACEMENT, settings, with_coverage=False)
    monkeypatch.setattr(timing, "_TOPPRA_SWEEP_STRIDE", timing._TOPPRA_GRID_STRIDE)
    fine = plan_scan(sail, SMALL_PLACEMENT, settings, with_coverage=False)
    assert np.array_equal(coarse.trajectory.q_deg, fine.trajectory.q_deg)
    assert coarse.scan_time_s == fine.scan_time_s
    assert coarse.toppra_time_s == pytest.approx(fine.toppra_time_s, rel=5e-3)
    assert replace(coarse, toppra_time_s=0.0).summary()["passes"] == fine.summary()["passes"]
