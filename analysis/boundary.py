"""Boundary and corners of the plate's top surface (paper section 2.1.2), for any placement angle.

Steps, on the top-surface points from ``segment``:

1. **Raster axes in the base plane.** The minimum-area rectangle around the points' XY convex hull
   gives the raster's axes ``u`` and ``v`` (counter-clockwise from ``u``); nothing assumes the
   plate lies square to the bed, nor that it is a rectangle.
2. **Boundary feature points.** The XY projection is rasterised (``pixel_mm``) in the (u, v)
   frame. The outline of the occupied area is split into four edges at its four largest turns
   (:func:`analysis.design.outline.outline_corners` on its convex hull: any corner angle, bowed edges);
   each outline point belongs to the edge whose chord it lies nearest. For each ``bin_mm`` strip
   along a chord, the outermost point is that edge's feature point (where the scan leaves the
   plate); its height is extrapolated to it from the points just inside (``z_window_mm``), as the
   outermost points may be the first hundredths of the thickness face. Strips within
   ``corner_margin_mm`` of a corner are left out: corners are where the data is incomplete, and
   they are recovered by intersection instead.
3. **Outlier removal by curvature.** Along each edge, feature points where the discrete curvature
   of the edge curve jumps (second difference beyond ``outlier_mad`` robust deviations) or that lie
   off a cubic spline through the others are dropped, repeatedly.
4. **Cubic splines per edge.** Each edge is a least-squares cubic spline (knots ``knot_mm`` apart
   for the base-plane offset, whose curves are gentle, ``z_knot_mm`` for the height) of its offset
   from its chord and of its height over the along-chord coordinate.
5. **Corners.** Neighbouring projected edges are intersected in the base plane (Newton's method on
   the two along-edge coordinates: the splines meet wherever they meet, at any angle); the corner's
   height is the mean of the two edges' height splines at the intersection, as the paper takes it.

Corner order is the project convention (see ``plates``): counter-clockwise seen from +z, corner 0
starts a long edge, of the two long edges the one whose direction is closest to the bed's +x.
Edge k runs from corner k to corner k+1. The design's ``plates.design_corners`` uses the same
order, so design and measured corners correspond up to a half turn.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import structlog
from scipy import ndimage
from scipy.interpolate import make_lsq_spline
from scipy.spatial import ConvexHull, QhullError

from analysis.design.outline import OutlineError, outline_corners
from analysis.design.plates import canonical_corner_order

__all__ = ["BoundaryError", "BoundaryResult", "BoundarySettings", "EdgeFit", "find_corners"]

log = structlog.get_logger(__name__)


class BoundaryError(ValueError):
    """The points do not outline a four-sided plate (too few points, an edge without data)."""


@dataclass(frozen=True)
class BoundarySettings:
    """Knobs of :func:`find_corners` (mm)."""

    pixel_mm: float = 1.0
    bin_mm: float = 2.0
    corner_margin_mm: float = 15.0
    outlier_mad: float = 5.0
    min_outlier_mm: float = 0.3
    min_points_per_edge: int = 10
    knot_mm: float = 250.0
    z_knot_mm: float = 100.0
    z_window_mm: tuple[float, float] = (0.3, 4.0)


@dataclass
class EdgeFit:
    """One plate edge: its feature points and cubic splines, from corner k to corner k+1.

    points_mm: (m, 3) float64 inlier boundary feature points (bed frame, mm).
    n_outliers: feature points removed by the curvature / residual test.
    rms_mm: RMS of the inliers' cross-edge offset about the spline (mm).
    """

    points_mm: np.ndarray
    n_outliers: int
    rms_mm: float
    _origin: np.ndarray = field(repr=False)
    _along: np.ndarray = field(repr=False)
    _cross: np.ndarray = field(repr=False)
    _cross_spline: object = field(repr=False)
    _z_spline: object = field(repr=False)
    _t0: float = field(repr=False, default=0.0)
    _t1: float = field(repr=False, default=1.0)

    def evaluate(self, s: np.ndarray) -> np.ndarray:
        """(m, 3) points on the edge at s in [0, 1] (0: corner k, 1: corner k+1), bed frame, mm."""
        s = np.atleast_1d(np.asarray(s, dtype=np.float64))
        t = self._t0 + s * (self._t1 - self._t0)
        c = self._cross_spline(t)
        xy = self._origin + t[:, None] * self._along + c[:, None] * self._cross
        return np.column_stack([xy, self._z_spline(t)])

    def sample_mm(self, step_mm: float = 1.0) -> np.ndarray:
        """(m, 3) points along the edge from corner k to corner k+1, about ``step_mm`` apart."""
        n = max(2, int(np.ceil(abs(self._t1 - self._t0) / step_mm)) + 1)
        return self.evaluate(np.linspace(0.0, 1.0, n))

    @property
    def length_mm(self) -> float:
        """Length of the edge's 3-D curve between its corners (mm)."""
        p = self.sample_mm(1.0)
        return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


