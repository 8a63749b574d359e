"""Where the plate lies on the bed, from a sparse cloud of a few fast passes over it.

The cell's locate run sweeps a handful of passes over the bed at a standoff from which the plate's
edges are in the sensor's range; this module turns that cloud into the design's placement:

1. :func:`plate_boundary` -- the plate's points (above the bed plane) and, on each pass's scan grid,
   the points where the plate ends inside the laser line or along the pass: the outline where the
   passes cross it. A run of points that ends because the surface left the sensor's depth range is
   no edge; boundary points within ``range_margin_mm`` of either end of the range are dropped.
2. :func:`design_outline` -- the design's outline: the free edges of the design mesh, projected on
   its x-y plane, sampled every ``outline_step_mm`` with outward normals.
3. :func:`fit_outline` -- a 2D rigid fit (yaw + x, y) of the outline to the boundary points:
   coarse, every yaw (``coarse_yaw_step_deg``) with the translation voted by every boundary point
   against every outline sample (a generalised Hough transform, so that no start has to be near);
   fine, trimmed point-to-line ICP from the best hypotheses; then z from the plate's top (the median
   of measured minus design height). The result says the residual (RMS over the inliers), the part
   of the outline the passes saw (coverage) and how a half turn was decided.
4. The along-pass shift. A timing error between the sensor and the arm (a latency not calibrated,
   or calibrated at another load) puts every point of a pass a little ahead of (or behind) where it
   was measured, along the pass's direction of travel: at the locate speed, 225 mm/s, 1 ms is
   0.23 mm. Passes run both ways, so the shift turns the outline between them, which a short plate's
   edges read as yaw (measured: 0.65 mm ahead on every pass of the simulated cell, 0.2-0.3 deg on a
   300 mm plate at 45 deg). Where the boundary points come from passes run both ways, the chosen
   fit is refined once more with that shift as a fourth unknown (``along_shift_mm``, bounded by
   ``max_along_shift_mm``); it is reported with the result.

The half turn. A rectangle (and most plates' outlines) looks the same turned by 180 deg. Both fits
are made; when one is clearly better (boundary RMS and design-height RMS both lower by more than
``ambiguity_mm``), the design's own asymmetry decides (``resolved_by = "fit"``). Otherwise the yaw
nearer ``yaw_hint_deg`` wins: the trigger's placement where one was given (``"hint"``), else the
cell's convention, a yaw within 90 deg of ``convention_yaw_deg`` (``"convention"``). Either face up:
with ``allow_face_down`` the mirrored outline is fitted too and a clearly better mirrored fit says
the plate lies face down (the placement then has roll 180 deg); a design that looks the same either
way round gives no such answer, and ``face_down`` stays False.

Pure numpy / scipy on whole arrays; never imports ``cellctl``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from analysis.cloud_io import ScanCloud
from analysis.contracts.placement import Placement
from analysis.design.mesh import TriMesh
from analysis.design.outline import mesh_free_edges

__all__ = [
    "DesignOutline",
    "LocateError",
    "LocateResult",
    "LocateSettings",
    "PlateBoundary",
    "design_outline",
    "fit_outline",
    "locate_plate",
    "placement_offset",
    "plate_boundary",
]


class LocateError(ValueError):
    """The plate's outline could not be found or fitted; the message says what was missing."""


