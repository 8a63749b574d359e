"""Coverage planning: raster and edge passes over a design surface, and the predicted coverage.

The plan is built in the plate's design frame (x along the length, y across, z up; see
``analysis.design.plates``) and moved into the robot base frame with the nominal placement. Raster passes run
along the plate's longer footprint axis, the laser line across them; the sensor looks along the
surface normal from the standoff, so the curved surface stays inside the depth range, which is
checked for every waypoint (including the height change the placement uncertainty can bring). The
passes cover the outline grown by the placement-uncertainty margin: each pass runs only as far as the
plate (and the margin) reaches inside its strip, so a sheared or tapered plate is not swept over its
bounding box's empty corners. Edge passes follow the design's own outline (the mesh's boundary loop
and its four corners, :mod:`analysis.design.outline`): along each edge between two corners, following a
bowed edge's curve, with the sensor tilted outward along the outline's outward normal in the plate
plane, so the edge and the thickness face are lit whatever the corner angles. Links lift over the
surface between passes; the approach and retract move along the normal.

The predicted coverage casts the laser fan of every simulated profile onto the design with open3d's
``RaycastingScene`` and counts the cells of the plate (cell centre inside the outline) that receive
a valid return.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np
import open3d as o3d
import structlog
from scipy.interpolate import RectBivariateSpline
from scipy.ndimage import binary_erosion, distance_transform_edt

from analysis.contracts.placement import Placement, placement_transform
from analysis.design.mesh import TriMesh
from analysis.design.outline import OutlineError, mesh_boundary_loops, outline_corners
from analysis.design.plates import canonical_corner_order
from cellctl.planning.plan import (
    PASS_AXES,
    CoverageReport,
    PlanInputError,
    PlanRefused,
    Segment,
    rotation_angle_deg,
    slerp_frames,
)
from cellctl.planning.settings import PlannerSettings

__all__ = [
    "DesignSurface",
    "EdgeFaceCoverage",
    "OutlineEdgeCurve",
    "build_segments",
    "design_surface",
    "outline_in_plan",
    "placement_margin_mm",
    "predict_coverage",
    "predict_edge_face_coverage",
]

log = structlog.get_logger(__name__)

_GRID_PITCH_MM = 10.0
_DEPTH_SAMPLES = 11
_LINK_MAX_ROT_STEP_DEG = 3.0
_OUTLINE_STEP_MM = 2.0  # the outline is resampled this finely for the raster passes' reach
_STRAIGHT_TOL_MM = 0.05  # an edge whose outline strays less from its chord is taken as straight
_BOW_DEGREE = 4  # polynomial across the chord: a parabolic or circular bow of 2 % to well under 0.1 mm


def _raycasting_scene(mesh: TriMesh) -> o3d.t.geometry.RaycastingScene:
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(mesh.vertices_mm.astype(np.float32)),
        o3d.core.Tensor(mesh.triangles.astype(np.uint32)),
    )
    return scene


@dataclass(frozen=True)
class OutlineEdgeCurve:
    """One edge of the design's outline in plan (plate frame, mm), from corner ``a`` to corner ``b``.

    ``p(s) = a + s e + bow(s) n`` for chord coordinates ``s`` in [0, chord_mm]; ``e`` the unit chord
    direction, ``n`` its outward normal (the outline runs counter-clockwise seen from +z), ``bow`` a
    polynomial in ``s / chord_mm`` with coefficients ``bow_coef`` (lowest first; all zero for a
    straight edge). Beyond the corners the edge continues along its end tangent.
    """

    a: np.ndarray
    b: np.ndarray
    e: np.ndarray
    n: np.ndarray
    chord_mm: float
    bow_coef: np.ndarray

    @property
    def straight(self) -> bool:
        return not np.any(self.bow_coef)

    def at(self, s_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(points (m, 2), unit tangents (m, 2) along e, unit outward normals (m, 2)) at chord
        coordinates ``s_mm`` (m,)."""
        s = np.atleast_1d(np.asarray(s_mm, dtype=np.float64))
        s0 = np.clip(s, 0.0, self.chord_mm)
        t = s0 / self.chord_mm
        c = np.polynomial.polynomial.polyval(t, self.bow_coef)
        dc = (
            np.polynomial.polynomial.polyval(t, np.polynomial.polynomial.polyder(self.bow_coef))
            / self.chord_mm
        )
        tangent = _unit(self.e[None] + dc[:, None] * self.n[None])
        outward = _unit(self.n[None] - dc[:, None] * self.e[None])
        pts = self.a[None] + s0[:, None] * self.e[None] + c[:, None] * self.n[None]
        return pts + (s - s0)[:, None] * tangent, tangent, outward

    def path(self, run_mm: float, step_mm: float, forward: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """An edge pass's surface points (m, 2), travel directions and outward normals ((2,) for a
        straight edge, else (m, 2)): from ``run_mm`` before the first corner to ``run_mm`` beyond
        the second, from ``a`` to ``b`` when ``forward``, else back."""
        s = _samples(-run_mm, self.chord_mm + run_mm, step_mm)
        if self.straight:
            p_from, d = (self.a, self.e) if forward else (self.b, -self.e)
            return p_from[None] + s[:, None] * d[None], d, self.n
        xy, tangent, outward = self.at(s if forward else self.chord_mm - s)
        return xy, tangent if forward else -tangent, outward


def _edge_curve(chain_xy: np.ndarray) -> OutlineEdgeCurve:
    """The edge through outline points ``chain_xy`` (m, 2), corner to corner, counter-clockwise."""
    a, b = chain_xy[0].copy(), chain_xy[-1].copy()
    e = _unit(b - a)
    n = np.array([e[1], -e[0]])
    chord = float(np.linalg.norm(b - a))
    rel = chain_xy - a
    c = rel @ n
    coef = np.zeros(_BOW_DEGREE + 1)
    if np.abs(c).max() > _STRAIGHT_TOL_MM:
        deg = min(_BOW_DEGREE, len(chain_xy) - 1)
        coef[: deg + 1] = np.polynomial.polynomial.polyfit((rel @ e) / chord, c, deg)
    return OutlineEdgeCurve(a, b, e, n, chord, coef)


def outline_in_plan(design: TriMesh) -> tuple[np.ndarray, np.ndarray] | None:
    """The design's outline in plan: ``(outline_xy (k, 2), corner_index (4,))`` or None.

    outline_xy: the mesh's outer boundary loop (plate frame), counter-clockwise seen from +z,
    starting at the reference corner (corner 0 of :func:`analysis.design.plates.canonical_corner_order`);
    corner_index: the four corners' indices into it, ascending (the first is 0). None when the mesh
    has no open boundary with four corners (the planner then follows the footprint's bounds).
    """
    loops = mesh_boundary_loops(design)
    if not loops:
        return None
    loop = design.vertices_mm[loops[0]]
    try:
        idx = outline_corners(loop, np.array([0.0, 0.0, 1.0]))
    except OutlineError:
        return None
    xy = loop[:, :2].astype(np.float64)
    area = 0.5 * float(np.sum(xy[:, 0] * np.roll(xy[:, 1], -1) - np.roll(xy[:, 0], -1) * xy[:, 1]))
    if area < 0:
        xy = xy[::-1]
        idx = np.sort(len(xy) - 1 - idx)
    c0 = canonical_corner_order(np.column_stack([xy[idx], np.zeros(4)]))[0, :2]
    first = int(idx[np.argmin(np.linalg.norm(xy[idx] - c0, axis=1))])
    xy = np.roll(xy, -first, axis=0)
    idx = np.sort((idx - first) % len(xy))
    return xy, idx


_K4 = np.arange(4)


def _cubic_basis(t: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cubic B-splines on knots ``t`` that are non-zero at ``x`` (n,): ``(span (n,), B (n, 4),
    dB/dx (n, 4))``, B[:, a] the basis function span - 3 + a (Cox-de Boor as in FITPACK's fpbspl,
    on all of a point's basis functions at once; ``x`` clamped to the spline's domain and the last
    span closed, as its bispeu does)."""
    x = np.clip(x, t[3], t[-4])
    span = np.clip(np.searchsorted(t, x, side="right") - 1, 3, len(t) - 5)
    knots = t[span[:, None] + _KNOT_OFFSETS[None, :]]  # t[span - 3] .. t[span + 4]
    left = x[:, None] - knots[:, 3:0:-1]  # x - t[span + 1 - j], j = 1 .. 3
    right = knots[:, 4:7] - x[:, None]  # t[span + j] - x, j = 1 .. 3
    basis = np.ones((x.size, 1))
    for j in range(1, 4):
        if j == 3:
            quad = basis  # B(span - 2, 2) .. B(span, 2): the cubic's derivative
        # basis[:, r] / (t[span + r + 1] - t[span + r + 1 - j]), never zero inside a span
        f = basis / (right[:, :j] + left[:, j - 1 :: -1])
        grown = np.zeros((x.size, j + 1))
        grown[:, :j] += right[:, :j] * f
        grown[:, 1:] += left[:, j - 1 :: -1] * f
        basis = grown
    # d/dx B(i, 3) = 3 (B(i, 2) / (t[i+3] - t[i]) - B(i+1, 2) / (t[i+4] - t[i+1])), i = span - 3 .. span;
    # B(span - 3, 2) and B(span + 1, 2) are zero at x, and so is a term over a zero-width span
    q = np.zeros((x.size, 5))
    q[:, 1:4] = quad
    w = knots[:, 3:8] - knots[:, 0:5]  # t[i + 3] - t[i], i = span - 3 .. span + 1
    qw = q / np.where(w > 0.0, w, 1.0)
    return span, basis, 3.0 * (qw[:, :4] - qw[:, 1:])


_KNOT_OFFSETS = np.arange(-3, 5)


@dataclass(frozen=True)
class DesignSurface:
    """A smooth height field z(x, y) fitted to a design's top surface (plate frame, mm).

    ``x_min_mm``..``y_max_mm``: the footprint (the mesh's XY bounds). ``valid`` (nx, ny) bool: grid
    cells where a vertical ray hit the mesh. Outside the footprint, heights are extrapolated along the
    tangent plane at the nearest footprint point. ``outline_xy`` / ``corner_index``: the design's
    outline (see :func:`outline_in_plan`), None when it has none with four corners.
    """

    x_min_mm: float
    x_max_mm: float
    y_min_mm: float
    y_max_mm: float
    xs_mm: np.ndarray
    ys_mm: np.ndarray
    valid: np.ndarray
    spline: RectBivariateSpline
    outline_xy: np.ndarray | None = None
    corner_index: np.ndarray | None = None

    @property
    def size_mm(self) -> tuple[float, float]:
        """(length along x, width along y) of the footprint."""
        return self.x_max_mm - self.x_min_mm, self.y_max_mm - self.y_min_mm

    def height_and_gradient(
        self, x_mm: np.ndarray, y_mm: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Height (n,) mm and gradient dz/dx, dz/dy (n,) at plate-frame points (n,), extrapolated
        linearly outside the footprint."""
        x = np.asarray(x_mm, dtype=np.float64)
        y = np.asarray(y_mm, dtype=np.float64)
        xc = np.clip(x, self.x_min_mm, self.x_max_mm)
        yc = np.clip(y, self.y_min_mm, self.y_max_mm)
        tx, ty, c = self._bicubic
        ix, bx, dbx = _cubic_basis(tx, xc.ravel())
        iy, by, dby = _cubic_basis(ty, yc.ravel())
        # the 4 x 4 coefficients under each point (one flat gather), weighted by the tensor products
        # of the bases (and their derivatives) along x and y
        ny = c.shape[1]
        cc = np.take(c, ((ix - 3) * ny + (iy - 3))[:, None] + (_K4[:, None] * ny + _K4[None, :]).ravel())
        cc = cc.reshape(-1, 4, 4)
        wy = np.einsum("nab,nb->na", cc, by)
        h = np.einsum("na,na->n", wy, bx).reshape(xc.shape)
        gx = np.einsum("na,na->n", wy, dbx).reshape(xc.shape)
        gy = np.einsum("nb,nb->n", np.einsum("nab,na->nb", cc, bx), dby).reshape(xc.shape)
        return h + gx * (x - xc) + gy * (y - yc), gx, gy

    @cached_property
    def _bicubic(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The spline's knots along x and y and its coefficients (nx, ny): what
        :meth:`height_and_gradient` evaluates (the spline's own ``ev`` looks each point's knot span
        up by a linear search: on the 6 m plate's 600 knots most of the planner's surface time)."""
        tx, ty, c = self.spline.tck
        kx, ky = self.spline.degrees
        if (kx, ky) != (3, 3):
            raise PlanInputError(f"design surface: a bicubic spline expected, got degrees {(kx, ky)}")
        return tx, ty, np.asarray(c, dtype=np.float64).reshape(len(tx) - 4, len(ty) - 4)

    def inside(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        """(n,) bool: the point lies over the design surface (a hit in the sampled grid)."""
        ix = np.clip(
            np.rint((np.asarray(x_mm) - self.xs_mm[0]) / (self.xs_mm[1] - self.xs_mm[0])),
            0,
            len(self.xs_mm) - 1,
        )
        iy = np.clip(
            np.rint((np.asarray(y_mm) - self.ys_mm[0]) / (self.ys_mm[1] - self.ys_mm[0])),
            0,
            len(self.ys_mm) - 1,
        )
        inb = (
            (x_mm >= self.x_min_mm)
            & (x_mm <= self.x_max_mm)
            & (y_mm >= self.y_min_mm)
            & (y_mm <= self.y_max_mm)
        )
        return inb & self.valid[ix.astype(int), iy.astype(int)]

    def outline_edges(self) -> tuple[OutlineEdgeCurve, ...]:
        """The outline's four edges, edge k from corner k to corner k + 1 (counter-clockwise); the
        footprint's bounds when the design has no four-cornered outline."""
        if self.outline_xy is None or self.corner_index is None:
            xy = np.array(
                [
                    [self.x_min_mm, self.y_min_mm],
                    [self.x_max_mm, self.y_min_mm],
                    [self.x_max_mm, self.y_max_mm],
                    [self.x_min_mm, self.y_max_mm],
                ]
            )
            return tuple(_edge_curve(xy[[k, (k + 1) % 4]]) for k in range(4))
        ring = np.vstack([self.outline_xy, self.outline_xy[:1]])
        ci = [*self.corner_index.tolist(), len(self.outline_xy)]
        return tuple(_edge_curve(ring[ci[k] : ci[k + 1] + 1]) for k in range(4))

    @cached_property
    def _dense_outline(self) -> np.ndarray | None:
        """(m, 2) the closed outline resampled every ``_OUTLINE_STEP_MM`` or finer (vertices kept)."""
        if self.outline_xy is None:
            return None
        ring = np.vstack([self.outline_xy, self.outline_xy[:1]])
        seg = np.diff(ring, axis=0)
        n = np.maximum(1, np.ceil(np.linalg.norm(seg, axis=1) / _OUTLINE_STEP_MM).astype(np.int64))
        j = np.repeat(np.arange(len(seg)), n)
        frac = np.arange(j.size) - np.repeat(np.cumsum(n) - n, n)
        return ring[j] + (frac / n[j])[:, None] * seg[j]

    def reach_along(
        self, along: np.ndarray, across: np.ndarray, lo_mm: float, hi_mm: float
    ) -> tuple[float, float] | None:
        """(min, max) of the plate's coordinate along ``along`` (2,) within the strip ``lo_mm`` <=
        coordinate along ``across`` (2,) <= ``hi_mm``; None without an outline or when the strip
        misses the plate. For a convex outline the extremes lie on the outline."""
        pts = self._dense_outline
        if pts is None:
            return None
        c = pts @ across
        a = pts[(c >= lo_mm) & (c <= hi_mm)] @ along
        if a.size == 0:
            return None
        return float(a.min()), float(a.max())

    def on_plate(self, cx_mm: np.ndarray, cy_mm: np.ndarray) -> np.ndarray:
        """(nx, ny) bool: the grid points ``cx_mm`` (nx,) x ``cy_mm`` (ny,) over the plate: inside the
        outline (even-odd rule) and not over a hole of the sampled surface (a hole is where the
        vertical rays missed the mesh over at least two grid steps)."""
        X, Y = np.meshgrid(cx_mm, cy_mm, indexing="ij")
        holes = binary_erosion(~self.valid, border_value=0)
        ix = np.clip(np.rint((X - self.xs_mm[0]) / (self.xs_mm[1] - self.xs_mm[0])), 0, len(self.xs_mm) - 1)
        iy = np.clip(np.rint((Y - self.ys_mm[0]) / (self.ys_mm[1] - self.ys_mm[0])), 0, len(self.ys_mm) - 1)
        solid = ~holes[ix.astype(int), iy.astype(int)]
        if self.outline_xy is None:
            return solid & self.inside(X.ravel(), Y.ravel()).reshape(X.shape)
        p0 = self.outline_xy
        p1 = np.roll(p0, -1, axis=0)
        inside = np.zeros(X.shape, dtype=bool)
        for i, x in enumerate(np.asarray(cx_mm, dtype=np.float64)):
            cross = (p0[:, 0] <= x) != (p1[:, 0] <= x)
            if not cross.any():
                continue
            a, b = p0[cross], p1[cross]
            y_cross = np.sort(a[:, 1] + (x - a[:, 0]) * (b[:, 1] - a[:, 1]) / (b[:, 0] - a[:, 0]))
            inside[i] = np.searchsorted(y_cross, cy_mm) % 2 == 1
        return inside & solid


def _fill_outside(xs: np.ndarray, ys: np.ndarray, Z: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Heights ``Z`` (nx, ny) with the cells not ``valid`` filled: quadric fit + nearest residual."""
    X, Y = np.meshgrid((xs - xs.mean()) / np.ptp(xs), (ys - ys.mean()) / np.ptp(ys), indexing="ij")
    A = np.stack([np.ones_like(X), X, Y, X * X, X * Y, Y * Y], axis=-1)
    coef, *_ = np.linalg.lstsq(A[valid], Z[valid], rcond=None)
    base = A @ coef
    _, (ix, iy) = distance_transform_edt(~valid, return_indices=True)
    residual = (Z - base)[ix, iy]
    return np.where(valid, Z, base + residual)


def design_surface(design: TriMesh) -> DesignSurface:
    """Fit a :class:`DesignSurface` to a design mesh (top surface, plate frame, mm).

    Raises:
        PlanInputError: an empty or degenerate mesh, or one that is not a surface seen from above.
    """
    v = design.vertices_mm
    if v.shape[0] < 3 or design.triangles.shape[0] < 1:
        raise PlanInputError("design: the mesh has no triangles")
    lo, hi = v.min(axis=0), v.max(axis=0)
    ext = hi - lo
    if ext[0] < 10 or ext[1] < 10:
        raise PlanInputError(f"design: footprint {ext[0]:.1f} x {ext[1]:.1f} mm is too small to plan a scan")
    if ext[0] > 50_000 or ext[1] > 50_000:
        raise PlanInputError(f"design: footprint {ext[0]:.0f} x {ext[1]:.0f} mm is not a plate in mm")
    nx = int(np.clip(np.ceil(ext[0] / _GRID_PITCH_MM) + 1, 8, 600))
    ny = int(np.clip(np.ceil(ext[1] / _GRID_PITCH_MM) + 1, 8, 600))
    # sample just inside the bounds so the rays along the border still hit the mesh
    eps = 1e-3 * ext[:2]
    xs = np.linspace(lo[0] + eps[0], hi[0] - eps[0], nx)
    ys = np.linspace(lo[1] + eps[1], hi[1] - eps[1], ny)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    rays = np.zeros((X.size, 6), dtype=np.float32)
    rays[:, 0], rays[:, 1], rays[:, 2], rays[:, 5] = X.ravel(), Y.ravel(), hi[2] + 100.0, -1.0
    hit = _raycasting_scene(design).cast_rays(o3d.core.Tensor(rays))
    t = hit["t_hit"].numpy().reshape(nx, ny).astype(np.float64)
    valid = np.isfinite(t)
    if valid.mean() < 0.5:
        raise PlanInputError(
            f"design: only {valid.mean():.0%} of the footprint is hit from above; expected a plate's top surface"
        )
    Z = hi[2] + 100.0 - np.where(valid, t, 0.0)
    if not valid.all():
        # holes and a non-rectangular outline: continue the surface over the empty cells of the bounds
        # along the least-squares quadric through it, shifted by the nearest sample's residual, so the
        # fill meets the surface without a step and the spline (and the normals near the outline's
        # corners) stays smooth
        Z = _fill_outside(xs, ys, Z, valid)
    spline = RectBivariateSpline(xs, ys, Z, kx=3, ky=3)
    outline = outline_in_plan(design)
    if outline is None:
        log.warning(
            "design_outline_missing", note="no four-cornered open boundary; edge passes follow the bounds"
        )
    outline_xy, corner_index = outline if outline is not None else (None, None)
    return DesignSurface(
        float(lo[0]),
        float(hi[0]),
        float(lo[1]),
        float(hi[1]),
        xs,
        ys,
        valid,
        spline,
        outline_xy,
        corner_index,
    )


def placement_margin_mm(surface: DesignSurface, settings: PlannerSettings) -> float:
    """How far beyond the nominal footprint the passes must reach: the placement shift plus the
    displacement of the farthest corner under the rotation uncertainty."""
    L, W = surface.size_mm
    half_diag = 0.5 * float(np.hypot(L, W))
    return settings.placement_uncertainty_mm + half_diag * float(
        np.sin(np.deg2rad(settings.placement_uncertainty_deg))
    )


def _outline_drift_mm(surface: DesignSurface, settings: PlannerSettings) -> float:
    """The farthest any point of the outline moves at a corner of the placement uncertainty (the
    shift in x and y at once, the rotation about the plate frame's origin)."""
    pts = (
        np.array([e.a for e in surface.outline_edges()]) if surface.outline_xy is None else surface.outline_xy
    )
    r = float(np.max(np.linalg.norm(pts, axis=1)))
    du = settings.placement_uncertainty_mm
    return float(np.hypot(du, du)) + 2.0 * r * float(
        np.sin(np.deg2rad(settings.placement_uncertainty_deg) / 2)
    )


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _sensor_frames(
    surface: DesignSurface,
    xy: np.ndarray,
    travel_xy: np.ndarray,
    sign: float,
    standoff_mm: float,
    outward_xy: np.ndarray | None = None,
    tilt_deg: float = 0.0,
    pitch_deg: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Sensor poses looking at surface points ``xy`` (n, 2) plate frame; ``travel_xy`` and
    ``outward_xy`` are (2,) or one per point (n, 2).

    Returns ``(pos_mm (n, 3), R_plate_sensor (n, 3, 3), surface_pt_mm (n, 3), normal (n, 3))``: the
    sensor z axis along minus the normal (tilted ``tilt_deg`` towards ``-outward`` for edge passes),
    the sensor y axis along ``sign * travel`` and the laser line (x) across it; ``pitch_deg`` leans
    the sensor's view about its line towards ``+travel`` (the line stays where it was).
    """
    h, gx, gy = surface.height_and_gradient(xy[:, 0], xy[:, 1])
    n = _unit(np.column_stack([-gx, -gy, np.ones_like(gx)]))
    pts = np.column_stack([xy, h])
    z = -n
    if outward_xy is not None and tilt_deg > 0:
        o = np.zeros_like(n)
        o[:, :2] = outward_xy
        o = _unit(o - np.sum(o * n, axis=1, keepdims=True) * n)
        a = np.deg2rad(tilt_deg)
        # looking in from outside and above, so the vertical thickness face is lit
        z = _unit(-n * np.cos(a) - o * np.sin(a))
    t3 = np.zeros_like(z)
    t3[:, :2] = travel_xy
    y = _unit(t3 - np.sum(t3 * z, axis=1, keepdims=True) * z)
    if pitch_deg > 0:
        b = np.deg2rad(pitch_deg)
        z, y = z * np.cos(b) + y * np.sin(b), y * np.cos(b) - z * np.sin(b)
    y = sign * y
    x = np.cross(y, z)
    R = np.stack([x, y, z], axis=2)
    return pts - standoff_mm * z, R, pts, n


def _check_depth(
    surface: DesignSurface,
    labels: list[str],
    poss: list[np.ndarray],
    Rs: list[np.ndarray],
    settings: PlannerSettings,
    margin_mm: float,
) -> None:
    """Refuse when the laser line, at any waypoint of the passes ``labels`` (their plate-frame poses
    ``poss`` (n_i, 3), ``Rs`` (n_i, 3, 3)), would leave the depth range on the curved surface (the
    placement uncertainty moves the surface under the line by up to |gradient| x margin); the
    refusal names the first such pass in order and its first such waypoint."""
    pos, R = np.concatenate(poss), np.concatenate(Rs)
    u = np.linspace(-settings.line_width_mm / 2, settings.line_width_mm / 2, _DEPTH_SAMPLES)
    x_s, z_s = R[:, :, 0], R[:, :, 2]
    # points of the laser line in the standoff plane, (n, k, 3)
    line = pos[:, None, :] + settings.standoff_mm * z_s[:, None, :] + u[None, :, None] * x_s[:, None, :]
    lx, ly = line[..., 0].ravel(), line[..., 1].ravel()
    h, gx, gy = surface.height_and_gradient(lx, ly)
    on_plate = surface.inside(lx, ly).reshape(line.shape[:2])
    surf = np.stack([lx, ly, h], axis=1).reshape(line.shape)
    depth = np.einsum("nkj,nj->nk", surf - pos[:, None, :], z_s)
    spread = (np.hypot(gx, gy) * margin_mm).reshape(line.shape[:2])
    too_near = on_plate & (depth - spread < settings.depth_min_mm)
    too_far = on_plate & (depth + spread > settings.depth_max_mm)
    bad = too_near | too_far
    if bad.any():
        n, k = np.argwhere(bad)[0]
        starts = np.cumsum([0] + [len(p) for p in poss])
        j = int(np.searchsorted(starts, n, side="right") - 1)
        raise PlanRefused(
            f"the laser line would leave the depth range: predicted depth {depth[n, k]:.1f} +/- "
            f"{spread[n, k]:.1f} mm at {u[k]:+.1f} mm along the line",
            pass_label=labels[j],
            point_index=int(n - starts[j]),
            limit=f"depth range [{settings.depth_min_mm}, {settings.depth_max_mm}] mm",
        )


def _samples(a: float, b: float, step: float) -> np.ndarray:
    n = max(2, int(np.ceil(abs(b - a) / step)) + 1)
    return np.linspace(a, b, n)


def _link(
    surface: DesignSurface,
    label: str,
    kind: str,
    p0: np.ndarray,
    R0: np.ndarray,
    p1: np.ndarray,
    R1: np.ndarray,
    settings: PlannerSettings,
    lift_mm: float,
) -> Segment:
    """A smooth hump from pose 0 to pose 1 (plate frame): straight chord plus ``lift * sin(pi u)`` up,
    raised further where the chord would come closer to the surface than the standoff."""
    dist = float(np.linalg.norm(p1 - p0))
    rot = rotation_angle_deg(R0, R1)
    # denser than the passes: the spline through the joint waypoints must follow the smooth hump
    step = 0.5 * settings.waypoint_step_mm
    n = max(8, int(np.ceil(dist / step)), int(np.ceil(rot / _LINK_MAX_ROT_STEP_DEG))) + 1
    u = np.linspace(0.0, 1.0, n)
    chord = p0[None] + u[:, None] * (p1 - p0)[None]
    h, _, _ = surface.height_and_gradient(chord[:, 0], chord[:, 1])
    shortfall = h + settings.standoff_mm - chord[:, 2]
    bump = np.sin(np.pi * u)
    inner = bump > 0.2
    extra = float(np.max(np.where(inner, shortfall / np.where(inner, bump, 1.0), 0.0)))
    # short links (neighbouring passes) need little lift: a tall hump over a short chord is a tight
    # curve the arm must take slowly
    lift = min(lift_mm, 0.25 * dist) + max(0.0, extra)
    pos = chord.copy()
    pos[:, 2] += lift * bump
    return Segment(kind=kind, label=label, pos_mm=pos, R_base_sensor=slerp_frames(R0, R1, u))


#: a turnaround's tangents at its ends, as a multiple of the distance between them (the quintic's
#: loop, used where the two passes' ends are not side by side: larger is rounder and longer, smaller
#: tighter and slower)
_TURN_TANGENT_FACTOR = 2.0
#: waypoints of a turnaround: its tight curve needs them closer than the passes'
_TURN_STEP_MM = 3.0
#: which pass-to-pass links are flown at speed: (kind before, kind after)
_FLY = {("scan", "scan"): True, ("scan", "edge"): True}
#: a link that turns the sensor at least this much (deg) is not flown: it goes at rest at both ends,
#: as a line in joint space where that is faster (:func:`~cellctl.planning.planner.joint_space_links`;
#: the wrist then turns at its own pace, where a flown link would turn it at the pace of its curve)
JOINT_LINK_MIN_TURN_DEG = 10.0
#: a turnaround may come this much closer to the (extrapolated) surface than the standoff
_TURN_CLEARANCE_TOL_MM = 5.0
#: the U-turn between neighbouring raster passes, in units of the pass step: it runs out
#: ``_UTURN_OUT * (sin(pi t) + _UTURN_OUT_3 * sin(3 pi t))`` beyond the pass end and across
#: ``h(t) + _UTURN_ACROSS_2 * 16 sin(2 pi t) t^2 (1 - t)^2`` (``h`` the quintic smooth step), for t in
#: [0, 1]. The joints' jerk in the reversal along the pass bounds a turnaround's speed, not its
#: length; these coefficients gave the sail's plan its shortest time, searched on the real plan with
#: its timing (docs/operations.md, "Planning the scan": 0.36-0.37 s a turnaround where the quintic
#: loop took 0.36-0.44 s)
_UTURN_OUT = 0.695
_UTURN_OUT_3 = 0.014
_UTURN_ACROSS_2 = 0.04
#: the U-turn is used where the next pass runs back within this angle of the previous one, with its
#: start at most this share of the pass step ahead of or behind the previous pass's end (else the
#: quintic loop)
_UTURN_MAX_ANGLE_DEG = 10.0
_UTURN_MAX_STAGGER = 0.5


def _uturn_unit(n: int = 4001) -> tuple[np.ndarray, np.ndarray]:
    """The U-turn for a unit pass step: ``(u, xy)``, ``xy`` (n, 2) from (0, 0) heading +x to (0, 1)
    heading -x, at the fractions ``u`` (n,) of its arc length (uniform over [0, 1])."""
    t = np.linspace(0.0, 1.0, n)
    x = _UTURN_OUT * (np.sin(np.pi * t) + _UTURN_OUT_3 * np.sin(3 * np.pi * t))
    y = 10 * t**3 - 15 * t**4 + 6 * t**5 + _UTURN_ACROSS_2 * 16 * np.sin(2 * np.pi * t) * (t * (1 - t)) ** 2
    s = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(x), np.diff(y)))])
    u = np.linspace(0.0, 1.0, n)
    return u, np.column_stack([np.interp(u * s[-1], s, x), np.interp(u * s[-1], s, y)])


_UTURN = _uturn_unit()
_UTURN_LENGTH = float(np.sum(np.linalg.norm(np.diff(_UTURN[1], axis=0), axis=1)))


def _turn_path(p0: np.ndarray, t0: np.ndarray, p1: np.ndarray, t1: np.ndarray, step_mm: float) -> np.ndarray:
    """The turnaround's positions (n, 3), waypoints about ``step_mm`` apart, from ``p0`` leaving along
    ``t0`` to ``p1`` arriving along ``t1`` (unit vectors): the U-turn (:data:`_UTURN_OUT`) where the
    passes lie side by side and run opposite ways, else the quintic Hermite loop. Both meet the
    passes with their direction and zero curvature, so the joint path stays continuous in speed and
    acceleration across the joins."""
    chord = p1 - p0
    ahead = float(chord @ t0)
    side = chord - ahead * t0
    across = float(np.linalg.norm(side))
    opposite = float(t0 @ t1) <= -np.cos(np.radians(_UTURN_MAX_ANGLE_DEG))
    if opposite and across > 1e-6 and abs(ahead) <= _UTURN_MAX_STAGGER * across:
        length = _UTURN_LENGTH * across
        u = np.linspace(0.0, 1.0, max(16, int(np.ceil(length / step_mm))) + 1)
        xy = np.column_stack([np.interp(u, _UTURN[0], _UTURN[1][:, k]) for k in range(2)]) * across
        pos = p0[None] + xy[:, :1] * t0[None] + xy[:, 1:] * (side / across)[None]
        # what the planar U-turn leaves out (one end ahead of the other, the next pass not quite
        # parallel) is blended in by terms that keep both ends' position, direction and zero curvature
        u = u[:, None]
        h01 = 10 * u**3 - 15 * u**4 + 6 * u**5
        h11 = -4 * u**3 + 7 * u**4 - 3 * u**5
        return pos + h01 * (p1 - pos[-1])[None] + h11 * (length * (t1 + t0))[None]
    m = _TURN_TANGENT_FACTOR * float(np.linalg.norm(chord))
    u = np.linspace(0.0, 1.0, max(16, int(np.ceil(2.0 * m / step_mm))) + 1)[:, None]
    # quintic Hermite basis with zero second derivatives at both ends
    h00 = 1 - 10 * u**3 + 15 * u**4 - 6 * u**5
    h10 = u - 6 * u**3 + 8 * u**4 - 3 * u**5
    h01 = 10 * u**3 - 15 * u**4 + 6 * u**5
    h11 = -4 * u**3 + 7 * u**4 - 3 * u**5
    return h00 * p0[None] + h10 * (m * t0)[None] + h01 * p1[None] + h11 * (m * t1)[None]


def _turnaround(
    surface: DesignSurface,
    label: str,
    p0: np.ndarray,
    R0: np.ndarray,
    t0: np.ndarray,
    p1: np.ndarray,
    R1: np.ndarray,
    t1: np.ndarray,
    settings: PlannerSettings,
) -> Segment | None:
    """A turnaround flown at speed from one pass's end to the next pass's start (plate frame), or
    None where it would not keep its clearance (the caller then links them by a hump).

    The path (:func:`_turn_path`) meets each pass with its position and direction of travel
    (``t0``, ``t1``, unit) and zero curvature, so the curvature grows smoothly from the straight
    pass and the joint path is continuous in speed and acceleration across the joins
    (:func:`~cellctl.planning.timing.time_segments` times the passes and the turnaround as one
    path). It turns outside the pass ends, beyond the plate: the speed never drops to zero there.
    The sensor turns on a smooth-step geodesic from ``R0`` to ``R1`` (no angular speed at the joins).
    """
    if float(np.linalg.norm(p1 - p0)) < 1e-6:
        return None
    pos = _turn_path(p0, t0, p1, t1, _TURN_STEP_MM)
    h, _, _ = surface.height_and_gradient(pos[:, 0], pos[:, 1])
    # no lower above the (extrapolated) surface than at the lower of its two ends
    clearance = float(min(pos[0, 2] - h[0], pos[-1, 2] - h[-1]))
    if float(np.max(h + clearance - pos[:, 2])) > _TURN_CLEARANCE_TOL_MM:
        return None
    w = np.linspace(0.0, 1.0, len(pos))
    smooth = w**3 * (10 - 15 * w + 6 * w**2)
    return Segment(
        kind="link", label=label, pos_mm=pos, R_base_sensor=slerp_frames(R0, R1, smooth), flying=True
    )


#: the sensor's x and y columns negated: its frame looking the other way round along a pass
_FLIP_XY = np.array([-1.0, -1.0, 1.0])


def _line_symmetric(settings: PlannerSettings) -> bool:
    """The depth check's points along the line are symmetric about its middle (then a pass and the
    same pass the other way round check the same points)."""
    u = np.linspace(-settings.line_width_mm / 2, settings.line_width_mm / 2, _DEPTH_SAMPLES)
    return bool(np.array_equal(u, -u[::-1]))


def _start_segments(sweeps: list[tuple], settings: PlannerSettings) -> list[Segment]:
    """The approach along the first pass's view axis and the first pass (plate frame)."""
    kind, label, pos, R = sweeps[0]
    p0, R0 = pos[0], R[0]
    up0 = -R0[:, 2]
    s = np.linspace(
        settings.approach_mm, 0.0, max(3, int(np.ceil(settings.approach_mm / settings.waypoint_step_mm)) + 1)
    )
    approach = Segment(
        "approach", "approach", p0[None] + s[:, None] * up0[None], np.broadcast_to(R0, (s.size, 3, 3)).copy()
    )
    return [approach, Segment(kind, label, pos, R)]


def _join_sweeps(
    surface: DesignSurface,
    settings: PlannerSettings,
    segments: list[Segment],
    sweeps: list[tuple],
    n_link: int,
) -> int:
    """Append ``sweeps`` (kind, label, pos, R; plate frame) to ``segments``, each after a link from
    the segment before it (a flown turnaround where one fits, else a hump); links are numbered on
    from ``n_link``. Returns the last link's number."""
    for kind, label, pos, R in sweeps:
        n_link += 1
        prev = segments[-1]
        turn = None
        if (
            prev.is_sweep
            and settings.flying_turns
            and _FLY.get((prev.kind, kind), False)
            and rotation_angle_deg(prev.R_base_sensor[-1], R[0]) < JOINT_LINK_MIN_TURN_DEG
        ):
            turn = _turnaround(
                surface, f"link {n_link}", prev.pos_mm[-1], prev.R_base_sensor[-1],
                _unit(prev.pos_mm[-1] - prev.pos_mm[-2]), pos[0], R[0], _unit(pos[1] - pos[0]),
                settings,
            )  # fmt: skip
        if turn is None:
            turn = _link(
                surface, f"link {n_link}", "link", prev.pos_mm[-1], prev.R_base_sensor[-1], pos[0], R[0],
                settings, settings.link_clearance_mm,
            )  # fmt: skip
        segments.append(turn)
        segments.append(Segment(kind, label, pos, R))
    return n_link


def build_segments(
    surface: DesignSurface,
    placement: Placement,
    settings: PlannerSettings,
    *,
    sign: float = 1.0,
    edge_tilts_deg: Mapping[str, float] | None = None,
    edge_reverse: bool = False,
    raster_cache: dict | None = None,
    axis: str = "longer",
) -> tuple[list[Segment], float]:
    """The ordered segments of a scan (base frame) and the placement margin used (mm).

    Order: approach, raster passes (serpentine) with links, links to and along the four edge passes
    (nearest edge first, around the plate), retract. ``sign`` (+1 / -1) picks which way the sensor's
    y axis points along the raster passes; the joint path tries both. ``edge_tilts_deg``: the tilt
    of some edge passes by label (``"edge 2"``) where it differs from ``settings.edge_tilt_deg``
    (the planner lowers it on an edge the arm cannot reach at the full tilt; the edge passes' order
    does not depend on their tilts). The edge passes go round the plate the way whose first edge
    starts nearest the last raster pass's end; ``edge_reverse`` goes round the other way (the
    sensor's heading then turns the other way, and so do the wrist's joints 4 and 6).
    ``raster_cache``: a dict the caller keeps across calls with the same surface and settings; the
    raster passes (plate frame, which depend on neither the placement, the edge tilts nor the edge
    order) are then computed once per ``sign``. ``axis``: the raster passes run along the
    footprint's ``"longer"`` axis (x when the two are equal) or its ``"shorter"`` one (the planner
    tries both when ``settings.pass_axis`` is ``"fastest"``).

    Raises:
        PlanRefused: the line would leave the depth range somewhere.
    """
    margin = placement_margin_mm(surface, settings)
    L, W = surface.size_mm
    if axis not in PASS_AXES:
        raise PlanInputError(f"axis: {axis!r} is not one of {PASS_AXES}")
    along_x = (L >= W) == (axis == "longer")
    a2 = np.array([1.0, 0.0]) if along_x else np.array([0.0, 1.0])
    c2 = np.array([0.0, 1.0]) if along_x else np.array([1.0, 0.0])
    lo_a, hi_a = (surface.x_min_mm, surface.x_max_mm) if along_x else (surface.y_min_mm, surface.y_max_mm)
    lo_c, hi_c = (surface.y_min_mm, surface.y_max_mm) if along_x else (surface.x_min_mm, surface.x_max_mm)
    width = hi_c - lo_c + 2 * margin
    w = settings.line_width_mm
    n_pass = 1 if width <= w else int(np.ceil((width - w) / settings.pass_step_mm)) + 1
    first, last = lo_c - margin + w / 2, hi_c + margin - w / 2
    centres = np.array([0.5 * (lo_c + hi_c)]) if n_pass == 1 else np.linspace(first, last, n_pass)
    # the serpentine's start: the first pass's direction and the side the passes start from
    reversed_first = settings.passes_reversed
    if settings.start_corner is not None:
        sx, sy = settings.start_corner
        reversed_first = (sx if along_x else sy) > 0
        if (sy if along_x else sx) > 0:
            centres = centres[::-1]

    # (kind, label, pos, R) plate frame; the raster passes from the caller's cache when it has them
    sweeps: list[tuple[str, str, np.ndarray, np.ndarray]] = list((raster_cache or {}).get(sign, ()))
    mirrored = (raster_cache or {}).get(-sign)
    if not sweeps and mirrored is not None and _line_symmetric(settings):
        # the other way round: the same positions and view axes, the sensor's x and y reversed
        # (``sign`` enters only there), so the same depth check passed: the same numbers, negated
        sweeps = [(k, lab, pos, R * _FLIP_XY) for k, lab, pos, R in mirrored]
    # how far any plate point can move at a corner of the uncertainty box (shift in x and y at once)
    drift = _outline_drift_mm(surface, settings)
    pass_xy = []
    for i, c in enumerate(() if sweeps else centres):
        # the pass reaches as far as the plate does inside the strip it may see under the uncertainty,
        # never beyond the footprint's bounds plus the margin (a rectangle keeps its passes)
        reach = surface.reach_along(a2, c2, c - w / 2 - drift, c + w / 2 + drift)
        lo_i, hi_i = lo_a - margin, hi_a + margin
        if reach is not None:
            lo_i, hi_i = max(lo_i, reach[0] - drift), min(hi_i, reach[1] + drift)
        a0, a1 = (lo_i, hi_i) if (i + reversed_first) % 2 == 0 else (hi_i, lo_i)
        s = _samples(a0, a1, settings.waypoint_step_mm)
        pass_xy.append(s[:, None] * a2[None] + c * c2[None])
    if pass_xy:
        # every pass's frames and depth check at once (the surface's evaluation costs per call)
        pos, R, _, _ = _sensor_frames(
            surface,
            np.concatenate(pass_xy),
            a2,
            sign,
            settings.standoff_mm,
            pitch_deg=settings.sweep_pitch_deg,
        )
        cut = np.cumsum([len(xy) for xy in pass_xy])[:-1]
        labels = [f"scan {i + 1}" for i in range(len(pass_xy))]
        _check_depth(surface, labels, np.split(pos, cut), np.split(R, cut), settings, margin)
        sweeps.extend(
            ("scan", lab, p, r)
            for lab, p, r in zip(labels, np.split(pos, cut), np.split(R, cut), strict=True)
        )
    if raster_cache is not None:
        raster_cache.setdefault(sign, tuple(sweeps))

    if settings.edge_passes:
        edges = surface.outline_edges()
        run = settings.placement_uncertainty_mm + w / 2
        paths = {
            (e, ccw): edges[e].path(run, settings.waypoint_step_mm, forward=ccw)
            for e in range(4)
            for ccw in (True, False)
        }
        end_xy = sweeps[-1][2][-1, :2]
        best = None
        best_way: dict[bool, tuple[float, list[int]]] = {}  # per way round: the order from its nearest start
        for start in range(4):
            for ccw in (True, False):
                order = [(start + k) % 4 for k in range(4)] if ccw else [(start - k) % 4 for k in range(4)]
                dist = float(np.linalg.norm(paths[(order[0], ccw)][0][0] - end_xy))
                if best is None or dist < best[0]:
                    best = (dist, order, ccw)
                if ccw not in best_way or dist < best_way[ccw][0]:
                    best_way[ccw] = (dist, order)
        _, order, ccw = best
        if edge_reverse:
            ccw = not ccw
            order = best_way[ccw][1]
        prev_x = sweeps[-1][3][-1, :, 0]
        for k, e in enumerate(order):
            xy, travel, outward = paths[(e, ccw)]
            # the sensor's line direction is kept as close as possible to the previous pass's (less wrist roll)
            options = [
                _sensor_frames(
                    surface,
                    xy,
                    travel,
                    sg,
                    settings.standoff_mm,
                    outward,
                    (edge_tilts_deg or {}).get(f"edge {k + 1}", settings.edge_tilt_deg),
                    settings.sweep_pitch_deg,
                )
                for sg in (1.0, -1.0)
            ]
            pos, R, _, _ = max(options, key=lambda o: float(o[1][0, :, 0] @ prev_x))
            prev_x = R[-1, :, 0]
            sweeps.append(("edge", f"edge {k + 1}", pos, R))

    # the approach, the raster passes and the links between them depend on the raster passes alone:
    # kept in the caller's cache (fresh Segment objects each call: the caller moves and solves them)
    n_raster = len(sweeps) - sum(1 for k, *_ in sweeps if k == "edge")
    head = (raster_cache or {}).get(("head", sign))
    if head is not None:
        segments = [replace(seg) for seg in head]
        n_link = sum(1 for seg in head if seg.kind == "link")
        _join_sweeps(surface, settings, segments, sweeps[n_raster:], n_link)
    else:
        segments = _start_segments(sweeps, settings)
        n_link = _join_sweeps(surface, settings, segments, sweeps[1:n_raster], 0)
        if raster_cache is not None:
            raster_cache[("head", sign)] = tuple(replace(seg) for seg in segments)
        _join_sweeps(surface, settings, segments, sweeps[n_raster:], n_link)
    pe, Re = segments[-1].pos_mm[-1], segments[-1].R_base_sensor[-1]
    upe = -Re[:, 2]
    s = np.linspace(
        0.0, settings.approach_mm, max(3, int(np.ceil(settings.approach_mm / settings.waypoint_step_mm)) + 1)
    )
    segments.append(
        Segment(
            "retract",
            "retract",
            pe[None] + s[:, None] * upe[None],
            np.broadcast_to(Re, (s.size, 3, 3)).copy(),
        )
    )

    # plate frame -> base frame
    T = placement_transform(placement)
    for seg in segments:
        seg.pos_mm = seg.pos_mm @ T[:3, :3].T + T[:3, 3]
        seg.R_base_sensor = T[:3, :3][None] @ seg.R_base_sensor
    return segments, margin


def _resample_sweep(seg: Segment, step_mm: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sensor poses every ``step_mm`` along a sweep: (m, 3) positions, (m, 3) line dirs, (m, 3) view dirs."""
    d = np.linalg.norm(np.diff(seg.pos_mm, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(d)])
    if s[-1] <= 0:
        return seg.pos_mm[:1], seg.R_base_sensor[:1, :, 0], seg.R_base_sensor[:1, :, 2]
    q = np.linspace(0.0, s[-1], max(2, int(np.ceil(s[-1] / step_mm)) + 1))
    pos = np.column_stack([np.interp(q, s, seg.pos_mm[:, k]) for k in range(3)])
    x = _unit(np.column_stack([np.interp(q, s, seg.R_base_sensor[:, k, 0]) for k in range(3)]))
    z = _unit(np.column_stack([np.interp(q, s, seg.R_base_sensor[:, k, 2]) for k in range(3)]))
    return pos, x, z


def _sensor_poses(
    segments: list[Segment], settings: PlannerSettings
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The simulated profiles' sensor poses (base frame) along every sweep, one every
    ``coverage_profile_step_mm``: ``(origins (m, 3), line directions (m, 3), view axes (m, 3))``."""
    sweeps = [s for s in segments if s.is_sweep]
    if not sweeps:
        raise PlanInputError("segments: no sweep to predict coverage from")
    parts = [_resample_sweep(s, settings.coverage_profile_step_mm) for s in sweeps]
    return tuple(np.concatenate([p[k] for p in parts]) for k in range(3))  # type: ignore[return-value]


def _fan_rays(
    pos: np.ndarray, x: np.ndarray, z: np.ndarray, settings: PlannerSettings
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The laser fans of the sensor poses ``pos``, ``x``, ``z`` (m, 3): ``(origins (r, 3), unit
    directions (r, 3), the view axis per ray (r, 3))``, ``coverage_rays`` rays per pose as wide as
    the line at the standoff."""
    u = np.linspace(-settings.line_width_mm / 2, settings.line_width_mm / 2, settings.coverage_rays)
    dirs = _unit(settings.standoff_mm * z[:, None, :] + u[None, :, None] * x[:, None, :]).reshape(-1, 3)
    return np.repeat(pos, u.size, axis=0), dirs, np.repeat(z, u.size, axis=0)


def _laser_fans(
    segments: list[Segment], settings: PlannerSettings
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """The simulated profiles' rays (base frame): ``(origins (r, 3), unit directions (r, 3), the
    sensor's view axis per ray (r, 3), profiles)``; one fan of ``coverage_rays`` rays as wide as the
    line at the standoff every ``coverage_profile_step_mm`` along each sweep."""
    pos, x, z = _sensor_poses(segments, settings)
    return (*_fan_rays(pos, x, z, settings), int(pos.shape[0]))


def _ray_tensor(origins: np.ndarray, dirs: np.ndarray) -> o3d.core.Tensor:
    """(r, 6) float32 rays for open3d's ray casting (written straight into float32: no (r, 6)
    float64 copy on the way; the values are those of ``np.hstack(...).astype(np.float32)``)."""
    out = np.empty((origins.shape[0], 6), dtype=np.float32)
    out[:, :3] = origins
    out[:, 3:] = dirs
    return o3d.core.Tensor(out)


def _uncertainty_corners(placement: Placement, settings: PlannerSettings) -> list[Placement]:
    """The placement moved to the four corners of its uncertainty (shift and rotation)."""
    du, dd = settings.placement_uncertainty_mm, settings.placement_uncertainty_deg
    if not (du > 0 or dd > 0):
        return []
    return [
        Placement.on_bed(
            placement.x_mm + sx * du,
            placement.y_mm + sy * du,
            placement.yaw_deg + sa * dd,
            z_mm=placement.z_mm,
        )
        for sx, sy, sa in ((1, 1, 1), (-1, -1, -1), (1, -1, -1), (-1, 1, 1))
    ]


#: a ray's stretch between the depth limits is widened this much (mm) before the cells it spans are
#: looked up: the ray is cast in float32 and its line direction is interpolated
_CULL_PAD_MM = 0.5


def predict_coverage(
    segments: list[Segment],
    design: TriMesh,
    surface: DesignSurface,
    placement: Placement,
    settings: PlannerSettings,
) -> CoverageReport:
    """Predicted coverage of the design's top surface by the sweeps (ray casting the laser fans).

    Every ``coverage_profile_step_mm`` along each sweep a fan of ``coverage_rays`` rays, as wide as the
    laser line at the standoff, is cast onto the placed design; returns inside the depth range and
    below ``max_incidence_deg`` count. The footprint is divided into square cells of
    ``coverage_cell_mm``; a cell of the plate (its centre inside the design's outline, not over a
    hole) is seen when it holds at least one return: the fraction is of the plate, not of its
    bounds. The same rays are cast against the plate moved to four corners of the placement
    uncertainty (shift and rotation) for ``worst_fraction``.

    A ray's counted return lies on the stretch of the ray between the depth limits, so a ray whose
    stretch spans only cells already seen (or off the plate) cannot change the figures: per
    placement every other ray of each fan is cast first, then only the others that could still add
    a cell (on the 6 m plate and the sail: none). The figures are those of casting every ray
    (``exhaustive=True``, tests/planning/test_planning_scale.py).
    """
    return _predict_coverage(segments, design, surface, placement, settings)


def _plate_xy(p: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The plate-frame x and y of base-frame points ``p`` (..., 3) for the placement ``T`` (4, 4)
    (``(p - t) @ R`` written out by columns: a matmul of (n, 3) by (3, 3) costs many times more)."""
    d0, d1, d2 = p[..., 0] - T[0, 3], p[..., 1] - T[1, 3], p[..., 2] - T[2, 3]
    return d0 * T[0, 0] + d1 * T[1, 0] + d2 * T[2, 0], d0 * T[0, 1] + d1 * T[1, 1] + d2 * T[2, 1]


#: the margin (deg) of the incidence shortcut in :func:`_predict_coverage`, beyond the float32 error
#: of open3d's normals (:func:`_steepest_facet_deg`)
_INCIDENCE_PAD_DEG = 0.05


def _steepest_facet_deg(design: TriMesh, reach_mm: float) -> float:
    """The largest angle (deg) between a facet's normal line and the vertical (90 for a degenerate
    facet, whose normal is not defined), plus a bound on the error of a normal computed from float32
    vertices (as open3d's ray casting does) that lie within ``reach_mm`` of the origin: a few float32
    roundings of the coordinates over the facet's smallest altitude."""
    v = design.vertices_mm[design.triangles]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    norm = np.linalg.norm(n, axis=1)
    if not design.triangles.shape[0] or not np.all(norm > 0):
        return 90.0
    cos_z = np.abs(n[:, 2]) / norm
    longest = np.max(np.linalg.norm(v - np.roll(v, 1, axis=1), axis=2), axis=1)
    altitude = float(np.min(norm / longest))  # twice the area over the longest side
    err_rad = 8.0 * float(np.finfo(np.float32).eps) * reach_mm / altitude
    return float(np.rad2deg(np.arccos(np.clip(cos_z.min(), 0.0, 1.0)) + err_rad))


def _plate_xy_columns(p: list[np.ndarray], T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_plate_xy` of points given as their three coordinate columns ``p`` (3 x (n,))."""
    d0, d1, d2 = p[0] - T[0, 3], p[1] - T[1, 3], p[2] - T[2, 3]
    return d0 * T[0, 0] + d1 * T[1, 0] + d2 * T[2, 0], d0 * T[0, 1] + d1 * T[1, 1] + d2 * T[2, 1]


@dataclass(frozen=True)
class _Rays:
    """Rays to cast, by coordinate columns (contiguous (r,) arrays, base frame): ``origins``,
    unit ``dirs``, ``depth_per_t`` (the depth along the sensor's view axis per unit of ray length),
    and the (r, 6) float32 ``tensor`` open3d casts."""

    origins: tuple[np.ndarray, np.ndarray, np.ndarray]
    dirs: tuple[np.ndarray, np.ndarray, np.ndarray]
    depth_per_t: np.ndarray
    tensor: o3d.core.Tensor

    @property
    def n(self) -> int:
        return int(self.depth_per_t.shape[0])

    @classmethod
    def of(cls, origins: np.ndarray, dirs: np.ndarray, zs: np.ndarray) -> _Rays:
        """From (r, 3) origins, unit directions and view axes."""
        return cls(
            tuple(np.ascontiguousarray(origins[:, k]) for k in range(3)),  # type: ignore[arg-type]
            tuple(np.ascontiguousarray(dirs[:, k]) for k in range(3)),  # type: ignore[arg-type]
            _dot(dirs, zs),
            _ray_tensor(origins, dirs),
        )


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot products of (n, 3) arrays."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def _predict_coverage(
    segments: list[Segment],
    design: TriMesh,
    surface: DesignSurface,
    placement: Placement,
    settings: PlannerSettings,
    *,
    exhaustive: bool = False,
) -> CoverageReport:
    """:func:`predict_coverage`; ``exhaustive``: cast every ray (the reference its culling keeps to)."""
    pos, x, z = _sensor_poses(segments, settings)
    m = int(pos.shape[0])
    cos_max = np.cos(np.deg2rad(settings.max_incidence_deg))

    cell = settings.coverage_cell_mm
    nx = max(1, int(np.ceil((surface.x_max_mm - surface.x_min_mm) / cell)))
    ny = max(1, int(np.ceil((surface.y_max_mm - surface.y_min_mm) / cell)))
    cx = surface.x_min_mm + (np.arange(nx) + 0.5) * (surface.x_max_mm - surface.x_min_mm) / nx
    cy = surface.y_min_mm + (np.arange(ny) + 0.5) * (surface.y_max_mm - surface.y_min_mm) / ny
    surface_cells = surface.on_plate(cx, cy)
    total = int(surface_cells.sum())
    if total == 0:
        raise PlanInputError("design: no footprint cell lies over the surface")

    u = np.linspace(-settings.line_width_mm / 2, settings.line_width_mm / 2, settings.coverage_rays)
    k_all = np.arange(u.size)
    k_first = k_all if exhaustive else k_all[::2]
    k_rest = k_all[:0] if exhaustive else k_all[1::2]

    def fan(ks: np.ndarray) -> np.ndarray:
        """(len(ks), m, 3) the unit directions of rays ``ks`` of every profile's fan."""
        v = settings.standoff_mm * z[None] + u[ks][:, None, None] * x[None]
        return v / np.sqrt(v[..., 0] ** 2 + v[..., 1] ** 2 + v[..., 2] ** 2)[..., None]

    def batch(origins: np.ndarray, dirs: np.ndarray, zs: np.ndarray) -> _Rays:
        """Rays to cast from ``origins`` along unit ``dirs`` (r, 3), the view axes ``zs`` (r, 3)."""
        return _Rays.of(origins, dirs, zs)

    # the first round's rays are the same for every placement: built once
    first = batch(np.tile(pos, (k_first.size, 1)), fan(k_first).reshape(-1, 3), np.tile(z, (k_first.size, 1)))
    dirs_rest = fan(k_rest)
    # a counted return of ray k of a profile lies at pos + depth (z + u_k / standoff x), the depth
    # in its range (to rounding: the stretch is widened by _CULL_PAD_MM)
    ends = [
        pos[None] + d * (z[None] + (u[k_rest] / settings.standoff_mm)[:, None, None] * x[None])
        for d in (settings.depth_min_mm, settings.depth_max_mm)
    ]

    def cell_index(lx: np.ndarray, ly: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ix = np.floor((lx - surface.x_min_mm) / (surface.x_max_mm - surface.x_min_mm) * nx)
        iy = np.floor((ly - surface.y_min_mm) / (surface.y_max_mm - surface.y_min_mm) * ny)
        return ix.astype(np.int64), iy.astype(np.int64)

    # a ray within (max_incidence - the design's steepest facet) of the vertical meets every facet
    # within max_incidence (the angles between lines obey the triangle inequality): its incidence
    # need not be looked at (on the plates planned so far: every ray)
    reach = float(np.abs(design.vertices_mm).max()) + float(
        np.linalg.norm(placement_transform(placement)[:3, 3])
    )
    steep_deg = _steepest_facet_deg(design, reach + 2.0 * _outline_drift_mm(surface, settings))
    cos_sure = np.cos(np.deg2rad(max(0.0, settings.max_incidence_deg - steep_deg - _INCIDENCE_PAD_DEG)))

    def cast(scene, T: np.ndarray, seen: np.ndarray, rays: _Rays) -> None:
        """Cast ``rays``; mark the cells their counted returns land in."""
        if rays.n == 0:
            return
        hit = scene.cast_rays(rays.tensor)
        # in range first (a miss is inf: never), on the rays' columns: the arithmetic of the (r, 3)
        # rows it replaces (the same numbers), without their strided copies of every ray
        t = hit["t_hit"].numpy().astype(np.float64)
        depth = t * rays.depth_per_t
        i = np.flatnonzero((depth >= settings.depth_min_mm) & (depth <= settings.depth_max_mm))
        up = T[:3, 2]  # the plate's normal line: base z for a placement lying flat
        if np.array_equal(up, [0.0, 0.0, 1.0]):
            cos_up = np.abs(rays.dirs[2][i])
        else:
            cos_up = np.abs(sum(c[i] * up[k] for k, c in enumerate(rays.dirs)))
        check = i[cos_up < cos_sure]
        if check.size:
            nrm = hit["primitive_normals"].numpy()[check].astype(np.float64)
            d = [c[check] for c in rays.dirs]
            steep = np.abs(nrm[:, 0] * d[0] + nrm[:, 1] * d[1] + nrm[:, 2] * d[2]) < cos_max
            if steep.any():
                i = np.setdiff1d(i, check[steep], assume_unique=True)
        t = t[i]
        p = [o[i] + t * c[i] for o, c in zip(rays.origins, rays.dirs, strict=True)]
        ix, iy = cell_index(*_plate_xy_columns(p, T))
        keep = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
        seen[ix[keep], iy[keep]] = True

    def fraction(pl: Placement) -> tuple[float, int]:
        T = placement_transform(pl)
        scene = _raycasting_scene(design.transformed(T))
        seen = np.zeros((nx, ny), dtype=bool)
        cast(scene, T, seen, first)
        need = surface_cells & ~seen
        if need.any() and k_rest.size:
            S = np.zeros((nx + 1, ny + 1), dtype=np.int64)
            S[1:, 1:] = need.cumsum(axis=0).cumsum(axis=1)

            def unseen_in(xs: list[np.ndarray], ys: list[np.ndarray]) -> np.ndarray:
                """Whether the box around points ``xs``, ``ys`` (plate frame) holds a cell still unseen."""
                ix0, iy0 = cell_index(
                    np.minimum.reduce(xs) - _CULL_PAD_MM, np.minimum.reduce(ys) - _CULL_PAD_MM
                )
                ix1, iy1 = cell_index(
                    np.maximum.reduce(xs) + _CULL_PAD_MM, np.maximum.reduce(ys) + _CULL_PAD_MM
                )
                on_grid = (ix1 >= 0) & (ix0 < nx) & (iy1 >= 0) & (iy0 < ny)
                ix0, ix1 = np.clip(ix0, 0, nx - 1), np.clip(ix1, 0, nx - 1)
                iy0, iy1 = np.clip(iy0, 0, ny - 1), np.clip(iy1, 0, ny - 1)
                return on_grid & (S[ix1 + 1, iy1 + 1] - S[ix0, iy1 + 1] - S[ix1 + 1, iy0] + S[ix0, iy0] > 0)

            # the profiles whose remaining rays' stretches can reach an unseen cell: every such stretch
            # lies in the quadrilateral of the outermost remaining rays' ends (the ends are affine in
            # the ray's offset along the line and in the depth), so in its box
            corners = [_plate_xy(e[j], T) for e in ends for j in (0, -1)]
            ii = np.flatnonzero(unseen_in([c[0] for c in corners], [c[1] for c in corners]))
            # of those, the rays whose own stretch spans a cell still unseen
            (ax, ay), (bx, by) = (_plate_xy(e[:, ii], T) for e in ends)
            kk, jj = np.nonzero(unseen_in([ax, bx], [ay, by]))
            ii = ii[jj]
            cast(scene, T, seen, batch(pos[ii], dirs_rest[kk, ii], z[ii]))
        n_seen = int((seen & surface_cells).sum())
        return n_seen / total, n_seen

    frac, n_seen = fraction(placement)
    worst = frac
    for moved in _uncertainty_corners(placement, settings):
        worst = min(worst, fraction(moved)[0])
    n_rays = m * u.size
    log.debug("coverage_predicted", fraction=frac, worst=worst, rays=n_rays)
    return CoverageReport(
        fraction=frac,
        worst_fraction=worst,
        cells_total=total,
        cells_seen=n_seen,
        cell_mm=cell,
        profiles=m,
        rays=n_rays,
    )


@dataclass(frozen=True)
class EdgeFaceCoverage:
    """Predicted coverage of the plate's thickness faces (the outline's four edge faces).

    fraction / worst_fraction: of the outline's length, in pieces of ``coverage_cell_mm``, whose face
    receives a valid return, at the nominal placement / the worst corner of the placement
    uncertainty. per_edge: the nominal fraction of each edge (edge k from corner k to k + 1).
    """

    fraction: float
    worst_fraction: float
    per_edge: tuple[float, float, float, float]
    pieces_total: int


def _edge_face_mesh(
    surface: DesignSurface, thickness_mm: float, piece_mm: float
) -> tuple[TriMesh, np.ndarray]:
    """The thickness face below the outline (plate frame) as a mesh of vertical quads, one per piece
    of ``piece_mm`` along each edge, and the edge (m,) of each piece (triangles j and j + m are piece j)."""
    tops, bottoms, owner = [], [], []
    for k, ed in enumerate(surface.outline_edges()):
        n_piece = max(1, int(np.ceil(ed.chord_mm / piece_mm)))
        xy, _, _ = ed.at(np.linspace(0.0, ed.chord_mm, n_piece + 1))
        h, _, _ = surface.height_and_gradient(xy[:, 0], xy[:, 1])
        top = np.column_stack([xy, h])
        tops.append(top[:-1])
        bottoms.append(top[1:])
        owner.extend([k] * n_piece)
    a = np.concatenate(tops)
    b = np.concatenate(bottoms)
    down = np.array([0.0, 0.0, thickness_mm])
    m = len(a)
    vertices = np.concatenate([a, b, b - down, a - down])
    i = np.arange(m)
    # outward-facing quads (a, a - t, b - t) and (a, b - t, b): the outline runs counter-clockwise
    triangles = np.concatenate(
        [np.column_stack([i, i + 3 * m, i + 2 * m]), np.column_stack([i, i + 2 * m, i + m])]
    )
    return TriMesh(vertices, triangles), np.asarray(owner, dtype=np.int64)


def predict_edge_face_coverage(
    segments: list[Segment],
    design: TriMesh,
    surface: DesignSurface,
    placement: Placement,
    settings: PlannerSettings,
    thickness_mm: float,
) -> EdgeFaceCoverage:
    """Predicted coverage of the thickness faces: the laser fans of every sweep (as in
    :func:`predict_coverage`) cast onto the design together with a vertical face ``thickness_mm``
    deep under its outline; a piece of the face is seen when a ray inside the depth range and below
    ``max_incidence_deg`` lands on it first (the top surface shadows what it hides)."""
    if not thickness_mm > 0:
        raise PlanInputError(f"thickness_mm: must be positive, got {thickness_mm!r}")
    origins, dirs, zrep, _ = _laser_fans(segments, settings)
    rays = _ray_tensor(origins, dirs)
    cos_max = np.cos(np.deg2rad(settings.max_incidence_deg))
    faces, owner = _edge_face_mesh(surface, thickness_mm, settings.coverage_cell_mm)
    n_top = design.triangles.shape[0]
    both = TriMesh(
        np.concatenate([design.vertices_mm, faces.vertices_mm]),
        np.concatenate([design.triangles, faces.triangles + len(design.vertices_mm)]),
    )
    m = len(owner)
    n_edge_pieces = np.bincount(owner, minlength=4)

    def seen_per_edge(pl: Placement) -> np.ndarray:
        hit = _raycasting_scene(both.transformed(placement_transform(pl))).cast_rays(rays)
        t = hit["t_hit"].numpy().astype(np.float64)
        prim = hit["primitive_ids"].numpy().astype(np.int64)
        nrm = hit["primitive_normals"].numpy().astype(np.float64)
        ok = np.isfinite(t) & (prim >= n_top) & (prim < n_top + 2 * m)
        depth = t * np.sum(dirs * zrep, axis=1)
        ok &= (depth >= settings.depth_min_mm) & (depth <= settings.depth_max_mm)
        ok &= np.abs(np.sum(nrm * dirs, axis=1)) >= cos_max
        pieces = np.unique((prim[ok] - n_top) % m)
        return np.bincount(owner[pieces], minlength=4)

    total = int(n_edge_pieces.sum())
    seen = seen_per_edge(placement)
    worst = float(seen.sum()) / total
    for moved in _uncertainty_corners(placement, settings):
        worst = min(worst, float(seen_per_edge(moved).sum()) / total)
    per_edge = tuple(float(v) for v in seen / n_edge_pieces)
    return EdgeFaceCoverage(float(seen.sum()) / total, worst, per_edge, total)  # type: ignore[arg-type]
