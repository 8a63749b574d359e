"""The outline fit of the locate run (analysis/locate.py) on synthesised sparse locate clouds."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from analysis.cloud_io import ScanCloud
from analysis.locate import (
    LocateError,
    LocateSettings,
    design_outline,
    fit_outline,
    locate_plate,
    placement_offset,
    plate_boundary,
)
from analysis.placement import Placement
from analysis.plates import design_height_mm, design_mesh, plate_spec

PLATE = plate_spec("sail", length_mm=1200.0, width_mm=800.0)
MESH = design_mesh(PLATE, pitch_mm=20.0)
BED_MIN, BED_MAX = np.array([800.0, -700.0]), np.array([2200.0, 700.0])
SENSOR_Z, RANGE = 440.0, (70.0, 130.0)  # flat passes 440 mm up: world z 310 ... 370 is measured


def locate_clouds(
    placement: Placement,
    *,
    spec=PLATE,
    bed_min=BED_MIN,
    bed_max=BED_MAX,
    spacing_mm: float = 300.0,
    sensor_z_mm: float = SENSOR_Z,
    noise_mm: float = 0.02,
    seed: int = 0,
) -> list[ScanCloud]:
    """Two families of straight passes (along x over the bed, along y over its middle square), a
    50 mm line of 500 points, profiles every 1.1 mm; a point where the plate is, in the depth range."""
    rng = np.random.default_rng(seed)
    out = []
    yaw = np.deg2rad(placement.yaw_deg)
    c, s = np.cos(yaw), np.sin(yaw)
    cx, cy = (bed_min + bed_max) / 2
    side = float(min(bed_max - bed_min))
    families = [
        (0, bed_min, bed_max),
        (1, np.array([cx - side / 2, cy - side / 2]), np.array([cx + side / 2, cy + side / 2])),
    ]
    for axis, lo, hi in families:
        across = 1 - axis
        w = hi[across] - lo[across]
        n = int(np.ceil((w - spacing_mm) / spacing_mm)) + 1
        centres = np.linspace(lo[across] + spacing_mm / 2, hi[across] - spacing_mm / 2, max(n, 1))
        xs, ps, prs, pts = [], [], [], []
        prof0 = 0
        for k, cc in enumerate(centres):
            along = np.arange(lo[axis], hi[axis], 1.1)
            line = cc + (np.arange(500) - 249.5) * 0.1
            A, L = np.meshgrid(along, line, indexing="ij")
            X, Y = (A, L) if axis == 0 else (L, A)
            dx, dy = X - placement.x_mm, Y - placement.y_mm
            u, v = c * dx + s * dy, -s * dx + c * dy
            inside = (np.abs(u) <= spec.length_mm / 2) & (np.abs(v) <= spec.width_mm / 2)
            Z = placement.z_mm + design_height_mm(spec, u, v) + rng.normal(0, noise_mm, u.shape)
            depth = sensor_z_mm - Z
            ok = inside & (depth >= RANGE[0]) & (depth <= RANGE[1])
            i, j = np.nonzero(ok)
            xs.append(np.column_stack([X[i, j], Y[i, j], Z[i, j]]))
            ps.append(np.full(len(i), k + 1))
            prs.append(i + prof0)
            pts.append(j)
            prof0 += len(along)
        out.append(
            ScanCloud(
                np.concatenate(xs),
                np.concatenate(ps).astype(np.int32),
                np.concatenate(prs).astype(np.int32),
                np.concatenate(pts).astype(np.int32),
            )
        )
    return out


def _settings(**kw) -> LocateSettings:
    return LocateSettings(range_z_mm=(SENSOR_Z - RANGE[1], SENSOR_Z - RANGE[0]), **kw)


def _random_placement(rng: np.random.Generator, spec=PLATE, bed_min=BED_MIN, bed_max=BED_MAX) -> Placement:
    """A placement whose footprint lies on the bed, yaw within 90 deg of 0 (the bed convention)."""
    while True:
        yaw = rng.uniform(-89.0, 89.0)
        a = np.deg2rad(yaw)
        hx = abs(np.cos(a)) * spec.length_mm / 2 + abs(np.sin(a)) * spec.width_mm / 2
        hy = abs(np.sin(a)) * spec.length_mm / 2 + abs(np.cos(a)) * spec.width_mm / 2
        if hx * 2 < bed_max[0] - bed_min[0] and hy * 2 < bed_max[1] - bed_min[1]:
            x = rng.uniform(bed_min[0] + hx, bed_max[0] - hx)
            y = rng.uniform(bed_min[1] + hy, bed_max[1] - hy)
            return Placement.on_bed(x, y, yaw, z_mm=300.0)


def test_outline_of_a_plate_mesh_is_its_perimeter_with_outward_normals():
    ol = design_outline(MESH, 2.0)
    assert ol.length_mm == pytest.approx(2 * (1200 + 800), rel=1e-6)
    # outward: every normal points away from the centre
    assert np.all(np.einsum("ij,ij->i", ol.xy_mm, ol.normal) > 0)


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), noise=st.sampled_from([0.0, 0.02, 0.1]))
def test_a_random_placement_on_the_bed_is_found_within_2_mm_and_a_fifth_of_a_degree(seed, noise):
    truth = _random_placement(np.random.default_rng(seed))
    clouds = locate_clouds(truth, noise_mm=noise, seed=seed)
    res = locate_plate(clouds, MESH, _settings())
    d_mm, d_deg = placement_offset(res.placement, truth)
    assert d_mm < 2.0 and d_deg < 0.2, (truth, res.summary())
    assert abs(res.placement.z_mm - truth.z_mm) < 1.0
    assert res.rms_mm < 1.0
    assert res.ambiguous and res.resolved_by == "convention"  # a sail plate looks the same turned


def test_the_half_turn_of_a_symmetric_plate_follows_the_hint():
    truth = Placement.on_bed(1500.0, 50.0, 20.0, z_mm=300.0)
    clouds = locate_clouds(truth)
    res = locate_plate(clouds, MESH, _settings(yaw_hint_deg=-160.0))
    assert res.resolved_by == "hint"
    d_mm, d_deg = placement_offset(res.placement, Placement.on_bed(1500.0, 50.0, -160.0, z_mm=300.0))
    assert d_mm < 2.0 and d_deg < 0.2


def test_an_asymmetric_outline_decides_the_half_turn_itself():
    # a plate with one corner cut off: the outline is not the same after a half turn
    spec = plate_spec("flat", length_mm=1000.0, width_mm=600.0)
    mesh = design_mesh(spec, pitch_mm=20.0)
    v = mesh.vertices_mm
    cut = (v[:, 0] - v[:, 1]) > 300.0  # the corner at (+x, -y)
    keep = ~cut[mesh.triangles].any(axis=1)
    from analysis.mesh import TriMesh

    mesh = TriMesh(v, mesh.triangles[keep])
    truth = Placement.on_bed(1450.0, -30.0, 150.0, z_mm=300.0)
    # flat plate 300 up: passes 400 up see it at 100 mm depth
    clouds = _flat_clouds(truth, mesh, sensor_z=400.0)
    res = locate_plate(clouds, mesh, LocateSettings(range_z_mm=(270.0, 330.0)))
    d_mm, d_deg = placement_offset(res.placement, truth)
    assert res.resolved_by == "fit" and not res.ambiguous
    assert d_mm < 2.0 and d_deg < 0.2, res.summary()


def _flat_clouds(truth: Placement, mesh, sensor_z: float) -> list[ScanCloud]:
    """Locate clouds of a flat plate of any outline: inside = the mesh's triangles contain the point."""
    from matplotlib.path import Path as MplPath  # the outline as a polygon test

    ol = design_outline(mesh, 2.0)
    order = np.argsort(np.arctan2(ol.xy_mm[:, 1], ol.xy_mm[:, 0]))
    poly = MplPath(ol.xy_mm[order])
    spec = plate_spec("flat", length_mm=float(np.ptp(ol.xy_mm[:, 0])), width_mm=float(np.ptp(ol.xy_mm[:, 1])))
    clouds = locate_clouds(truth, spec=spec, sensor_z_mm=sensor_z)
    out = []
    a = np.deg2rad(truth.yaw_deg)
    for c in clouds:
        d = c.xyz_mm[:, :2] - truth.pos_mm[:2]
        u = np.column_stack(
            [np.cos(a) * d[:, 0] + np.sin(a) * d[:, 1], -np.sin(a) * d[:, 0] + np.cos(a) * d[:, 1]]
        )
        k = poly.contains_points(u)
        out.append(ScanCloud(c.xyz_mm[k], c.pass_id[k], c.profile_index[k], c.point_index[k]))
    return out


def test_range_dropouts_are_no_edges():
    truth = Placement.on_bed(1500.0, 0.0, 0.0, z_mm=300.0)
    b = plate_boundary(locate_clouds(truth), _settings())
    # the centre of the sail (z < 313) is below the range: its rim is dropped, not taken as an edge
    assert b.dropped_range > 0
    assert np.all(b.boundary_mm[:, 2] > SENSOR_Z - RANGE[1] + 3.0)


def test_no_plate_and_the_wrong_design_are_refused_with_a_reason():
    truth = Placement.on_bed(1500.0, 0.0, 10.0, z_mm=300.0)
    empty = [ScanCloud(np.zeros((0, 3)), np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros(0, np.int32))]
    with pytest.raises(LocateError, match="no plate points"):
        locate_plate(empty, MESH, _settings())
    small = design_mesh(plate_spec("sail", length_mm=700.0, width_mm=500.0), pitch_mm=20.0)
    with pytest.raises(LocateError, match="does not fit"):
        fit_outline(plate_boundary(locate_clouds(truth), _settings()), design_outline(small), _settings())