@dataclass(frozen=True)
class LocateSettings:
    """How the locate cloud is read and the outline fitted (mm, deg).

    ``bed_z_mm``: the bed's top face (points up to ``min_height_mm`` above it are the bed, not the
    plate; None: the bed is not in the cloud). ``range_z_mm``: (lowest, highest) world z the sensor
    measures on the locate passes (flat passes at one height): a boundary point within
    ``range_margin_mm`` of either is where the surface left the range, no edge. None: no such
    rejection. ``wall_step_mm``: a point this much lower than a neighbour on its pass's grid is on
    the plate's thickness face (a formed plate's edge face is square to its surface, so it leans
    out and a sensor leaning towards it sees it), not its top: no plate point, so that the edge is
    the top's; 0: kept. A cloud's own range, where its passes fly at their own height, is given to
    :func:`plate_boundary` (``ranges_z_mm``). ``column_step``: every k-th point along the laser line is read (0.4 mm at the
    HD8's 0.1 mm pitch; the profiles are 1 mm apart along the pass). ``closing_px``: small holes in a pass's grid closed before its boundary is taken.
    ``boundary_cell_mm``: boundary points thinned to one per cell. ``coarse_yaw_step_deg``,
    ``vote_cell_mm``: the coarse search. ``icp_iterations``, ``trim_mm``: the fine fit (residuals
    beyond ``max(trim_mm, 3 x median)`` are outliers). ``ambiguity_mm``, ``yaw_hint_deg``,
    ``convention_yaw_deg``, ``allow_face_down``: see the module docstring. ``max_rms_mm``,
    ``min_boundary_points``: below these the result is refused (LocateError).
    ``min_constraint_points``: below it the result says it is not ``constrained`` (more passes, across
    the first, are needed). ``max_along_shift_mm``: the largest along-pass shift the final fit may
    estimate (step 4 of the module docstring; 0: none estimated).
    """

    bed_z_mm: float | None = None
    min_height_mm: float = 5.0
    plate_z_mm: tuple[float, float] | None = None
    range_z_mm: tuple[float, float] | None = None
    range_margin_mm: float = 3.0
    wall_step_mm: float = 1.0
    closing_px: int = 2
    column_step: int = 4
    boundary_cell_mm: float = 1.0
    outline_step_mm: float = 2.0
    coarse_yaw_step_deg: float = 5.0
    vote_cell_mm: float = 12.0
    coarse_points: int = 200
    coarse_hypotheses: int = 6
    icp_iterations: int = 40
    trim_mm: float = 5.0
    coverage_mm: float = 3.0
    ambiguity_mm: float = 0.2
    yaw_hint_deg: float | None = None
    convention_yaw_deg: float = 0.0
    allow_face_down: bool = False
    max_rms_mm: float = 2.0
    min_boundary_points: int = 30
    min_constraint_points: float = 40.0
    max_fit_points: int = 3000
    max_along_shift_mm: float = 3.0
    seed: int = 0


@dataclass(frozen=True)
class PlateBoundary:
    """The plate in a locate cloud.

    plate_mm: (n, 3) float64 points on the plate (above the bed), world frame.
    boundary_mm: (k, 3) float64 points where the plate ends (edge crossings), thinned.
    dropped_range: boundary points dropped because the surface left the depth range there.
    travel_xy: (k, 2) unit vectors, world x-y: the direction of travel of each boundary point's pass
    (zeros where a pass's direction could not be told); None: not known.
    """

    plate_mm: np.ndarray
    boundary_mm: np.ndarray
    dropped_range: int
    travel_xy: np.ndarray | None = None


@dataclass(frozen=True)
class DesignOutline:
    """The design's outline in its own frame: ``xy_mm`` (k, 2) samples, ``normal`` (k, 2) outward
    unit normals, ``length_mm`` the perimeter; ``vertices_mm`` (n, 3) the mesh vertices (heights)."""

    xy_mm: np.ndarray
    normal: np.ndarray
    length_mm: float
    vertices_mm: np.ndarray

    def mirrored(self) -> DesignOutline:
        """The outline of the plate turned over about its x axis (y -> -y), heights negated."""
        v = self.vertices_mm * np.array([1.0, -1.0, -1.0])
        return DesignOutline(self.xy_mm * [1.0, -1.0], self.normal * [1.0, -1.0], self.length_mm, v)


