"""The design surface as a height field: the design mesh rasterised once onto a regular grid.

The design mesh (top surface, design plate frame, z up -- the convention of
``analysis.design.plates``) becomes a :class:`HeightField`, so that a correspondence for a million
points is a bilinear lookup (O(n) numpy, no k-d tree). Every registration stage reads the design
through it.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from analysis.design.mesh import TriMesh
from analysis.register.transforms import RegistrationError

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
    height = np.full((ny, nx), np.nan)
    # the (triangle, node) pairs a block of triangles at a time, in the triangles' order (a node two
    # triangles share keeps the later one's value, as in one pass): about 150 bytes a pair, and a
    # design holds several pairs per node -- at once, a 3 x 1 m design's 1 mm grid took 1.2 GB
    end = np.cumsum(count)
    cuts = np.searchsorted(
        end, np.arange(_RASTER_BLOCK_PAIRS, int(end[-1]), _RASTER_BLOCK_PAIRS), side="right"
    )
    for t0, t1 in itertools.pairwise([0, *np.unique(cuts).tolist(), len(a)]):
        if t1 > t0:
            _raster_block(height, lo, step_mm, a[t0:t1], b[t0:t1], c[t0:t1], det[t0:t1], i0[t0:t1], j0[t0:t1],
                          wi[t0:t1], count[t0:t1])  # fmt: skip
    if not np.isfinite(height).any():
        raise RegistrationError("design mesh rasterised to an empty height field")
    pad = max(int(np.ceil(pad_mm / step_mm)), 0)
    if pad:
        height = _pad_linear(height, pad)
    return HeightField(float(lo[0] - pad * step_mm), float(lo[1] - pad * step_mm), float(step_mm), height)


#: (triangle, node) pairs rasterised at once by :func:`height_field_from_mesh`
_RASTER_BLOCK_PAIRS = 1 << 19


def _raster_block(height: np.ndarray, lo: np.ndarray, step_mm: float, a: np.ndarray, b: np.ndarray, c: np.ndarray,
                  det: np.ndarray, i0: np.ndarray, j0: np.ndarray, wi: np.ndarray, count: np.ndarray) -> None:  # fmt: skip
    """Write into ``height`` (ny, nx) the nodes inside the triangles (a, b, c (k, 3), ``det`` their XY
    determinants) among each one's bounding-box nodes (``wi`` wide from (i0, j0), ``count`` of them)."""
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
    height[gj[inside], gi[inside]] = z[inside]


def _pad_linear(z: np.ndarray, pad: int) -> np.ndarray:
    """``z`` (ny, nx) grown by ``pad`` cells on every side, extrapolating each border row/column linearly."""
    k = np.arange(1, pad + 1, dtype=np.float64)
    left = z[:, :1] + (z[:, :1] - z[:, 1:2]) * k[::-1]
    right = z[:, -1:] + (z[:, -1:] - z[:, -2:-1]) * k
    z = np.hstack([left, z, right])
    low = z[:1, :] + (z[:1, :] - z[1:2, :]) * k[::-1, None]
    high = z[-1:, :] + (z[-1:, :] - z[-2:-1, :]) * k[:, None]
    return np.vstack([low, z, high])
