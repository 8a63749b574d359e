"""Registration of the design surface to a measured plate: section 2.2 of the paper.

Three stages, each a pure function returning a small result object:

1. :func:`coarse_register` -- the paper's boundary fit (2.2.1): corner centroids, the diagonal
   normals, the edge midpoints snapped to the data, Kabsch/SVD. The order of the measured corners
   relative to the design's is only known up to a cyclic shift, so :func:`register` tries every
   shift and keeps the one whose ICP fit is best (this resolves the 180 degree turn of a nearly
   symmetric plate).
2. :func:`icp_point_to_plane` -- point-to-plane ICP (2.2.2) of the measured points against the
   design surface.
3. :func:`nonpenetrating_fit` -- the one-sided fit (2.2.3): the design rests on the measured plate
   like a worker's template, on or above every measured point in the deflection direction, as
   close as possible in the least-squares sense. Solved on every surface point: linearised
   rotation, six unknowns, one linear constraint per point with its exact Jacobian, an exact
   active-set solution of that small quadratic programme, correspondences renewed in an outer loop.

The design surface is used through a :class:`HeightField`: the design mesh (top surface, design
plate frame, z up -- the convention of ``analysis.plates``) rasterised once onto a regular grid,
so that a correspondence for a million points is a bilinear lookup (O(n) numpy, no k-d tree).

Frames: every transform is a 4x4 homogeneous matrix in millimetres, ``T_meas_design`` maps design
coordinates into the measurement (robot base) frame. The deflection direction is +z of the
measurement frame.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import cached_property
from itertools import pairwise

import numpy as np
import structlog

from analysis.mesh import TriMesh

log = structlog.get_logger(__name__)


TIE_RELATIVE = 0.01  # candidate ICP fits within 1 % (plus TIE_ABSOLUTE_MM) of the best are a tie
TIE_ABSOLUTE_MM = 0.002


class RegistrationError(ValueError):
    """Inputs that cannot be registered: wrong shapes, no overlap with the design, degenerate corners."""


# --------------------------------------------------------------------------------------------------
# small rigid-body helpers


def _check_points(name: str, points: np.ndarray, min_count: int = 1) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise RegistrationError(f"{name} must be (n, 3) mm, got shape {p.shape}")
    if len(p) < min_count:
        raise RegistrationError(f"{name} needs at least {min_count} points, got {len(p)}")
    if not np.isfinite(p).all():
        raise RegistrationError(f"{name} contains non-finite coordinates")
    return p


def _check_transform(name: str, T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise RegistrationError(f"{name} must be a finite 4x4 transform, got shape {T.shape}")
    return T


def make_transform(R: np.ndarray, t_mm: np.ndarray) -> np.ndarray:
    """The 4x4 homogeneous transform ``x -> R x + t_mm`` (R (3, 3), t_mm (3,) mm)."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t_mm
    return T