@dataclass(frozen=True)
class LocateResult:
    """A fitted placement and how well it fits.

    placement: design frame -> world (yaw, and roll 180 deg when ``face_down``).
    rms_mm: RMS point-to-outline distance of the inlier boundary points after the fit.
    height_rms_mm: RMS of measured minus design height (after the z offset) over the plate points.
    coverage: fraction of the outline with a boundary point within ``coverage_mm``.
    boundary_points, inliers, plate_points: counts. ambiguous: the half-turned fit was as good.
    resolved_by: ``"fit"``, ``"hint"`` or ``"convention"`` (how the half turn was decided).
    score_mm, alternative_score_mm: the fit's and the half-turned fit's robust score (RMS of the
    point-to-outline distances of every boundary point, each capped at ``trim_mm``): what decides
    between them. iterations: of the fine fit. along_shift_mm: how far ahead along its pass's
    travel every boundary point lay (step 4 of the module docstring; 0 when not estimated).
    constraint_points: the smaller eigenvalue of the sum of the inliers' outline normals' outer
    products (about: boundary points, 1 per ``boundary_cell_mm``, that pin the weaker direction);
    near 0 when the passes crossed only edges of one direction (the fit may then slide along them).
    """

    placement: Placement
    face_down: bool
    rms_mm: float
    height_rms_mm: float
    coverage: float
    boundary_points: int
    inliers: int
    plate_points: int
    ambiguous: bool
    resolved_by: str
    score_mm: float
    alternative_score_mm: float
    iterations: int
    constraint_points: float = 0.0
    constrained: bool = True
    candidates: list[dict[str, float]] = field(default_factory=list)
    along_shift_mm: float = 0.0

    def summary(self) -> dict[str, object]:
        """JSON-ready figures for the job record and report."""
        return {
            "placement": self.placement.model_dump(),
            "face_down": self.face_down,
            "rms_mm": round(self.rms_mm, 4),
            "height_rms_mm": round(self.height_rms_mm, 4),
            "coverage": round(self.coverage, 4),
            "boundary_points": self.boundary_points,
            "inliers": self.inliers,
            "plate_points": self.plate_points,
            "ambiguous": self.ambiguous,
            "resolved_by": self.resolved_by,
            "score_mm": round(self.score_mm, 4),
            "alternative_score_mm": round(self.alternative_score_mm, 4),
            "constraint_points": round(self.constraint_points, 1),
            "along_shift_mm": round(self.along_shift_mm, 3),
        }


# ------------------------------------------------------------------------------------------ boundary


