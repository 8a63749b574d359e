"""Surface extraction (paper section 2.1.1): keep the plate's top surface, drop everything else.

A scan holds the bed, the supports, the plate's thickness faces (seen by the edge passes), sparse
outliers and holes where returns are missing. The paper triangulates the scan and grows regions
over triangle normals; the plate's top is the large smooth region. We do the same, at the speed of
whole-array operations:

1. **Triangulate on the scan grid.** An organised scan (pass, profile, point per point) is a grid
   per pass: neighbouring profiles and neighbouring points are neighbours. We group the grid into
   small cells (``cell_mm``, about 2 x 2 mm: 20 points x 4 profiles at HD8 density) and give each
   cell its mean point and a normal from the neighbouring cells' means (the normal of the two
   triangles of the cell's quad, averaged over the stencil, so 0.02 mm sensor noise no longer
   dominates the normal). Points more than ``gross_outlier_mm`` off their cell's plane are dropped
   and the cells recomputed, so a sparse outlier cannot tilt a cell.
2. **Region growing by normals.** Two neighbouring cells belong to one region when their normals
   differ by less than ``max_normal_angle_deg``; a cell is a growth cell when it agrees with all
   four neighbours. The regions are the connected components of that adjacency, found per pass
   with ``scipy.ndimage.label`` (the vectorised equivalent of seed-and-grow). Passes overlap, so
   regions of different passes that share space (a ``link_voxel_mm`` voxel) with agreeing normals
   are joined with ``scipy.sparse.csgraph.connected_components``.
3. **Keep the plate's top.** The largest region (by cell count) is the plate's top surface. Its
   cells' points, and the points of the cells just around it (the edge band, where the cell
   stencil straddles the edge), are kept when they lie within ``inlier_sigmas`` noise levels of
   the nearest plate cell's plane. The noise level is measured from the plate's own points and
   reported (``noise_sigma_mm``): metrics use it to set their smoothing.

Unorganised clouds (PCD, XYZ) take the paper's Delaunay route: 3-D cells (``cell_mm``, or larger
so that each holds a dozen points) with a PCA plane each, Delaunay triangulation of the cell means'
XY projection plus the cells' 3-D grid neighbours (where the bed shows under the plate's overhang
two layers share the XY plane), region growing over those edges with the same normal-angle test,
then the same point test against the nearest plate cell's plane.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import structlog
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from analysis.cloud_io import ScanCloud

__all__ = [
    "NoPlateError",
    "PassCells",
    "SegmentError",
    "SegmentResult",
    "SegmentSettings",
    "pass_cells",
    "segment_plate",
]

log = structlog.get_logger(__name__)


class SegmentError(ValueError):
    """The input cannot be segmented (wrong shape, too few points)."""


class NoPlateError(SegmentError):
    """No smooth surface large enough to be a plate was found in the cloud."""


@dataclass(frozen=True)
class SegmentSettings:
    """Knobs of :func:`segment_plate` (defaults suit HD8 scans of 1-12 m plates)."""

    cell_mm: float = 2.0
    max_normal_angle_deg: float = 6.0
    gross_outlier_mm: float = 1.0
    inlier_sigmas: float = 6.0
    min_inlier_tol_mm: float = 0.05
    link_voxel_mm: float = 4.0
    min_plate_area_mm2: float = 10_000.0
    min_cell_fill: float = 0.5
    edge_band_cells: int = 5
    max_cell_sample: int = 3_000_000


@dataclass
class SegmentResult:
    """The plate's top surface found in a scan.

    mask: (n,) bool over the input points, True for the plate's top surface.
    points_mm: (k, 3) float64 the selected points (bed frame, mm), whatever the input's dtype.
    source: the input cloud.
    cloud: the selected points as a ScanCloud (organisation kept when the input had it), made on
        first use.
    noise_sigma_mm: robust standard deviation of the top-surface points about their local plane.
    inlier_tol_mm: the plane-distance tolerance used to accept points.
    plate_area_mm2: area of the plate region (cells x cell area, projected on the cell planes).
    n_regions: number of smooth regions found (after joining across passes).
    region_cells: cell counts of the regions, largest first (at most 10).
    method: "grid" (organised scan) or "delaunay".
    point_spacing_mm: the scan's coarser sampling pitch (profile step or line pitch, median over
        passes; for unorganised clouds the 4th-neighbour distance): a mesh or raster built on the
        points needs cells at least this large to be free of holes.
    timings_s: seconds per step.
    """

    mask: np.ndarray
    points_mm: np.ndarray
    source: ScanCloud
    noise_sigma_mm: float
    inlier_tol_mm: float
    plate_area_mm2: float
    n_regions: int
    region_cells: list[int]
    method: str
    point_spacing_mm: float
    timings_s: dict[str, float] = field(default_factory=dict)
    _cloud: ScanCloud | None = field(default=None, repr=False)

    @property
    def cloud(self) -> ScanCloud:
        """The selected points as a ScanCloud, organisation kept (built once, on first use)."""
        if self._cloud is None:
            self._cloud = self.source.subset(self.mask)
        return self._cloud


def dense_ranks(ids: np.ndarray) -> np.ndarray:
    """(n,) int64: each of the non-negative integer ``ids`` replaced by its rank among the distinct
    ids (``np.unique(ids, return_inverse=True)[1]``); counted, not sorted, when the ids are not much
    sparser than the points (a scan's pass ids: 0.2 s of sorting 2.6 M points saved)."""
    ids = np.asarray(ids, dtype=np.int64)
    if len(ids) == 0 or int(ids.min()) < 0 or int(ids.max()) > max(8 * len(ids), 1_000_000):
        return np.unique(ids, return_inverse=True)[1].astype(np.int64)
    rank = np.cumsum(np.bincount(ids) > 0) - 1
    return rank[ids]


#: Within a pass whose grid would be mostly empty, a run of more than this many missing profiles
#: is numbered as this many. The transit rows of a whole scan are one pass (pass 0), from the move
#: to the start to the retract: when some near both ends see the plate (a scan that starts over it,
#: where a stopped scan left the arm) that pass's grid spans every frame of the scan, and a cloud
#: that sparse was taken for no scan grid at all (the slow Delaunay route, which mis-sized such a
#: plate). Far more profiles than a cell spans, so no cell reaches across a shortened gap.
MAX_PROFILE_GAP = 256


def _local_profiles(profile_index: np.ndarray, point_index: np.ndarray) -> np.ndarray:
    """One pass's profile indices numbered from 0 (n,) int64; when the pass's grid (profiles x
    points) would be less than a quarter full, every run of more than :data:`MAX_PROFILE_GAP`
    missing profiles is shortened to that. Decided by the pass's own points alone (a streamed pass
    and the same pass in the whole cloud are numbered alike), and idempotent."""
    p = profile_index.astype(np.int64) - int(profile_index.min())
    span = int(p.max()) + 1
    if span * (int(point_index.max()) + 1) <= 4 * len(p):
        return p
    # the profiles present, counted when the span is not much larger than the points, else sorted
    present = np.flatnonzero(np.bincount(p)) if span <= max(8 * len(p), 1_000_000) else np.unique(p)
    excess = np.maximum(np.diff(present) - 1 - MAX_PROFILE_GAP, 0)
    if not excess.any():
        return p
    shift = np.concatenate([[0], np.cumsum(excess)])
    return p - shift[np.searchsorted(present, p)]


def _profiles_from_zero(cloud: ScanCloud) -> tuple[ScanCloud, int]:
    """Number each pass's profiles from 0 (:func:`_local_profiles`): an acquisition numbers profiles
    by frame over the whole scan (and pass ids may be sparse), which would make the scan grid mostly
    empty places. Returns the cloud so numbered and its passes' grid places (profiles x points,
    summed over the passes)."""
    pid = cloud.pass_id.astype(np.int64)
    prof = cloud.profile_index.astype(np.int64)
    pass_idx = dense_ranks(pid)
    m = int(pass_idx.max()) + 1
    first = np.full(m, np.iinfo(np.int64).max)
    np.minimum.at(first, pass_idx, prof)
    local = prof - first[pass_idx]
    span, width = np.zeros(m, np.int64), np.zeros(m, np.int64)
    np.maximum.at(span, pass_idx, local)
    np.maximum.at(width, pass_idx, cloud.point_index.astype(np.int64))
    span, width = span + 1, width + 1
    for k in np.flatnonzero(span * width > 4 * np.bincount(pass_idx, minlength=m)).tolist():
        sel = np.flatnonzero(pass_idx == k)
        local[sel] = _local_profiles(local[sel], cloud.point_index[sel])
        span[k] = int(local[sel].max()) + 1
    places = int(np.sum(span * width))
    if np.array_equal(local, prof) and np.array_equal(pass_idx, pid):
        return cloud, places
    return ScanCloud(
        cloud.xyz_mm, pass_idx.astype(np.int32), local.astype(np.int32), cloud.point_index
    ), places


def segment_plate(
    cloud: ScanCloud | np.ndarray,
    settings: SegmentSettings | None = None,
    *,
    passes: dict[int, PassCells] | None = None,
) -> SegmentResult:
    """Extract the plate's top surface from a scan cloud.

    cloud: a :class:`ScanCloud` (organised or not) or an (n, 3) float array in mm.
    passes: cells already made by :func:`pass_cells` (a streamed scan), by the pass id of ``cloud``;
    made here for the other passes (used only by the scan-grid route, with these settings).
    Returns a :class:`SegmentResult`; raises :class:`NoPlateError` when no smooth region reaches
    ``min_plate_area_mm2`` and :class:`SegmentError` on unusable input.
    """
    settings = settings or SegmentSettings()
    if not isinstance(cloud, ScanCloud):
        arr = np.asarray(cloud, dtype=np.float64)
        if arr.ndim != 2 or arr.shape[1] != 3:
            raise SegmentError(f"points must be (n, 3), got {arr.shape}")
        cloud = ScanCloud(arr)
    if len(cloud) < 100:
        raise SegmentError(f"{len(cloud)} points: too few to hold a plate")
    if not np.isfinite(cloud.xyz_mm).all():
        raise SegmentError("xyz_mm holds non-finite coordinates")
    if cloud.organised:
        dense = np.unique(cloud.pass_id)  # _profiles_from_zero numbers the passes densely
        done = {int(k): passes[int(pid)] for k, pid in enumerate(dense) if passes and int(pid) in passes}
        cloud, n_grid = _profiles_from_zero(cloud)
        if n_grid <= max(8 * len(cloud), 1_000_000):
            return _segment_grid(cloud, settings, done)
        # Indices this sparse are not a scan grid (a renumbered or merged file): do not allocate it.
        log.warning("segment_sparse_organisation", points=len(cloud), grid_places=n_grid)
    return _segment_delaunay(cloud, settings)


# --------------------------------------------------------------------------------------------- grid


def _cells(X5: np.ndarray, V5: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cells of a (Pc, by, Wc, bx, 3) grid whose invalid entries are zero: (count, sum, mean)."""
    cnt = V5.sum(axis=(1, 3), dtype=np.float64)
    s = X5.sum(axis=3).sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = s / cnt[..., None]
    return cnt, s, mean


def _plane_residual(X5: np.ndarray, mean: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Signed distance (Pc, by, Wc, bx) of every grid point from its cell's plane (mean, normal)."""
    offset = np.einsum("ijk,ijk->ij", mean, normal).astype(X5.dtype)[:, None, :, None]
    n = normal.astype(X5.dtype)[:, None, :, None, :]  # one dtype: no upcast copy of X5
    return X5[..., 0] * n[..., 0] + X5[..., 1] * n[..., 1] + X5[..., 2] * n[..., 2] - offset


def _normals(mean: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Cell normals from central differences of neighbouring cell means; NaN where a neighbour is missing."""
    Pc, Wc, _ = mean.shape
    normal = np.full((Pc, Wc, 3), np.nan)
    if Pc < 3 or Wc < 3:
        return normal
    d_row = mean[2:, 1:-1] - mean[:-2, 1:-1]
    d_col = mean[1:-1, 2:] - mean[1:-1, :-2]
    n = np.cross(d_col, d_row)
    length = np.linalg.norm(n, axis=-1, keepdims=True)
    good = ok[2:, 1:-1] & ok[:-2, 1:-1] & ok[1:-1, 2:] & ok[1:-1, :-2] & ok[1:-1, 1:-1]
    with np.errstate(invalid="ignore", divide="ignore"):
        n = n / length
    n[~good] = np.nan
    normal[1:-1, 1:-1] = n
    return normal


def _smooth(normal: np.ndarray, cos_max: float) -> np.ndarray:
    """Cells whose normal agrees with all four neighbours' (the growth criterion)."""
    Pc, Wc, _ = normal.shape
    sm = np.zeros((Pc, Wc), bool)
    if Pc < 3 or Wc < 3:
        return sm
    c = normal[1:-1, 1:-1]
    agree = np.isfinite(c[..., 0])
    for nb in (normal[2:, 1:-1], normal[:-2, 1:-1], normal[1:-1, 2:], normal[1:-1, :-2]):
        with np.errstate(invalid="ignore"):
            agree &= np.einsum("ijk,ijk->ij", c, nb) > cos_max
    sm[1:-1, 1:-1] = agree
    return sm


def _grid_pitch(points: np.ndarray, idx: np.ndarray) -> tuple[float, float]:
    """Median spacing along the line (points) and across (profiles) of one pass grid, mm."""
    P, W = idx.shape
    rows = np.linspace(0, P - 1, min(P, 64)).astype(int)
    a = idx[rows]
    ok = (a[:, 1:] >= 0) & (a[:, :-1] >= 0)

    def gap(i: np.ndarray, j: np.ndarray) -> np.ndarray:  # float64 whatever the cloud's dtype (a sample)
        return np.linalg.norm(points[i].astype(np.float64) - points[j], axis=1)

    d_pt = gap(a[:, 1:][ok], a[:, :-1][ok]) if ok.any() else np.array([1.0])
    cols = np.linspace(0, W - 1, min(W, 64)).astype(int)
    b = idx[:, cols]
    okb = (b[1:] >= 0) & (b[:-1] >= 0)
    d_pr = gap(b[1:][okb], b[:-1][okb]) if okb.any() else np.array([1.0])
    return float(np.median(d_pt)), float(np.median(d_pr))


@dataclass
class PassCells:
    """One pass's cells and regions (:func:`pass_cells`), made from that pass's points alone: a
    streamed scan computes them as each pass arrives, the whole scan in :func:`segment_plate`.

    index: (k,) the pass's points' indices in the whole cloud; centre: the pass's own origin of its
    float32 coordinates (:func:`_pass_float32`, made again from the cloud where they are needed: a
    scan's passes are kept to the end, their coordinates would be a second copy of the cloud);
    idx: (Pp, Wp) grid -> position in the pass (-1: empty);
    labels: (Pc, Wc) region label within the pass, -1 outside (offset per pass when joined).
    """

    index: np.ndarray
    centre: np.ndarray
    idx: np.ndarray
    by: int
    bx: int
    mean: np.ndarray  # (Pc, Wc, 3) in the pass's coordinates (about ``centre``)
    normal: np.ndarray  # (Pc, Wc, 3), NaN where undefined
    count: np.ndarray  # (Pc, Wc)
    labels: np.ndarray
    n_labels: int
    pitch_mm: float


def _pass_float32(xyz_mm: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """(k, 3) float32 a pass's points about its centre: the cell statistics' coordinates (half the
    memory traffic, and at +-2 m the rounding, 0.1 um, is far below the sensor noise). No float64
    temporary: both operands are rounded to float32 first (a float32 cloud's values exactly)."""
    return np.subtract(xyz_mm, centre, dtype=np.float32)


def pass_cells(
    xyz_mm: np.ndarray,
    profile_index: np.ndarray,
    point_index: np.ndarray,
    index: np.ndarray,
    settings: SegmentSettings | None = None,
) -> PassCells | None:
    """The cells of one pass (step 1 and the per-pass part of step 2 of the module docstring): its
    points ``xyz_mm`` (k, 3) in the cloud's order, their profile (any origin: numbered from the
    pass's first) and point indices, and ``index`` (k,) their indices in the whole cloud. None for
    a pass of fewer than three profiles."""
    st = settings or SegmentSettings()
    n = len(xyz_mm)
    if n == 0:
        return None
    prof = _local_profiles(profile_index, point_index)
    P, width = int(prof.max()) + 1, int(point_index.max()) + 1
    if P < 3:
        return None
    # Cell statistics in float32 about the pass's centre: half the memory traffic, and at +-2 m
    # the rounding (0.1 um) is far below the sensor noise. The selection is exact per point.
    centre = xyz_mm[:: max(1, n // 1000)].mean(axis=0, dtype=np.float64)
    p32 = _pass_float32(xyz_mm, centre)
    # (profile, point) -> position in the pass; duplicated places (a malformed file) keep the last
    itype = np.int32 if n < 2**31 - 1 else np.int64
    grid = np.full(P * width, -1, dtype=itype)
    grid[prof * width + point_index] = np.arange(n, dtype=itype)
    idx = grid.reshape(P, width)
    pitch_pt, pitch_pr = _grid_pitch(xyz_mm, idx)
    bx = max(1, round(st.cell_mm / max(pitch_pt, 1e-6)))
    by = max(1, round(st.cell_mm / max(pitch_pr, 1e-6)))
    Pp, Wp = -(-P // by) * by, -(-width // bx) * bx
    idxp = np.full((Pp, Wp), -1, itype)
    idxp[:P, :width] = idx
    V = idxp >= 0
    Pc, Wc = Pp // by, Wp // bx
    X = p32[np.where(V, idxp, 0)]
    X[~V] = 0.0  # empty grid places add nothing to the cell sums
    X5 = X.reshape(Pc, by, Wc, bx, 3)
    V5 = V.reshape(Pc, by, Wc, bx)
    min_count = st.min_cell_fill * by * bx
    cnt, csum, mean = _cells(X5, V5)
    normal = _normals(mean, cnt >= min_count)
    # Take gross outliers out of their cells' sums: one outlier must not tilt a cell. They are
    # rare, so the cells are corrected rather than summed again.
    with np.errstate(invalid="ignore"):
        gross = V5 & (np.abs(_plane_residual(X5, mean, normal)) > st.gross_outlier_mm)
    if gross.any():
        gi, ga, gj, gb = np.nonzero(gross)
        np.subtract.at(cnt, (gi, gj), 1.0)
        np.subtract.at(csum, (gi, gj), X5[gi, ga, gj, gb])
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = np.where(cnt[..., None] > 0, csum / cnt[..., None], np.nan)
    ok = cnt >= min_count
    normal = _normals(mean, ok)
    smooth = _smooth(normal, float(np.cos(np.deg2rad(st.max_normal_angle_deg))))
    lab, nlab = ndimage.label(smooth)
    index = np.asarray(index)
    index = index.astype(np.int32, copy=False) if len(index) and int(index.max()) < 2**31 - 1 else index
    return PassCells(index, centre, idxp, by, bx, mean, normal, cnt,
                     np.where(lab > 0, lab - 1, -1), int(nlab), max(pitch_pt, pitch_pr))  # fmt: skip


def _segment_grid(
    cloud: ScanCloud, st: SegmentSettings, done: dict[int, PassCells] | None = None
) -> SegmentResult:
    t0 = time.perf_counter()
    timings: dict[str, float] = {}
    pts = cloud.xyz_mm
    n = len(pts)
    pass_id = cloud.pass_id  # int32: no per-point copy
    n_pass = int(pass_id.max()) + 1
    # each pass's points in the cloud's order; int32 positions (4 bytes a point, not 8) where they fit
    order = np.argsort(pass_id, kind="stable").astype(np.int32 if n < 2**31 - 1 else np.int64, copy=False)
    bounds = np.concatenate([[0], np.cumsum(np.bincount(pass_id, minlength=n_pass))])
    timings["grid"] = time.perf_counter() - t0

    cos_max = float(np.cos(np.deg2rad(st.max_normal_angle_deg)))
    passes: list[PassCells | None] = []
    offsets: list[int] = []
    next_label = 0
    t1 = time.perf_counter()
    for p in range(n_pass):
        pc = (done or {}).get(p)
        if pc is None:
            sel = order[bounds[p] : bounds[p + 1]]
            pc = pass_cells(pts[sel], cloud.profile_index[sel], cloud.point_index[sel], sel, st)
        passes.append(pc)
        offsets.append(next_label)
        if pc is not None:
            next_label += pc.n_labels
    pitches = [pc.pitch_mm for pc in passes if pc is not None]
    timings["cells_and_regions"] = time.perf_counter() - t1

    t2 = time.perf_counter()
    if next_label == 0:
        raise NoPlateError("no smooth surface in the cloud (every cell is an edge, a hole or noise)")
    # Join regions across passes where they share space with agreeing normals.
    keys, labs, nrms = [], [], []
    v = st.link_voxel_mm
    for pc, off in zip(passes, offsets, strict=True):
        if pc is None:
            continue
        sel = pc.labels >= 0
        keys.append(np.floor((pc.mean[sel] + pc.centre) / v).astype(np.int64))
        labs.append(pc.labels[sel] + off)
        nrms.append(pc.normal[sel])
    K = np.concatenate(keys)
    L = np.concatenate(labs)
    N = np.concatenate(nrms)
    K -= K.min(axis=0)
    span = K.max(axis=0) + 1
    key = (K[:, 0] * span[1] + K[:, 1]) * span[2] + K[:, 2]
    order = np.argsort(key, kind="stable")
    key, L, N = key[order], L[order], N[order]
    same = (key[1:] == key[:-1]) & (L[1:] != L[:-1])
    agree = np.abs(np.einsum("ij,ij->i", N[1:], N[:-1])) > cos_max
    link = same & agree
    a, b = L[:-1][link], L[1:][link]
    adj = coo_matrix((np.ones(len(a)), (a, b)), shape=(next_label, next_label))
    n_groups, group = connected_components(adj, directed=False)
    cells_per_label = np.bincount(L, minlength=next_label)
    cells_per_group = np.bincount(group, weights=cells_per_label, minlength=n_groups)
    plate_group = int(np.argmax(cells_per_group))
    ranking = np.sort(cells_per_group)[::-1]
    timings["join_passes"] = time.perf_counter() - t2

    # Select points: plate cells and the band around them, against the nearest plate cell's plane.
    t3 = time.perf_counter()
    mean_fill = float(np.mean([pc.count[pc.count > 0].mean() for pc in passes if pc is not None]))
    cand_idx, cand_r, interior_r, area = [], [], [], 0.0
    for k, (pc, off) in enumerate(zip(passes, offsets, strict=True)):
        if pc is not None and k not in (done or {}):
            passes[k] = None  # made here: dropped once its points are tested (its grid, its positions)
        if pc is None or pc.n_labels == 0:
            # a pass with cells but no smooth region (a scan cut a few profiles into its last pass:
            # no cell has its four neighbours) holds no plate cell; its offset may be the label count
            continue
        plate = (pc.labels >= 0) & (group[np.maximum(pc.labels, 0) + off] == plate_group)
        if not plate.any():
            continue
        cell_area = _cell_area(pc.mean, plate)
        area += cell_area
        # The band: cells whose stencil reached over the edge are not growth cells, so the plate's
        # last few millimetres sit in cells around the region; test their points individually.
        band = ndimage.binary_dilation(plate, iterations=st.edge_band_cells) & (pc.count > 0)
        _, (di, dj) = ndimage.distance_transform_edt(~plate, return_indices=True)
        Pc, Wc = plate.shape
        by, bx = pc.by, pc.bx
        dn = pc.normal[di, dj]
        dn[~band] = np.nan
        X5 = _pass_float32(pts[pc.index], pc.centre)[np.maximum(pc.idx, 0)].reshape(Pc, by, Wc, bx, 3)
        with np.errstate(invalid="ignore"):
            r5 = _plane_residual(X5, pc.mean[di, dj], dn)
        sel5 = (pc.idx.reshape(Pc, by, Wc, bx) >= 0) & np.isfinite(r5)
        cand_idx.append(pc.index[pc.idx.reshape(Pc, by, Wc, bx)[sel5]])
        cand_r.append(r5[sel5])
        inner5 = sel5 & plate[:, None, :, None]
        interior_r.append(r5[inner5][::4])
        del pc, X5, r5, sel5, inner5, dn
    if not cand_idx:
        raise NoPlateError("no plate region in the cloud")
    idx_all = np.concatenate(cand_idx)
    r_all = np.concatenate(cand_r)
    del cand_idx, cand_r  # the per-pass parts: not held twice
    r_in = np.concatenate(interior_r)
    r_in = r_in[np.abs(r_in) < st.gross_outlier_mm]
    # Residuals about a cell mean that includes the point itself shrink by sqrt((c - 1) / c).
    shrink = np.sqrt(mean_fill / max(mean_fill - 1.0, 1.0)) if mean_fill > 1.5 else 1.0
    sigma = float(1.4826 * np.median(np.abs(r_in - np.median(r_in))) * shrink) if len(r_in) else 0.0
    tol = max(st.inlier_sigmas * sigma, st.min_inlier_tol_mm)
    mask = np.zeros(n, bool)
    mask[idx_all[np.abs(r_all) < tol]] = True
    timings["select_points"] = time.perf_counter() - t3
    timings["total"] = time.perf_counter() - t0
    if area < st.min_plate_area_mm2:
        raise NoPlateError(
            f"largest smooth region is {area:.0f} mm^2, below min_plate_area_mm2={st.min_plate_area_mm2:.0f}"
        )
    log.info(
        "segment", method="grid", points=n, plate_points=int(mask.sum()), regions=n_groups,
        noise_sigma_mm=round(sigma, 4), area_mm2=round(area), total_s=round(timings["total"], 3),
    )  # fmt: skip
    return SegmentResult(
        mask=mask,
        points_mm=_take_float64(pts, mask),
        source=cloud,
        noise_sigma_mm=sigma,
        inlier_tol_mm=tol,
        plate_area_mm2=area,
        n_regions=int(n_groups),
        region_cells=[int(c) for c in ranking[:10]],
        method="grid",
        point_spacing_mm=float(np.median(pitches)),
        timings_s=timings,
    )


def _take_float64(pts: np.ndarray, mask: np.ndarray, block: int = 1 << 20) -> np.ndarray:
    """(k, 3) float64 the rows of ``pts`` (n, 3) where ``mask``: the plate's points, which every later
    stage does arithmetic on (sums over millions, transforms: float64; docs/operations.md "float32:
    where and where not"), taken from a float32 cloud block by block without a float32 copy first."""
    if pts.dtype == np.float64:
        return np.take(pts, np.flatnonzero(mask), axis=0)  # (a boolean index of (n, 3) takes 3x as long)
    out = np.empty((int(np.count_nonzero(mask)), 3), np.float64)
    at = 0
    for lo in range(0, len(pts), block):
        idx = np.flatnonzero(mask[lo : lo + block])
        idx += lo
        out[at : at + len(idx)] = np.take(pts, idx, axis=0)
        at += len(idx)
    return out


def _cell_area(mean: np.ndarray, sel: np.ndarray) -> float:
    """Approximate area (mm^2) of the selected cells from the spacing of neighbouring cell means."""
    Pc, Wc, _ = mean.shape
    d_row = np.full((Pc, Wc), np.nan)
    d_col = np.full((Pc, Wc), np.nan)
    if Pc > 1:
        d_row[:-1] = np.linalg.norm(mean[1:] - mean[:-1], axis=-1)
    if Wc > 1:
        d_col[:, :-1] = np.linalg.norm(mean[:, 1:] - mean[:, :-1], axis=-1)
    a = d_row[sel] * d_col[sel]
    a = a[np.isfinite(a)]
    if not len(a):
        return 0.0
    # Cells at the region's rim have one undefined spacing; count them at the median size.
    return float(np.median(a) * sel.sum())


# ----------------------------------------------------------------------------------------- delaunay


def _point_spacing_mm(pts: np.ndarray) -> float:
    """Distance to the 4th nearest neighbour (the coarser of the two scan pitches), at the XY median."""
    from scipy.spatial import cKDTree

    c = np.median(pts[:: max(1, len(pts) // 10_000), :2], axis=0)
    for half in (20.0, 60.0, 200.0, 1e9):
        win = pts[(np.abs(pts[:, 0] - c[0]) < half) & (np.abs(pts[:, 1] - c[1]) < half)]
        if len(win) >= 200:
            break
    win = win[:50_000]
    d, _ = cKDTree(win).query(win, k=5)
    return float(np.median(d[:, 4]))


def _segment_delaunay(cloud: ScanCloud, st: SegmentSettings) -> SegmentResult:
    from scipy.spatial import Delaunay

    t0 = time.perf_counter()
    timings: dict[str, float] = {}
    # the route of unorganised files (read in float64): its moments and planes want float64 throughout
    pts = np.asarray(cloud.xyz_mm, dtype=np.float64)
    n = len(pts)
    # Cells big enough for a dozen points over at least two scan lines each, so every cell has its
    # own plane (PCA normal).
    spacing = _point_spacing_mm(pts)
    v = max(st.cell_mm, 2.5 * spacing)
    origin = pts.min(axis=0)
    rel = np.subtract(pts, origin, dtype=np.float32)  # float32: no (n, 3) float64 temporary
    rel *= np.float32(1.0 / v)
    q = rel.astype(np.int64)  # non-negative, so truncation is floor
    del rel
    span = q.max(axis=0) + 1
    key = (q[:, 0] * span[1] + q[:, 1]) * span[2] + q[:, 2]
    # Cell planes need a dozen points, not all of them: a dense cloud's cells are fitted on a
    # regular subsample, then every point is looked up in the cells by binary search.
    stride = max(1, n // st.max_cell_sample)
    if stride > 1:
        uniq, inv_s, counts = np.unique(key[::stride], return_inverse=True, return_counts=True)
        pos = np.minimum(np.searchsorted(uniq, key), len(uniq) - 1)
        inv = np.where(uniq[pos] == key, pos, -1)
        local = pts[::stride] - origin
    else:
        uniq, inv, counts = np.unique(key, return_inverse=True, return_counts=True)
        inv_s = inv
        local = pts - origin  # moments about a nearby origin keep the covariances well conditioned
    m = len(uniq)
    mean = (
        np.column_stack([np.bincount(inv_s, weights=local[:, k], minlength=m) for k in range(3)])
        / counts[:, None]
    )
    cov = np.empty((m, 3, 3))
    for a in range(3):
        for b in range(a, 3):
            s_ab = np.bincount(inv_s, weights=local[:, a] * local[:, b], minlength=m) / counts
            cov[:, a, b] = cov[:, b, a] = s_ab - mean[:, a] * mean[:, b]
    vals, vecs = np.linalg.eigh(cov)
    nrm = vecs[:, :, 0]
    nrm[nrm[:, 2] < 0] *= -1.0
    # Points along a single scan line define no plane: require a spread in two directions.
    has_plane = (counts >= 5) & (vals[:, 1] > 0.05 * vals[:, 2])
    mean += origin
    timings["cells"] = time.perf_counter() - t0

    t1 = time.perf_counter()
    if m < 4:
        raise NoPlateError("too few distinct cells to triangulate")
    # Delaunay in the XY projection gives the cells' neighbours (bridging holes); grow over its edges.
    tri = Delaunay(mean[:, :2])
    simp = tri.simplices
    e = np.concatenate([simp[:, [0, 1]], simp[:, [1, 2]], simp[:, [2, 0]]])
    # Where the edge passes see the bed under the plate's overhang, two layers share the XY plane
    # and Delaunay interleaves them; the cells' 3-D grid neighbours keep each layer connected.
    qc = np.column_stack([uniq // (span[1] * span[2]), (uniq // span[2]) % span[1], uniq % span[2]])
    grid_edges = []
    for off in (
        (1, 0, 0),
        (0, 1, 0),
        (0, 0, 1),
        (1, 1, 0),
        (1, -1, 0),
        (1, 0, 1),
        (0, 1, 1),
        (1, 0, -1),
        (0, 1, -1),
    ):
        nq = qc + off
        ok = (nq >= 0).all(axis=1) & (nq < span).all(axis=1)
        nkey = (nq[:, 0] * span[1] + nq[:, 1]) * span[2] + nq[:, 2]
        pos = np.clip(np.searchsorted(uniq, nkey), 0, m - 1)
        found = ok & (uniq[pos] == nkey)
        grid_edges.append(np.column_stack([np.flatnonzero(found), pos[found]]))
    e = np.sort(np.concatenate([e, *grid_edges]), axis=1).astype(np.int64)
    ekey = np.unique(e[:, 0] * m + e[:, 1])  # 1-D keys: far faster than unique rows
    i, j = ekey // m, ekey % m
    cos_max = float(np.cos(np.deg2rad(st.max_normal_angle_deg)))
    near = np.linalg.norm(mean[i] - mean[j], axis=1) < 2.0 * v
    grow = near & has_plane[i] & has_plane[j] & (np.einsum("ij,ij->i", nrm[i], nrm[j]) > cos_max)
    # A growth cell agrees with every neighbour it has; cells on creases and edges do not grow.
    disagree = near & has_plane[i] & has_plane[j] & ~grow
    bad = np.zeros(m, bool)
    bad[i[disagree]] = True
    bad[j[disagree]] = True
    growth = has_plane & ~bad
    link = grow & growth[i] & growth[j]
    adj = coo_matrix((np.ones(int(link.sum())), (i[link], j[link])), shape=(m, m))
    n_groups, group = connected_components(adj, directed=False)
    group = np.where(growth, group, -1)
    cells_per_group = np.bincount(group[growth], minlength=n_groups)
    plate_group = int(np.argmax(cells_per_group))
    plate = group == plate_group
    area = float(plate.sum() * v * v)
    timings["triangulate_and_grow"] = time.perf_counter() - t1
    if area < st.min_plate_area_mm2:
        raise NoPlateError(
            f"largest smooth region is {area:.0f} mm^2, below min_plate_area_mm2={st.min_plate_area_mm2:.0f}"
        )
    t2 = time.perf_counter()
    # Donor plane per cell: its own for plate cells, a neighbouring plate cell's for the ring around.
    donor = np.where(plate, np.arange(m), -1)
    for _ in range(3):  # growth stops a cell or two short of an edge: reach three cells out
        has = donor >= 0
        ring = near & (has[i] ^ has[j])
        src = np.where(has[i[ring]], i[ring], j[ring])
        dst = np.where(has[i[ring]], j[ring], i[ring])
        donor[dst] = donor[src]
    pd_ = np.where(inv >= 0, donor[inv], -1)
    cand = pd_ >= 0
    r = np.full(n, np.inf)
    r[cand] = np.einsum("ij,ij->i", pts[cand] - mean[pd_[cand]], nrm[pd_[cand]])
    in_plate = (inv >= 0) & plate[inv]
    r_in = r[in_plate & (np.abs(r) < st.gross_outlier_mm)]
    mean_fill = float(counts[plate].mean()) if plate.any() else 1.0
    # A plane fitted through the point itself pulls its residual in; not so for subsampled cells.
    shrink = np.sqrt(mean_fill / max(mean_fill - 3.0, 1.0)) if mean_fill > 4 and stride == 1 else 1.0
    sigma = float(1.4826 * np.median(np.abs(r_in - np.median(r_in))) * shrink) if len(r_in) else 0.0
    tol = max(st.inlier_sigmas * sigma, st.min_inlier_tol_mm)
    mask = np.abs(r) < tol
    timings["select_points"] = time.perf_counter() - t2
    timings["total"] = time.perf_counter() - t0
    ranking = np.sort(cells_per_group)[::-1]
    log.info(
        "segment", method="delaunay", points=n, plate_points=int(mask.sum()), regions=n_groups,
        noise_sigma_mm=round(sigma, 4), area_mm2=round(area), total_s=round(timings["total"], 3),
    )  # fmt: skip
    return SegmentResult(
        mask=mask,
        points_mm=_take_float64(pts, mask),
        source=cloud,
        noise_sigma_mm=sigma,
        inlier_tol_mm=tol,
        plate_area_mm2=area,
        n_regions=int(n_groups),
        region_cells=[int(c) for c in ranking[:10]],
        method="delaunay",
        point_spacing_mm=spacing,
        timings_s=timings,
    )
