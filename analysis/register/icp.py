"""Stage 2 of the registration: point-to-plane ICP (2.2.2) of the measured points against the design surface.

:func:`icp_point_to_plane` refines the coarse fit; the corners enter as weighted terms so that a
nearly flat plate cannot slide along itself.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from analysis.register.coarse import _check_corners
from analysis.register.height_field import HeightField
from analysis.register.transforms import (
    RegistrationError,
    _check_points,
    _check_transform,
    apply_transform,
    invert_transform,
    make_transform,
    rotation_from_vector,
)

# --------------------------------------------------------------------------------------------------
# 2. point-to-plane ICP (2.2.2)


@dataclass(frozen=True)
class IcpResult:
    """Point-to-plane ICP of measured points against the design surface.

    transform: (4, 4) design -> measured, mm.
    rms_mm: RMS point-to-plane distance over the inliers at the end.
    iterations: Gauss-Newton steps taken. converged: the last step was below the tolerance.
    inliers: points used in the last step (on the footprint, within the rejection distance).
    """

    transform: np.ndarray
    rms_mm: float
    iterations: int
    converged: bool
    inliers: int


def _corner_terms(
    T_inv: np.ndarray,
    corners: tuple[np.ndarray, np.ndarray] | None,
    c: np.ndarray,
    scale: float,
    weight: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Linearised in-plane corner residuals (boundary anchoring), rows already weighted.

    corners: (design (4, 3), matched measured (4, 3)) or None. The measured corners are taken into
    the design frame and compared with the design corners in x and y only: a surface fit cannot
    tell where on a nearly spherical plate it sits (sliding along the sphere costs almost nothing),
    the boundary can; the heights stay with the surface, which is measured far better than the
    corners. Returns ``(K (8, 6), e (8,))`` with the same parameter scaling as the surface rows,
    or empty arrays.
    """
    if corners is None or weight <= 0.0:
        return np.zeros((0, 6)), np.zeros(0)
    d, m = corners
    a = apply_transform(T_inv, m)
    e = (a - d)[:, :2]
    r = a - c
    K = np.zeros((4, 2, 6))
    # d/d(omega) of (p + omega x r) is -[r]x ; rows x and y of it
    K[:, 0, 1], K[:, 0, 2] = r[:, 2], -r[:, 1]
    K[:, 1, 0], K[:, 1, 2] = -r[:, 2], r[:, 0]
    K[:, :, :3] /= scale
    K[:, 0, 3] = 1.0
    K[:, 1, 4] = 1.0
    w = np.sqrt(weight)
    return w * K.reshape(8, 6), w * e.reshape(8)


def _matched_corners(
    design_corners_mm: np.ndarray | None, measured_corners_mm: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray] | None:
    if design_corners_mm is None or measured_corners_mm is None:
        return None
    return (
        _check_corners("design_corners_mm", design_corners_mm),
        _check_corners("measured_corners_mm", measured_corners_mm),
    )


def _subsample(points: np.ndarray, max_points: int | None, seed: int) -> np.ndarray:
    if max_points is None or len(points) <= max_points:
        return points
    idx = np.random.default_rng(seed).choice(len(points), size=max_points, replace=False)
    return points[idx]


def _surface_normals(slope: np.ndarray) -> np.ndarray:
    n = np.column_stack([-slope[:, 0], -slope[:, 1], np.ones(len(slope))])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


# The corners' weight against the surface's in the fine fits (see icp_point_to_plane): their share of
# the surface's weight when the surface's residual RMS equals the corners' accuracy, CORNER_SIGMA_MM
# (about what the boundary finder gives); the share follows the ratio of the two variances.
BOUNDARY_WEIGHT = 1e-1
CORNER_SIGMA_MM = 1.0


