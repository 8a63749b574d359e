"""The synthetic scan: realistic content, exact ground truth, files and command line."""

from __future__ import annotations

import json
from functools import cache

import numpy as np
import pytest

from analysis.cloud_io import read_cloud
from analysis.contracts.placement import Placement
from analysis.design.mesh import load_mesh
from analysis.design.plates import (
    FormingError,
    GaussianBump,
    PlateError,
    default_forming_error,
    formed_height_mm,
    plate_spec,
)
from analysis.synth import ScanSettings, SynthError, synthesize_scan
from cellctl.commands.synth_cmd import parse_deform, synth_main


@cache
def _scan(seed: int = 3, noise_mm: float = 0.02, yaw: float | None = None, kind: str = "sail"):
    placement = None if yaw is None else Placement.on_bed(30.0, -20.0, yaw, tilt_deg=0.3, tilt_axis_deg=40)
    return synthesize_scan(
        plate_spec(kind),
        settings=ScanSettings.coarse(
            noise_mm=noise_mm, point_pitch_mm=2.0, points_per_profile=25, profile_step_mm=4.0
        ),
        placement=placement,
        seed=seed,
    )


def _design_frame(scan) -> np.ndarray:
    T = scan.T_bed_design
    return (scan.xyz_mm - T[:3, 3]) @ T[:3, :3]


def test_noise_free_top_surface_points_lie_exactly_on_the_formed_surface():
    scan = _scan(noise_mm=0.0)
    q = _design_frame(scan)
    z = formed_height_mm(scan.spec, scan.error, q[:, 0], q[:, 1])
    inside = (np.abs(q[:, 0]) < 599.0) & (np.abs(q[:, 1]) < 399.0) & ~scan.is_outlier
    on_top = inside & (np.abs(q[:, 2] - z) < 1.0)
    assert on_top.sum() > 100_000
    assert np.abs(q[on_top, 2] - z[on_top]).max() < 1e-5


def test_range_noise_on_the_top_surface_has_the_configured_sigma():
    scan = _scan()
    q = _design_frame(scan)
    z = formed_height_mm(scan.spec, scan.error, q[:, 0], q[:, 1])
    inside = (np.abs(q[:, 0]) < 590.0) & (np.abs(q[:, 1]) < 390.0) & ~scan.is_outlier
    r = q[inside, 2] - z[inside]
    r = r[np.abs(r) < 1.0]
    assert np.std(r) == pytest.approx(0.02, rel=0.05)