def invert_transform(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform (uses R^T, no general matrix inverse)."""
    R = T[:3, :3]
    return make_transform(R.T, -R.T @ T[:3, 3])


def apply_transform(T: np.ndarray, points_mm: np.ndarray) -> np.ndarray:
    """Points (n, 3) mm moved by the 4x4 transform ``T``."""
    # (3, 3) @ (3, n) is one BLAS call; (n, 3) @ (3, 3) takes a slow small-matrix path (10x here).
    # The result is the Fortran-ordered transpose: each coordinate column is contiguous.
    out = T[:3, :3] @ points_mm.T
    out += T[:3, 3:4]
    return out.T


def rotation_from_vector(omega_rad: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector ``omega_rad`` (3,) (exponential map, Rodrigues)."""
    theta = float(np.linalg.norm(omega_rad))
    if theta < 1e-15:
        return np.eye(3)
    k = omega_rad / theta
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(theta) * K + (1.0 - np.cos(theta)) * (K @ K)


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking direction ``a`` (3,) onto direction ``b`` (3,)."""
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    v = np.cross(a, b)
    s = float(np.linalg.norm(v))
    c = float(a @ b)
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        # antiparallel: half turn about any axis perpendicular to a
        perp = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        return rotation_from_vector(np.pi * perp / np.linalg.norm(perp))
    return rotation_from_vector(v / s * np.arctan2(s, c))


def kabsch(source_mm: np.ndarray, target_mm: np.ndarray) -> np.ndarray:
    """Least-squares rigid transform (4x4) taking ``source_mm`` (n, 3) onto ``target_mm`` (n, 3).

    SVD of the cross-covariance of the centred point sets, with the reflection guard.
    """
    cs = source_mm.mean(axis=0)
    ct = target_mm.mean(axis=0)
    H = (source_mm - cs).T @ (target_mm - ct)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    R = Vt.T @ np.diag([1.0, 1.0, d if d != 0 else 1.0]) @ U.T
    return make_transform(R, ct - R @ cs)


def pose_error(T_a: np.ndarray, T_b: np.ndarray, points_mm: np.ndarray) -> tuple[float, float]:
    """(max displacement in mm over ``points_mm``, rotation angle in degrees) between two poses."""
    d = apply_transform(T_a, points_mm) - apply_transform(T_b, points_mm)
    R = T_a[:3, :3].T @ T_b[:3, :3]
    angle = np.degrees(np.arccos(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)))
    return float(np.linalg.norm(d, axis=1).max()), float(angle)


# --------------------------------------------------------------------------------------------------
# the design surface as a height field


@dataclass(frozen=True)
class HeightField:
    """The design's top surface z = f(x, y) on a regular grid, design plate frame, mm.

    ``z_mm`` is (ny, nx): the height at node (j, i), which lies at
    ``(x0_mm + i * step_mm, y0_mm + j * step_mm)``; NaN outside the design's footprint. Between
    nodes the surface is the bilinear interpolant, and its slopes are that interpolant's exact
    derivatives (so Newton steps and Jacobians agree with the surface the gaps are measured to).
    """

    x0_mm: float
    y0_mm: float
    step_mm: float
    z_mm: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        return self.z_mm.shape[0], self.z_mm.shape[1]

    def points_mm(self, stride: int = 1) -> np.ndarray:
        """(n, 3) the grid nodes on the surface (every ``stride``-th node per axis), mm."""
        ny, nx = self.shape
        j, i = np.mgrid[0:ny:stride, 0:nx:stride]
        z = self.z_mm[j, i]
        ok = np.isfinite(z)
        return np.column_stack([self.x0_mm + i[ok] * self.step_mm, self.y0_mm + j[ok] * self.step_mm, z[ok]])

    @cached_property
    def cells(self) -> np.ndarray:
        """(ny - 1) * nx rows of bilinear coefficients ``(a, b, c, d)``, one row per grid cell, mm.

        Row ``j * nx + i`` describes the cell whose lower-left node is (j, i): the height at the cell
        coordinates (ax, ay) in [0, 1)^2 is ``a + b ax + c ay + d ax ay``. The last column's rows are
        NaN (no cell to their right). One gather of a 32-byte row per point replaces four scattered
        node reads -- the lookup of a million points is memory-bound.
        """
        z = self.z_mm
        ny, nx = self.shape
        tab = np.full((ny - 1, nx, 4), np.nan)
        tab[:, :-1, 0] = z[:-1, :-1]
        tab[:, :-1, 1] = z[:-1, 1:] - z[:-1, :-1]
        tab[:, :-1, 2] = z[1:, :-1] - z[:-1, :-1]
        tab[:, :-1, 3] = (z[1:, 1:] - z[1:, :-1]) - tab[:, :-1, 1]
        return tab.reshape(-1, 4)

    def evaluate(self, xy_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Bilinear lookup at (n, 2) positions, mm.

        Returns ``(z_mm (n,), slope (n, 2) dz/dx and dz/dy, valid (n,) bool)``; invalid points (off
        the footprint) have z = slope = 0.
        """
        xy_mm = np.asarray(xy_mm, dtype=np.float64)
        z, sx, sy, valid = self.lookup(xy_mm[:, 0], xy_mm[:, 1])
        return z, np.column_stack([sx, sy]), valid

    def lookup(
        self, x_mm: np.ndarray, y_mm: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Bilinear lookup at positions given as two (n,) coordinate arrays, mm.

        Returns ``(z_mm, dz/dx, dz/dy, valid)``, each (n,); invalid points (off the footprint) have
        z = slope = 0. The column form of :meth:`evaluate`, without (n, 2) temporaries.
        """
        ny, nx = self.shape
        inv_h = 1.0 / self.step_mm
        fx = x_mm - self.x0_mm
        fx *= inv_h
        fy = y_mm - self.y0_mm
        fy *= inv_h
        valid = (fx >= 0) & (fx < nx - 1) & (fy >= 0) & (fy < ny - 1)
        # truncate, then clip: invalid points read a harmless cell and are zeroed below
        ix = fx.astype(np.intp)
        np.clip(ix, 0, nx - 2, out=ix)
        iy = fy.astype(np.intp)
        np.clip(iy, 0, ny - 2, out=iy)
        fx -= ix  # now the cell coordinates ax, ay
        fy -= iy
        iy *= nx
        iy += ix
        coef = np.take(self.cells, iy, axis=0)
        a, b, c, d = coef.T
        sx = d * fy
        sx += b
        sy = d * fx
        sy += c
        z = sx * fx
        z += a
        z += c * fy
        sx *= inv_h
        sy *= inv_h
        valid &= np.isfinite(z)
        bad = ~valid
        if bad.any():
            z[bad] = 0.0
            sx[bad] = 0.0
            sy[bad] = 0.0
        return z, sx, sy, valid


def height_field_from_mesh(mesh: TriMesh, step_mm: float = 1.0, pad_mm: float = 20.0) -> HeightField:
    """Rasterise a design mesh (top surface, z up, design plate frame) onto a grid of ``step_mm``.

    Every grid node inside a triangle's XY projection gets the triangle's linear interpolant, so the
    field reproduces the mesh exactly at the nodes (and within kappa * step^2 / 8 between them).
    The field is extended by ``pad_mm`` beyond the footprint's bounding box by linear extrapolation:
    a fit that slides a measured edge point just off the design would otherwise drop that point's
    cost -- a discontinuity an iterative fit happily exploits by drifting.
    Vectorised over (triangle, node) pairs. Raises :class:`RegistrationError` when the mesh is not a
    height field over its footprint (no triangle faces up).
    """
    if step_mm <= 0:
        raise RegistrationError(f"step_mm must be positive, got {step_mm}")
    tv = mesh.triangle_vertices_mm
    if len(tv) == 0:
        raise RegistrationError("design mesh has no triangles")
    lo = mesh.vertices_mm[:, :2].min(axis=0)
    hi = mesh.vertices_mm[:, :2].max(axis=0)
    nx = int(np.floor((hi[0] - lo[0]) / step_mm)) + 1
    ny = int(np.floor((hi[1] - lo[1]) / step_mm)) + 1
    if nx < 2 or ny < 2:
        raise RegistrationError(f"design footprint {hi - lo} mm is smaller than two grid steps")
    # barycentric set-up per triangle in XY
    a, b, c = tv[:, 0], tv[:, 1], tv[:, 2]
    det = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    keep = np.abs(det) > 1e-12  # vertical triangles (thickness faces) have no height
    if not keep.any():
        raise RegistrationError("design mesh has no triangle with an XY footprint (not a height field)")
    a, b, c, det = a[keep], b[keep], c[keep], det[keep]
    txy = np.stack([a[:, :2], b[:, :2], c[:, :2]], axis=1)
    i0 = np.ceil((txy[:, :, 0].min(axis=1) - lo[0]) / step_mm - 1e-9).astype(np.int64)
    i1 = np.floor((txy[:, :, 0].max(axis=1) - lo[0]) / step_mm + 1e-9).astype(np.int64)
    j0 = np.ceil((txy[:, :, 1].min(axis=1) - lo[1]) / step_mm - 1e-9).astype(np.int64)
    j1 = np.floor((txy[:, :, 1].max(axis=1) - lo[1]) / step_mm + 1e-9).astype(np.int64)
    wi = np.maximum(i1 - i0 + 1, 0)
    wj = np.maximum(j1 - j0 + 1, 0)
    count = wi * wj
    tri = np.repeat(np.arange(len(a)), count)
    start = np.cumsum(count) - count
    local = np.arange(count.sum()) - np.repeat(start, count)
    gi = i0[tri] + local % wi[tri]
    gj = j0[tri] + local // wi[tri]
    px = lo[0] + gi * step_mm
    py = lo[1] + gj * step_mm
    at, bt, ct, dt = a[tri], b[tri], c[tri], det[tri]
    w1 = ((px - at[:, 0]) * (ct[:, 1] - at[:, 1]) - (ct[:, 0] - at[:, 0]) * (py - at[:, 1])) / dt
    w2 = ((bt[:, 0] - at[:, 0]) * (py - at[:, 1]) - (px - at[:, 0]) * (bt[:, 1] - at[:, 1])) / dt
    w0 = 1.0 - w1 - w2
    eps = 1e-9
    inside = (w0 >= -eps) & (w1 >= -eps) & (w2 >= -eps)
    z = w0 * at[:, 2] + w1 * bt[:, 2] + w2 * ct[:, 2]
    height = np.full((ny, nx), np.nan)
    # on shared edges both triangles give the same value; which one wins does not matter
    height[gj[inside], gi[inside]] = z[inside]
    if not np.isfinite(height).any():
        raise RegistrationError("design mesh rasterised to an empty height field")
    pad = max(int(np.ceil(pad_mm / step_mm)), 0)
    if pad:
        height = _pad_linear(height, pad)
    return HeightField(float(lo[0] - pad * step_mm), float(lo[1] - pad * step_mm), float(step_mm), height)


def _pad_linear(z: np.ndarray, pad: int) -> np.ndarray:
    """``z`` (ny, nx) grown by ``pad`` cells on every side, extrapolating each border row/column linearly."""
    k = np.arange(1, pad + 1, dtype=np.float64)
    left = z[:, :1] + (z[:, :1] - z[:, 1:2]) * k[::-1]
    right = z[:, -1:] + (z[:, -1:] - z[:, -2:-1]) * k
    z = np.hstack([left, z, right])
    low = z[:1, :] + (z[:1, :] - z[1:2, :]) * k[::-1, None]
    high = z[-1:, :] + (z[-1:, :] - z[-2:-1, :]) * k[:, None]
    return np.vstack([low, z, high])


# --------------------------------------------------------------------------------------------------
# 1. coarse fit from the corners (2.2.1)


@dataclass(frozen=True)
class CoarseResult:
    """The paper's boundary-based coarse fit for one corner correspondence.

    transform: (4, 4) design -> measured, mm.
    shift: measured corner ``(k + shift) % 4`` was matched with design corner ``k``.
    corner_rms_mm: RMS distance of the moved design corners to the measured corners.
    midpoint_rms_mm: RMS distance of the moved design edge midpoints to the measured ones.
    """

    transform: np.ndarray
    shift: int
    corner_rms_mm: float
    midpoint_rms_mm: float


def _check_corners(name: str, corners: np.ndarray) -> np.ndarray:
    c = np.asarray(corners, dtype=np.float64)
    if c.shape != (4, 3) or not np.isfinite(c).all():
        raise RegistrationError(f"{name} must be a finite (4, 3) array of corners in mm, got shape {c.shape}")
    n = np.cross(c[2] - c[0], c[3] - c[1])
    if np.linalg.norm(n) < 1e-6 * max(1.0, float(np.ptp(c, axis=0).max()) ** 2):
        raise RegistrationError(f"{name}: degenerate corners (diagonals are parallel)")
    return c


def _snap_to_cloud(query_mm: np.ndarray, cloud_mm: np.ndarray | None, normal: np.ndarray) -> np.ndarray:
    """The cloud point under each of a few query points, seen along the plate normal.

    The chord midpoint of a curved edge lies tens of millimetres off the surface, where the
    nearest point in 3-D slides along a flat-bottomed edge; seen along the normal of the diagonal
    plane the edge's midpoint is sharply defined. Brute force: a k-d tree for 4 points costs more.
    """
    if cloud_mm is None or len(cloud_mm) == 0:
        return query_mm
    n = normal / np.linalg.norm(normal)
    out = np.empty_like(query_mm)
    for k, q in enumerate(query_mm):  # 4 queries, each vectorised over the cloud
        d = cloud_mm - q
        d2 = (d**2).sum(axis=1) - (d @ n) ** 2
        out[k] = cloud_mm[int(np.argmin(d2))]
    return out


def coarse_register(
    design_corners_mm: np.ndarray,
    measured_corners_mm: np.ndarray,
    *,
    design_points_mm: np.ndarray | None = None,
    measured_points_mm: np.ndarray | None = None,
    shift: int = 0,
    design_midpoints_mm: np.ndarray | None = None,
    measured_midpoints_mm: np.ndarray | None = None,
) -> CoarseResult:
    """The paper's three-step coarse registration for one corner correspondence.

    design_corners_mm, measured_corners_mm: (4, 3) mm, counter-clockwise seen from +z.
    design_points_mm, measured_points_mm: optional (n, 3) clouds; the edge midpoints are snapped to
    the cloud as the paper does (the chord midpoint of a curved edge is off the surface), nearest
    as seen along the diagonal normal.
    shift: measured corner ``(k + shift) % 4`` corresponds to design corner ``k``.
    design_midpoints_mm, measured_midpoints_mm: optional (4, 3) edge midpoints already snapped
    (edge k from corner k to k + 1, in the corners' own order), to snap once for all shifts.

    Steps: (1) corner centroid onto corner centroid (corners rather than the cloud centroid, which
    moves with uneven sampling and missing returns); (2) rotate the design's diagonal normal
    (cross product of the diagonals) onto the measured one; (3) Kabsch/SVD on the edge midpoints and
    corners for the remaining in-plane rotation, translation from the centroid difference.
    """
    D = _check_corners("design_corners_mm", design_corners_mm)
    M = np.roll(_check_corners("measured_corners_mm", measured_corners_mm), -int(shift), axis=0)
    # (1) centroids
    cD, cM = D.mean(axis=0), M.mean(axis=0)
    # (2) diagonal normals
    nD = np.cross(D[2] - D[0], D[3] - D[1])
    nM = np.cross(M[2] - M[0], M[3] - M[1])
    R1 = rotation_between(nD, nM)
    T1 = make_transform(R1, cM - R1 @ cD)
    # (3) edge midpoints snapped to the data, then SVD
    if design_midpoints_mm is not None:
        mid_D = np.asarray(design_midpoints_mm, dtype=np.float64)
    else:
        mid_D = _snap_to_cloud(0.5 * (D + np.roll(D, -1, axis=0)), design_points_mm, nD)
    if measured_midpoints_mm is not None:
        mid_M = np.roll(np.asarray(measured_midpoints_mm, dtype=np.float64), -int(shift), axis=0)
    else:
        mid_M = _snap_to_cloud(0.5 * (M + np.roll(M, -1, axis=0)), measured_points_mm, nM)
    src = apply_transform(T1, np.vstack([mid_D, D]))
    dst = np.vstack([mid_M, M])
    T2 = kabsch(src, dst)
    T = T2 @ T1
    corner_rms = float(np.sqrt(((apply_transform(T, D) - M) ** 2).sum(axis=1).mean()))
    mid_rms = float(np.sqrt(((apply_transform(T, mid_D) - mid_M) ** 2).sum(axis=1).mean()))
    return CoarseResult(T, int(shift) % 4, corner_rms, mid_rms)


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


# --------------------------------------------------------------------------------------------------
# 3. non-penetrating fit (2.2.3)


@dataclass(frozen=True)
class NonPenetratingResult:
    """One-sided (template-resting) fit of the design onto the measured surface.

    transform: (4, 4) design -> measured, mm.
    objective_mm2: sum of squared gaps (design minus measured, along +z of the measured frame).
    rms_mm: sqrt(objective / points). min_gap_mm: smallest gap (>= 0 after the fit).
    iterations: outer (correspondence) iterations. qp_iterations: active-set steps, all together.
    points: measured points constrained (on the design's footprint, within the rejection distance).
    penetrating_before / penetrating_after: points with a negative gap at the start / the end.
    active_points: constraints active (gap 0) at the solution.
    """

    transform: np.ndarray
    objective_mm2: float
    rms_mm: float
    min_gap_mm: float
    iterations: int
    qp_iterations: int
    points: int
    penetrating_before: int
    penetrating_after: int
    active_points: int
    converged: bool


def deflection_gaps(
    surface: HeightField,
    measured_points_mm: np.ndarray,
    T_meas_design: np.ndarray,
    up: np.ndarray = np.array([0.0, 0.0, 1.0]),
    newton_steps: int = 2,
    geometry: bool = True,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None, np.ndarray]:
    """Gap from each measured point to the moved design surface along the deflection direction.

    measured_points_mm: (n, 3) mm, measured frame; up: (3,) deflection direction, measured frame.
    Returns ``(gap_mm (n,), surface_point_mm (n, 3) design frame, normal (n, 3) design frame,
    valid (n,) bool)``. The gap is positive when the design lies above the point (no penetration).
    The intersection of the ray ``p + s * up`` with z = f(x, y) is found by Newton's method.
    ``geometry=False`` skips the surface points and normals (returned as None) when only the gaps
    are wanted. Large clouds are split over a small thread pool: numpy releases the GIL on whole
    arrays, so both cores work, and the answer is the same.
    """
    g = _ray_gaps(surface, measured_points_mm, T_meas_design, up, newton_steps, geometry)
    if not geometry:
        return g.gap_mm, None, None, g.valid
    m = g.tilt.T
    return g.gap_mm, g.q_design_mm.T, m / np.linalg.norm(m, axis=1, keepdims=True), g.valid


@dataclass(frozen=True)
class _RayGaps:
    """Gaps along the deflection direction in the column layout the fit works in.

    gap_mm (n,); valid (n,) bool; q_design_mm (3, n) the ray/surface intersections, design frame;
    tilt (3, n) the surface normals scaled to a unit z component, ``(-dz/dx, -dz/dy, 1)`` (the
    Jacobian needs only their direction over their projection on the ray, so no square root).
    The geometry rows are None when not asked for.
    """

    gap_mm: np.ndarray
    valid: np.ndarray
    q_design_mm: np.ndarray | None = None
    tilt: np.ndarray | None = None


def _ray_gaps(
    surface: HeightField,
    measured_points_mm: np.ndarray,
    T_meas_design: np.ndarray,
    up: np.ndarray,
    newton_steps: int,
    geometry: bool,
) -> _RayGaps:
    """:func:`deflection_gaps` in column layout, split over the thread pool for large clouds."""
    n = len(measured_points_mm)
    T_inv = invert_transform(np.asarray(T_meas_design, dtype=np.float64))
    up = np.asarray(up, dtype=np.float64)
    u = T_inv[:3, :3] @ (up / np.linalg.norm(up))
    _ = surface.cells  # build the shared table once, before the threads read it
    workers = _gap_workers()
    if workers < 2 or n < 2 * _PARALLEL_MIN_POINTS:
        return _ray_gaps_serial(surface, measured_points_mm, T_inv, u, newton_steps, geometry)
    # blocks of at most _GAP_BLOCK_POINTS, two at a time: the per-point temporaries of a block (about
    # 40 float64 columns) stay bounded whatever the cloud (a 6 m plate's 28 M points: ~9 GB at once)
    bounds = np.linspace(0, n, max(workers, -(-n // _GAP_BLOCK_POINTS)) + 1).astype(int)
    parts = list(
        _gap_pool().map(
            lambda ab: _ray_gaps_serial(
                surface, measured_points_mm[ab[0] : ab[1]], T_inv, u, newton_steps, geometry
            ),
            pairwise(bounds),
        )
    )
    s = np.concatenate([p.gap_mm for p in parts])
    valid = np.concatenate([p.valid for p in parts])
    if not geometry:
        return _RayGaps(s, valid)
    q = np.concatenate([p.q_design_mm for p in parts], axis=1)
    return _RayGaps(s, valid, q, np.concatenate([p.tilt for p in parts], axis=1))


_PARALLEL_MIN_POINTS = 100_000
_GAP_BLOCK_POINTS = 1_000_000
_POOL: ThreadPoolExecutor | None = None


def _gap_workers() -> int:
    return min(os.cpu_count() or 1, 4)


def _gap_pool() -> ThreadPoolExecutor:
    global _POOL
    if _POOL is None:
        _POOL = ThreadPoolExecutor(max_workers=_gap_workers(), thread_name_prefix="gaps")
    return _POOL


def _ray_gaps_serial(
    surface: HeightField,
    measured_points_mm: np.ndarray,
    T_inv: np.ndarray,
    u: np.ndarray,
    newton_steps: int,
    geometry: bool,
) -> _RayGaps:
    """Gaps of one block of points, in the calling thread. T_inv: (4, 4) measured -> design;
    u: (3,) the unit deflection direction in the design frame."""
    # (3, 3) @ (3, n): one BLAS call, and each coordinate row comes out contiguous
    p = T_inv[:3, :3] @ np.asarray(measured_points_mm, dtype=np.float64).T
    p += T_inv[:3, 3:4]
    px, py, pz = p
    ux, uy, uz = float(u[0]), float(u[1]), float(u[2])
    # Newton on F(s) = f(p_xy + s u_xy) - (p_z + s u_z) from s = 0; the ray is within a few degrees
    # of the design's z, so two steps leave an error of order slope change * tilt^2, far below a
    # nanometre. The first step reads the surface at p_xy itself.
    z, sx, sy, valid = surface.lookup(px, py)
    F = z - pz
    den = sx * ux
    den += sy * uy
    den -= uz
    s = F / den
    np.negative(s, out=s)
    for _ in range(1, newton_steps):
        z, sx, sy, ok = surface.lookup(px + s * ux, py + s * uy)
        valid &= ok
        F = z - (pz + s * uz)
        den = sx * ux
        den += sy * uy
        den -= uz
        s -= F / den
    if not geometry:
        return _RayGaps(s, valid)
    q = p + np.outer(u, s)
    tilt = np.empty_like(p)
    np.negative(sx, out=tilt[0])
    np.negative(sy, out=tilt[1])
    tilt[2] = 1.0
    return _RayGaps(s, valid, q, tilt)


def _active_set_qp(
    H: np.ndarray, g: np.ndarray, A: np.ndarray, b: np.ndarray, x0: np.ndarray, max_iter: int = 200
) -> tuple[np.ndarray, int, np.ndarray]:
    """Exact primal active-set solution of min 1/2 x'Hx + g'x subject to A x >= b (Nocedal-Wright 16.3).

    H (k, k) positive definite, A (m, k), b (m,), x0 (k,) feasible. k is 6 here and m may be 10^6:
    each step solves a KKT system of at most 6 + 6 unknowns and scans all constraints once for the
    blocking one. Returns ``(x, iterations, working set indices)``.
    """
    k = len(g)
    x = x0.copy()
    W: list[int] = []
    for it in range(1, max_iter + 1):
        grad = H @ x + g
        # equality-constrained step in the null space of the working constraints: A_W p = 0 holds
        # to round-off, which a full KKT solve of this badly scaled system does not guarantee
        if W:
            _, sv, Vt = np.linalg.svd(A[W])
            rank = int((sv > 1e-12 * sv[0]).sum())
            Z = Vt[rank:].T
        else:
            Z = np.eye(k)
        if Z.shape[1]:
            p = Z @ np.linalg.solve(Z.T @ H @ Z, -(Z.T @ grad))
        else:
            p = np.zeros(k)
        # p is "zero" when it would not lower the objective measurably (scale-free test)
        gain = -(grad @ p) - 0.5 * (p @ H @ p)
        f = 0.5 * (x @ H @ x) + g @ x
        if gain <= 1e-12 * (1.0 + abs(f)):
            if not W:
                return x, it, np.asarray(W, dtype=np.intp)
            lam = np.linalg.lstsq(A[W].T, H @ (x + p) + g, rcond=None)[0]
            if lam.min() >= -1e-9 * (1.0 + np.abs(lam).max()):
                return x, it, np.asarray(W, dtype=np.intp)
            W.pop(int(np.argmin(lam)))
            continue
        Ap = A @ p
        slack = np.maximum(A @ x - b, 0.0)
        blocking = Ap < 0.0
        if W:
            blocking[W] = False
        alpha, j = 1.0, -1
        if blocking.any():
            idx = np.flatnonzero(blocking)
            ratios = slack[idx] / -Ap[idx]
            m = int(np.argmin(ratios))
            if ratios[m] < 1.0:
                alpha, j = float(ratios[m]), int(idx[m])
        x = x + alpha * p
        if j >= 0:
            W.append(j)
    raise RegistrationError(f"active-set QP did not converge in {max_iter} steps")


def solve_onesided_qp(
    J: np.ndarray,
    s: np.ndarray,
    lift: np.ndarray,
    damping: float,
    K: np.ndarray | None = None,
    e: np.ndarray | None = None,
    box: float | None = None,
) -> tuple[np.ndarray, int, int]:
    """min ||s + J x||^2 + ||e + K x||^2 + damping ||x||^2 subject to s + J x >= 0, exactly.

    J (m, k) with k unknowns (6 here, 3 for a motion in a section plane).

    By constraint generation: the objective uses every row; the constraints start with the rows of smallest gap and grow by
    the violated ones until none is violated -- then the solution of the reduced problem is the
    solution of the full one (it is feasible for a relaxation's optimum). J (m, 6), s (m,).
    lift (6,): the parameter vector that adds exactly 1 mm to every gap (a pure lift along the
    deflection direction), which gives a feasible start. box: optional trust region, |x_i| <= box
    for every parameter (12 more linear constraints, always in the working problem). Returns ``(x, active-set steps, active constraints)``.
    """
    k = J.shape[1]  # 6 for a rigid motion in space, 3 for one in a section plane
    H = J.T @ J
    H[np.diag_indices(k)] += damping
    g = J.T @ s
    if K is not None and e is not None and len(e):
        H += K.T @ K
        g += K.T @ e
    m = len(s)
    x0 = max(0.0, -float(s.min())) * lift
    if box is not None:
        box = max(box, 1.5 * float(np.abs(x0).max()))  # the lift itself must stay allowed
        Abox = np.vstack([np.eye(k), -np.eye(k)])
        bbox = np.full(2 * k, -box)
    else:
        Abox, bbox = np.zeros((0, k)), np.zeros(0)
    k0 = min(m, 256)
    work = np.argpartition(s, k0 - 1)[:k0] if k0 < m else np.arange(m)
    steps = 0
    for _ in range(50):
        A = np.vstack([J[work], Abox])
        b = np.concatenate([-s[work], bbox])
        x, it, active = _active_set_qp(H, g, A, b, x0)
        steps += it
        viol = np.flatnonzero(s + J @ x < -1e-10 * (1.0 + np.abs(s).max()))
        if len(viol) == 0:
            return x, steps, int((active < len(work)).sum())
        # add the worst violators (not all: a bad linearisation could violate many at once)
        worst = viol[np.argsort((s + J @ x)[viol])[:256]]
        work = np.union1d(work, worst)
    raise RegistrationError("one-sided QP: constraint generation did not settle")


_solve_onesided_qp = solve_onesided_qp  # the name the fits below and the tests use


# relative Levenberg-Marquardt damping of the one-sided step: without boundary anchoring the slide of a
# nearly spherical plate along itself is almost free, and undamped steps along it overshoot and cycle
DAMPING = 1e-6


def nonpenetrating_fit(
    surface: HeightField,
    measured_points_mm: np.ndarray,
    T_init: np.ndarray,
    *,
    up: np.ndarray = np.array([0.0, 0.0, 1.0]),
    max_iterations: int = 30,
    tolerance_mm: float = 1e-4,
    max_distance_mm: float = 25.0,
    design_corners_mm: np.ndarray | None = None,
    measured_corners_mm: np.ndarray | None = None,
    boundary_weight: float = BOUNDARY_WEIGHT,
    subsample: int = 20_000,
    rel_tolerance: float = 1e-5,
) -> NonPenetratingResult:
    """Rest the design on the measured surface: least squares with no point penetrating.

    surface: design height field (design frame). measured_points_mm: (n, 3) mm, measured frame,
    every surface point (no subsampling). T_init: (4, 4) design -> measured start (after ICP).
    up: (3,) deflection direction in the measured frame.

    Minimises sum_i gap_i^2 subject to gap_i >= 0, gap_i = distance from measured point i up to the
    design surface. Outer loop: correspondences along ``up``, then the gaps are linearised in the
    six motion parameters (rotation vector about the centroid, translation) with the exact
    Jacobian -[(q_i - c) x n_i, n_i] / (n_i . u) of the ray/tangent-plane intersection, and the
    resulting QP (6 unknowns, one linear constraint per point) is solved exactly by an active-set
    method; the rotation is applied through the exponential map. Finally any round-off penetration
    is removed by a pure lift along ``up`` (which raises every gap by exactly the same amount), so
    the result has zero penetrating points. Points off the footprint or more than
    ``max_distance_mm`` from the surface are not constrained (they are not on this plate).
    With matched corners the in-plane corner residuals are added to the objective, weighted as in
    :func:`icp_point_to_plane` by the two terms' information, with the RMS gap as the surface's
    scale (the QP stays exact; ``objective_mm2`` reports the gaps alone). Resting the unformed
    design on a formed plate is one-sided: whatever in-plane motion lowers the gaps pays for
    forming error with it, and on a nearly flat plate the surface hardly sees the yaw; large gaps
    hand the in-plane pose to the corners. (With a constant share of 1e-3 the e2e cell's plate
    turned 1.7 degrees off the true plate, 5-6 mm at its corners.)
    The first iterations run on a seeded ``subsample`` of the points, the last ones on all.
    The outer loop stops when a step moves less than ``tolerance_mm`` or, with every point
    feasible, lowers the objective by less than ``rel_tolerance`` of itself.
    """
    corners = _matched_corners(design_corners_mm, measured_corners_mm)
    P = _check_points("measured_points_mm", measured_points_mm, 6)
    T = _check_transform("T_init", T_init).copy()
    up = np.asarray(up, dtype=np.float64)
    up = up / np.linalg.norm(up)
    # one Newton step is within about 1e-6 mm here (the ray is nearly the design's z); the exact
    # two-step gaps decide the lift and the final count below
    s, _, _, valid = deflection_gaps(surface, P, T, up, newton_steps=1, geometry=False)
    use = valid & (np.abs(s) < max_distance_mm)
    if use.sum() < 6:
        raise RegistrationError(f"non-penetrating fit: only {int(use.sum())} points lie over the design")
    Pu, s_all = P[use], s[use]
    penetrating_before = int((s_all < 0).sum())
    # coarse to fine: a seeded subsample walks most of the way cheaply, then every point decides
    # the last steps (the solution and its zero penetration are those of the full problem)
    sub = None
    if len(Pu) > 2 * subsample:
        # a seeded random share carries the objective; the points standing highest above the design
        # now are the ones likely to carry it at the end, so they come along as well
        rand = np.random.default_rng(0).choice(len(Pu), size=subsample, replace=False)
        high = np.argpartition(s_all, subsample // 4)[: subsample // 4]
        sub = np.union1d(rand, high)
    qp_steps, active, it_total, converged = 0, 0, 0, False
    # the subsample walks all the way (cheap), the full set only polishes
    stages = [(Pu[sub], tolerance_mm, rel_tolerance * 1e-3)] if sub is not None else []
    stages.append((Pu, tolerance_mm, rel_tolerance))
    for stage_points, tol, rel_tol in stages:
        T, steps, its, active, converged, kept = _onesided_iterations(
            surface, stage_points, T, up, corners, boundary_weight, max_iterations, tol, rel_tol
        )
        qp_steps += steps
        it_total += its
    Pu = kept
    for refit in range(4):
        # the fit may have moved the design over points that were off its footprint at the start:
        # they are plate points now and must not penetrate either
        s, _, _, valid = deflection_gaps(surface, P, T, up, geometry=False)
        now = valid & (np.abs(s) < max_distance_mm)
        if refit == 3 or len(Pu) == int(now.sum()) or not (s[now] < 0).any():
            break
        Pu = P[now]
        T, steps, its, active, converged, Pu = _onesided_iterations(
            surface, Pu, T, up, corners, boundary_weight, max_iterations, tolerance_mm, rel_tolerance
        )
        qp_steps += steps
        it_total += its
    T, s = _settle(surface, P, np.flatnonzero(now), s[now], T, up)
    objective = float((s**2).sum())
    result = NonPenetratingResult(
        transform=T,
        objective_mm2=objective,
        rms_mm=float(np.sqrt(objective / len(s))),
        min_gap_mm=float(s.min()),
        iterations=it_total,
        qp_iterations=qp_steps,
        points=len(s),
        penetrating_before=penetrating_before,
        penetrating_after=int((s < 0).sum()),
        active_points=active,
        converged=converged,
    )
    log.debug(
        "nonpenetrating_fit",
        points=result.points,
        iterations=it_total,
        penetrating_before=penetrating_before,
        penetrating_after=result.penetrating_after,
        rms_mm=round(result.rms_mm, 5),
    )
    return result


# the lowest gap after the fit: far above the gaps' round-off (1e-13 mm), far below anything that
# costs (the whole cloud's objective rises by 2 * sum(gap) * margin, 1e-9 of itself)
CONTACT_MARGIN_MM = 1e-9
# gaps below this after the final shift are recomputed from scratch rather than shifted
_RECHECK_MM = 1e-3


def _settle(
    surface: HeightField, P: np.ndarray, idx: np.ndarray, s: np.ndarray, T: np.ndarray, up: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Shift the design along ``up`` until its lowest gap over ``P[idx]`` is CONTACT_MARGIN_MM.

    P: (N, 3) mm, measured frame; idx: (n,) the points that count; s: (n,) their exact gaps at ``T``. A shift along ``up`` changes every gap by exactly the
    shift (the ray meets the surface at the same point), so a lift removes the round-off
    penetration the linearised steps leave and a drop removes the float they leave; either way the
    design ends in contact and the objective is the lowest of all poses along ``up`` that penetrate
    nowhere. The shifted gaps are taken as computed, except the few near contact, which decide
    feasibility: those are evaluated afresh (and any shortfall lifted again). Returns ``(T, gaps)``.
    """
    s = s.copy()
    keep = np.ones(len(s), dtype=bool)
    for _ in range(4):
        shift = CONTACT_MARGIN_MM - float(s[keep].min())
        T = make_transform(np.eye(3), shift * up) @ T
        s += shift
        near = np.flatnonzero(keep & (s < _RECHECK_MM))
        g = _ray_gaps(surface, P[idx[near]], T, up, 2, False)
        s[near] = g.gap_mm
        keep[near] = g.valid  # a point exactly on the footprint's edge may round either way
        if s[keep].min() >= 0.0:
            break
    return T, s[keep]


def _onesided_iterations(
    surface: HeightField,
    P: np.ndarray,
    T: np.ndarray,
    up: np.ndarray,
    corners: tuple[np.ndarray, np.ndarray] | None,
    boundary_weight: float,
    max_iterations: int,
    tolerance_mm: float,
    rel_tolerance: float,
    trust_mm: float = 5.0,
) -> tuple[np.ndarray, int, int, int, bool, np.ndarray]:
    """Outer correspondence loop of the one-sided fit on the points ``P`` (measured frame).

    The corners weigh as in :func:`icp_point_to_plane`, with the RMS gap as the surface's scale.

    Each step is confined to a trust region of ``trust_mm`` per parameter (translation in mm,
    rotation in mm at the points' RMS radius): the correspondences are only valid near the current
    pose, and a weakly determined direction (sliding along a nearly spherical plate) would
    otherwise take steps of hundreds of millimetres on a linear model that is long wrong there.
    Returns ``(T, active-set steps, iterations, active constraints, converged, points kept)``.
    """
    qp_steps, active, converged, it = 0, 0, False, 0
    trust, x_prev = float(trust_mm), np.zeros(6)
    for it in range(1, max_iterations + 1):
        # the linearisation only needs one Newton step; the caller checks with two
        g = _ray_gaps(surface, P, T, up, 1, True)
        s, q, m = g.gap_mm, g.q_design_mm, g.tilt
        if not g.valid.all():
            # a point slid off the footprint edge during the fit: keep it out from now on
            P, s, q, m = P[g.valid], s[g.valid], q[:, g.valid], m[:, g.valid]
        T_inv = invert_transform(T)
        u = T_inv[:3, :3] @ up
        c = q.mean(axis=1)
        d = q - c[:, None]
        scale = float(np.sqrt(np.einsum("ij,ij->", d, d) / len(s))) or 1.0
        # J = -[(q - c) x n, n] / (n . u): the normal's length cancels, so the unnormalised tilt
        # (-dz/dx, -dz/dy, 1) serves; rows (6, n) so that J^T J is one BLAS call
        w = m[0] * u[0]
        w += m[1] * u[1]
        w += u[2]
        np.reciprocal(w, out=w)
        np.negative(w, out=w)
        J6 = np.empty((6, len(s)))
        dx, dy, dz = d
        np.multiply(dz, m[1], out=J6[0])
        np.subtract(dy, J6[0], out=J6[0])
        np.multiply(dz, m[0], out=J6[1])
        J6[1] -= dx
        np.multiply(dx, m[1], out=J6[2])
        J6[2] -= dy * m[0]
        J6[:3] *= w * (1.0 / scale)
        np.multiply(m, w, out=J6[3:])
        J = J6.T
        lift = np.concatenate([np.zeros(3), -u])  # moving the points down along u lifts every gap by 1
        damping = DAMPING * float(np.einsum("ij,ij->", J6, J6)) / 6.0
        share = boundary_weight * float(s @ s) / len(s) / CORNER_SIGMA_MM**2
        K, e = _corner_terms(T_inv, corners, c, scale, share * len(s) / 8.0)
        x, steps, active = _solve_onesided_qp(J, s, lift, damping, K, e, box=trust)
        qp_steps += steps
        # a step that turns back on the last one means the linear model is overreaching: shrink
        # (never grow again: after ICP the fit has millimetres to go, not metres)
        if x @ x_prev < 0.0:
            trust *= 0.5
        x_prev = x
        omega, t = x[:3] / scale, x[3:]
        R = rotation_from_vector(omega)
        # the motion acts on the measured points in the design frame; the design moves by its inverse
        T = invert_transform(make_transform(R, c - R @ c + t) @ T_inv)
        step_mm = float(np.linalg.norm(x[:3]) + np.linalg.norm(t))
        obj = float(s @ s) + float(e @ e)
        r = s + J @ x
        gain = (obj - float(r @ r) - float(np.sum((e + K @ x) ** 2))) / max(obj, 1e-300)
        log.debug("onesided_step", it=it, step_mm=step_mm, relative_gain=gain, points=len(s))
        # converged when the step is negligible, or when, already feasible, it no longer lowers the
        # objective measurably: without boundary anchoring a nearly spherical plate can slide along
        # itself for ever at no cost, and such sliding is not worth iterating for
        if step_mm < tolerance_mm or (s.min() >= -10.0 * tolerance_mm and gain < rel_tolerance):
            converged = True
            break
    return T, qp_steps, it, active, converged, P


def grid_average(points_mm: np.ndarray, cell_mm: float = 1.0) -> np.ndarray:
    """Mean point of every occupied ``cell_mm`` square of the XY plane: (m, 3) mm.

    An HD8 scan puts about 20 points in every square millimetre; their cell means keep the shape,
    cut sensor noise by the square root of the count (which a one-sided fit would otherwise turn
    into a lift of the design by the noise's largest excursion) and make the non-penetrating fit
    ten to twenty times cheaper. Vectorised: one sort, one pass of bincounts.
    """
    P = _check_points("points_mm", points_mm)
    if cell_mm <= 0:
        raise RegistrationError(f"cell_mm must be positive, got {cell_mm}")
    ij = np.floor(P[:, :2] / cell_mm).astype(np.int64)
    ij -= ij.min(axis=0)
    key = ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1]
    _, inv, count = np.unique(key, return_inverse=True, return_counts=True)
    out = np.empty((len(count), 3))
    for k in range(3):
        out[:, k] = np.bincount(inv, weights=P[:, k]) / count
    return out


# --------------------------------------------------------------------------------------------------
# the whole registration


@dataclass(frozen=True)
class RegistrationResult:
    """Coarse fit, ICP and non-penetrating fit of one design onto one measured plate.

    transform: (4, 4) design -> measured, mm (the non-penetrating pose).
    coarse: the coarse fit of the chosen corner correspondence; icp: the ICP from it.
    nonpenetrating: the final one-sided fit. candidates: ICP RMS (mm) per corner shift tried.
    """

    transform: np.ndarray
    coarse: CoarseResult
    coarse_rms_mm: float
    icp: IcpResult
    nonpenetrating: NonPenetratingResult
    candidates: dict[int, float] = field(default_factory=dict)

    @property
    def penetration_points(self) -> int:
        return self.nonpenetrating.penetrating_after


def coarse_candidates(
    design_corners_mm: np.ndarray,
    measured_corners_mm: np.ndarray,
    *,
    design_points_mm: np.ndarray | None = None,
    measured_points_mm: np.ndarray | None = None,
    max_corner_rms_mm: float | None = None,
) -> list[CoarseResult]:
    """Coarse fits for all four cyclic corner correspondences, best corner RMS first.

    With ``max_corner_rms_mm`` the candidates whose corners cannot be matched (a 90 degree shift on
    an oblong plate) are dropped; by default the bound is the best RMS plus 10 % of the plate's
    shorter side, which always keeps the 180 degree twin of a rectangle.
    """
    D = _check_corners("design_corners_mm", design_corners_mm)
    M = _check_corners("measured_corners_mm", measured_corners_mm)

    def snapped(c: np.ndarray, cloud: np.ndarray | None) -> np.ndarray:
        # the edge midpoints do not depend on the shift: snap them once; a 200,000-point share of
        # the cloud places them to its spacing, which is all the coarse fit needs
        if cloud is not None and len(cloud) > 200_000:
            cloud = cloud[:: len(cloud) // 200_000]
        n = np.cross(c[2] - c[0], c[3] - c[1])
        return _snap_to_cloud(0.5 * (c + np.roll(c, -1, axis=0)), cloud, n)

    mid_D, mid_M = snapped(D, design_points_mm), snapped(M, measured_points_mm)
    cands = [
        coarse_register(D, M, shift=k, design_midpoints_mm=mid_D, measured_midpoints_mm=mid_M)
        for k in range(4)
    ]
    cands.sort(key=lambda c: c.corner_rms_mm)
    if max_corner_rms_mm is None:
        D = np.asarray(design_corners_mm, dtype=np.float64)
        side = float(min(np.linalg.norm(D[1] - D[0]), np.linalg.norm(D[2] - D[1])))
        max_corner_rms_mm = cands[0].corner_rms_mm + 0.1 * side
    return [c for c in cands if c.corner_rms_mm <= max_corner_rms_mm]


def coarse_fit_rms(surface: HeightField, measured_points_mm: np.ndarray, T: np.ndarray) -> float:
    """RMS vertical distance (mm) of the measured points to the design surface at pose ``T``."""
    s, _, _, valid = deflection_gaps(surface, measured_points_mm, T)
    return float(np.sqrt(np.mean(s[valid] ** 2))) if valid.any() else float("inf")


def register(
    design: TriMesh | HeightField,
    measured_points_mm: np.ndarray,
    design_corners_mm: np.ndarray,
    measured_corners_mm: np.ndarray,
    *,
    up: np.ndarray = np.array([0.0, 0.0, 1.0]),
    grid_step_mm: float = 1.0,
    icp_points: int = 100_000,
    boundary_weight: float = BOUNDARY_WEIGHT,
    nonpen_cell_mm: float | None = None,
    rest_points: Callable[[np.ndarray], np.ndarray] | None = None,
    nominal_transform: np.ndarray | None = None,
    seed: int = 0,
) -> RegistrationResult:
    """Coarse fit (all corner shifts), ICP per candidate, best ICP kept, then the non-penetrating fit.

    design: the design mesh (top surface, design plate frame, z up) or its height field.
    measured_points_mm: (n, 3) plate top-surface points, measured frame.
    design_corners_mm, measured_corners_mm: (4, 3), counter-clockwise from +z.
    The candidates' ICP runs on a 20,000-point subsample; the winner is refined on ``icp_points``.
    ICP and the non-penetrating fit keep the plate anchored in its own plane by the matched corners
    (``boundary_weight``, see :func:`icp_point_to_plane`); 0 turns that off.
    ``nominal_transform``: the operator's nominal placement (4x4 design -> measured); it only
    breaks ties between equally good fits of a symmetric design (which corner is the reference).
    ``nonpen_cell_mm``: None rests the design on every measured point; a cell size (1 mm for HD8
    scans) rests it on the :func:`grid_average` cell means instead -- the noise no longer lifts
    the design and 10^7 points cost what 10^6 do; penetration is then counted on the cell means.
    ``rest_points``: given the ICP pose (4x4 design -> measured), the (m, 3) points the design
    rests on instead (``analysis.rest_surface``: patch estimates with a bounded noise bias);
    penetration is then counted on those.
    """
    P = _check_points("measured_points_mm", measured_points_mm, 6)
    surface = design if isinstance(design, HeightField) else height_field_from_mesh(design, grid_step_mm)
    design_vertices = surface.points_mm()
    cands = coarse_candidates(
        design_corners_mm, measured_corners_mm, design_points_mm=design_vertices, measured_points_mm=P
    )
    trials: dict[int, tuple[float, CoarseResult, IcpResult]] = {}
    D = np.asarray(design_corners_mm, dtype=np.float64)
    matched = {
        c.shift: np.roll(np.asarray(measured_corners_mm, dtype=np.float64), -c.shift, axis=0) for c in cands
    }
    for cand in cands:
        try:
            icp = icp_point_to_plane(
                surface,
                P,
                cand.transform,
                max_points=20_000,
                max_iterations=30,
                seed=seed,
                design_corners_mm=D,
                measured_corners_mm=matched[cand.shift],
                boundary_weight=boundary_weight,
            )
        except RegistrationError:
            continue
        trials[cand.shift] = (icp.rms_mm, cand, icp)
    if not trials:
        raise RegistrationError(
            "no corner correspondence gives an ICP fit: the cloud does not match the design"
        )
    # A design symmetric under a half turn fits both ways equally well: the corner labelling (and with
    # it the line numbering) must then not depend on noise. Ties go to the candidate whose rotation is
    # nearest the nominal placement when one is given, else to the lowest shift (the measured corners'
    # own order: corner 0 starts the long edge pointing along the bed's +x).
    best_rms = min(v[0] for v in trials.values())
    tied = [k for k, v in trials.items() if v[0] <= best_rms * (1.0 + TIE_RELATIVE) + TIE_ABSOLUTE_MM]
    if nominal_transform is not None and len(tied) > 1:
        R_nom = _check_transform("nominal_transform", nominal_transform)[:3, :3]
        best_shift = min(tied, key=lambda k: (-float(np.trace(R_nom.T @ trials[k][1].transform[:3, :3])), k))
    else:
        best_shift = min(tied)
    _, coarse, icp0 = trials[best_shift]
    anchor = dict(
        design_corners_mm=D, measured_corners_mm=matched[best_shift], boundary_weight=boundary_weight
    )
    icp = icp_point_to_plane(surface, P, icp0.transform, max_points=icp_points, seed=seed, **anchor)
    coarse_rms = coarse_fit_rms(surface, _subsample(P, 20_000, seed), coarse.transform)
    if rest_points is not None:
        P_np = _check_points("rest_points", rest_points(icp.transform), 6)
    else:
        P_np = P if nonpen_cell_mm is None else grid_average(P, nonpen_cell_mm)
    npf = nonpenetrating_fit(surface, P_np, icp.transform, up=up, **anchor)
    log.info(
        "registered",
        shift=best_shift,
        candidates={k: round(v[0], 4) for k, v in trials.items()},
        coarse_rms_mm=round(coarse_rms, 3),
        icp_rms_mm=round(icp.rms_mm, 4),
        penetrating_before=npf.penetrating_before,
        penetrating_after=npf.penetrating_after,
    )
    return RegistrationResult(
        transform=npf.transform,
        coarse=coarse,
        coarse_rms_mm=coarse_rms,
        icp=icp,
        nonpenetrating=npf,
        candidates={k: v[0] for k, v in trials.items()},
    )


def register_from_placement(
    design: TriMesh | HeightField,
    measured_points_mm: np.ndarray,
    design_corners_mm: np.ndarray,
    nominal_transform: np.ndarray,
    *,
    up: np.ndarray = np.array([0.0, 0.0, 1.0]),
    grid_step_mm: float = 1.0,
    icp_points: int = 100_000,
    boundary_weight: float = BOUNDARY_WEIGHT,
    rest_points: Callable[[np.ndarray], np.ndarray] | None = None,
    seed: int = 0,
) -> RegistrationResult:
    """The registration of a scan that saw only part of the plate (a scan cut short): the plate's
    corners were not seen, so they are taken from the placement the scan was planned from.

    ``nominal_transform`` (4x4 design -> measured) is first lowered or raised onto the measured
    surface (the median vertical gap: a placement's height is the bed's, not the plate's top), which
    gives the corners the fits are anchored to; then ICP and the non-penetrating fit run as in
    :func:`register`. The in-plane pose is as good as the placement (the located one: about a
    millimetre); the height and tilt are the measured surface's. ``coarse`` is that corrected
    nominal pose (shift 0, corner RMS 0: the corners are the placement's).
    """
    P = _check_points("measured_points_mm", measured_points_mm, 6)
    surface = design if isinstance(design, HeightField) else height_field_from_mesh(design, grid_step_mm)
    T0 = _check_transform("nominal_transform", nominal_transform).copy()
    D = np.asarray(design_corners_mm, dtype=np.float64)
    sample = _subsample(P, 20_000, seed)
    gap, _, _, valid = deflection_gaps(surface, sample, T0, up=up, geometry=False)
    if not valid.any():
        raise RegistrationError(
            "the scanned part of the plate lies outside the design placed where the scan was planned"
        )
    T0[:3, 3] -= float(np.median(gap[valid])) * np.asarray(up, dtype=np.float64)
    M = D @ T0[:3, :3].T + T0[:3, 3]
    anchor = dict(design_corners_mm=D, measured_corners_mm=M, boundary_weight=boundary_weight)
    icp = icp_point_to_plane(surface, P, T0, max_points=icp_points, seed=seed, **anchor)
    coarse_rms = coarse_fit_rms(surface, sample, T0)
    P_np = _check_points("rest_points", rest_points(icp.transform), 6) if rest_points is not None else P
    npf = nonpenetrating_fit(surface, P_np, icp.transform, up=up, **anchor)
    log.info(
        "registered_from_placement",
        coarse_rms_mm=round(coarse_rms, 3),
        icp_rms_mm=round(icp.rms_mm, 4),
        penetrating_before=npf.penetrating_before,
        penetrating_after=npf.penetrating_after,
    )
    return RegistrationResult(
        transform=npf.transform,
        coarse=CoarseResult(T0, 0, 0.0, 0.0),
        coarse_rms_mm=coarse_rms,
        icp=icp,
        nonpenetrating=npf,
        candidates={0: icp.rms_mm},
    )
