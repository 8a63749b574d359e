"""Synthetic scans without a robot: a formed plate on the bed, scanned like the cell scans it.

What the generator models, in the bed frame (x, y on the bed, z up, bed top at z = 0):

* **Scene.** The bed plane, support beams (boxes standing on the bed, see :class:`BedScene`) and
  the formed plate: top surface ``z = height + dz`` in the design frame (see ``plates``), bottom
  ``thickness_mm`` below it, vertical thickness faces over the footprint's edges. The plate gets a
  random placement: any yaw, an XY offset, a small tilt, then it is lowered onto the supports.
  ``T_bed_design`` (design frame -> bed frame) is exact and written to the truth file.
* **Raster passes.** Straight passes at a heading close to the plate's long axis (as a planner
  working from the nominal placement would choose; ``heading_error_deg`` off), covering the
  plate's footprint plus ``margin_mm`` so the bed and supports appear. Each profile is a laser line
  of ``points_per_profile`` rays ``point_pitch_mm`` apart looking straight down (an orthographic
  line, like the HD8's resampled output); profiles every ``profile_step_mm``; neighbouring passes
  overlap by ``pass_overlap_mm``.
* **Edge passes.** One pass along each plate edge with the line across the edge and the view
  tilted ``edge_view_deg`` outward, so the thickness face is seen as well as the top edge and the
  bed beyond it.
* **Sensor effects.** Every ray is cast exactly (bed, support boxes, plate top by Newton on the
  analytic surface, thickness faces), then: Gaussian range noise ``noise_mm`` along the ray;
  missing returns where the incidence angle exceeds ``grazing_limit_deg`` and at random
  (``dropout_fraction``); sparse outliers (``outlier_fraction``) displaced 1 mm to
  ``outlier_range_mm`` along the ray. A sensor clock offset (``clock_offset_ms`` at
  ``scan_speed_mm_s``) places each raster profile off along its travel, alternately forward and
  backward (the passes of a real raster run both ways).

Organisation: ``pass_id`` numbers raster passes from 0 and the four edge passes after them,
``profile_index`` counts profiles within a pass, ``point_index`` counts rays along the line. Missing returns
are absent from the output, the indices of the others are kept.

The command line, ``cellctl synth``, lives with the other commands (``cellctl/commands/synth_cmd.py``).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import structlog

from analysis.cloud_io import ScanCloud, write_cloud_ply
from analysis.contracts.placement import Placement, placement_transform
from analysis.design.mesh import TriMesh, save_mesh
from analysis.design.plates import (
    FormingError,
    PlateSpec,
    canonical_corner_order,
    default_forming_error,
    design_mesh,
    footprint_bounds,
    footprint_contains,
    footprint_grid,
    formed_corners,
    outline_edges,
    plate_spec,
    surface_gradient,
)

__all__ = [
    "BedScene",
    "ScanSettings",
    "SupportBox",
    "SynthError",
    "SynthScan",
    "formed_plate_mesh",
    "random_placement",
    "synthesize_scan",
    "write_formed_mesh",
    "write_synth",
]

log = structlog.get_logger(__name__)


class SynthError(ValueError):
    """Settings that cannot produce a scan (named field and value in the message)."""


@dataclass(frozen=True)
class SupportBox:
    """An axis-aligned support standing on the bed (bed frame, mm)."""

    x_min_mm: float
    x_max_mm: float
    y_min_mm: float
    y_max_mm: float
    height_mm: float


@dataclass(frozen=True)
class BedScene:
    """The bed (plane z = 0) and its supports. Default: three 80 mm beams, 60 mm high, across y."""

    supports: tuple[SupportBox, ...] = (
        SupportBox(-490.0, -410.0, -1100.0, 1100.0, 60.0),
        SupportBox(-40.0, 40.0, -1100.0, 1100.0, 60.0),
        SupportBox(410.0, 490.0, -1100.0, 1100.0, 60.0),
    )


@dataclass(frozen=True)
class ScanSettings:
    """How the synthetic scan is taken. Defaults: HD8-0050W density (0.1 mm x 500 points, 0.5 mm)."""

    point_pitch_mm: float = 0.1
    points_per_profile: int = 500
    profile_step_mm: float = 0.5
    pass_overlap_mm: float = 5.0
    margin_mm: float = 30.0
    heading_error_deg: float = 3.0
    edge_passes: bool = True
    edge_view_deg: float = 30.0
    noise_mm: float = 0.02
    outlier_fraction: float = 1e-4
    outlier_range_mm: float = 20.0
    dropout_fraction: float = 0.002
    grazing_limit_deg: float = 80.0
    # a sensor clock off the robot's by this much places every profile that far along its travel:
    # speed x offset, forward on even raster passes, backward on odd ones (the cell scans both ways)
    clock_offset_ms: float = 0.0
    scan_speed_mm_s: float = 100.0

    def __post_init__(self) -> None:
        for name in ("point_pitch_mm", "profile_step_mm"):
            if not getattr(self, name) > 0:
                raise SynthError(f"{name}: must be positive, got {getattr(self, name)!r}")
        if self.points_per_profile < 8:
            raise SynthError(f"points_per_profile: need at least 8, got {self.points_per_profile}")
        line = (self.points_per_profile - 1) * self.point_pitch_mm
        if not 0 <= self.pass_overlap_mm < line:
            raise SynthError(
                f"pass_overlap_mm: must be in [0, {line}) (the line length), got {self.pass_overlap_mm}"
            )
        for name in ("noise_mm", "outlier_fraction", "dropout_fraction", "margin_mm"):
            if getattr(self, name) < 0:
                raise SynthError(f"{name}: must not be negative, got {getattr(self, name)!r}")
        if not 0 < self.edge_view_deg < 80:
            raise SynthError(f"edge_view_deg: must be in (0, 80), got {self.edge_view_deg}")

    @classmethod
    def coarse(cls, **overrides) -> ScanSettings:
        """Test-speed settings: 1 mm points, 2 mm profiles (about 0.6 M points for the sail plate)."""
        base = {"point_pitch_mm": 1.0, "points_per_profile": 50, "profile_step_mm": 2.0}
        base.update(overrides)
        return cls(**base)


def random_placement(
    rng: np.random.Generator,
    *,
    offset_mm: float = 100.0,
    tilt_max_deg: float = 0.5,
    yaw_deg: float | None = None,
) -> Placement:
    """Any yaw (or ``yaw_deg``), an XY offset within +-offset_mm, a tilt up to tilt_max_deg about a
    random horizontal axis. The height is left 0: :func:`synthesize_scan` lowers the plate onto the
    supports."""
    yaw = float(rng.uniform(0.0, 360.0))
    x, y = float(rng.uniform(-offset_mm, offset_mm)), float(rng.uniform(-offset_mm, offset_mm))
    tilt, tilt_axis = float(rng.uniform(0.0, tilt_max_deg)), float(rng.uniform(0.0, 360.0))
    return Placement.on_bed(x, y, yaw if yaw_deg is None else yaw_deg, tilt_deg=tilt, tilt_axis_deg=tilt_axis)


@dataclass
class SynthScan:
    """A synthetic scan with its ground truth.

    xyz_mm: (n, 3) float64, bed frame.
    pass_id, profile_index, point_index: (n,) int32 scan organisation (the names of
    :class:`~analysis.cloud_io.ScanCloud`).
    T_bed_design: (4, 4) design frame -> bed frame (exact).
    is_outlier: (n,) bool, points the generator displaced on purpose.
    """

    xyz_mm: np.ndarray
    pass_id: np.ndarray
    profile_index: np.ndarray
    point_index: np.ndarray
    T_bed_design: np.ndarray
    spec: PlateSpec
    error: FormingError
    placement: Placement
    settings: ScanSettings
    scene: BedScene
    seed: int | None
    n_raster_passes: int
    is_outlier: np.ndarray = field(repr=False)

    @property
    def cloud(self) -> ScanCloud:
        """The scan as an organised :class:`ScanCloud`."""
        return ScanCloud(self.xyz_mm, self.pass_id, self.profile_index, self.point_index)

    def design_mesh(self, pitch_mm: float = 5.0) -> TriMesh:
        """The design top surface (design frame) the plate was formed from."""
        return design_mesh(self.spec, pitch_mm=pitch_mm)

    def corners_bed_mm(self) -> np.ndarray:
        """(4, 3) the formed plate's top corners in the bed frame, in ``boundary.find_corners`` order."""
        c = formed_corners(self.spec, self.error)
        cb = c @ self.T_bed_design[:3, :3].T + self.T_bed_design[:3, 3]
        return canonical_corner_order(cb)

    def truth_dict(self) -> dict:
        """Everything needed to check an analysis of this scan (JSON-ready)."""
        return {
            "plate": self.spec.to_dict(),
            "forming_error": self.error.to_dict(),
            "T_bed_design": self.T_bed_design.tolist(),
            "placement": self.placement.model_dump(),
            "corners_bed_mm": self.corners_bed_mm().tolist(),
            "settings": asdict(self.settings),
            "scene": asdict(self.scene),
            "seed": self.seed,
            "n_points": len(self.xyz_mm),
            "n_raster_passes": self.n_raster_passes,
            "n_outliers": int(self.is_outlier.sum()),
            "frames": "points in the bed frame; design frame per analysis.design.plates; T maps design -> bed",
        }


