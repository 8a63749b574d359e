"""The 6000 x 2000 plate on the long-plate cell (docs/examples/cell-track.toml): the robot on a riser
on a 7 m track, the plate 800 mm below its base (issue 20, item 5)."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest

from analysis.contracts.placement import Placement
from analysis.design.plates import design_mesh, plate_spec
from cellctl.config import load_config
from cellctl.planning import PlannerSettings, plan_scan
from cellctl.planning.coverage import build_segments, design_surface, predict_edge_face_coverage
from cellctl.planning.planner import EDGE_TILT_MIN_DEG

REPO = Path(__file__).resolve().parents[2]
TRACK_CELL = REPO / "docs" / "examples" / "cell-track.toml"
LONG_SPEC = plate_spec("sail", length_mm=6000.0, width_mm=2000.0, radius_x_mm=20000.0, radius_y_mm=10000.0)

#: what the long-plate cell changes in cell.toml (section.key); everything else is cell.toml's
CHANGED = {
    "cell.id",
    "robot.egm_max_pos_deviation_deg",
    "robot.workspace_min_mm",
    "robot.track",
    "scan.placement_uncertainty_deg",
    "scan.placement_z_mm",
    "scan.sweep_pitch_deg",
    "locate.bed_min_xy_mm",
    "locate.bed_max_xy_mm",
    "locate.bed_z_mm",
    "sim.egm_track_start_mm",
    "sim.plate.length_mm",
    "sim.plate.width_mm",
    "sim.plate.radius_x_mm",
    "sim.plate.radius_y_mm",
    "sim.placement.pos_mm",
    "sim.placement.angle_deg",
}


def _flat(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict) and key != "robot.track":
            out.update(_flat(v, key + "."))
        else:
            out[key] = v
    return out


def test_the_long_plate_cell_is_cell_toml_but_for_its_geometry():
    shipped = _flat(tomllib.loads((REPO / "cell.toml").read_text()))
    track = _flat(tomllib.loads(TRACK_CELL.read_text()))
    differ = {k for k in shipped.keys() | track.keys() if shipped.get(k) != track.get(k)}
    assert differ == CHANGED
    cfg = load_config(TRACK_CELL)
    assert cfg.robot.track is not None and cfg.scan.sweep_pitch_deg > 0
    # the plate's top lies below the robot base: the riser is the track origin's height
    assert cfg.robot.track.origin_mm[2] - cfg.sim.placement.pos_mm[2] == 800.0


def test_an_edge_pass_tilted_the_least_the_planner_allows_still_lights_the_thickness_face():
    """The far edge's tilt may be lowered to EDGE_TILT_MIN_DEG: the face is still seen there (the
    sail, every edge at that tilt, against the full 30 deg)."""
    mesh = design_mesh(plate_spec("sail"), pitch_mm=10.0)
    surface = design_surface(mesh)
    placement = Placement.on_bed(1500.0, 0.0, 3.0, z_mm=300.0)
    settings = PlannerSettings()
    low = {f"edge {k}": EDGE_TILT_MIN_DEG for k in range(1, 5)}
    full, _ = build_segments(surface, placement, settings)
    lowered, _ = build_segments(surface, placement, settings, edge_tilts_deg=low)
    seen_full = predict_edge_face_coverage(full, mesh, surface, placement, settings, 15.0)
    seen_low = predict_edge_face_coverage(lowered, mesh, surface, placement, settings, 15.0)
    assert min(seen_full.per_edge) >= 0.99
    assert min(seen_low.per_edge) >= 0.99
    # a little less and the face goes dark: the floor is where it is for a reason
    darker = {label: EDGE_TILT_MIN_DEG - 2.5 for label in low}
    dark, _ = build_segments(surface, placement, settings, edge_tilts_deg=darker)
    assert max(predict_edge_face_coverage(dark, mesh, surface, placement, settings, 15.0).per_edge) < 0.5


def test_a_sensor_leaning_along_the_passes_keeps_its_line_across_them_at_the_standoff():
    mesh = design_mesh(plate_spec("sail"), pitch_mm=10.0)
    surface = design_surface(mesh)
    placement = Placement.on_bed(1500.0, 0.0, 3.0, z_mm=300.0)
    straight, _ = build_segments(surface, placement, PlannerSettings())
    leaning, _ = build_segments(surface, placement, PlannerSettings(sweep_pitch_deg=15.0))
    for a, b in zip(straight, leaning, strict=True):
        if a.kind != "scan":
            continue
        # the laser line (x) is where it was; the view (z) leans 15 deg about it
        np.testing.assert_allclose(a.R_base_sensor[:, :, 0], b.R_base_sensor[:, :, 0], atol=1e-12)
        cos = np.einsum("ni,ni->n", a.R_base_sensor[:, :, 2], b.R_base_sensor[:, :, 2])
        np.testing.assert_allclose(cos, np.cos(np.deg2rad(15.0)), atol=1e-12)
        # both look at the same surface point at the standoff
        np.testing.assert_allclose(
            a.pos_mm + 100.0 * a.R_base_sensor[:, :, 2],
            b.pos_mm + 100.0 * b.R_base_sensor[:, :, 2],
            atol=1e-9,
        )


@pytest.mark.slow
def test_the_6000_x_2000_plate_plans_on_the_long_plate_cell_within_the_sweep_ratio():
    cfg = load_config(TRACK_CELL)
    settings = PlannerSettings.from_config(cfg)
    design = design_mesh(LONG_SPEC, pitch_mm=25.0)
    placement = cfg.sim.placement.to_placement()
    plan = plan_scan(design, placement, settings, with_coverage=False)

    assert plan.sweep_ratio <= 1.2
    assert sum(1 for s in plan.segments if s.kind == "scan") >= 50  # 2 m across at 40 mm per pass
    # the carriage carries the arm along the whole plate; the arm never leaves the joint margins
    carriage = plan.trajectory.q_deg[:, 0]
    assert np.ptp(carriage) > 5500.0
    track = settings.track
    assert carriage.min() >= track.travel_min_mm and carriage.max() <= track.travel_max_mm
    assert plan.choices["track"]["mode"] == "follow"
    # the far edge pass was tilted less to stay in reach, and says so; no tilt below the floor
    tilts = plan.choices.get("edge_tilt_deg", {})
    assert tilts and all(EDGE_TILT_MIN_DEG <= t < settings.edge_tilt_deg for t in tilts.values())
    surface = design_surface(design)
    faces = predict_edge_face_coverage(
        plan.segments, design, surface, placement, settings, LONG_SPEC.thickness_mm
    )
    assert min(faces.per_edge) >= 0.99


def test_the_edges_go_round_the_other_way_and_the_raster_passes_come_from_the_cache_unchanged():
    mesh = design_mesh(plate_spec("sail"), pitch_mm=10.0)
    surface = design_surface(mesh)
    placement = Placement.on_bed(1500.0, 0.0, 3.0, z_mm=300.0)
    settings = PlannerSettings()
    cache: dict = {}
    plain, _ = build_segments(surface, placement, settings)
    cached, _ = build_segments(surface, placement, settings, raster_cache=cache)
    again, _ = build_segments(surface, placement, settings, raster_cache=cache)
    reverse, _ = build_segments(surface, placement, settings, raster_cache=cache, edge_reverse=True)
    assert set(cache) == {1.0, ("head", 1.0)}  # the raster passes and the head (approach, passes, links)
    for a, b, c in zip(plain, cached, again, strict=True):
        assert a.label == b.label == c.label
        assert np.array_equal(a.pos_mm, b.pos_mm) and np.array_equal(a.pos_mm, c.pos_mm)
        assert np.array_equal(a.R_base_sensor, c.R_base_sensor)
    scans = [s for s in plain if s.kind == "scan"]
    assert [s.label for s in reverse if s.kind == "scan"] == [s.label for s in scans]

    def heading_turns(segments) -> float:
        """How far the sensor's line turns about the vertical over the edge passes (deg, signed)."""
        x = np.concatenate([s.R_base_sensor[:, :2, 0] for s in segments if s.kind == "edge"])
        a = np.unwrap(np.arctan2(x[:, 1], x[:, 0]))
        return float(np.rad2deg(a[-1] - a[0]))

    # round the plate one way, then the other: the line's heading turns the other way
    forward, backward = heading_turns(plain), heading_turns(reverse)
    assert abs(forward) > 180.0 and abs(backward) > 180.0
    assert np.sign(forward) != np.sign(backward)