def icp_point_to_plane(
    surface: HeightField,
    measured_points_mm: np.ndarray,
    T_init: np.ndarray,
    *,
    max_iterations: int = 50,
    tolerance_mm: float = 1e-4,
    max_distance_mm: float = 50.0,
    min_distance_mm: float = 1.0,
    max_points: int | None = 200_000,
    seed: int = 0,
    design_corners_mm: np.ndarray | None = None,
    measured_corners_mm: np.ndarray | None = None,
    boundary_weight: float = BOUNDARY_WEIGHT,
) -> IcpResult:
    """Point-to-plane ICP, vectorised: correspondences by vertical projection onto the height field.

    surface: the design top surface (design frame). measured_points_mm: (n, 3) mm, measured frame.
    T_init: (4, 4) design -> measured start pose. Each step linearises the rotation about the
    centroid and solves the 6x6 normal equations of sum (n . (p - q))^2. Points off the footprint
    or farther than the rejection distance are dropped; the distance starts at ``max_distance_mm``
    and shrinks to 3 robust sigmas (never below ``min_distance_mm``), so forming errors stay in and
    stray points go. Stops when the step moves no point by more than ``tolerance_mm``.
    ``max_points`` subsamples the cloud (seeded) -- ICP does not need every point; the
    non-penetrating fit does.
    design_corners_mm, measured_corners_mm: optional matched (4, 3) corners (design frame /
    measured frame, same order) that anchor the plate in its own plane; their in-plane residuals
    enter with total weight ``boundary_weight * (rms / CORNER_SIGMA_MM)^2`` times the number of
    surface points, ``rms`` the surface residuals' RMS at that step. The weights follow
    the two terms' information: a surface the rigid design fits to its noise holds the in-plane pose
    itself (a curved plate, whose slopes see every in-plane motion), and noisy corners must not pull
    it away; a surface whose residuals are forming error the design cannot follow says little about
    the in-plane pose, above all on a nearly flat plate whose surface hardly sees the yaw, and the
    corners hold it. (With a constant share, 1e-2 let 1 mm corner noise move a curved plate by more
    than a millimetre, and 1e-5 let a nearly flat formed plate turn by a degree.) The RMS, not a
    robust scale: a local dent is forming error the in-plane pose must not follow either.
    """
    corners = _matched_corners(design_corners_mm, measured_corners_mm)
    P = _subsample(_check_points("measured_points_mm", measured_points_mm, 6), max_points, seed)
    T_inv = invert_transform(_check_transform("T_init", T_init))
    threshold = float(max_distance_mm)
    rms, inl, converged, iterations = float("nan"), 0, False, 0
    for it in range(1, max_iterations + 1):
        iterations = it
        p = apply_transform(T_inv, P)
        z, slope, valid = surface.evaluate(p[:, :2])
        n = _surface_normals(slope)
        r = (p[:, 2] - z) * n[:, 2]  # signed distance to the tangent plane at the vertical projection
        use = valid & (np.abs(r) < threshold)
        inl = int(use.sum())
        if inl < 6:
            raise RegistrationError(
                f"ICP: only {inl} measured points lie over the design within {threshold:.1f} mm; "
                "the cloud does not overlap the design"
            )
        pu, nu, ru = p[use], n[use], r[use]
        c = pu.mean(axis=0)
        scale = float(np.sqrt(((pu - c) ** 2).sum(axis=1).mean())) or 1.0
        J = np.hstack([np.cross(pu - c, nu) / scale, nu])
        rms = float(np.sqrt(np.mean(ru**2)))
        share = boundary_weight * (rms / CORNER_SIGMA_MM) ** 2
        K, e = _corner_terms(T_inv, corners, c, scale, share * inl / 8.0)
        H = J.T @ J + K.T @ K
        H[np.diag_indices(6)] += 1e-12 * np.trace(H)
        x = np.linalg.solve(H, -(J.T @ ru + K.T @ e))
        omega, t = x[:3] / scale, x[3:]
        R = rotation_from_vector(omega)
        T_inv = make_transform(R, c - R @ c + t) @ T_inv
        sigma = 1.4826 * float(np.median(np.abs(ru)))
        threshold = max(
            min(threshold, 3.0 * sigma + 3.0 * np.linalg.norm(x[:3]) + np.linalg.norm(t)), min_distance_mm
        )
        step_mm = float(np.linalg.norm(x[:3]) + np.linalg.norm(t))
        if step_mm < tolerance_mm:
            converged = True
            break
    return IcpResult(invert_transform(T_inv), rms, iterations, converged, inl)