def _place(spec: PlateSpec, error: FormingError, placement: Placement, scene: BedScene) -> np.ndarray:
    """T_bed_design: rotate, then lower the plate until its bottom touches the highest support under it
    (the placement's height is not used)."""
    R = placement_transform(placement)[:3, :3]
    U, V = footprint_grid(spec, 241, 161)
    Z, _, _ = surface_gradient(spec, error, U, V)
    bottom = np.column_stack([U.ravel(), V.ravel(), Z.ravel() - spec.thickness_mm]) @ R.T
    bottom[:, :2] += (placement.x_mm, placement.y_mm)
    lift = -bottom[:, 2].min()  # no support under it: it lies on the bed
    for s in scene.supports:
        over = (
            (bottom[:, 0] >= s.x_min_mm)
            & (bottom[:, 0] <= s.x_max_mm)
            & (bottom[:, 1] >= s.y_min_mm)
            & (bottom[:, 1] <= s.y_max_mm)
        )
        if over.any():
            lift = max(lift, s.height_mm - bottom[over, 2].min())
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = (placement.x_mm, placement.y_mm, lift)
    return T


def _height_range(spec: PlateSpec, error: FormingError) -> tuple[float, float]:
    """Bounds of the formed top surface's height over the footprint (mm), with a safety margin."""
    U, V = footprint_grid(spec, 241, 161)
    Z, _, _ = surface_gradient(spec, error, U, V)
    return float(Z.min()) - 5.0, float(Z.max()) + 5.0