@dataclass
class BoundaryResult:
    """Corners and edges of the plate's top surface.

    corners_mm: (4, 3) float64, bed frame, mm, in the project's corner order.
    edges: four :class:`EdgeFit`, edge k from corner k to corner k+1.
    boundary_points_mm: (m, 3) all inlier feature points.
    timings_s: seconds per step.
    """

    corners_mm: np.ndarray
    edges: tuple[EdgeFit, EdgeFit, EdgeFit, EdgeFit]
    boundary_points_mm: np.ndarray
    timings_s: dict[str, float] = field(default_factory=dict)

    @property
    def size_mm(self) -> tuple[float, float]:
        """(length, width): mean chord lengths of the long and of the short edges in XY (mm)."""
        c = self.corners_mm[:, :2]
        e = np.linalg.norm(np.roll(c, -1, axis=0) - c, axis=1)
        return float((e[0] + e[2]) / 2), float((e[1] + e[3]) / 2)

    def plate_frame(self) -> np.ndarray:
        """T_bed_plate (4, 4): origin at the corners' mean, x along edges 0 and 2, z the diagonal normal.

        z = (c2 - c0) x (c3 - c1), the paper's "diagonal normal", pointing up.
        """
        c = self.corners_mm
        z = np.cross(c[2] - c[0], c[3] - c[1])
        z /= np.linalg.norm(z)
        if z[2] < 0:
            z = -z
        x = (c[1] - c[0]) + (c[2] - c[3])
        x -= z * (x @ z)
        x /= np.linalg.norm(x)
        T = np.eye(4)
        T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
        T[:3, 3] = c.mean(axis=0)
        return T


def _min_area_axes(xy: np.ndarray) -> np.ndarray:
    """Unit long axis (2,) of the minimum-area rectangle around the XY points."""
    hull = xy[ConvexHull(xy).vertices]
    e = np.roll(hull, -1, axis=0) - hull
    ang = np.unique(np.mod(np.arctan2(e[:, 1], e[:, 0]), np.pi / 2))
    c, s = np.cos(ang), np.sin(ang)
    a = hull @ np.vstack([c, s])  # (h, k) coordinates along each candidate axis
    b = hull @ np.vstack([-s, c])
    ext_a = a.max(axis=0) - a.min(axis=0)
    ext_b = b.max(axis=0) - b.min(axis=0)
    k = int(np.argmin(ext_a * ext_b))
    u = np.array([c[k], s[k]])
    if ext_b[k] > ext_a[k]:
        u = np.array([-s[k], c[k]])
    # Keep the axis direction in (-90, 90] deg so "edge 0" is well defined.
    ang_u = np.arctan2(u[1], u[0])
    if not (-np.pi / 2 < ang_u <= np.pi / 2):
        u = -u
    return u