def plate_boundary(
    clouds: list[ScanCloud],
    settings: LocateSettings | None = None,
    ranges_z_mm: list[tuple[float, float] | None] | None = None,
) -> PlateBoundary:
    """The plate's points and its boundary crossings in organised locate clouds (world frame, mm).

    ``ranges_z_mm``: each cloud's (lowest, highest) world z the sensor measured on its passes, in
    the clouds' order (passes flown at different heights); None: ``settings.range_z_mm`` for all.

    Each pass (``pass_id`` > 0, numbered from 1; the transit, under 0, is ignored) is a grid of profiles x line points; a
    plate point with a missing neighbour on that grid (after closing holes of ``closing_px``) is a
    boundary point. The ends of the laser line are no boundary; the ends of a pass are (the locate
    passes run from bed edge to bed edge, beyond the plate).

    Raises:
        LocateError: a cloud without its scan organisation, or no plate points at all.
    """
    st = settings or LocateSettings()
    if ranges_z_mm is None:
        ranges_z_mm = [st.range_z_mm] * len(clouds)
    elif len(ranges_z_mm) != len(clouds):
        raise LocateError(f"{len(ranges_z_mm)} depth ranges for {len(clouds)} locate clouds")
    plate_parts, edge_parts, travel_parts = [], [], []
    dropped = 0
    for cloud, range_z in zip(clouds, ranges_z_mm, strict=True):
        if cloud.pass_id is None:
            raise LocateError("the locate cloud has no scan organisation (pass, profile, point)")
        xyz = np.asarray(cloud.xyz_mm, dtype=np.float64)  # a locate run's few passes: its fits in float64
        keep = np.isfinite(xyz).all(axis=1) & (cloud.pass_id > 0)
        if st.bed_z_mm is not None:
            keep &= xyz[:, 2] > st.bed_z_mm + st.min_height_mm
        if st.plate_z_mm is not None:
            keep &= (xyz[:, 2] >= st.plate_z_mm[0]) & (xyz[:, 2] <= st.plate_z_mm[1])
        if st.column_step > 1:  # along the line the points are far denser than along the pass
            keep &= np.asarray(cloud.point_index) % st.column_step == 0
        idx = np.nonzero(keep)[0]
        if not len(idx):
            continue
        plate_parts.append(xyz[idx])
        pid = np.asarray(cloud.pass_id)[idx]
        prof = np.asarray(cloud.profile_index)[idx].astype(np.int64)
        col = np.asarray(cloud.point_index)[idx].astype(np.int64)
        # the publication may thin the line: the columns present, ranked
        present = np.zeros(int(col.max()) + 1, dtype=bool)
        present[col] = True
        rank = np.cumsum(present) - 1
        n_cols = int(present.sum())
        for p in np.unique(pid):  # a handful of passes: one mask each
            sel = np.flatnonzero(pid == p)
            r = prof[sel] - prof[sel].min()
            c = rank[col[sel]]
            grid = np.zeros((int(r.max()) + 1, n_cols), dtype=bool)
            grid[r, c] = True
            if st.wall_step_mm > 0:
                wall = _on_wall(r, c, xyz[idx[sel], 2], grid.shape, st.wall_step_mm)
                grid[r[wall], c[wall]] = False
            # Beyond the first and last profile the pass saw nothing there (no plate): padded empty.
            # Beyond the line's ends it saw nothing at all: padded with copies of the end columns, so
            # that the line's end is never taken for an edge.
            k = st.closing_px + 1
            g = np.pad(grid, ((k, k), (0, 0)))
            g = np.pad(g, ((0, 0), (k, k)), mode="edge")
            if st.closing_px > 0:
                g = ndimage.binary_closing(g, iterations=st.closing_px) | g
            inner = ndimage.binary_erosion(g)[k:-k, k:-k]
            on_edge = ~inner[r, c]
            edge = xyz[idx[sel[on_edge]]]
            if range_z is not None:  # where the surface left the depth range: no edge
                ok = (edge[:, 2] > range_z[0] + st.range_margin_mm) & (
                    edge[:, 2] < range_z[1] - st.range_margin_mm
                )
                dropped += int((~ok).sum())
                edge = edge[ok]
            edge_parts.append(edge)
            travel_parts.append(np.broadcast_to(_travel_xy(prof[sel], xyz[idx[sel], :2]), (len(edge), 2)))
    if not plate_parts:
        raise LocateError(
            "no plate points in the locate cloud: nothing above the bed within the sensor's range"
        )
    plate = np.concatenate(plate_parts)
    edge = np.concatenate(edge_parts) if edge_parts else np.empty((0, 3))
    travel = np.concatenate(travel_parts) if travel_parts else np.empty((0, 2))
    if len(edge) and st.boundary_cell_mm > 0:
        cell = np.floor(edge[:, :2] / st.boundary_cell_mm).astype(np.int64)
        _, first = np.unique(cell, axis=0, return_index=True)
        keep_first = np.sort(first)
        edge, travel = edge[keep_first], travel[keep_first]
    return PlateBoundary(plate_mm=plate, boundary_mm=edge, dropped_range=dropped, travel_xy=travel)