@dataclass
class _Hits:
    t: np.ndarray
    normal: np.ndarray  # bed frame, unit, facing any way


def _cast(
    o: np.ndarray, d: np.ndarray, spec: PlateSpec, error: FormingError, T: np.ndarray, scene: BedScene
) -> _Hits:
    """Exact first hit of rays o + t d (bed frame, d unit, pointing down) with the scene."""
    n = len(o)
    inf = np.full(n, np.inf)
    # Bed plane z = 0.
    t_best = np.where(d[:, 2] < 0, -o[:, 2] / np.minimum(d[:, 2], -1e-12), inf)
    normal = np.zeros((n, 3))
    normal[:, 2] = 1.0
    # Support boxes, slab method, on the rays whose path between the box's top and the bed
    # crosses the box's XY extent.
    with np.errstate(divide="ignore", invalid="ignore"):
        for s in scene.supports:
            t_top = (o[:, 2] - s.height_mm) / -d[:, 2]
            xa, xb = o[:, 0] + t_top * d[:, 0], o[:, 0] + t_best * d[:, 0]
            ya, yb = o[:, 1] + t_top * d[:, 1], o[:, 1] + t_best * d[:, 1]
            sub = np.flatnonzero(
                (np.maximum(xa, xb) >= s.x_min_mm)
                & (np.minimum(xa, xb) <= s.x_max_mm)
                & (np.maximum(ya, yb) >= s.y_min_mm)
                & (np.minimum(ya, yb) <= s.y_max_mm)
            )
            if len(sub) == 0:
                continue
            lo = np.array([s.x_min_mm, s.y_min_mm, 0.0])
            hi = np.array([s.x_max_mm, s.y_max_mm, s.height_mm])
            with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
                # slab test: a ray parallel to a slab gets +-inf there, which the min/max below expect
                inv = 1.0 / d[sub]
                t1 = (lo - o[sub]) * inv
                t2 = (hi - o[sub]) * inv
            tmin = np.fmin(t1, t2)
            t_enter = np.nanmax(tmin, axis=1)
            t_exit = np.nanmin(np.fmax(t1, t2), axis=1)
            hit = (t_enter <= t_exit) & (t_enter > 0) & (t_enter < t_best[sub])
            if hit.any():
                axis = np.nanargmax(tmin[hit], axis=1)
                nrm = np.zeros((int(hit.sum()), 3))
                nrm[np.arange(len(axis)), axis] = 1.0
                t_best[sub[hit]] = t_enter[hit]
                normal[sub[hit]] = nrm
    # Plate, in the design frame. Only rays that can reach the plate's bounding slab are cast.
    R, p0 = T[:3, :3], T[:3, 3]
    od = (o - p0) @ R
    dd = d @ R
    x_min, x_max, y_min, y_max = footprint_bounds(spec)
    th = spec.thickness_mm
    z_lo, z_hi = _height_range(spec, error)
    z_lo -= th
    with np.errstate(divide="ignore", invalid="ignore"):
        t_hi = (od[:, 2] - z_hi) / -dd[:, 2]
        t_lo = (od[:, 2] - z_lo) / -dd[:, 2]
    xa, xb = od[:, 0] + t_hi * dd[:, 0], od[:, 0] + t_lo * dd[:, 0]
    ya, yb = od[:, 1] + t_hi * dd[:, 1], od[:, 1] + t_lo * dd[:, 1]
    near = (
        (dd[:, 2] < 0)
        & (np.minimum(xa, xb) <= x_max + 1.0)
        & (np.maximum(xa, xb) >= x_min - 1.0)
        & (np.minimum(ya, yb) <= y_max + 1.0)
        & (np.maximum(ya, yb) >= y_min - 1.0)
    )
    sub = np.flatnonzero(near)
    if len(sub) == 0:
        return _Hits(t_best, normal)
    o_s, d_s = od[sub], dd[sub]
    # Start where the ray meets the height of the surface below its origin: exact for a vertical
    # ray over a level plate, so Newton needs two or three steps instead of six.
    z_o, _, _ = surface_gradient(spec, error, o_s[:, 0], o_s[:, 1])
    t = np.clip((o_s[:, 2] - z_o) / -d_s[:, 2], t_hi[sub], t_lo[sub])
    for _ in range(12):
        x = o_s[:, 0] + t * d_s[:, 0]
        y = o_s[:, 1] + t * d_s[:, 1]
        z, gx, gy = surface_gradient(spec, error, x, y)
        g = o_s[:, 2] + t * d_s[:, 2] - z
        dg = d_s[:, 2] - gx * d_s[:, 0] - gy * d_s[:, 1]
        step = g / np.where(np.abs(dg) > 1e-9, dg, -1e-9)
        t = t - step
        if np.max(np.abs(step)) < 1e-7:
            break
    x = o_s[:, 0] + t * d_s[:, 0]
    y = o_s[:, 1] + t * d_s[:, 1]
    z, gx, gy = surface_gradient(spec, error, x, y)
    ok = (np.abs(o_s[:, 2] + t * d_s[:, 2] - z) < 1e-5) & footprint_contains(spec, x, y) & (t > 0)
    hit = ok & (t < t_best[sub])
    if hit.any():
        nd = np.column_stack([-gx[hit], -gy[hit], np.ones(int(hit.sum()))])
        nd /= np.linalg.norm(nd, axis=1, keepdims=True)
        t_best[sub[hit]] = t[hit]
        normal[sub[hit]] = nd @ R.T
    # Thickness faces: vertical walls over the outline's edges, facing the ray. In edge k's chord
    # frame (s along, c outward) the wall is c = k s (chord - s): a quadratic in the ray's t.
    with np.errstate(divide="ignore", invalid="ignore"):
        for ed in outline_edges(spec):
            s0 = (o_s[:, 0] - ed.a[0]) * ed.e[0] + (o_s[:, 1] - ed.a[1]) * ed.e[1]
            s1 = d_s[:, 0] * ed.e[0] + d_s[:, 1] * ed.e[1]
            c0 = (o_s[:, 0] - ed.a[0]) * ed.n[0] + (o_s[:, 1] - ed.a[1]) * ed.n[1]
            c1 = d_s[:, 0] * ed.n[0] + d_s[:, 1] * ed.n[1]
            kb, L = ed.k_per_mm, ed.chord_mm
            qa = -kb * s1 * s1
            qb = kb * s1 * (L - 2.0 * s0) - c1
            qc = kb * s0 * (L - s0) - c0
            lin = np.abs(qa) < 1e-14 * np.maximum(np.abs(qb), 1e-300)
            disc = qb * qb - 4.0 * qa * qc
            root = np.sqrt(np.maximum(disc, 0.0))
            qd = np.where(lin, 1.0, 2.0 * qa)
            roots = [
                np.where(lin, -qc / qb, (-qb - root) / qd),
                np.where(lin, np.inf, (-qb + root) / qd),
            ]
            tw = np.full(len(sub), np.inf)
            for r in roots:
                sr = s0 + r * s1
                nrm_xy = ed.outward(sr)
                facing = nrm_xy[:, 0] * d_s[:, 0] + nrm_xy[:, 1] * d_s[:, 1] < 0
                zr = o_s[:, 2] + r * d_s[:, 2]
                good = (disc >= 0) & (r > 0) & (sr >= 0) & (sr <= L) & facing & (zr <= z_hi) & (zr >= z_lo)
                tw = np.where(good & (r < tw), r, tw)
            cand = np.flatnonzero(np.isfinite(tw))
            if len(cand) == 0:
                continue
            tw = tw[cand]
            q = o_s[cand] + tw[:, None] * d_s[cand]
            zt, _, _ = surface_gradient(spec, error, q[:, 0], q[:, 1])
            inside = (q[:, 2] <= zt) & (q[:, 2] >= zt - th) & (tw < t_best[sub[cand]])
            if inside.any():
                sq = (q[inside, 0] - ed.a[0]) * ed.e[0] + (q[inside, 1] - ed.a[1]) * ed.e[1]
                nd = np.column_stack([ed.outward(sq), np.zeros(int(inside.sum()))])
                rows = sub[cand[inside]]
                t_best[rows] = tw[inside]
                normal[rows] = nd @ R.T
    return _Hits(t_best, normal)