def _edge_samples(
    along: np.ndarray,
    cross: np.ndarray,
    z: np.ndarray,
    idx: np.ndarray,
    bin_mm: float,
    lo: float,
    hi: float,
    z_window_mm: tuple[float, float],
) -> tuple[np.ndarray, np.ndarray]:
    """Per ``bin_mm`` bin of ``along`` in [lo, hi]: the outermost point and the edge height.

    Returns (indices into ``idx`` of the max-``cross`` point per bin, edge height per bin (mm)).
    The height is a straight-line fit of z over the cross offset, on the points between
    ``z_window_mm`` inside the outermost one, extrapolated to it: the outermost points themselves
    may be the first hundredths of the thickness face, a little below the top edge.
    """
    keep = (along >= lo) & (along <= hi)
    along, cross, z, idx = along[keep], cross[keep], z[keep], idx[keep]
    if len(along) == 0:
        return idx, z
    b = np.floor((along - lo) / bin_mm).astype(np.int64)
    order = np.lexsort((-cross, b))
    b_sorted = b[order]
    first = np.flatnonzero(np.r_[True, b_sorted[1:] != b_sorted[:-1]])
    out_pos = order[first]
    nb = int(b.max()) + 1 if len(b) else 0
    c_out = np.full(nb, np.nan)
    c_out[b[out_pos]] = cross[out_pos]
    depth = c_out[b] - cross
    w = ((depth >= z_window_mm[0]) & (depth <= z_window_mm[1])).astype(np.float64)
    s0 = np.bincount(b, w, nb)
    s1 = np.bincount(b, w * depth, nb)
    s2 = np.bincount(b, w * depth * depth, nb)
    sz = np.bincount(b, w * z, nb)
    s1z = np.bincount(b, w * depth * z, nb)
    det = s0 * s2 - s1 * s1
    with np.errstate(invalid="ignore", divide="ignore"):
        z0 = (s2 * sz - s1 * s1z) / det  # intercept at depth 0 (the outermost point)
    bins = b[out_pos]
    z_edge = z[out_pos].copy()
    good = (s0[bins] >= 3) & (np.abs(det[bins]) > 1e-9)
    z_edge[good] = z0[bins][good]
    return idx[out_pos], z_edge


class _EdgeSpline:
    """A cubic B-spline over the data's range, continued by its end tangents beyond it.

    The corners lie a little beyond the last feature points; a cubic's own extrapolation can
    swing there, a straight continuation does not.
    """

    def __init__(self, spline) -> None:
        self._s = spline
        self._d = spline.derivative()
        self._lo, self._hi = float(spline.t[0]), float(spline.t[-1])

    def __call__(self, t):
        t = np.asarray(t, dtype=np.float64)
        tc = np.clip(t, self._lo, self._hi)
        return self._s(tc) + self._d(tc) * (t - tc)

    def derivative(self, t):
        """dc/dt, the end tangents' slope beyond the data."""
        return self._d(np.clip(np.asarray(t, dtype=np.float64), self._lo, self._hi))


def _cubic_spline(t: np.ndarray, c: np.ndarray, knot_mm: float) -> _EdgeSpline:
    """Least-squares cubic B-spline c(t) with interior knots about ``knot_mm`` apart (t increasing)."""
    lo, hi = float(t[0]), float(t[-1])
    n_int = max(0, int((hi - lo) / knot_mm) - 1)
    inner = np.linspace(lo, hi, n_int + 2)[1:-1]
    knots = np.r_[[lo] * 4, inner, [hi] * 4]
    return _EdgeSpline(make_lsq_spline(t, c, knots, k=3))


