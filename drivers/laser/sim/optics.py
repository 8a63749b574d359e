"""Line-laser measurement model: a fan of rays in the sensor's x-z plane cast onto a scene.

Sensor frame (used throughout ``drivers.laser``): the laser plane is the sensor's x-z plane; rays
leave the sensor origin towards +z, fanned across x. A profile point is ``(x_mm, 0, z_mm)`` in that
frame. ``T_world_sensor`` maps sensor coordinates into the world frame (mm).

The model: every ray of the fan is cast at the sensor's pose at mid-exposure; a ray returns a point if
it hits within ``[z_min_mm, z_max_mm]`` and the incidence angle to the surface normal is below
``max_incidence_deg`` (grazing light does not reach the camera). For the uniform format the hits are
resampled onto the x grid by linear interpolation between neighbouring rays on the same surface
(neighbours further apart in z than the slope limit are an edge and are not bridged), then Gaussian
depth noise and sparse outliers are added. Triangulation shadowing (the camera's view being blocked)
is not modelled.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from drivers.laser.sim.scene import SceneRaycaster

__all__ = ["LaserOptics", "ProfileRender", "render_points", "render_uniform"]


@dataclass(frozen=True)
class LaserOptics:
    """Geometry and noise of the line laser (HD8-0050W-like defaults; see docs/hd8-protocol.md).

    Attributes:
        width: points per uniform profile.
        x_pitch_mm: uniform x grid pitch.
        z_min_mm, z_max_mm: measuring range along +z.
        noise_sigma_mm: standard deviation of the Gaussian depth noise.
        outlier_probability: chance that a returned point is replaced by a uniform random depth.
        max_incidence_deg: returns with a larger angle between ray and surface normal are missing.
        ray_oversampling: rays per grid pitch at ``z_max_mm`` (>= 1 keeps every grid point lit).
        max_slope: |dz/dx| above which neighbouring rays are treated as an edge and not interpolated.
    """

    width: int = 500
    x_pitch_mm: float = 0.1
    z_min_mm: float = 70.0
    z_max_mm: float = 130.0
    noise_sigma_mm: float = 0.02
    outlier_probability: float = 1e-4
    max_incidence_deg: float = 80.0
    ray_oversampling: float = 1.05
    max_slope: float = 6.0

    def __post_init__(self) -> None:
        if self.width <= 1 or self.x_pitch_mm <= 0:
            raise ValueError(f"LaserOptics width {self.width} / x_pitch_mm {self.x_pitch_mm} invalid")
        if not 0 < self.z_min_mm < self.z_max_mm:
            raise ValueError(f"LaserOptics z range [{self.z_min_mm}, {self.z_max_mm}] invalid")

    @property
    def x_start_mm(self) -> float:
        """x of the first uniform grid point (the grid is centred on the laser axis)."""
        return -0.5 * (self.width - 1) * self.x_pitch_mm

    @property
    def half_angle_rad(self) -> float:
        """Fan half angle: wide enough to light the whole grid already at ``z_min_mm``."""
        return math.atan((-self.x_start_mm + self.x_pitch_mm) / self.z_min_mm)

    @property
    def n_rays(self) -> int:
        """Rays per profile for the uniform format (spacing at ``z_max_mm`` below one pitch)."""
        th = self.half_angle_rad
        # x spacing of neighbouring rays at depth z is about z * dtheta / cos^2(theta)
        span = 2.0 * th * self.z_max_mm / (math.cos(th) ** 2)
        return math.ceil(span / self.x_pitch_mm * self.ray_oversampling) + 1

    def grid_x_mm(self) -> np.ndarray:
        """(width,) float64 x of the uniform grid, mm."""
        return self.x_start_mm + np.arange(self.width) * self.x_pitch_mm


@dataclass(frozen=True)
class ProfileRender:
    """Rendered profiles, sensor frame.

    Attributes:
        x_mm: (n, w) float32; the uniform grid for the uniform format, hit x for the point format.
        z_mm: (n, w) float32, NaN where ``valid`` is False.
        valid: (n, w) bool.
    """

    x_mm: np.ndarray
    z_mm: np.ndarray
    valid: np.ndarray


def _cast_fan(
    raycaster: SceneRaycaster, T_world_sensor: np.ndarray, theta: np.ndarray, optics: LaserOptics
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cast the fan at each pose; return hit x (n, r), z (n, r) float32 in the sensor frame and validity."""
    T = np.asarray(T_world_sensor, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ValueError(f"T_world_sensor must be (n, 4, 4), got {T.shape}")
    n, r = len(T), len(theta)
    sin_t = np.sin(theta).astype(np.float32)
    cos_t = np.cos(theta).astype(np.float32)
    # direction in the sensor frame is (sin, 0, cos): its world image is sin * R[:, :, 0] + cos * R[:, :, 2]
    R = T[:, :3, :3].astype(np.float32)
    rays = np.empty((n, r, 6), dtype=np.float32)
    rays[:, :, :3] = (T[:, :3, 3] - raycaster.shift_mm).astype(np.float32)[:, None, :]
    d_w = rays[:, :, 3:]
    np.multiply(sin_t[None, :, None], R[:, None, :, 0], out=d_w)
    d_w += cos_t[None, :, None] * R[:, None, :, 2]
    hits = raycaster.cast_shifted(rays.reshape(-1, 6))
    t = hits.t_mm.reshape(n, r)
    nrm = hits.normal.reshape(n, r, 3)
    cos_inc = np.abs(nrm[..., 0] * d_w[..., 0] + nrm[..., 1] * d_w[..., 1] + nrm[..., 2] * d_w[..., 2])
    with np.errstate(invalid="ignore"):
        x = t * sin_t
        z = t * cos_t
        ok = (z >= optics.z_min_mm) & (z <= optics.z_max_mm)  # inf and NaN compare False
        ok &= cos_inc >= np.float32(math.cos(math.radians(optics.max_incidence_deg)))
    return x, z, ok


def _add_noise(z: np.ndarray, valid: np.ndarray, optics: LaserOptics, rng: np.random.Generator) -> None:
    """Gaussian depth noise and sparse outliers, in place on (n, w) float32 ``z``."""
    if optics.noise_sigma_mm > 0:
        z += rng.standard_normal(size=z.shape, dtype=np.float32) * np.float32(optics.noise_sigma_mm)
    if optics.outlier_probability > 0:
        # Draw the number of outliers, then their places: cheaper than one uniform draw per point.
        k = int(rng.binomial(z.size, optics.outlier_probability))
        if k:
            flat = rng.integers(0, z.size, size=k)
            flat = flat[valid.ravel()[flat]]
            z.ravel()[flat] = rng.uniform(optics.z_min_mm, optics.z_max_mm, size=len(flat))


def render_uniform(
    raycaster: SceneRaycaster, T_world_sensor: np.ndarray, optics: LaserOptics, rng: np.random.Generator
) -> ProfileRender:
    """Render ``n`` uniform (resampled) profiles.

    Args:
        raycaster: the scene.
        T_world_sensor: (n, 4, 4) sensor pose at each profile's mid-exposure, mm.
        optics: sensor geometry and noise.
        rng: noise source.

    Returns:
        Profiles on the ``optics.width`` point grid at ``optics.x_pitch_mm``.
    """
    th = optics.half_angle_rad
    theta = np.linspace(-th, th, optics.n_rays)
    x, z, ok = _cast_fan(raycaster, T_world_sensor, theta, optics)
    n, w = len(x), optics.width
    u = (x - optics.x_start_mm) / optics.x_pitch_mm  # continuous grid coordinate
    # Segments between neighbouring rays that lie on one surface are bridged by linear interpolation.
    u0, u1, z0, z1 = u[:, :-1], u[:, 1:], z[:, :-1], z[:, 1:]
    with np.errstate(invalid="ignore"):
        seg = (
            ok[:, :-1]
            & ok[:, 1:]
            & (np.abs(z1 - z0) <= optics.max_slope * np.abs(x[:, 1:] - x[:, :-1]) + 1e-6)
        )
        lo = np.minimum(u0, u1)
        hi = np.maximum(u0, u1)
    pi, ji = np.nonzero(seg)
    lo, hi, a0, a1, b0, b1 = lo[pi, ji], hi[pi, ji], u0[pi, ji], u1[pi, ji], z0[pi, ji], z1[pi, ji]
    out = np.full(n * w, np.inf, dtype=np.float32)
    span = np.maximum(a1 - a0, 1e-12) * np.sign(a1 - a0 + 1e-300)
    first = np.ceil(lo)
    n_steps = int(min(np.max(hi - first, initial=0.0), 8.0)) + 1
    for k in range(n_steps):
        b = first + k
        m = (b <= hi) & (b >= 0) & (b < w)
        zb = b0[m] + (b[m] - a0[m]) / span[m] * (b1[m] - b0[m])
        # Where segments overlap (the surface folds back) one of them wins arbitrarily; a real
        # triangulation sensor is just as ambiguous there.
        out[pi[m] * w + b[m].astype(np.int64)] = zb
    zz = out.reshape(n, w)
    valid = np.isfinite(zz)
    _add_noise(zz, valid, optics, rng)  # inf + noise stays inf
    z_mm = np.where(valid, zz, np.float32(np.nan))
    x_mm = np.broadcast_to(optics.grid_x_mm().astype(np.float32), (n, w)).copy()
    return ProfileRender(x_mm=x_mm, z_mm=z_mm, valid=valid)


def render_points(
    raycaster: SceneRaycaster, T_world_sensor: np.ndarray, optics: LaserOptics, rng: np.random.Generator
) -> ProfileRender:
    """Render ``n`` unresampled profiles: one point per ray, ``optics.width`` rays per profile.

    Args: as :func:`render_uniform`.
    """
    th = optics.half_angle_rad
    theta = np.linspace(-th, th, optics.width)
    x, z, ok = _cast_fan(raycaster, T_world_sensor, theta, optics)
    zn = np.where(ok, z, np.float32(0.0))
    _add_noise(zn, ok, optics, rng)
    return ProfileRender(
        x_mm=np.where(ok, x, np.nan).astype(np.float32),
        z_mm=np.where(ok, zn, np.nan).astype(np.float32),
        valid=ok,
    )
