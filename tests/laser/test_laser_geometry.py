"""What the simulated sensor sees: depths on a plane, the edge of a step, missing returns, the cell scene."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from laser_helpers import collect, looking_down, run, sim_and_client
from scipy.spatial.transform import Rotation

from drivers.laser.sim.optics import LaserOptics, render_points, render_uniform
from drivers.laser.sim.scene import (
    Scene,
    SceneRaycaster,
    box_scene,
    cell_scene,
    plane_scene,
    plate_solid,
    step_scene,
)
from drivers.laser.sim.sensor import LaserSimulator, SimConfig
from drivers.laser.source import ProfileBatch


def expected_depth_on_floor(T: np.ndarray, x_mm: np.ndarray) -> np.ndarray:
    """z in the sensor frame where the laser plane meets the world plane z = 0 at sensor x."""
    return -(T[2, 3] + x_mm * T[2, 0]) / T[2, 2]


def test_plane_at_a_known_tilted_pose_gives_depths_within_the_noise() -> None:
    T = looking_down(100.0, x_mm=20.0, y_mm=-5.0)
    T[:3, :3] = T[:3, :3] @ Rotation.from_euler("yx", [8.0, -5.0], degrees=True).as_matrix()
    cfg = SimConfig(rate_hz=500.0, outlier_probability=0.0, noise_sigma_mm=0.02, seed=5)

    async def scenario() -> ProfileBatch:
        async with sim_and_client(plane_scene(0.0), T, config=cfg) as (_sim, client):
            await client.start()
            return ProfileBatch.concat(await collect(client, 100))

    b = run(scenario())
    assert b.valid.mean() > 0.99
    resid = b.z_mm[b.valid] - expected_depth_on_floor(T, b.x_mm[b.valid])
    assert abs(resid.mean()) < 0.003
    assert 0.017 < resid.std() < 0.023


def test_step_edge_appears_where_the_step_is() -> None:
    edge_x_mm = 3.37
    T = looking_down(100.0)
    cfg = SimConfig(rate_hz=500.0, outlier_probability=0.0, noise_sigma_mm=0.0, seed=6)

    async def scenario() -> ProfileBatch:
        async with sim_and_client(step_scene(edge_x_mm, 0.0, 10.0), T, config=cfg) as (_sim, client):
            await client.start()
            return ProfileBatch.concat(await collect(client, 20))

    b = run(scenario())
    for x, z, v in zip(b.x_mm, b.z_mm, b.valid, strict=True):
        low = v & (z > 95.0)  # floor, 100 mm away
        high = v & (z < 95.0)  # top of the step, 90 mm away
        np.testing.assert_allclose(z[low], 100.0, atol=0.002)
        np.testing.assert_allclose(z[high], 90.0, atol=0.002)
        last_low = x[low].max()
        first_high = x[high].min()
        assert last_low < edge_x_mm < first_high
        # Rays on the wall itself return nothing (grazing), so at most one grid point goes missing.
        assert first_high - last_low <= 0.2 + 1e-5
        assert abs((first_high + last_low) / 2 - edge_x_mm) < 0.1


@settings(max_examples=15, deadline=None)
@given(tilt_deg=st.floats(-35.0, 35.0), standoff_mm=st.floats(80.0, 120.0))
def test_uniform_profile_of_a_tilted_plane_lies_on_the_plane(tilt_deg: float, standoff_mm: float) -> None:
    optics = LaserOptics(noise_sigma_mm=0.0, outlier_probability=0.0)
    T = looking_down(standoff_mm)
    T[:3, :3] = T[:3, :3] @ Rotation.from_euler("y", tilt_deg, degrees=True).as_matrix()
    r = render_uniform(SceneRaycaster(plane_scene(0.0)), T[None], optics, np.random.default_rng(0))
    zx = expected_depth_on_floor(T, r.x_mm[0].astype(np.float64))
    in_range = (zx >= optics.z_min_mm + 0.5) & (zx <= optics.z_max_mm - 0.5)
    assert r.valid[0][in_range].all()
    np.testing.assert_allclose(r.z_mm[0][r.valid[0]], zx[r.valid[0]], atol=1e-3)


def test_grazing_incidence_gives_no_return() -> None:
    optics = LaserOptics(noise_sigma_mm=0.0, outlier_probability=0.0, max_incidence_deg=75.0)
    rc = SceneRaycaster(plane_scene(0.0, half_size_mm=5000.0))
    # Laser plane tipped 80 deg about the sensor x axis: every ray meets the floor >= 80 deg from its
    # normal, while the depth (20 mm / cos 80 = 115 mm) is inside the range.
    T = looking_down(20.0)
    T[:3, :3] = T[:3, :3] @ Rotation.from_euler("x", 80.0, degrees=True).as_matrix()
    assert not render_uniform(rc, T[None], optics, np.random.default_rng(0)).valid.any()
    assert not render_points(rc, T[None], optics, np.random.default_rng(0)).valid.any()
    T2 = looking_down(50.0)  # 60 deg: the light still comes back
    T2[:3, :3] = T2[:3, :3] @ Rotation.from_euler("x", 60.0, degrees=True).as_matrix()
    assert render_uniform(rc, T2[None], optics, np.random.default_rng(0)).valid.mean() > 0.99


def test_surface_beyond_the_depth_range_gives_no_return() -> None:
    rc = SceneRaycaster(plane_scene(0.0))
    optics = LaserOptics()
    for standoff in (50.0, 200.0):
        assert not render_uniform(
            rc, looking_down(standoff)[None], optics, np.random.default_rng(0)
        ).valid.any()


def test_outliers_are_sparse_and_inside_the_range() -> None:
    optics = LaserOptics(noise_sigma_mm=0.0, outlier_probability=0.01)
    Ts = np.repeat(looking_down(100.0)[None], 200, axis=0)
    r = render_uniform(SceneRaycaster(plane_scene(0.0)), Ts, optics, np.random.default_rng(1))
    off = np.abs(r.z_mm[r.valid] - 100.0) > 1e-3
    assert 0.005 < off.mean() < 0.015
    assert np.all((r.z_mm[r.valid] >= 70.0) & (r.z_mm[r.valid] <= 130.0))


def test_profiles_are_rendered_at_the_pose_at_mid_exposure() -> None:
    # Ramp z = 0.2 y, sensor moving along +y at 200 mm/s: each depth tells where the sensor was.
    ramp = Scene(
        np.array(
            [[-500.0, -500.0, -100.0], [500.0, -500.0, -100.0], [500.0, 500.0, 100.0], [-500.0, 500.0, 100.0]]
        ),
        np.array([[0, 1, 2], [0, 2, 3]]),
    )
    speed = 200.0
    t0 = {}

    def pose_at(t: np.ndarray) -> np.ndarray:
        t0.setdefault("t", float(t[0]))
        T = np.repeat(looking_down(100.0)[None], len(t), axis=0)
        T[:, 1, 3] = speed * (t - t0["t"])
        return T

    cfg = SimConfig(rate_hz=500.0, exposure_ns=1_500_000, noise_sigma_mm=0.0, outlier_probability=0.0, seed=7)

    async def scenario() -> None:
        sim = LaserSimulator(ramp, pose_at, config=cfg)
        ctl, dat = await sim.start()
        from drivers.laser.client import HD8Client

        client = HD8Client("127.0.0.1", ctl, dat)
        try:
            await client.connect()
            await client.start()
            b = ProfileBatch.concat(await collect(client, 50))
            y_seen = (100.0 - np.nanmean(b.z_mm, axis=1)) / 0.2
            y_true = speed * (sim.exposure_mid_true_s(b.frame_index) - t0["t"])
            np.testing.assert_allclose(y_seen, y_true, atol=0.01)
        finally:
            await client.close()
            await sim.stop()

    run(scenario())


def _curved_top(nx: int = 25, ny: int = 17) -> tuple[np.ndarray, np.ndarray]:
    xs, ys = np.linspace(-600, 600, nx), np.linspace(-400, 400, ny)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    Z = 500.0 + 2000.0 - np.sqrt(2000.0**2 - X**2)  # bent about y, 2 m radius, lowest in the middle
    v = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
    idx = np.arange(nx * ny).reshape(nx, ny)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return v, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def _edge_use_counts(t: np.ndarray) -> np.ndarray:
    e = np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1)
    return np.unique(e, axis=0, return_counts=True)[1]


def _signed_volume(s: Scene) -> float:
    v = s.vertices_mm[s.triangles]
    return float(np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0)


def test_plate_solid_is_closed_with_outward_normals_and_the_given_thickness() -> None:
    v, t = _curved_top()
    solid = plate_solid(v, t, thickness_mm=12.0)
    assert np.all(_edge_use_counts(solid.triangles) == 2)  # watertight
    area = 1200.0 * 800.0
    assert _signed_volume(solid) == pytest.approx(area * 12.0, rel=0.03)  # positive: normals point out
    rc = SceneRaycaster(solid)
    hits = rc.cast(
        np.array([[0.0, 0.0, 1000.0], [0.0, 0.0, 0.0]]), np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]])
    )
    np.testing.assert_allclose([1000.0 - hits.t_mm[0], hits.t_mm[1]], [500.0, 488.0], atol=0.05)


def test_plate_solid_accepts_a_top_wound_the_other_way() -> None:
    v, t = _curved_top()
    flipped = plate_solid(v, t[:, ::-1], thickness_mm=12.0)
    assert _signed_volume(flipped) == pytest.approx(_signed_volume(plate_solid(v, t, thickness_mm=12.0)))


def test_cell_scene_has_bed_and_supports_touching_the_plate_underside() -> None:
    v, t = _curved_top()
    scene = cell_scene(
        v, t, thickness_mm=12.0, bed_z_mm=300.0, supports_xy_mm=np.array([[0.0, 0.0], [400.0, 0.0]])
    )
    rc = SceneRaycaster(scene)
    down = np.array([0.0, 0.0, -1.0])
    # beside the plate the sensor sees the bed; on the plate, the plate top
    hits = rc.cast(np.array([[800.0, 0.0, 1500.0], [0.0, 0.0, 1500.0]]), np.tile(down, (2, 1)))
    np.testing.assert_allclose(1500.0 - hits.t_mm, [300.0, 500.0], atol=0.05)
    # a support fills the gap between bed and plate: a horizontal ray at mid height hits it
    side = rc.cast(np.array([[-300.0, 0.0, 400.0]]), np.array([[1.0, 0.0, 0.0]]))
    assert side.t_mm[0] == pytest.approx(300.0 - 40.0, abs=0.05)
    # the supports reach the underside: no gap between support top and plate bottom over the centre
    up = rc.cast(np.array([[0.0, 0.0, 301.0]]), np.array([[0.0, 0.0, 1.0]]))
    top_of_support = 301.0 + up.t_mm[0]
    assert top_of_support == pytest.approx(488.0, abs=0.5)


def test_box_scene_is_closed_and_outward() -> None:
    b = box_scene((0, 0, 0), (1, 2, 3))
    assert np.all(_edge_use_counts(b.triangles) == 2)
    assert _signed_volume(b) == pytest.approx(6.0)


def test_scene_rejects_bad_shapes() -> None:
    with pytest.raises(ValueError, match="vertices_mm"):
        Scene(np.zeros((3, 2)), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="index outside"):
        Scene(np.zeros((3, 3)), np.array([[0, 1, 3]]))