def _robust_spline_fit(
    t: np.ndarray, c: np.ndarray, st: BoundarySettings
) -> tuple[np.ndarray, object, float]:
    """Inlier mask, cross-offset cubic spline and RMS after curvature / residual outlier removal."""
    keep = np.ones(len(t), bool)
    spline = None
    for _ in range(4):
        ti, ci = t[keep], c[keep]
        if len(ti) < st.min_points_per_edge:
            break
        # Discrete curvature of the edge curve (second difference over the spacing squared).
        h = np.diff(ti)
        h = np.where(h > 0, h, 1e-9)
        d2 = np.zeros(len(ti))
        d2[1:-1] = 2 * ((ci[2:] - ci[1:-1]) / h[1:] - (ci[1:-1] - ci[:-2]) / h[:-1]) / (h[1:] + h[:-1])
        mad2 = 1.4826 * np.median(np.abs(d2[1:-1] - np.median(d2[1:-1]))) + 1e-12
        curv_bad = np.abs(d2) > st.outlier_mad * mad2 + st.min_outlier_mm / max(np.median(h), 1e-6) ** 2
        spline = _cubic_spline(ti, ci, st.knot_mm)
        res = ci - spline(ti)
        mad = 1.4826 * np.median(np.abs(res - np.median(res))) + 1e-12
        res_bad = np.abs(res) > max(st.outlier_mad * mad, st.min_outlier_mm)
        bad = curv_bad & res_bad | (np.abs(res) > 4 * max(st.outlier_mad * mad, st.min_outlier_mm))
        if not bad.any():
            break
        keep[np.flatnonzero(keep)[bad]] = False
    ti, ci = t[keep], c[keep]
    if len(ti) < st.min_points_per_edge:
        raise BoundaryError(
            f"an edge has only {len(ti)} usable feature points (need {st.min_points_per_edge})"
        )
    spline = _cubic_spline(ti, ci, st.knot_mm)
    rms = float(np.sqrt(np.mean((ci - spline(ti)) ** 2)))
    return keep, spline, rms