def _sense(
    o: np.ndarray, d: np.ndarray, hits: _Hits, settings: ScanSettings, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Apply the sensor: returns (points (k, 3), kept mask (n,), outlier flags (k,))."""
    n = len(o)
    cos_inc = np.abs(np.einsum("ij,ij->i", hits.normal, d))
    keep = np.isfinite(hits.t) & (cos_inc >= np.cos(np.deg2rad(settings.grazing_limit_deg)))
    keep &= rng.random(n) >= settings.dropout_fraction
    t = hits.t + rng.normal(0.0, settings.noise_mm, n) if settings.noise_mm > 0 else hits.t.copy()
    outlier = rng.random(n) < settings.outlier_fraction
    if outlier.any():
        mag = rng.uniform(1.0, max(settings.outlier_range_mm, 1.0), int(outlier.sum()))
        t[outlier] += mag * rng.choice([-1.0, 1.0], int(outlier.sum()))
    pts = o[keep] + t[keep, None] * d[keep]
    return pts, keep, outlier[keep]


def synthesize_scan(
    spec: PlateSpec | None = None,
    error: FormingError | None = None,
    *,
    settings: ScanSettings | None = None,
    placement: Placement | None = None,
    scene: BedScene | None = None,
    seed: int | None = 0,
) -> SynthScan:
    """Scan a formed plate lying on the bed; returns the organised cloud and its exact truth.

    spec: the design (default: the paper's 1200 x 800 x 15 sail plate).
    error: forming error (default: :func:`plates.default_forming_error`; pass ``FormingError()``
        for a perfectly formed plate).
    placement: where the plate lies (default: random from ``seed``, any yaw).
    seed: seeds the placement, the heading error, noise, dropouts and outliers.
    """
    spec = spec or plate_spec()
    error = default_forming_error(spec) if error is None else error
    settings = settings or ScanSettings()
    scene = scene or BedScene()
    rng = np.random.default_rng(seed)
    placement = placement or random_placement(rng)
    T = _place(spec, error, placement, scene)
    R = T[:3, :3]

    # Footprint in the bed frame and the raster heading along the plate's long axis.
    fc = formed_corners(spec, error) @ R.T + T[:3, 3]
    axis_xy = R[:2, 0]
    heading = np.arctan2(axis_xy[1], axis_xy[0]) + np.deg2rad(rng.normal(0.0, settings.heading_error_deg))
    e_s = np.array([np.cos(heading), np.sin(heading)])
    e_c = np.array([-np.sin(heading), np.cos(heading)])
    s_vals, c_vals = fc[:, :2] @ e_s, fc[:, :2] @ e_c
    s0, s1 = s_vals.min() - settings.margin_mm, s_vals.max() + settings.margin_mm
    c0, c1 = c_vals.min() - settings.margin_mm, c_vals.max() + settings.margin_mm
    line = (settings.points_per_profile - 1) * settings.point_pitch_mm
    spacing = line - settings.pass_overlap_mm
    n_pass = max(1, int(np.ceil((c1 - c0 - line) / spacing)) + 1)
    c_start = 0.5 * (c0 + c1) - 0.5 * ((n_pass - 1) * spacing + line)
    n_prof = int(np.floor((s1 - s0) / settings.profile_step_mm)) + 1
    z_sensor = float(fc[:, 2].max() + 300.0)

    j = np.arange(settings.points_per_profile)
    k = np.arange(n_prof)
    out_pts, out_pass, out_prof, out_point, out_outl = [], [], [], [], []
    for p in range(n_pass):
        S, Jg = np.meshgrid(s0 + k * settings.profile_step_mm, j, indexing="ij")
        C = c_start + p * spacing + Jg * settings.point_pitch_mm
        xy = S.reshape(-1, 1) * e_s + C.reshape(-1, 1) * e_c
        o = np.column_stack([xy, np.full(len(xy), z_sensor)])
        d = np.tile([0.0, 0.0, -1.0], (len(o), 1))
        hits = _cast(o, d, spec, error, T, scene)
        pts, keep, outl = _sense(o, d, hits, settings, rng)
        if settings.clock_offset_ms:
            lag_mm = (
                settings.scan_speed_mm_s * settings.clock_offset_ms * 1e-3 * (1.0 if p % 2 == 0 else -1.0)
            )
            pts[:, :2] += lag_mm * e_s
        out_pts.append(pts)
        out_pass.append(np.full(len(pts), p, np.int32))
        prof_idx, pt_idx = np.meshgrid(k, j, indexing="ij")
        out_prof.append(prof_idx.ravel()[keep].astype(np.int32))
        out_point.append(pt_idx.ravel()[keep].astype(np.int32))
        out_outl.append(outl)

    if settings.edge_passes:
        alpha = np.deg2rad(settings.edge_view_deg)
        w = (j - (settings.points_per_profile - 1) / 2) * settings.point_pitch_mm
        for e, ed in enumerate(outline_edges(spec)):
            # along the edge curve (a bowed edge too), the line across it, the view tilted outward
            s = np.arange(-settings.margin_mm, ed.chord_mm + settings.margin_mm, settings.profile_step_mm)
            exy = ed.point(s)
            ez, _, _ = surface_gradient(spec, error, exy[:, 0], exy[:, 1])
            edge_bed = np.column_stack([exy, ez]) @ R.T + T[:3, 3]
            out_d = ed.outward(s)
            n_out = np.column_stack([out_d, np.zeros(len(s))]) @ R.T
            n_out[:, 2] = 0.0
            n_out /= np.linalg.norm(n_out, axis=1, keepdims=True)
            d1 = -np.sin(alpha) * n_out + np.array([0.0, 0.0, -np.cos(alpha)])
            u1 = np.cos(alpha) * n_out + np.array([0.0, 0.0, -np.sin(alpha)])
            o = (edge_bed[:, None, :] + w[None, :, None] * u1[:, None, :] - 300.0 * d1[:, None, :]).reshape(
                -1, 3
            )
            d = np.repeat(d1, len(w), axis=0)
            hits = _cast(o, d, spec, error, T, scene)
            pts, keep, outl = _sense(o, d, hits, settings, rng)
            out_pts.append(pts)
            out_pass.append(np.full(len(pts), n_pass + e, np.int32))
            prof_idx, pt_idx = np.meshgrid(np.arange(len(s)), j, indexing="ij")
            out_prof.append(prof_idx.ravel()[keep].astype(np.int32))
            out_point.append(pt_idx.ravel()[keep].astype(np.int32))
            out_outl.append(outl)

    scan = SynthScan(
        xyz_mm=np.concatenate(out_pts),
        pass_id=np.concatenate(out_pass),
        profile_index=np.concatenate(out_prof),
        point_index=np.concatenate(out_point),
        T_bed_design=T,
        spec=spec,
        error=error,
        placement=placement,
        settings=settings,
        scene=scene,
        seed=seed,
        n_raster_passes=n_pass,
        is_outlier=np.concatenate(out_outl),
    )
    log.info(
        "synth_scan", points=len(scan.xyz_mm), raster_passes=n_pass, profiles_per_pass=n_prof,
        yaw_deg=round(placement.yaw_deg, 3), plate=spec.kind,
    )  # fmt: skip
    return scan


def sibling_paths(out: str | Path) -> tuple[Path, Path, Path]:
    """(scan, design mesh, truth JSON) paths for ``--out``: scan.ply -> scan-design.ply, scan-truth.json."""
    out = Path(out)
    return out, out.with_name(f"{out.stem}-design.ply"), out.with_name(f"{out.stem}-truth.json")


def write_synth(scan: SynthScan, out: str | Path, *, design_pitch_mm: float = 5.0) -> tuple[Path, Path, Path]:
    """Write the scan PLY, ``<stem>-design.ply`` (design frame) and ``<stem>-truth.json``; returns the paths."""
    scan_path, design_path, truth_path = sibling_paths(out)
    if scan_path.suffix.lower() != ".ply":
        raise SynthError(f"out: the scan is written as PLY, got {scan_path.name!r}")
    scan_path.parent.mkdir(parents=True, exist_ok=True)
    write_cloud_ply(scan.cloud, scan_path)
    save_mesh(scan.design_mesh(design_pitch_mm), design_path)
    truth = scan.truth_dict()
    truth["design_mesh"] = design_path.name
    truth["design_pitch_mm"] = design_pitch_mm
    truth_path.write_text(json.dumps(truth, indent=2))
    return scan_path, design_path, truth_path


def formed_plate_mesh(
    spec: PlateSpec,
    error: FormingError | None,
    *,
    pitch_mm: float = 4.0,
    T_file_design: np.ndarray | None = None,
) -> TriMesh:
    """A formed plate's top surface (the design of ``spec`` plus ``error``; None: the design itself)
    as a triangle mesh on a ``pitch_mm`` grid, in the design frame or, with ``T_file_design`` (4x4,
    design frame -> file coordinates, mm: ship coordinates), in the file's coordinates as
    :func:`analysis.design.cad_write.write_design` writes the design."""
    mesh = design_mesh(spec, pitch_mm=pitch_mm, error=error)
    return mesh if T_file_design is None else mesh.transformed(np.asarray(T_file_design, dtype=np.float64))


def write_formed_mesh(
    spec: PlateSpec,
    error: FormingError | None,
    path: str | Path,
    *,
    pitch_mm: float = 4.0,
    T_file_design: np.ndarray | None = None,
) -> Path:
    """Write :func:`formed_plate_mesh` as PLY / STL / OBJ (by suffix; PLY keeps the vertices in
    double precision): the ``mesh_file`` of ``[sim.plate] kind = "mesh"``. Returns the path."""
    path = Path(path)
    if path.suffix.lower() not in {".ply", ".stl", ".obj"}:
        raise SynthError(f"formed mesh: write .ply, .stl or .obj, got {path.name!r}")
    path.parent.mkdir(parents=True, exist_ok=True)
    return save_mesh(formed_plate_mesh(spec, error, pitch_mm=pitch_mm, T_file_design=T_file_design), path)
