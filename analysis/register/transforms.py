"""Rigid-body helpers of the registration: 4x4 transforms, rotations, Kabsch, pose error, input checks.

Every transform is a 4x4 homogeneous matrix in millimetres; ``T_meas_design`` maps design
coordinates into the measurement (robot base) frame. :class:`RegistrationError` is what every stage
of :mod:`analysis.register` raises on inputs it cannot register.
"""

from __future__ import annotations

import numpy as np


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
