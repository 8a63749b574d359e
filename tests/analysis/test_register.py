"""Registration: coarse fit from corners, point-to-plane ICP, the exact non-penetrating fit.

The surfaces are analytic (z = x^2 / 2Rx + y^2 / 2Ry, plus an asymmetric cubic where the 180 degree
ambiguity must be resolvable), triangulated on a grid, so every expected answer is known.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st
from scipy.optimize import minimize

from analysis.design.plates import (
    default_forming_error,
    design_corners,
    design_mesh,
    formed_corners,
    formed_height_mm,
    plate_spec,
)
from analysis.register.coarse import coarse_register
from analysis.register.fit import register
from analysis.register.height_field import HeightField, height_field_from_mesh
from analysis.register.icp import icp_point_to_plane
from analysis.register.onesided import _solve_onesided_qp, deflection_gaps, grid_average, nonpenetrating_fit
from analysis.register.transforms import (
    RegistrationError,
    apply_transform,
    kabsch,
    make_transform,
    pose_error,
    rotation_from_vector,
)
from tests.support.surfaces import L_MM, W_MM, corners, grid_mesh, lopsided, sail


def scan(
    f, n: int, T: np.ndarray, noise_mm: float = 0.0, seed: int = 0, margin_mm: float = 5.0
) -> np.ndarray:
    """Points of z = f(x, y) (design frame), placed by T, with vertical noise."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(
        [-L_MM / 2 + margin_mm, -W_MM / 2 + margin_mm], [L_MM / 2 - margin_mm, W_MM / 2 - margin_mm], (n, 2)
    )
    P = np.column_stack([xy, f(xy[:, 0], xy[:, 1]) + rng.normal(0.0, noise_mm, n)])
    return apply_transform(T, P)


def placement(
    yaw_deg: float, tilt_deg: tuple[float, float] = (1.0, -0.5), t=(2500.0, 400.0, 650.0)
) -> np.ndarray:
    R = rotation_from_vector(np.radians([tilt_deg[0], tilt_deg[1], 0.0])) @ rotation_from_vector(
        np.radians([0.0, 0.0, yaw_deg])
    )
    return make_transform(R, np.asarray(t))


@pytest.fixture(scope="module")
def lopsided_field() -> HeightField:
    return height_field_from_mesh(grid_mesh(lopsided), step_mm=2.0)


def test_height_field_reproduces_the_mesh_surface_between_nodes():
    hf = height_field_from_mesh(grid_mesh(sail, step_mm=5.0), step_mm=1.0)
    rng = np.random.default_rng(3)
    xy = rng.uniform([-590, -390], [590, 390], (2000, 2))
    z, slope, valid = hf.evaluate(xy)
    assert valid.all()
    # a linear 5 mm facet on curvatures 1/3000 and 1/2000 deviates by at most 5^2 / 8 * (1/3000 + 1/2000)
    assert np.abs(z - sail(xy[:, 0], xy[:, 1])).max() < 2.7e-3
    assert np.abs(slope[:, 0] - xy[:, 0] / 3000.0).max() < 5e-3
    assert not hf.evaluate(np.array([[700.0, 0.0]]))[2][0]


def test_kabsch_recovers_a_rigid_motion_exactly():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(8, 3)) * 300
    T = placement(137.0)
    assert np.allclose(kabsch(src, apply_transform(T, src)), T, atol=1e-9)


@pytest.mark.parametrize("shift", [0, 1, 2, 3])
def test_register_resolves_corner_order_and_recovers_pose(lopsided_field, shift):
    T_true = placement(35.0 + 90.0 * shift)
    P = scan(lopsided, 30_000, T_true, noise_mm=0.02, seed=shift)
    Cd = corners(lopsided)
    rng = np.random.default_rng(10 + shift)
    # the boundary finder reports corners to about a millimetre, in an unknown cyclic order
    Cm = np.roll(apply_transform(T_true, Cd), shift, axis=0) + rng.normal(0.0, 1.0, (4, 3))
    res = register(lopsided_field, P, Cd, Cm, icp_points=30_000)
    disp_mm, angle_deg = pose_error(res.transform, T_true, Cd)
    assert res.coarse.shift == shift
    assert res.coarse.corner_rms_mm < 5.0
    assert disp_mm < 1.0 and angle_deg < 0.1
    assert res.nonpenetrating.penetrating_after == 0
    assert res.icp.rms_mm < 0.03


def test_coarse_fit_of_exact_corners_is_exact():
    Cd = corners(sail)
    T_true = placement(-70.0)
    res = coarse_register(Cd, apply_transform(T_true, Cd))
    disp_mm, angle_deg = pose_error(res.transform, T_true, Cd)
    assert disp_mm < 1e-6 and angle_deg < 1e-6
    assert res.corner_rms_mm < 1e-6