def test_placement_transform_is_a_rigid_motion_and_the_plate_rests_on_the_supports():
    scan = _scan()
    R = scan.T_bed_design[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    # The lowest point of the plate's bottom is at support height (60 mm) or above.
    xy = np.stack(np.meshgrid(np.linspace(-600, 600, 61), np.linspace(-400, 400, 41)), -1).reshape(-1, 2)
    bottom = np.column_stack([xy, formed_height_mm(scan.spec, scan.error, xy[:, 0], xy[:, 1]) - 15.0])
    zb = (bottom @ R.T + scan.T_bed_design[:3, 3])[:, 2]
    assert zb.min() == pytest.approx(60.0, abs=0.5)


def test_scan_shows_bed_supports_thickness_faces_and_outliers():
    scan = _scan()
    z = scan.xyz_mm[:, 2]
    q = _design_frame(scan)
    assert np.count_nonzero(np.abs(z) < 0.2) > 1000  # the bed
    assert np.count_nonzero(np.abs(z - 60.0) < 0.2) > 1000  # support tops
    zt = formed_height_mm(scan.spec, scan.error, q[:, 0], q[:, 1])
    wall = (np.abs(np.abs(q[:, 0]) - 600.0) < 0.1) & (q[:, 2] < zt - 1.0) & (q[:, 2] > zt - 14.0)
    assert wall.sum() > 100  # thickness faces, seen by the edge passes
    assert set(np.unique(scan.pass_id[wall])) <= set(range(scan.n_raster_passes, scan.n_raster_passes + 4))
    assert 0 < scan.is_outlier.sum() < 0.001 * len(z)


def test_vertical_raster_rays_miss_the_thickness_faces_at_grazing_incidence():
    scan = _scan()
    q = _design_frame(scan)
    zt = formed_height_mm(scan.spec, scan.error, q[:, 0], q[:, 1])
    raster = scan.pass_id < scan.n_raster_passes
    wall = (np.abs(np.abs(q[:, 0]) - 600.0) < 0.1) & (q[:, 2] < zt - 1.0) & (q[:, 2] > zt - 14.0)
    assert not (wall & raster & ~scan.is_outlier).any()


def test_organisation_indices_are_unique_per_point():
    scan = _scan()
    key = (scan.pass_id.astype(np.int64) * 100_000 + scan.profile_index) * 1000 + scan.point_index
    assert len(np.unique(key)) == len(key)
    assert scan.point_index.max() == scan.settings.points_per_profile - 1


def test_same_seed_gives_the_same_scan_and_another_seed_another_placement():
    a = synthesize_scan(
        settings=ScanSettings.coarse(point_pitch_mm=4.0, points_per_profile=13, profile_step_mm=8.0), seed=5
    )
    b = synthesize_scan(
        settings=ScanSettings.coarse(point_pitch_mm=4.0, points_per_profile=13, profile_step_mm=8.0), seed=5
    )
    c = synthesize_scan(
        settings=ScanSettings.coarse(point_pitch_mm=4.0, points_per_profile=13, profile_step_mm=8.0), seed=6
    )
    np.testing.assert_array_equal(a.xyz_mm, b.xyz_mm)
    assert a.placement != c.placement


@pytest.mark.parametrize("yaw", [0.0, 90.0, 137.0, 250.0])
def test_plate_appears_at_any_yaw_with_truth_corners_on_its_footprint(yaw):
    scan = _scan(yaw=yaw)
    corners = scan.corners_bed_mm()
    q = (corners - scan.T_bed_design[:3, 3]) @ scan.T_bed_design[:3, :3]
    np.testing.assert_allclose(np.sort(np.abs(q[:, 0])), [600] * 4, atol=1e-9)
    np.testing.assert_allclose(np.sort(np.abs(q[:, 1])), [400] * 4, atol=1e-9)
    d = corners[1, :2] - corners[0, :2]
    assert np.linalg.norm(d) == pytest.approx(1200, abs=1.0) and d[0] >= 0


def test_parse_deform_builds_dents_bumps_springback_and_bend():
    spec = plate_spec()
    err = parse_deform(["dent:x=100,y=-50,depth=2.5,sigma=60", "bump:x=0,y=0,height=1,sigma=40",
                        "springback:amp=1.5,decay=70", "bend:0.01"], spec)  # fmt: skip
    assert err.bumps == (GaussianBump(100, -50, -2.5, 60), GaussianBump(0, 0, 1.0, 40))
    assert err.springback.amplitude_mm == 1.5 and err.springback.decay_mm == 70
    assert err.bend_fraction == 0.01
    assert parse_deform(None, spec) == default_forming_error(spec)
    assert parse_deform(["none"], spec).is_zero


@pytest.mark.parametrize(
    ("item", "message"),
    [
        ("dent:x=1,y=2,sigma=3", "depth"),
        ("dent:x=a,y=1,depth=1,sigma=1", "not a number"),
        ("wobble:1", "unknown"),
    ],
)
def test_parse_deform_rejects_bad_items_by_name(item, message):
    with pytest.raises(PlateError, match=message):
        parse_deform([item], plate_spec())


def test_bad_scan_settings_name_the_field():
    with pytest.raises(SynthError, match="pass_overlap_mm"):
        ScanSettings(pass_overlap_mm=100.0)
    with pytest.raises(SynthError, match="profile_step_mm"):
        ScanSettings(profile_step_mm=0.0)


def test_synth_main_writes_scan_design_and_truth_that_read_back(tmp_path):
    out = tmp_path / "scan.ply"
    argv = ["--plate", "saddle", "--deform", "dent:x=150,y=100,depth=3,sigma=50", "--out", str(out), "--seed", "2",
            "--point-pitch-mm", "2", "--points-per-profile", "25", "--profile-step-mm", "4", "--formed-mesh"]  # fmt: skip
    assert synth_main(argv) == 0
    cloud = read_cloud(out)
    assert cloud.organised and len(cloud) > 50_000
    design = load_mesh(tmp_path / "scan-design.ply")
    assert design.vertices_mm[:, 0].max() == pytest.approx(600.0)
    truth = json.loads((tmp_path / "scan-truth.json").read_text())
    assert truth["plate"]["kind"] == "saddle"
    assert FormingError.from_dict(truth["forming_error"]).bumps[0].amplitude_mm == -3.0
    T = np.array(truth["T_bed_design"])
    q = (cloud.xyz_mm - T[:3, 3]) @ T[:3, :3]
    spec = plate_spec("saddle")
    err = FormingError.from_dict(truth["forming_error"])
    z = formed_height_mm(spec, err, q[:, 0], q[:, 1])
    inside = (np.abs(q[:, 0]) < 590) & (np.abs(q[:, 1]) < 390)
    r = q[inside, 2] - z[inside]
    # float32 storage and 0.02 mm noise: the written truth still places the cloud to a few hundredths.
    assert np.median(np.abs(r)) < 0.03
    # --formed-mesh: the formed top surface (the mesh_file of [sim.plate] kind = "mesh"), design frame
    formed = load_mesh(tmp_path / "scan-formed.ply")
    v = formed.vertices_mm
    np.testing.assert_allclose(v[:, 2], formed_height_mm(spec, err, v[:, 0], v[:, 1]), atol=1e-9)
    assert np.ptp(v[:, 0]) == pytest.approx(1200.0) and np.ptp(v[:, 1]) == pytest.approx(800.0)


def test_synth_main_returns_2_with_one_line_on_bad_input(tmp_path, capsys):
    assert synth_main(["--out", str(tmp_path / "s.ply"), "--deform", "dent:x=1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("cellctl synth:") and "\n" not in err
    assert synth_main(["--out", str(tmp_path / "s.xyz"), "--points-per-profile", "10", "--profile-step-mm", "50",
                       "--point-pitch-mm", "10", "--pass-overlap-mm", "1"]) == 2  # fmt: skip
    assert synth_main(["--out", str(tmp_path / "s.xyz"), "--points-per-profile", "10", "--profile-step-mm", "50",
                       "--point-pitch-mm", "10"]) == 2  # fmt: skip
    assert "PLY" in capsys.readouterr().err
    assert synth_main(["--plate", "banana", "--out", "x.ply"]) == 2