def _travel_xy(profile: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(2,) unit direction of travel of a pass from its points' positions against their profile
    index (zeros when the pass's points span less than two profiles)."""
    p = profile.astype(np.float64)
    dp = p - p.mean()
    den = float(dp @ dp)
    if den <= 0.0:
        return np.zeros(2)
    slope = dp @ (xy - xy.mean(axis=0)) / den  # mm per profile along x and y
    n = float(np.linalg.norm(slope))
    return slope / n if n > 0 else np.zeros(2)


def _on_wall(
    r: np.ndarray, c: np.ndarray, z: np.ndarray, shape: tuple[int, int], step_mm: float
) -> np.ndarray:
    """Points (grid rows ``r``, columns ``c``, heights ``z``) more than ``step_mm`` below one of their
    four grid neighbours: on a face that falls away from the top, not on the top."""
    zg = np.full((shape[0] + 2, shape[1] + 2), -np.inf)
    zg[r + 1, c + 1] = z
    above = np.maximum.reduce([zg[r, c + 1], zg[r + 2, c + 1], zg[r + 1, c], zg[r + 1, c + 2]])
    return above - z > step_mm


# ------------------------------------------------------------------------------------------- outline


def design_outline(mesh: TriMesh, step_mm: float = 2.0) -> DesignOutline:
    """The free edges of ``mesh`` (:func:`analysis.design.outline.mesh_free_edges`) on its x-y plane,
    sampled every ``step_mm``, with normals pointing away from the triangle each edge belongs to.

    Every free edge counts, not only the outer loop: a hole's edge or a separate piece's outline is
    an edge the locate passes see as well. Each edge is sampled on its own (at the middles of
    ``ceil(length / step_mm)`` equal parts), not the chained loop resampled by arc length.

    Raises:
        LocateError: a mesh without free edges (closed) or with no extent in x-y.
    """
    if step_mm <= 0:
        raise LocateError(f"outline step must be positive, got {step_mm}")
    e, opposite = mesh_free_edges(mesh)  # every free edge: holes' edges are edges the passes see too
    if not len(e):
        raise LocateError("the design mesh has no free edges: no outline to fit")
    v = mesh.vertices_mm
    a, b, o = v[e[:, 0], :2], v[e[:, 1], :2], v[opposite, :2]
    d = b - a
    seg_len = np.linalg.norm(d, axis=1)
    ok = seg_len > 1e-9
    a, b, o, d, seg_len = a[ok], b[ok], o[ok], d[ok], seg_len[ok]
    n = np.column_stack([d[:, 1], -d[:, 0]]) / seg_len[:, None]
    flip = np.einsum("ij,ij->i", n, o - a) > 0  # the triangle lies inside: the normal points away
    n[flip] *= -1.0
    k = np.maximum(1, np.ceil(seg_len / step_mm).astype(np.int64))
    seg = np.repeat(np.arange(len(a)), k)
    frac = (np.arange(k.sum()) - np.repeat(np.cumsum(k) - k, k) + 0.5) / np.repeat(k, k)
    xy = a[seg] + frac[:, None] * d[seg]
    if np.ptp(xy, axis=0).min() <= 0:
        raise LocateError("the design's outline has no extent in x-y")
    return DesignOutline(xy_mm=xy, normal=n[seg], length_mm=float(seg_len.sum()), vertices_mm=v.copy())


# ----------------------------------------------------------------------------------------------- fit


def _rot(yaw_rad: float) -> np.ndarray:
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.array([[c, -s], [s, c]])


def _wrap_deg(a: float) -> float:
    return float((a + 180.0) % 360.0 - 180.0)


@dataclass
class _Fit:
    yaw_rad: float
    t_mm: np.ndarray
    rms_mm: float
    inliers: int
    iterations: int
    score: float
    along_shift_mm: float = 0.0


def _coarse(
    bxy: np.ndarray, outline: DesignOutline, st: LocateSettings, rng: np.random.Generator
) -> list[tuple[float, np.ndarray, float]]:
    """(yaw_rad, t_mm, votes) hypotheses: for every yaw, the translation most boundary points vote for."""
    if len(bxy) > st.coarse_points:
        bxy = bxy[rng.choice(len(bxy), st.coarse_points, replace=False)]
    step = max(1, round(st.vote_cell_mm / st.outline_step_mm))
    oxy = outline.xy_mm[::step]
    cell = st.vote_cell_mm
    reach = float(np.linalg.norm(oxy, axis=1).max())
    lo = bxy.min(axis=0) - reach - cell
    hi = bxy.max(axis=0) + reach + cell
    nb = np.ceil((hi - lo) / cell).astype(np.int64) + 1
    best: list[tuple[float, np.ndarray, float]] = []
    for yaw in np.deg2rad(np.arange(0.0, 360.0, st.coarse_yaw_step_deg)):
        ro = oxy @ _rot(yaw).T
        votes = (bxy[:, None, :] - ro[None, :, :]).reshape(-1, 2)
        ij = np.floor((votes - lo) / cell).astype(np.int64)
        flat = ij[:, 0] * nb[1] + ij[:, 1]
        counts = np.bincount(flat, minlength=int(nb[0] * nb[1]))
        # a 2 x 2 box sum: a peak split over neighbouring bins counts whole
        c2 = counts.reshape(nb[0], nb[1])
        box = c2[:-1, :-1] + c2[1:, :-1] + c2[:-1, 1:] + c2[1:, 1:]
        k = int(np.argmax(box))
        i, j = divmod(k, box.shape[1])
        t = lo + (np.array([i, j]) + 1.0) * cell
        best.append((float(yaw), t, float(box[i, j])))
    best.sort(key=lambda h: -h[2])
    # the strongest hypotheses at distinct yaws (neighbouring yaw steps are one peak)
    chosen: list[tuple[float, np.ndarray, float]] = []
    for h in best:
        if all(abs(_wrap_deg(np.rad2deg(h[0] - c[0]))) > 3 * st.coarse_yaw_step_deg for c in chosen):
            chosen.append(h)
        if len(chosen) >= st.coarse_hypotheses:
            break
    return chosen


def _icp(
    bxy: np.ndarray,
    outline: DesignOutline,
    tree: cKDTree,
    yaw: float,
    t: np.ndarray,
    st: LocateSettings,
    travel: np.ndarray | None = None,
) -> _Fit:
    """Trimmed point-to-line ICP of world boundary points ``bxy`` onto the outline, from (yaw, t).
    With ``travel`` ((n, 2) world unit vectors, each point's pass's direction of travel), the shift
    along it is a fourth unknown (step 4 of the module docstring): each point is taken back by it."""
    t = np.asarray(t, dtype=np.float64).copy()
    inl = np.zeros(len(bxy), dtype=bool)
    it = 0
    res = np.zeros(len(bxy))
    shift = 0.0
    for it in range(1, st.icp_iterations + 1):
        R = _rot(yaw)
        p = bxy if travel is None else bxy - shift * travel
        q = (p - t) @ R  # world -> design frame
        d, j = tree.query(q)
        n = outline.normal[j]
        res = np.einsum("ij,ij->i", q - outline.xy_mm[j], n)
        gate = (
            max(st.trim_mm, 3.0 * float(np.median(d)))
            if it > 1
            else max(st.trim_mm, float(np.percentile(d, 80)))
        )
        inl = d <= gate
        if inl.sum() < 3:
            break
        # linearised: a small turn w and shift s of the points in the design frame
        qi, ni, ri = q[inl], n[inl], res[inl]
        A = np.column_stack([ni[:, 1] * qi[:, 0] - ni[:, 0] * qi[:, 1], ni[:, 0], ni[:, 1]])
        if travel is not None:  # d res / d shift = -n . (R^T u)
            A = np.column_stack([A, -np.einsum("ij,ij->i", ni, travel[inl] @ R)])
        x, *_ = np.linalg.lstsq(A, -ri, rcond=None)
        w, s = float(x[0]), x[1:3]
        if travel is not None:
            shift += float(x[3])
        # q' = Rw q + s with q = R^T (p - t)  =>  p = R Rw^T (q' - s) + t
        Rn = R @ _rot(w).T
        t = t - Rn @ s
        yaw = float(np.arctan2(Rn[1, 0], Rn[0, 0]))
        if abs(w) < 1e-7 and np.linalg.norm(s) < 1e-4 and (travel is None or abs(x[3]) < 1e-4):
            break
    R = _rot(yaw)
    q = ((bxy if travel is None else bxy - shift * travel) - t) @ R
    d, j = tree.query(q)
    res = np.einsum("ij,ij->i", q - outline.xy_mm[j], outline.normal[j])
    gate = max(st.trim_mm, 3.0 * float(np.median(d)))
    inl = d <= gate
    rms = float(np.sqrt(np.mean(res[inl] ** 2))) if inl.any() else np.inf
    # the score to compare fits: truncated squared distance over every point (outliers cost the cap)
    score = float(np.sqrt(np.mean(np.minimum(d, st.trim_mm) ** 2)))
    return _Fit(yaw, t, rms, int(inl.sum()), it, score, shift)


def _heights(plate_mm: np.ndarray, outline: DesignOutline, fit: _Fit) -> tuple[float, float]:
    """(z of the design origin, RMS of measured - design height) for the plate points under a fit."""
    q = (plate_mm[:, :2] - fit.t_mm) @ _rot(fit.yaw_rad)
    v = outline.vertices_mm
    tree = cKDTree(v[:, :2])
    _, j = tree.query(q, k=3)
    zd = v[j, 2].mean(axis=1)
    dz = plate_mm[:, 2] - zd
    z0 = float(np.median(dz))
    r = dz - z0
    r = r[np.abs(r) <= max(3.0, 3.0 * float(np.median(np.abs(r))))]
    return z0, float(np.sqrt(np.mean(r**2))) if len(r) else np.inf


def _coverage(bxy: np.ndarray, outline: DesignOutline, fit: _Fit, within_mm: float) -> float:
    q = (bxy - fit.t_mm) @ _rot(fit.yaw_rad)
    d, _ = cKDTree(q).query(outline.xy_mm, distance_upper_bound=within_mm)
    return float(np.mean(np.isfinite(d)))


def _constraint(bxy: np.ndarray, outline: DesignOutline, fit: _Fit, st: LocateSettings) -> float:
    q = (bxy - fit.t_mm) @ _rot(fit.yaw_rad)
    d, j = cKDTree(outline.xy_mm).query(q)
    n = outline.normal[j[d <= max(st.trim_mm, 3.0 * float(np.median(d)))]]
    return float(np.linalg.eigvalsh(n.T @ n)[0]) if len(n) else 0.0


def fit_outline(
    boundary: PlateBoundary, outline: DesignOutline, settings: LocateSettings | None = None
) -> LocateResult:
    """Fit the design's outline to the plate's boundary points (see the module docstring).

    Raises:
        LocateError: too few boundary points, or no fit within ``max_rms_mm``.
    """
    st = settings or LocateSettings()
    b = boundary.boundary_mm
    if len(b) < st.min_boundary_points:
        raise LocateError(
            f"only {len(b)} boundary points in the locate cloud (need {st.min_boundary_points}): the passes "
            "did not cross the plate's edges within the sensor's range (is the plate on the bed, and the "
            "[locate] standoff right for its height?)"
        )
    rng = np.random.default_rng(st.seed)
    bxy = b[:, :2]
    travel = boundary.travel_xy
    if travel is not None and travel.shape != bxy.shape:
        raise LocateError(f"{len(travel)} directions of travel for {len(bxy)} boundary points")
    if len(bxy) > st.max_fit_points:
        pick = rng.choice(len(bxy), st.max_fit_points, replace=False)
        bxy = bxy[pick]
        travel = None if travel is None else travel[pick]
    plate = boundary.plate_mm
    if len(plate) > 20000:
        plate = plate[rng.choice(len(plate), 20000, replace=False)]
    faces = [(False, outline)] + ([(True, outline.mirrored())] if st.allow_face_down else [])
    fits: list[tuple[bool, DesignOutline, _Fit]] = []
    for face_down, ol in faces:
        tree = cKDTree(ol.xy_mm)
        for yaw, t, _votes in _coarse(bxy, ol, st, rng):
            f = _icp(bxy, ol, tree, yaw, t, st)
            fits.append((face_down, ol, f))
            # its half turn, fitted on its own (the coarse vote may have seen only one of the two)
            # (turned about the design origin, which stays where it is)
            fits.append((face_down, ol, _icp(bxy, ol, tree, f.yaw_rad + np.pi, f.t_mm, st)))
    fits.sort(key=lambda x: x[2].score)
    face_down, ol, best = fits[0]
    # the half-turned partner of the best (same face), and the best of the other face
    partner = min(
        (
            x
            for x in fits
            if x[0] == face_down and abs(_wrap_deg(np.rad2deg(x[2].yaw_rad - best.yaw_rad) - 180.0)) < 5.0
        ),
        key=lambda x: x[2].score,
        default=None,
    )
    z0, hrms = _heights(plate, ol, best)
    ambiguous, resolved_by, alt_rms = False, "fit", np.inf
    if partner is not None:
        pf = partner[2]
        pz0, phrms = _heights(plate, ol, pf)
        if pf.score - best.score <= st.ambiguity_mm and abs(phrms - hrms) <= st.ambiguity_mm:
            ambiguous = True
            hint = st.yaw_hint_deg
            resolved_by = "hint" if hint is not None else "convention"
            ref = hint if hint is not None else st.convention_yaw_deg
            da = abs(_wrap_deg(np.rad2deg(best.yaw_rad) - ref))
            db = abs(_wrap_deg(np.rad2deg(pf.yaw_rad) - ref))
            if db < da:
                best, pf, z0, hrms = pf, best, pz0, phrms
        alt_rms = pf.score
    if st.allow_face_down:
        other = next((x for x in fits if x[0] != face_down), None)
        if other is not None and other[2].score - best.score <= st.ambiguity_mm:
            face_down, ol = False, outline  # both faces fit: a design the same either way round
            if best not in [x[2] for x in fits if not x[0]]:
                best = min((x[2] for x in fits if not x[0]), key=lambda f: f.score)
                z0, hrms = _heights(plate, ol, best)
    if st.max_along_shift_mm > 0 and travel is not None and _both_ways(travel):
        refined = _icp(bxy, ol, cKDTree(ol.xy_mm), best.yaw_rad, best.t_mm, st, travel)
        if abs(refined.along_shift_mm) <= st.max_along_shift_mm and refined.rms_mm <= best.rms_mm:
            best = refined
            bxy = bxy - best.along_shift_mm * travel
            z0, hrms = _heights(plate, ol, best)
    if not np.isfinite(best.rms_mm) or best.rms_mm > st.max_rms_mm:
        raise LocateError(
            f"the design's outline does not fit the plate's edges: RMS {best.rms_mm:.2f} mm over "
            f"{best.inliers} of {len(bxy)} boundary points (limit {st.max_rms_mm} mm); is it the right design?"
        )
    yaw_deg = _wrap_deg(np.rad2deg(best.yaw_rad))
    rpy = [180.0, 0.0, yaw_deg] if face_down else [0.0, 0.0, yaw_deg]
    placement = Placement(pos_mm=[float(best.t_mm[0]), float(best.t_mm[1]), z0], rpy_deg=rpy)
    return LocateResult(
        placement=placement,
        face_down=face_down,
        rms_mm=best.rms_mm,
        height_rms_mm=hrms,
        coverage=_coverage(bxy, ol, best, st.coverage_mm),
        boundary_points=len(b),
        inliers=best.inliers,
        plate_points=len(boundary.plate_mm),
        ambiguous=ambiguous,
        resolved_by=resolved_by,
        score_mm=best.score,
        alternative_score_mm=float(alt_rms),
        iterations=best.iterations,
        constraint_points=(cp := _constraint(bxy, ol, best, st) * len(b) / len(bxy)),
        constrained=cp >= st.min_constraint_points,
        along_shift_mm=best.along_shift_mm,
        candidates=[
            {
                "yaw_deg": round(_wrap_deg(np.rad2deg(f.yaw_rad)), 3),
                "score_mm": round(f.score, 4),
                "face_down": fd,
            }
            for fd, _, f in fits[:6]
        ],
    )


def _both_ways(travel: np.ndarray) -> bool:
    """Whether the boundary points come from passes run both ways along their main direction (the
    along-pass shift is then told from the placement): a tenth of them at least each way."""
    moving = travel[np.linalg.norm(travel, axis=1) > 0.5]
    if len(moving) == 0:
        return False
    main = np.linalg.eigh(moving.T @ moving)[1][:, -1]  # the principal direction, either sign
    along = moving @ main
    least = 0.1 * len(moving)
    return bool(np.count_nonzero(along > 0.5) >= least and np.count_nonzero(along < -0.5) >= least)


def locate_plate(
    clouds: list[ScanCloud],
    design: TriMesh,
    settings: LocateSettings | None = None,
    ranges_z_mm: list[tuple[float, float] | None] | None = None,
) -> LocateResult:
    """The placement of ``design`` in locate clouds: :func:`plate_boundary` (``ranges_z_mm``: each
    cloud's depth range in world z, see there), :func:`design_outline`, :func:`fit_outline`."""
    st = settings or LocateSettings()
    boundary = plate_boundary(clouds, st, ranges_z_mm)
    return fit_outline(boundary, design_outline(design, st.outline_step_mm), st)


def placement_offset(found: Placement, given: Placement) -> tuple[float, float]:
    """(xy distance of the design origins in mm, |yaw difference| in deg) between two placements."""
    d = float(np.hypot(found.x_mm - given.x_mm, found.y_mm - given.y_mm))
    return d, abs(_wrap_deg(found.yaw_deg - given.yaw_deg))