def find_corners(points_mm: np.ndarray, settings: BoundarySettings | None = None) -> BoundaryResult:
    """Boundary feature points, per-edge cubic splines and the four corners of a plate's top surface.

    points_mm: (n, 3) float64 top-surface points (``SegmentResult.points_mm``), bed frame, mm; the
        plate lies roughly horizontal (any yaw).
    Returns a :class:`BoundaryResult`; raises :class:`BoundaryError` when no four-sided outline
    with enough points per edge is found.
    """
    st = settings or BoundarySettings()
    t0 = time.perf_counter()
    P = np.asarray(points_mm, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise BoundaryError(f"points_mm must be (n, 3), got {P.shape}")
    if len(P) < 100:
        raise BoundaryError(f"{len(P)} points: too few to outline a plate")
    timings: dict[str, float] = {}
    sub = P[:: max(1, len(P) // 200_000), :2]
    centre = np.median(sub, axis=0)
    u = _min_area_axes(sub - centre)
    v = np.array([-u[1], u[0]])
    timings["axes"] = time.perf_counter() - t0

    t1 = time.perf_counter()
    # (u, v) coordinates about the centre, written out to avoid (n, 2) temporaries.
    a = P[:, 0] * u[0] + P[:, 1] * u[1] - centre @ u
    b = P[:, 0] * v[0] + P[:, 1] * v[1] - centre @ v
    # Pixels of pixel_mm, but no smaller than the points' spacing (the raster must be solid) and no
    # more than about 2e7 of them (a 5 x 4 m plate at 1 mm).
    extent = float((a.max() - a.min()) * (b.max() - b.min()))
    px = max(st.pixel_mm, float(np.sqrt(extent / len(P))), float(np.sqrt(extent / 2e7)))
    # Three empty pixels of margin: the closing below must not eat into the plate at the image border.
    a0, b0 = a.min() - 3 * px, b.min() - 3 * px
    ia = ((a - a0) * (1.0 / px)).astype(np.int32)
    ib = ((b - b0) * (1.0 / px)).astype(np.int32)
    na, nb = int(ia.max()) + 4, int(ib.max()) + 4
    lin = ia * np.int32(nb) + ib if na * nb < 2**31 else ia.astype(np.int64) * nb + ib
    occ = np.bincount(lin, minlength=na * nb).reshape(na, nb) > 0
    occ = ndimage.binary_closing(occ, iterations=2, border_value=0)
    lab, nlab = ndimage.label(occ, structure=np.ones((3, 3)))
    if nlab == 0:
        raise BoundaryError("no occupied area in the base-plane projection")
    biggest = 1 + int(np.argmax(ndimage.sum_labels(occ, lab, index=np.arange(1, nlab + 1))))
    occ = ndimage.binary_fill_holes(lab == biggest)
    # Only points near the outline can be feature points: a band a few pixels wide.
    band_img = occ & ~ndimage.binary_erosion(occ, iterations=3, border_value=0)
    idx_all = np.flatnonzero(band_img.ravel()[lin])
    timings["raster"] = time.perf_counter() - t1

    t2 = time.perf_counter()
    # Approximate corners: where the outline of the occupied area turns most (any corner angle;
    # a bowed edge turns it little). Only to split the outline into four edges: the corners
    # themselves come from the edge splines below.
    bi, bj = np.nonzero(band_img)
    band_ab = np.column_stack([a0 + (bi + 0.5) * px, b0 + (bj + 0.5) * px])
    try:
        hull = band_ab[ConvexHull(band_ab).vertices]  # counter-clockwise
        q = hull[outline_corners(np.column_stack([hull, np.zeros(len(hull))]), np.array([0.0, 0.0, 1.0]))]
    except (OutlineError, QhullError) as exc:
        raise BoundaryError(f"the points outline no four-sided plate ({str(exc).splitlines()[0]})") from None
    along_v = np.roll(q, -1, axis=0) - q
    chord = np.linalg.norm(along_v, axis=1)
    along_v /= chord[:, None]
    out_v = np.column_stack([along_v[:, 1], -along_v[:, 0]])  # right of a counter-clockwise edge
    pa, pb = a[idx_all], b[idx_all]
    # Each outline point belongs to the edge whose chord it lies nearest.
    dist = np.empty((4, len(idx_all)))
    t_on = np.empty((4, len(idx_all)))
    c_on = np.empty((4, len(idx_all)))
    for k in range(4):
        t_on[k] = (pa - q[k, 0]) * along_v[k, 0] + (pb - q[k, 1]) * along_v[k, 1]
        c_on[k] = (pa - q[k, 0]) * out_v[k, 0] + (pb - q[k, 1]) * out_v[k, 1]
        beyond = np.maximum(np.maximum(-t_on[k], t_on[k] - chord[k]), 0.0)
        dist[k] = np.hypot(c_on[k], beyond)
    owner = np.argmin(dist, axis=0)
    m = st.corner_margin_mm
    fits = []
    for k in range(4):
        sel = owner == k
        cand = idx_all[sel]
        t_all, c_all = t_on[k, sel], c_on[k, sel]
        pick_local, z_edge = _edge_samples(
            t_all,
            c_all,
            P[cand, 2],
            np.arange(len(cand)),
            max(st.bin_mm, px),
            m,
            chord[k] - m,
            st.z_window_mm,
        )
        if len(pick_local) < st.min_points_per_edge:
            raise BoundaryError(f"edge {k}: {len(pick_local)} feature points (need {st.min_points_per_edge})")
        t = t_all[pick_local]
        order = np.argsort(t)
        pick_local, t, z_edge = pick_local[order], t[order], z_edge[order]
        distinct = np.r_[True, np.diff(t) > 1e-9]  # the spline needs increasing abscissae
        pick_local, t, z_edge = pick_local[distinct], t[distinct], z_edge[distinct]
        c = c_all[pick_local]
        keep, cs, rms = _robust_spline_fit(t, c, st)
        zs = _cubic_spline(t[keep], z_edge[keep], st.z_knot_mm)
        fits.append((cand[pick_local], keep, cs, zs, rms))
    timings["edges"] = time.perf_counter() - t2

    t3 = time.perf_counter()

    def on_edge(k: int, tt: float) -> tuple[np.ndarray, np.ndarray]:
        """Point of edge k's curve at along-coordinate tt and its derivative, in (a, b)."""
        cs = fits[k][2]
        p = q[k] + tt * along_v[k] + float(cs(tt)) * out_v[k]
        return p, along_v[k] + float(cs.derivative(tt)) * out_v[k]

    # Corner j joins edge j-1 (near its end) and edge j (near its start): Newton on the two
    # along-coordinates, as the splines meet wherever they meet (no right angle assumed).
    corners_ab = np.empty((4, 2))
    t_ends = np.empty((4, 2))  # per edge: along-coordinates of its start and end corners
    heights = []
    for j in range(4):
        i = (j - 1) % 4
        ta, tb = float(chord[i]), 0.0
        for _ in range(50):
            pa_, da_ = on_edge(i, ta)
            pb_, db_ = on_edge(j, tb)
            J = np.column_stack([da_, -db_])
            if abs(np.linalg.det(J)) < 1e-9:
                raise BoundaryError(f"edges {i} and {j} are parallel: no corner between them")
            step = np.linalg.solve(J, pb_ - pa_)
            ta, tb = ta + float(step[0]), tb + float(step[1])
            if np.abs(step).max() < 1e-9:
                break
        if abs(ta - chord[i]) > 0.25 * chord[i] or abs(tb) > 0.25 * chord[j]:
            raise BoundaryError(f"edges {i} and {j} do not meet near their ends: no corner between them")
        corners_ab[j] = on_edge(j, tb)[0]
        t_ends[j, 0], t_ends[i, 1] = tb, ta
        heights.append(0.5 * (float(fits[i][3](ta)) + float(fits[j][3](tb))))
    corners_xy = centre + corners_ab[:, :1] * u + corners_ab[:, 1:] * v
    corners = np.column_stack([corners_xy, heights])

    # Edge objects, oriented from corner k to corner k+1, in the bed's XY.
    edges = []
    for k, (pick, keep, cs, zs, rms) in enumerate(fits):
        edges.append(
            EdgeFit(
                points_mm=P[pick[keep]],
                n_outliers=int((~keep).sum()),
                rms_mm=rms,
                _origin=centre + q[k, 0] * u + q[k, 1] * v,
                _along=along_v[k, 0] * u + along_v[k, 1] * v,
                _cross=out_v[k, 0] * u + out_v[k, 1] * v,
                _cross_spline=cs,
                _z_spline=zs,
                _t0=float(t_ends[k, 0]),
                _t1=float(t_ends[k, 1]),
            )
        )
    # Into the project's order (corner 0 starts a long edge pointing into the bed's +x half plane):
    # roll the edges with the corners.
    canon = canonical_corner_order(corners)
    shift = int(np.argmin([np.abs(np.roll(corners, -s, axis=0) - canon).sum() for s in range(4)]))
    corners = np.roll(corners, -shift, axis=0)
    edges = edges[shift:] + edges[:shift]
    timings["corners"] = time.perf_counter() - t3
    timings["total"] = time.perf_counter() - t0
    result = BoundaryResult(
        corners_mm=corners,
        edges=tuple(edges),  # type: ignore[arg-type]
        boundary_points_mm=np.concatenate([e.points_mm for e in edges]),
        timings_s=timings,
    )
    log.info(
        "boundary", points=len(P), feature_points=len(result.boundary_points_mm),
        outliers=sum(e.n_outliers for e in edges), size_mm=[round(x, 2) for x in result.size_mm],
        total_s=round(timings["total"], 3),
    )  # fmt: skip
    return result
