"""Stage 1 of the registration: the paper's boundary fit (2.2.1), from the corners.

:func:`coarse_register` -- corner centroids, the diagonal normals, the edge midpoints snapped to the
data, Kabsch/SVD. The order of the measured corners relative to the design's is only known up to a
cyclic shift; :func:`analysis.register.fit.register` tries every shift.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from analysis.register.transforms import (
    RegistrationError,
    apply_transform,
    kabsch,
    make_transform,
    rotation_between,
)

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