def test_icp_converges_to_the_true_pose_from_a_coarse_error(lopsided_field):
    T_true = placement(10.0)
    P = scan(lopsided, 20_000, T_true)
    T0 = make_transform(rotation_from_vector(np.radians([0.3, -0.2, 0.4])), [3.0, -2.0, 1.5]) @ T_true
    Cd = corners(lopsided)
    res = icp_point_to_plane(
        lopsided_field, P, T0, design_corners_mm=Cd, measured_corners_mm=apply_transform(T_true, Cd)
    )
    disp_mm, angle_deg = pose_error(res.transform, T_true, Cd)
    assert res.converged
    assert disp_mm < 0.05 and angle_deg < 0.005
    assert res.rms_mm < 0.01


def test_nonpenetrating_fit_of_rigidly_moved_design_touches_without_gap(lopsided_field):
    T_true = placement(200.0)
    P = scan(lopsided, 20_000, T_true)
    T0 = make_transform(np.eye(3), [0.0, 0.0, -0.5]) @ T_true  # design sunk 0.5 mm into the plate
    res = nonpenetrating_fit(lopsided_field, P, T0)
    assert res.penetrating_before == len(P)
    assert res.penetrating_after == 0
    assert res.min_gap_mm >= 0.0
    # what is left is the design mesh's chordal error: 10 mm facets on a convex plate lie above the
    # surface by at most 10^2 / 8 * (1/3000 + 1/2000) = 0.0104 mm
    assert res.rms_mm < 0.0105


@settings(
    max_examples=6,
    deadline=None,
    phases=[Phase.explicit, Phase.reuse, Phase.generate],  # shrinking a 1 s example takes minutes
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(
    yaw=st.floats(0.0, 360.0),
    dent_mm=st.floats(0.5, 6.0),
    noise_mm=st.floats(0.0, 0.1),
    seed=st.integers(0, 1000),
)
def test_nonpenetrating_fit_leaves_zero_penetrating_points(lopsided_field, yaw, dent_mm, noise_mm, seed):
    rng = np.random.default_rng(seed)
    cx, cy = rng.uniform(-400, 400), rng.uniform(-250, 250)

    def formed(x, y):
        return lopsided(x, y) - dent_mm * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * 70.0**2))

    T_true = placement(yaw)
    P = scan(formed, 8_000, T_true, noise_mm=noise_mm, seed=seed)
    icp = icp_point_to_plane(lopsided_field, P, T_true)
    res = nonpenetrating_fit(lopsided_field, P, icp.transform)
    gaps, _, _, valid = deflection_gaps(lopsided_field, P, res.transform)
    near = valid & (np.abs(gaps) < 25.0)
    assert res.penetrating_after == 0
    assert (gaps[near] >= 0.0).all()
    assert 0.9 * len(P) < res.points <= near.sum()


def test_nonpenetrating_fit_reaches_the_constrained_optimum_of_slsqp(lopsided_field):
    """Same problem, the paper's way (Euler angles, SLSQP, one constraint per point): ours is no worse."""
    T_true = placement(20.0)

    def formed(x, y):
        return lopsided(x, y) - 3.0 * np.exp(-((x - 150) ** 2 + (y + 80) ** 2) / (2 * 90.0**2))

    P = scan(formed, 158, T_true, noise_mm=0.05, seed=4)
    T0 = icp_point_to_plane(lopsided_field, P, T_true, max_points=None).transform
    ours = nonpenetrating_fit(lopsided_field, P, T0)
    c = P.mean(axis=0)

    def pose(x):
        R = rotation_from_vector(x[:3])  # rotation vector about the centroid
        return make_transform(R, c - R @ c + x[3:]) @ T0

    def gaps(x):
        return deflection_gaps(lopsided_field, P, pose(x))[0]

    base = minimize(
        lambda x: float((gaps(x) ** 2).sum()),
        np.zeros(6),
        method="SLSQP",
        constraints=[{"type": "ineq", "fun": gaps}],
        options={"maxiter": 300, "ftol": 1e-12},
    )
    base_obj = float((gaps(base.x) ** 2).sum())
    assert ours.penetrating_after == 0
    assert ours.objective_mm2 <= base_obj * (1 + 1e-3) + 1e-6


def test_active_set_qp_meets_the_kkt_conditions():
    rng = np.random.default_rng(7)
    A = rng.normal(size=(5000, 6))
    s = rng.normal(0.5, 1.0, 5000)
    lift = np.linalg.lstsq(A, np.ones(len(A)), rcond=None)[0]
    A = A - np.outer(A @ lift - 1.0, lift) / (lift @ lift)  # make `lift` raise every row by exactly 1
    x, _, active = _solve_onesided_qp(A, s, lift, 0.0)
    r = s + A @ x
    assert r.min() >= -1e-9
    # stationarity: the objective gradient is a non-negative combination of active constraint normals
    grad = 2 * A.T @ r
    act = np.flatnonzero(np.abs(r) < 1e-8)
    lam = np.linalg.lstsq(A[act].T, grad, rcond=None)[0]
    assert np.allclose(A[act].T @ lam, grad, atol=1e-6 * np.abs(grad).max())
    assert (lam >= -1e-8 * np.abs(lam).max()).all()
    assert active == len(act)


