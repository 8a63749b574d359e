"""The surface a template rests on: an estimate of the plate whose upward bias is bounded by the noise.

A one-sided fit rests the design on the highest of the points it is given. Given raw samples (or
cell means of a few points), that is the largest upward noise excursion among hundreds of thousands,
3.5-5 standard errors: the design floats that far above the plate and every Zmax reads that much too
high (about 1.8 sigma with 16-point cell means). The template must rest on the plate, not on the
noise, so the constraint acts on an estimate of the surface whose error is small against sigma with
a stated confidence:

1. **Noise from the data.** ``sigma`` is the robust spread (MAD) of the points' gaps to the design
   about the mean gap of small cells (``noise_cell_mm``), with the cells' degrees of freedom put
   back. The design takes out the plate's shape; a dent's slope across a 2 mm cell adds little, and
   the median ignores the few cells on steep dent flanks.
2. **Patch means of the gaps, read at the contact point.** The plate is cut into patches of side
   about ``h`` laid out in the design frame (so the edge patches sit the same way on the plate
   whatever its placement); each patch stands for its points by the *gap to the design* at the ICP
   pose. Measured as a gap, the estimate carries no bias from the plate's curvature (the design has
   the same curvature), only from the curvature of the forming error across the patch: a patch's
   mean of the gaps is the field's value at its centroid plus ``tr(H S) / 2`` (``H`` the gaps'
   Hessian, ``S`` the points' second moments), so a bump of height ``a`` and Gaussian width ``w``
   read ``a h^2 / (12 w^2)`` low at its top, and a centroid misses the top by up to 0.7 ``h``
   (:func:`_block_quadratics`, :func:`_contact_values`). The gaps' slope and Hessian at each patch
   come from a quadratic fitted on the means of its 3 x 3 block of patches (each mean's own second
   moments in its row); the patch's value is its mean with ``tr(H S) / 2`` taken out, read where the
   template touches -- the gaps' lowest point ``-H^-1 b`` where ``H`` is positive definite (the plate
   rises against the design) and it lies within reach, else the centroid. A patch whose block is
   incomplete keeps its mean at its centroid (the edge fits below hold the plate's edge).
   Measured on a 300 x 200 sail with the default forming error at 2 points per mm^2 (12-14 mm
   patches), the design's height against its rest on the exact plate: -0.06 .. -0.07 mm on patch
   means whatever the plate's radii (4000/3000 to 1000/750 mm), -0.02 .. -0.03 mm now; a block
   3 h across still reads a bump narrower than about 1.5 h with too little curvature (sigma 14 mm:
   -0.13 mm before, -0.07 mm now).
3. **Patch size from a stated confidence.** With ``M`` patches of at least ``n`` points each, the
   highest of the patch errors stays below ``q_M sigma / sqrt(n)`` with probability ``confidence``,
   ``q_M = Phi^-1(confidence^(1/M))`` (the maximum of ``M`` independent normals). ``n`` is chosen so
   that bound is ``target_sigmas * sigma`` (0.25 sigma: the template's lift stays below 0.3 sigma);
   ``h`` holds about 1.5 ``n`` points at the scan's density, so patches cut by the plate's edge down
   to ``n`` points are still used; smaller ones are not. ``max_cell_mm`` caps ``h`` (the narrowest
   bump that must still carry the template); a scan too sparse for the cap gets a larger bound, and
   the result says so.

4. **Edges.** A template on a raised (springback) edge touches the edge itself, not a patch's
   centroid inside it. Every patch on the plate's edge is also held at its outer extent by a local
   quadratic of the gaps across and along the edge, fitted on a block of patches big enough that its
   value there keeps the patches' bound (:func:`_edge_fits`); without, a plate with 1 mm springback
   let the design sink 0.15 mm below its edges.

Assumes independent noise between points (a correlated error -- a pass offset, a clock error on a
slope -- is not divided by ``sqrt(n)``) and a gap field smooth at the block's scale (3 ``h``).
Costs one gap evaluation, two binning passes over the points (linear, about 0.1 s per 10^6 points)
and a 6 x 6 solve per patch (batched), and the
plate's detail below ``h`` in the resting pose only: the figures are still computed on the full
reconstructed surface. Memory: no copy of the points (the caller's float64 array is read a chunk of
:data:`_CHUNK` points at a time, the design frame's coordinates made per chunk; every sum stays float64),
13 bytes held per point (gap float64, patch int32, weight bool) and the edge fits' points (those within
reach of the edge) copied; 37 B a point at the peak past the gap evaluation on a 3 x 1 m plate, 260
with the three float64 copies and the sorted columns before (docs/operations.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import structlog
from scipy.stats import norm

from analysis.register.height_field import HeightField
from analysis.register.onesided import deflection_gaps
from analysis.register.transforms import RegistrationError, apply_transform, invert_transform

log = structlog.get_logger(__name__)


@dataclass(frozen=True)
class RestSurface:
    """The patch estimate of the plate the design rests on.

    points_mm: (m, 3) one point per patch, measured frame: the patch's contact point's x and y (its
    centroid, or a bump's top within reach), and the height whose gap to the design (at the pose it
    was made at) is the patch's estimate there (:func:`_contact_values`).
    counts: (m,) effective points per patch n_eff (the estimate's variance is sigma^2 / n_eff). noise_mm: sigma estimated from the data. cell_mm: the patch side.
    min_count: the fewest points a kept patch holds. standard_error_mm: sigma / sqrt(min_count).
    bound_mm: the highest patch error stays below this with probability ``confidence``.
    target_met: bound_mm <= target_sigmas * noise_mm (False: the scan was too sparse for the cap).
    edge_patches: how many of the points are edge patches held at their outer extent.
    """

    points_mm: np.ndarray
    counts: np.ndarray
    noise_mm: float
    cell_mm: float
    min_count: int
    standard_error_mm: float
    bound_mm: float
    confidence: float
    target_sigmas: float
    target_met: bool
    edge_patches: int = 0

    def as_dict(self) -> dict:
        """The report's record of the estimate (no arrays)."""
        return {
            "estimator": (
                "patch means of gaps to the design less the block's curvature, at the contact point; "
                "edge patches also at their outer extent"
                if self.edge_patches
                else "patch means of gaps to the design less the block's curvature, at the contact point"
            ),
            "patches": len(self.counts),
            "cell_mm": round(self.cell_mm, 3),
            "min_points": self.min_count,
            "noise_mm": round(self.noise_mm, 5),
            "standard_error_mm": round(self.standard_error_mm, 5),
            "bound_mm": round(self.bound_mm, 5),
            "confidence": self.confidence,
            "target_sigmas": self.target_sigmas,
            "target_met": self.target_met,
        }


TRIM_SIGMAS = 3.0


# the points are worked through in chunks of this many: the per-point temporaries of the sums (a dozen
# float64 columns) stay a few tens of MB whatever the plate (a whole plate's: 100+ B a point)
_CHUNK = 1 << 18


class _Points:
    """The plate points over the design without a copy: the caller's (n_all, 3) float64 array and the
    positions of the kept points (None: all), read a chunk at a time (float64, as given)."""

    def __init__(self, P: np.ndarray, sel: np.ndarray | None) -> None:
        self.P, self.sel = P, sel
        self.n = len(P) if sel is None else len(sel)

    def chunks(self):
        """(a, b) the bounds of each chunk of the kept points."""
        for a in range(0, self.n, _CHUNK):
            yield a, min(a + _CHUNK, self.n)

    def get(self, a: int, b: int) -> np.ndarray:
        return self.P[a:b] if self.sel is None else self.P[self.sel[a:b]]

    def take(self, idx: np.ndarray) -> np.ndarray:
        """(k, 3) the kept points at the positions ``idx``."""
        return self.P[idx] if self.sel is None else self.P[self.sel[idx]]


def _patch_planes(
    inv: np.ndarray,
    m: int,
    pts: _Points,
    gap: np.ndarray,
    w: np.ndarray | None,
) -> tuple[np.ndarray, ...]:
    """Weighted plane of the gaps per patch: (centroid (m, 3), mean gap, slope x, slope y, weight sum,
    second moments (m, 3)). pts: the points (measured frame, float64, read in chunks; the offsets from
    the centroids are float64 chunk temporaries); w: their weights, bool (None: all 1)."""
    n_w = np.zeros(m)
    acc = np.zeros((4, m))
    for a, b in pts.chunks():
        i_c, p = inv[a:b], pts.get(a, b)
        w_c = None if w is None else w[a:b].astype(np.float64)
        n_w += np.bincount(i_c, weights=w_c, minlength=m)
        for k, v in enumerate((p[:, 0], p[:, 1], p[:, 2], gap[a:b])):
            acc[k] += np.bincount(i_c, weights=v if w_c is None else w_c * v, minlength=m)
    safe_n = np.maximum(n_w, 1.0)
    mean = np.column_stack([acc[k] / safe_n for k in range(3)])
    mean_gap = acc[3] / safe_n
    sums = np.zeros((5, m))
    for a, b in pts.chunks():
        i_c, p = inv[a:b], pts.get(a, b)
        dx, dy, dg = _offsets(i_c, p, gap[a:b], mean, mean_gap)
        w_c = None if w is None else w[a:b].astype(np.float64)
        wdx = dx if w_c is None else w_c * dx
        wdy = dy if w_c is None else w_c * dy
        for k, (u, v) in enumerate(((wdx, dx), (wdx, dy), (wdy, dy), (wdx, dg), (wdy, dg))):
            sums[k] += np.bincount(i_c, weights=u * v, minlength=m)
    sxx, sxy, syy, sxg, syg = sums
    det = sxx * syy - sxy**2
    ok = det > 1e-12 * np.maximum(sxx * syy, 1e-300)
    safe = np.where(ok, det, 1.0)
    b_x = np.where(ok, (syy * sxg - sxy * syg) / safe, 0.0)
    b_y = np.where(ok, (sxx * syg - sxy * sxg) / safe, 0.0)
    moments = np.column_stack([sxx, sxy, syy]) / safe_n[:, None]
    return mean, mean_gap, b_x, b_y, n_w, moments


def _offsets(
    i_c: np.ndarray, p: np.ndarray, gap_c: np.ndarray, mean: np.ndarray, mean_gap: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A chunk's offsets from its patches' centroids (dx, dy) and mean gap (dg), float64."""
    return (
        p[:, 0] - np.take(mean[:, 0], i_c),
        p[:, 1] - np.take(mean[:, 1], i_c),
        gap_c - np.take(mean_gap, i_c),
    )


# the contact point is looked for within this many patch sides of a patch's centroid (a patch's
# corner lies 0.71 side from its centre: every point of the plate is within reach of some patch)
CONTACT_REACH = 0.75


@dataclass(frozen=True)
class _BlockQuadratics:
    """Per patch, the quadratic of the gaps fitted on the means of its 3 x 3 block of patches.

    ok (m,) bool: the block determined it (every row and column of the block holds a patch, at least
    six patches); slope (m, 2) mm/mm and hessian (m, 3) (g_xx, g_xy, g_yy, 1/mm) of the gaps at the
    patch, measured frame; ``A`` (m, 6, 6) the weighted normal matrix (coordinates in patch sides
    ``h``) and ``X0`` (m, 6) the patch's own row, for the variance of a value read from the fit.
    """

    ok: np.ndarray
    slope: np.ndarray
    hessian: np.ndarray
    A: np.ndarray
    X0: np.ndarray


def _block_quadratics(
    grid: _Grid, centroid_xy: np.ndarray, mean_gap: np.ndarray, n_w: np.ndarray, moments: np.ndarray, h: float
) -> _BlockQuadratics:
    """The gaps' slope and curvature at every patch from the means of its 3 x 3 block (vectorised).

    A patch mean is the gap field averaged over the patch's points, not its value at the centroid:
    for a field with Hessian ``H`` it reads ``g(c) + tr(H S) / 2`` with ``S`` the points' second
    moments about ``c`` (``moments``: (m, 3) S_xx, S_xy, S_yy per point, mm^2). The block's means are
    therefore fitted, weighted by their counts, with the rows ``[1, dx, dy, (dx^2 + S_xx) / 2,
    dx dy + S_xy, (dy^2 + S_yy) / 2]`` (``d``: a neighbour's centroid from the patch's): the second
    moments of each patch go into its own row, so ``H`` is not misread from patches that hold their
    points differently (an edge patch, a scan's holes)."""
    m = len(n_w)
    cells = np.arange(m)
    rows, weights = [], []
    present = np.zeros((m, 3, 3), dtype=bool)
    for a, di in enumerate((-1, 0, 1)):
        for b, dj in enumerate((-1, 0, 1)):
            j = grid.lookup(di, dj, cells) if (di or dj) else cells
            has = j >= 0
            j = np.where(has, j, 0)
            present[:, a, b] = has & (n_w[j] > 0)
            d = (centroid_xy[j] - centroid_xy) / h
            s = moments[j] / h**2
            rows.append(np.column_stack([np.ones(m), d[:, 0], d[:, 1], 0.5 * (d[:, 0] ** 2 + s[:, 0]),
                                         d[:, 0] * d[:, 1] + s[:, 1], 0.5 * (d[:, 1] ** 2 + s[:, 2])]))  # fmt: skip
            weights.append(np.where(present[:, a, b], n_w[j], 0.0))
    X = np.stack(rows, axis=1)  # (m, 9, 6)
    w = np.stack(weights, axis=1)  # (m, 9)
    g = np.stack([mean_gap[np.where(r >= 0, r, 0)] for r in
                  [grid.lookup(di, dj, cells) if (di or dj) else cells for di in (-1, 0, 1) for dj in (-1, 0, 1)]],
                 axis=1)  # fmt: skip
    ok = present.any(axis=2).all(axis=1) & present.any(axis=1).all(axis=1) & (present.sum(axis=(1, 2)) >= 6)
    A = np.einsum("mk,mki,mkj->mij", w, X, X)
    A[~ok] = np.eye(6)
    theta = np.linalg.solve(A, np.einsum("mk,mki,mk->mi", w, X, g)[..., None])[..., 0]
    theta[~ok] = 0.0
    return _BlockQuadratics(ok, theta[:, 1:3] / h, theta[:, 3:6] / h**2, A, X[:, 4])


def _contact_values(
    q: _BlockQuadratics, mean_gap: np.ndarray, n_w: np.ndarray, moments: np.ndarray, h: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each patch's estimate of the gap at its contact point: (offset (m, 2) of that point from the
    centroid, measured frame mm; gap (m,) mm; n_eff (m,) the count whose mean has its variance).

    The gap near the patch is ``g(c + d) = mean - tr(H S) / 2 + b . d + d^T H d / 2`` (the patch's
    own mean, the block's slope ``b`` and Hessian ``H``): at the centroid the mean with the curvature's
    share taken out, and where ``H`` is positive definite (the plate rises against the design, a bump
    a template rests on) at the lowest gap ``d = -H^-1 b`` if that lies within :data:`CONTACT_REACH`
    patch sides -- the place where the template touches, which the centroid misses by up to 0.7 h.
    A patch whose block is incomplete keeps its mean at its centroid. The value is linear in the
    block's means (``d`` held): its variance is ``sigma^2 / n_eff`` with ``1 / n_eff = 1 / n_0 +
    2 X_0 . u + u^T A u``, ``u = A^-1 l`` for the value's functional ``l`` on the fit's parameters."""
    hxx, hxy, hyy = q.hessian.T
    det = hxx * hyy - hxy**2
    pd = q.ok & (hxx > 0) & (det > 0)
    safe = np.where(pd, det, 1.0)
    bx, by = q.slope.T
    d = np.where(
        pd[:, None], -np.column_stack([hyy * bx - hxy * by, hxx * by - hxy * bx]) / safe[:, None], 0.0
    )
    d[np.hypot(d[:, 0], d[:, 1]) > CONTACT_REACH * h] = 0.0
    dx, dy = d.T
    sxx, sxy, syy = moments.T
    # the value's functional on the parameters (h-scaled: slope x h, Hessian x h^2)
    ell = np.column_stack([np.zeros(len(dx)), dx / h, dy / h, 0.5 * (dx**2 - sxx) / h**2,
                           (dx * dy - sxy) / h**2, 0.5 * (dy**2 - syy) / h**2])  # fmt: skip
    ell[~q.ok] = 0.0
    theta_h = np.column_stack([np.zeros(len(dx)), q.slope * h, q.hessian * h**2])
    value = mean_gap + np.einsum("mi,mi->m", ell, theta_h)
    u = np.linalg.solve(q.A, ell[..., None])[..., 0]
    inv_n = 1.0 / np.maximum(n_w, 1e-300) + 2.0 * np.einsum("mi,mi->m", q.X0, u)
    inv_n += np.einsum("mi,mij,mj->m", u, q.A, u)
    return d, value, 1.0 / np.maximum(inv_n, 1e-300)


# the blocks an edge patch's surface is fitted on, tried in turn until its value at the edge keeps
# the bound: (cells deep across each edge, cells either side along an edge)
EDGE_BLOCKS = ((2, 2), (3, 2), (4, 2))
# where an edge patch's value is placed: this share of a patch inside its outer extent
EDGE_INSET = 0.2


def _edge_fits(
    grid: _Grid, inv: np.ndarray, Q: np.ndarray, gap: np.ndarray, w: np.ndarray, n_min: int, inset_mm: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Edge patches held at their outer extent by a local fit of the gaps across the edge.

    inv, Q, gap, w: the points of the patches a fit may use (:func:`_edge_points`: every point of
    each such patch), their patch, (k, 3) design frame, gaps and weights (bool). An axis on which the
    patch's neighbour is missing on one side is an edge axis; the patch is evaluated at its kept
    points' extreme on that side (on both axes at a corner; at the centroid's coordinate along an
    axis without an edge). The fit: least squares of the kept points' gaps (and heights, for the
    point's place) on a block of ``deep`` cells inward across every edge axis and ``2 along + 1`` cells
    along the other, quadratic in the distance across each edge and along it. The value at
    the point is the fit's intercept, its variance ``sigma^2 / n_eff`` with ``1 / n_eff`` the
    intercept's entry of ``(X^T X)^-1``; the first block of :data:`EDGE_BLOCKS` where
    ``n_eff >= n_min`` (the bound of a patch mean) serves, a patch none suffices for is left out.
    The point carrying the value is placed ``inset_mm`` inside the edge: on the footprint's very
    edge a slide of the design by a millimetre would take it off the footprint, where the fit does
    not constrain a point, and the fit could escape the edge that way (the design's tilt against
    the plate over the inset, 1e-3 x a few mm, is what that costs).
    A plane would read a curved rise by ``f'' W^2 / 12`` off (a dent's tail lifts the design, a
    springback rise lets it sink); a quadratic leaves the third derivative times ``W^3 / 120``.
    Returns (points (k, 3) design frame, gaps (k,), n_eff (k,)).
    """
    # the points sorted by patch (stable: each patch's in the cloud's order), so a block of patches
    # is a few contiguous runs
    m = len(grid.count)
    if len(inv) == 0:
        return np.zeros((0, 3)), np.zeros(0), np.zeros(0)
    order = np.argsort(inv, kind="stable")
    cnt = np.bincount(inv, minlength=m)
    start = np.concatenate([[0], np.cumsum(cnt)])
    has = cnt > 0  # the patches given (the others hold no point here: left at 0 and +-inf)
    first = start[:-1][has]
    use_s = w[order]
    q_s = [np.take(Q[:, k], order) for k in range(3)]
    gap_s = np.take(gap, order)
    w_s = use_s.astype(np.float64)

    def per_patch(ufunc, v: np.ndarray, empty: float) -> np.ndarray:
        out = np.full(m, empty)
        out[has] = ufunc.reduceat(v, first)
        return out

    n_c = per_patch(np.add, w_s, 0.0)
    safe = np.maximum(n_c, 1e-300)
    cen = np.column_stack([per_patch(np.add, w_s * q_s[k], 0.0) / safe for k in (0, 1)])
    # the kept points' extent per patch (+inf, -inf for a patch of none kept)
    lo_hi = [
        (per_patch(np.minimum, np.where(use_s, q_s[k], np.inf), np.inf),
         per_patch(np.maximum, np.where(use_s, q_s[k], -np.inf), -np.inf))
        for k in (0, 1)
    ]  # fmt: skip
    miss = grid.missing
    # side per axis: +1 the edge lies on the + side, -1 on the - side, 0 no edge on this axis
    side = np.column_stack(
        [(miss[:, 2 * k] & ~miss[:, 2 * k + 1]).astype(int) - (miss[:, 2 * k + 1] & ~miss[:, 2 * k]) for k in (0, 1)]
    )  # fmt: skip
    cells = np.flatnonzero((n_c > 0) & side.any(axis=1))
    index = {int(key): i for i, key in enumerate(grid.keys)}
    out_q, out_g, out_n = [], [], []
    for c in cells:
        sd = side[c]
        at = [lo_hi[k][1][c] if sd[k] > 0 else lo_hi[k][0][c] if sd[k] < 0 else cen[c, k] for k in (0, 1)]
        for deep, along in EDGE_BLOCKS:
            ranges = [range(-sd[k] * (deep - 1), 1) if sd[k] > 0 else range(0, deep) if sd[k] < 0
                      else range(-along, along + 1) for k in (0, 1)]  # fmt: skip
            block = [
                index.get(int(grid.keys[c]) + di * grid.width + dj) for di in ranges[0] for dj in ranges[1]
            ]
            cb = np.asarray([b for b in block if b is not None])
            pts = np.concatenate([np.arange(start[b], start[b + 1]) for b in cb])
            pts = pts[use_s[pts]]
            # the block's kept points' spread: from its cells' extents (the same min and max)
            spread = max(max(float(lo_hi[k][1][cb].max() - lo_hi[k][0][cb].min()) for k in (0, 1)), 1e-9)
            cols = [np.ones(len(pts))]
            for k in (0, 1):
                d = (q_s[k][pts] - at[k]) / spread
                cols += [d, d**2]
            X = np.column_stack(cols)
            if len(pts) <= 2 * X.shape[1]:
                continue
            XtX = X.T @ X
            try:
                inv00 = float(np.linalg.solve(XtX, np.eye(len(XtX))[0])[0])
                coef = np.linalg.solve(XtX, X.T @ np.column_stack([gap_s[pts], q_s[2][pts]]))
            except np.linalg.LinAlgError:
                continue
            n_eff = 1.0 / inv00 if inv00 > 0 else 0.0
            if n_eff >= n_min:
                out_q.append([at[0] - sd[0] * inset_mm, at[1] - sd[1] * inset_mm, coef[0, 1]])
                out_g.append(coef[0, 0])
                out_n.append(n_eff)
                break
    if not out_q:
        return np.zeros((0, 3)), np.zeros(0), np.zeros(0)
    return np.asarray(out_q), np.asarray(out_g), np.asarray(out_n)


def _edge_points(grid: _Grid, inv: np.ndarray) -> np.ndarray:
    """(k,) the positions of the points :func:`_edge_fits` may use: every point of each patch within
    the reach of :data:`EDGE_BLOCKS` of a patch on the plate's edge (a quarter of a 3 x 1 m plate's)."""
    reach = max(max(deep - 1, along) for deep, along in EDGE_BLOCKS)
    edge = np.flatnonzero(grid.missing.any(axis=1))
    near = np.zeros(len(grid.count), dtype=bool)
    for di in range(-reach, reach + 1):
        for dj in range(-reach, reach + 1):
            j = grid.lookup(di, dj, edge)
            near[j[j >= 0]] = True
    parts = [np.flatnonzero(near[inv[a : a + _CHUNK]]) + a for a in range(0, len(inv), _CHUNK)]
    return np.concatenate(parts) if parts else np.zeros(0, np.int64)


def max_normal_quantile(count: int, confidence: float) -> float:
    """q with P(max of ``count`` independent standard normals < q) = ``confidence``."""
    if count < 1 or not 0.0 < confidence < 1.0:
        raise RegistrationError(f"need count >= 1 and 0 < confidence < 1, got {count}, {confidence}")
    # 1 - confidence^(1/M) without cancellation
    return float(norm.isf(-math.expm1(math.log(confidence) / count)))


def _cells(xy: np.ndarray, cell_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """(inverse index (n,) int32, counts (m,)) of the occupied ``cell_mm`` squares."""
    g = _grid(*(np.floor(xy[:, k] / cell_mm).astype(np.int32) for k in (0, 1)))
    return g.inv, g.count


def _plate_cells(
    x_design_mm: np.ndarray, y_design_mm: np.ndarray, cell_mm: float
) -> tuple[np.ndarray, np.ndarray]:
    """(i (n,), j (n,)) the cell indices of patches laid out in the design frame from the points' lowest corner,
    the side stretched so that a whole number of patches spans the points: the edge patches then
    sit the same way on the plate in every scan, whatever its placement on the bed."""
    out = []
    for v in (x_design_mm, y_design_mm):
        lo = float(v.min())
        span = max(float(v.max()) - lo, 1e-9)
        n = max(round(span / cell_mm), 1)
        out.append(np.minimum(np.floor((v - lo) / (span / n)).astype(np.int64), n - 1))
    return out[0], out[1]


def _design_cells(
    pts: _Points, T_design_meas: np.ndarray, cell_mm: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_plate_cells` of the points moved into the design frame a chunk at a time (no (n, 3)
    copy): (i (n,) int32, j (n,) int32, the points' lowest corner (3,) design frame)."""
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for a, b in pts.chunks():
        q = apply_transform(T_design_meas, pts.get(a, b))
        lo = np.minimum(lo, q.min(axis=0))
        hi = np.maximum(hi, q.max(axis=0))
    steps, counts = [], []
    for k in (0, 1):
        span = max(float(hi[k]) - float(lo[k]), 1e-9)
        n = max(round(span / cell_mm), 1)
        steps.append(span / n)
        counts.append(n)
    ij = [np.empty(pts.n, np.int32) for _ in (0, 1)]
    for a, b in pts.chunks():
        q = apply_transform(T_design_meas, pts.get(a, b))
        for k in (0, 1):
            ij[k][a:b] = np.minimum(np.floor((q[:, k] - float(lo[k])) / steps[k]), counts[k] - 1)
    return ij[0], ij[1], lo


@dataclass(frozen=True)
class _Grid:
    """Occupied cells of integer indices: inv (n,) a point's cell, count (m,), keys (m,) sorted cell
    keys, width (the key's stride in i), missing (m, 4) bool -- the neighbour at +i, -i, +j, -j is
    absent (the cell lies on the plate's edge on that side)."""

    inv: np.ndarray
    count: np.ndarray
    keys: np.ndarray
    width: int
    missing: np.ndarray

    def lookup(self, di: int, dj: int, cells: np.ndarray) -> np.ndarray:
        """(k,) the index of the cell (di, dj) away from each of ``cells``, -1 where none."""
        want = self.keys[cells] + di * self.width + dj
        at = np.minimum(np.searchsorted(self.keys, want), len(self.keys) - 1)
        return np.where(self.keys[at] == want, at, -1)


# a grid's box of at most this many cells, and of at most 8 a point, is counted densely (8 bytes a
# cell, twice; 3-4 x faster than the sort on a plate's points), else sorted
_DENSE_GRID_MAX_CELLS = 40_000_000


def _grid(i: np.ndarray, j: np.ndarray) -> _Grid:
    """The occupied cells of the (n,) integer indices ``i``, ``j`` (int32 keeps them 4 bytes a point;
    the keys are formed a chunk at a time, the point's cell is int32)."""
    i_lo, j_lo = int(i.min()) - 1, int(j.min()) - 1  # a free row and column on every side
    width = int(j.max()) - j_lo + 2
    span = (int(i.max()) - i_lo + 2) * width
    steps = (width, -width, 1, -1)
    n = len(i)

    def key(a: int, b: int) -> np.ndarray:
        return (i[a:b].astype(np.int64) - i_lo) * width + (j[a:b] - j_lo)

    if span > min(_DENSE_GRID_MAX_CELLS, 8 * n):  # a sparse grid: sort
        keys, inv, count = np.unique(key(0, n), return_inverse=True, return_counts=True)
        missing = np.column_stack([~np.isin(keys + step, keys, assume_unique=True) for step in steps])
        return _Grid(inv.astype(np.int32), count, keys, width, missing)
    # every cell of the box counted at once (np.unique's sort of millions of keys took seconds), in
    # chunks of at least a quarter of the box (each chunk's count is the box's size)
    step = max(_CHUNK, span // 4)
    dense = np.zeros(span, np.int64)
    for a in range(0, n, step):
        dense += np.bincount(key(a, min(a + step, n)), minlength=span)
    keys = np.flatnonzero(dense)
    occupied = dense > 0
    rank = np.cumsum(occupied, dtype=np.int32) - 1
    missing = np.column_stack([~occupied[keys + step] for step in steps])
    inv = np.empty(n, np.int32)
    for a in range(0, n, _CHUNK):
        inv[a : a + _CHUNK] = rank[key(a, min(a + _CHUNK, n))]
    return _Grid(inv, dense[keys], keys, width, missing)


def _point_cells(pts: _Points, cell_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_cells` of the points' x and y, read a chunk at a time."""
    ij = [np.empty(pts.n, np.int32) for _ in (0, 1)]
    for a, b in pts.chunks():
        p = pts.get(a, b)
        for k in (0, 1):
            ij[k][a:b] = np.floor(p[:, k] / cell_mm)
    g = _grid(*ij)
    return g.inv, g.count


def noise_from_gaps(
    xy_mm: np.ndarray | None,
    gap_mm: np.ndarray,
    cell_mm: float = 2.0,
    cells: tuple[np.ndarray, np.ndarray] | None = None,
) -> float:
    """Robust noise sigma (mm) of points from their gaps' spread about small cells' means.

    xy_mm: (n, 2) positions; gap_mm: (n,) gaps to a design (the plate's shape taken out). Each
    residual is scaled by sqrt(k / (k - 1)) for its cell of k points; cells of one point do not count.
    cells: ``_cells(xy_mm, cell_mm)`` when the caller has it already (then ``xy_mm`` may be None).
    """
    inv, count = _cells(xy_mm, cell_mm) if cells is None else cells
    m, n = len(count), len(inv)
    mean = np.zeros(m)
    for a in range(0, n, _CHUNK):
        mean += np.bincount(inv[a : a + _CHUNK], weights=gap_mm[a : a + _CHUNK], minlength=m)
    mean /= count
    n_use = int(count[count > 1].sum())
    if n_use < 10:
        raise RegistrationError("too few points share a cell to estimate the noise")
    # the residuals in the points' order, a chunk at a time, into one array the median may reorder
    r = np.empty(n_use)
    at = 0
    for a in range(0, n, _CHUNK):
        i_c = inv[a : a + _CHUNK]
        k = count[i_c]
        use = k > 1
        k, i_c = k[use], i_c[use]
        r[at : at + len(k)] = np.abs((gap_mm[a : a + _CHUNK][use] - mean[i_c]) * np.sqrt(k / (k - 1.0)))
        at += len(k)
    return float(1.4826 * np.median(r, overwrite_input=True))


def rest_surface(
    surface: HeightField,
    points_mm: np.ndarray,
    T_meas_design: np.ndarray,
    *,
    noise_mm: float | None = None,
    target_sigmas: float = 0.25,
    confidence: float = 0.99,
    max_cell_mm: float = 20.0,
    min_cell_mm: float = 1.0,
    noise_cell_mm: float = 2.0,
    edge_aware: bool = True,
    up: np.ndarray = np.array([0.0, 0.0, 1.0]),
) -> RestSurface:
    """The patch estimate of the plate (see the module docstring) at the pose ``T_meas_design``.

    surface: the design's height field; points_mm: (n, 3) plate top-surface points, measured frame;
    T_meas_design: (4, 4) design -> measured, near the final pose (after ICP). noise_mm: None
    estimates sigma from the data (:func:`noise_from_gaps`). ``edge_aware`` (the default) also
    holds every patch on the plate's edge at its outer extent by the plane of a block around it
    (:func:`_edge_fits`): without, a plate with raised (springback) edges lets the design sink
    below them by the rise over half a patch (0.1-0.3 mm for 1 mm of springback). Raises
    RegistrationError when fewer than 6 patches remain.
    """
    P = np.asarray(points_mm, dtype=np.float64)  # the caller's (n, 3) float64: no copy is made of it
    if P.ndim != 2 or P.shape[1] != 3 or len(P) < 6:
        raise RegistrationError(f"points_mm must be (n >= 6, 3) mm, got shape {P.shape}")
    if target_sigmas <= 0.0:
        raise RegistrationError(f"target_sigmas must be positive, got {target_sigmas}")
    gap, _, _, valid = deflection_gaps(surface, P, T_meas_design, up, geometry=False)
    # the points over the design: the caller's array and their positions in it (no copy of the points;
    # every per-point array below is a gap (float64), a patch index (int32) or a weight (bool))
    sel = None
    if not valid.all():
        sel = np.flatnonzero(valid)
        sel = sel.astype(np.int32) if len(P) < 2**31 else sel
        gap = gap[sel]
    del valid
    pts = _Points(P, sel)
    if pts.n < 6:
        raise RegistrationError("rest surface: fewer than 6 points lie over the design")
    # the occupied area at 2 mm, so holes and an oblique footprint do not dilute the density
    cells_2mm = _point_cells(pts, 2.0)
    occ = cells_2mm[1]
    if noise_mm is not None:
        sigma = float(noise_mm)
    else:
        sigma = noise_from_gaps(
            None, gap, noise_cell_mm, cells_2mm if noise_cell_mm == 2.0 else _point_cells(pts, noise_cell_mm)
        )
    del cells_2mm
    area = max(len(occ) * 4.0, 1.0)
    density = pts.n / area
    # n from the bound, h from n, M from h: a fixed point reached in a few rounds
    patches = max(area / 25.0, 1.0)
    for _ in range(4):
        q = max_normal_quantile(math.ceil(patches), confidence)
        n_min = max(math.ceil((q / target_sigmas) ** 2), 1)
        cell = float(np.clip(math.sqrt(1.5 * n_min / density), min_cell_mm, max_cell_mm))
        patches = max(2.0 * area / cell**2, 1.0)  # twice: the part-filled patches along the edges
    n_min = min(n_min, max(int(0.66 * density * cell**2), 1))  # the cap: what a patch can hold
    # patches anchored at the points' lower-left corner (any anchor is as good), laid out in the
    # design frame (the points moved into it a chunk at a time)
    T_design_meas = invert_transform(np.asarray(T_meas_design, dtype=np.float64))
    i_cell, j_cell, origin = _design_cells(pts, T_design_meas, cell)
    grid = _grid(i_cell, j_cell)
    del i_cell, j_cell
    inv, count = grid.inv, grid.count
    m = len(count)
    keep = count >= n_min
    if keep.sum() < 6:
        xy = pts.take(np.arange(pts.n))[:, :2]
        raise RegistrationError(
            f"rest surface: only {int(keep.sum())} patches of {cell:.1f} mm hold {n_min} points "
            f"(span {np.ptp(xy, axis=0)} mm)"
        )
    # per patch, the plane of the gaps about the centroid, fitted twice: the second time without the
    # points more than TRIM_SIGMAS off the first plane (the edge band's points of the thickness face,
    # outliers the segmentation's 6-sigma test let through)
    # (the residuals about the patch's plane and the block's curvature: about a plane alone, a bump of
    # sigma 10 mm leaves 0.3 mm of curvature in a 14 mm patch, and the trim took it for outliers)
    w = None
    for _ in range(2):
        mean, mean_gap, b_x, b_y, n_w, moments = _patch_planes(inv, m, pts, gap, w)
        quad = _block_quadratics(grid, mean[:, :2], mean_gap, n_w, moments, cell)
        w = np.empty(pts.n, dtype=bool)
        for a, b in pts.chunks():
            i_c, g_c = inv[a:b], gap[a:b]
            dx, dy, _ = _offsets(i_c, pts.get(a, b), g_c, mean, mean_gap)
            hxx, hxy, hyy = (np.take(v, i_c) for v in quad.hessian.T)
            sxx, sxy, syy = (np.take(v, i_c) for v in moments.T)
            resid = g_c - np.take(mean_gap, i_c) - np.take(b_x, i_c) * dx - np.take(b_y, i_c) * dy
            resid -= 0.5 * (hxx * (dx * dx - sxx) + hyy * (dy * dy - syy)) + hxy * (dx * dy - sxy)
            w[a:b] = np.abs(resid) <= TRIM_SIGMAS * sigma
    count = n_w.astype(np.int64)
    keep &= count >= n_min
    # each patch at its contact point (the centroid, or the bump's top within reach), its gap there
    # from its mean and the block's slope and curvature (a patch mean alone reads a bump's top low)
    offset_xy, contact_gap, n_eff = _contact_values(quad, mean_gap, n_w, moments, cell)
    at = mean.copy()
    at[:, :2] += offset_xy
    reps = [at[keep]]
    rep_gap = [contact_gap[keep]]
    rep_count = [n_eff[keep]]
    n_edge = 0
    if edge_aware:
        # a template resting on a raised edge touches the edge itself: the edge patches are also
        # held at their outer extent, by a plane fitted on a block big enough to keep the bound
        # (only the points of the patches near the edge, moved into the design frame)
        sub = _edge_points(grid, inv)
        e_q, e_g, e_n = _edge_fits(
            grid, inv[sub], apply_transform(T_design_meas, pts.take(sub)) - origin, gap[sub], w[sub],
            n_min, EDGE_INSET * cell,
        )  # fmt: skip
        del sub
        n_edge = len(e_g)
        reps.append(apply_transform(np.asarray(T_meas_design, dtype=np.float64), e_q + origin))
        rep_gap.append(e_g)
        rep_count.append(e_n)
    rep, rep_g, count_eff = np.vstack(reps), np.concatenate(rep_gap), np.concatenate(rep_count)
    # a point's own gap is linear in its height along up: move it so that its gap is the estimate
    g_c, _, _, ok = deflection_gaps(surface, rep, T_meas_design, up, geometry=False)
    up_n = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    rest = rep + np.outer(g_c - rep_g, up_n)
    rest, count = rest[ok], count_eff[ok]
    n_used = max(int(count.min()), 1)
    se = sigma / math.sqrt(n_used)
    bound = max_normal_quantile(len(count), confidence) * se
    result = RestSurface(
        points_mm=rest,
        counts=count,
        noise_mm=sigma,
        cell_mm=cell,
        min_count=n_used,
        standard_error_mm=se,
        bound_mm=bound,
        confidence=confidence,
        target_sigmas=target_sigmas,
        target_met=bound <= target_sigmas * sigma * (1.0 + 1e-9),
        edge_patches=n_edge,
    )
    log.debug("rest_surface", **result.as_dict())
    return result