def test_register_rejects_a_cloud_that_is_not_over_the_design(lopsided_field):
    P = scan(lopsided, 2000, placement(0.0, t=(2500.0, 400.0, 650.0)))
    far = P + np.array([5000.0, 0.0, 0.0])
    with pytest.raises(RegistrationError, match=r"does not overlap the design"):
        icp_point_to_plane(lopsided_field, far, placement(0.0))


def test_bad_shapes_name_the_offending_argument(lopsided_field):
    with pytest.raises(RegistrationError, match="measured_points_mm"):
        nonpenetrating_fit(lopsided_field, np.zeros((10, 2)), np.eye(4))
    with pytest.raises(RegistrationError, match="measured_corners_mm"):
        coarse_register(corners(sail), np.zeros((3, 3)))
    with pytest.raises(RegistrationError, match="T_init"):
        icp_point_to_plane(lopsided_field, np.zeros((10, 3)), np.eye(3))


def test_grid_average_keeps_the_surface_and_cuts_the_noise():
    rng = np.random.default_rng(5)
    xy = rng.uniform(-100, 100, (200_000, 2))
    P = np.column_stack([xy, sail(xy[:, 0], xy[:, 1]) + rng.normal(0.0, 0.02, len(xy))])
    A = grid_average(P, cell_mm=2.0)
    assert 9_000 < len(A) <= 10_201
    resid = A[:, 2] - sail(A[:, 0], A[:, 1])
    # about 20 points per cell: noise / sqrt(20), plus the curvature over a 2 mm cell
    assert np.std(resid) < 0.02 / np.sqrt(20) * 1.5
    with pytest.raises(RegistrationError, match="cell_mm"):
        grid_average(P, cell_mm=0.0)


def test_register_on_cell_means_rests_the_design_without_the_noise_lift(lopsided_field):
    T_true = placement(75.0)
    rng = np.random.default_rng(8)
    xy = rng.uniform([-590, -390], [590, 390], (150_000, 2))
    true = np.column_stack([xy, lopsided(xy[:, 0], xy[:, 1])])
    P = apply_transform(T_true, true + np.outer(rng.normal(0, 0.05, len(xy)), [0.0, 0.0, 1.0]))
    Cd = corners(lopsided)
    Cm = apply_transform(T_true, Cd)
    raw = register(lopsided_field, P, Cd, Cm, icp_points=30_000)
    avg = register(lopsided_field, P, Cd, Cm, icp_points=30_000, nonpen_cell_mm=10.0)
    assert raw.penetration_points == 0 and avg.penetration_points == 0
    assert avg.nonpenetrating.points < len(P) / 10

    def lift(res):  # how far the rested design stands above the noise-free plate
        return float(
            np.median(deflection_gaps(lopsided_field, apply_transform(T_true, true), res.transform)[0])
        )

    # the raw fit stands on the highest noise spikes (about 4 sigma); means of ~16 points on a quarter
    assert 0.1 < lift(raw) < 0.3
    assert lift(avg) < 0.5 * lift(raw)


def test_the_corners_hold_a_nearly_flat_plate_in_its_plane_whatever_points_it_rests_on():
    """The e2e cell's case: a small, nearly flat plate with a dent, a bump and spring-back, rested on
    a thousand patch estimates (as analysis.register.rest_surface gives) rather than the 20,000 cell means
    ICP used. The surface hardly sees the yaw; the corners hold it, and their hold must not fall
    with the number of points the design rests on (it did: the design turned 1.7 degrees)."""
    spec = plate_spec("sail", length_mm=300.0, width_mm=200.0)
    error = default_forming_error(spec)
    field = height_field_from_mesh(design_mesh(spec, pitch_mm=5.0))
    T_true = placement(3.0, tilt_deg=(0.3, -0.2))
    rng = np.random.default_rng(2)
    xy = rng.uniform([-148.0, -98.0], [148.0, 98.0], (20_000, 2))
    P = apply_transform(T_true, np.column_stack([xy, formed_height_mm(spec, error, xy[:, 0], xy[:, 1])]))
    Cd = design_corners(spec)
    Cm = apply_transform(T_true, formed_corners(spec, error)) + rng.normal(0.0, 0.3, (4, 3))
    patches = P[rng.choice(len(P), 1_000, replace=False)]
    dense = register(field, P, Cd, Cm)
    sparse = register(field, P, Cd, Cm, rest_points=lambda T: patches)
    for res in (dense, sparse):
        moved = apply_transform(res.transform, Cd) - apply_transform(T_true, Cd)
        assert np.hypot(moved[:, 0], moved[:, 1]).max() < 1.0, moved
        assert res.nonpenetrating.penetrating_after == 0
