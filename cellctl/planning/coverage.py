"""Coverage planning: raster and edge passes over a design surface, and the predicted coverage.

The plan is built in the plate's design frame (x along the length, y across, z up; see
``analysis.plates``) and moved into the robot base frame with the nominal placement. Raster passes run
along the plate's longer footprint axis, the laser line across them; the sensor looks along the
surface normal from the standoff, so the curved surface stays inside the depth range, which is
checked for every waypoint (including the height change the placement uncertainty can bring). The
passes cover the footprint grown by the placement-uncertainty margin. Edge passes run along the four
edges with the sensor tilted outward, so the edge and the thickness face are lit. Links lift over the
surface between passes; the approach and retract move along the normal.

The predicted coverage casts the laser fan of every simulated profile onto the design with open3d's
``RaycastingScene`` and counts the footprint cells that receive a valid return.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
import structlog
from scipy.interpolate import RectBivariateSpline
from scipy.ndimage import distance_transform_edt

from analysis.mesh import TriMesh
from analysis.placement import Placement, placement_transform
from cellctl.planning.plan import CoverageReport, PlanInputError, PlanRefused, Segment
from cellctl.planning.settings import PlannerSettings

__all__ = ["DesignSurface", "build_segments", "design_surface", "placement_margin_mm", "predict_coverage"]

log = structlog.get_logger(__name__)

_GRID_PITCH_MM = 10.0
_DEPTH_SAMPLES = 11
_LINK_MAX_ROT_STEP_DEG = 3.0


def _raycasting_scene(mesh: TriMesh) -> o3d.t.geometry.RaycastingScene:
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(mesh.vertices_mm.astype(np.float32)),
        o3d.core.Tensor(mesh.triangles.astype(np.uint32)),
    )
    return scene


@dataclass(frozen=True)
class DesignSurface:
    """A smooth height field z(x, y) fitted to a design's top surface (plate frame, mm).

    ``x_min_mm``..``y_max_mm``: the footprint (the mesh's XY bounds). ``valid`` (nx, ny) bool: grid
    cells where a vertical ray hit the mesh. Outside the footprint, heights are extrapolated along the
    tangent plane at the nearest footprint point.
    """

    x_min_mm: float
    x_max_mm: float
    y_min_mm: float
    y_max_mm: float
    xs_mm: np.ndarray
    ys_mm: np.ndarray
    valid: np.ndarray
    spline: RectBivariateSpline

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
        h = self.spline.ev(xc, yc)
        gx = self.spline.ev(xc, yc, dx=1)
        gy = self.spline.ev(xc, yc, dy=1)
        return h + gx * (x - xc) + gy * (y - yc), gx, gy

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
        # holes and a non-rectangular outline: fill with the nearest sampled height so the spline is smooth
        _, (ix, iy) = distance_transform_edt(~valid, return_indices=True)
        Z = Z[ix, iy]
    spline = RectBivariateSpline(xs, ys, Z, kx=3, ky=3)
    return DesignSurface(float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1]), xs, ys, valid, spline)


def placement_margin_mm(surface: DesignSurface, settings: PlannerSettings) -> float:
    """How far beyond the nominal footprint the passes must reach: the placement shift plus the
    displacement of the farthest corner under the rotation uncertainty."""
    L, W = surface.size_mm
    half_diag = 0.5 * float(np.hypot(L, W))
    return settings.placement_uncertainty_mm + half_diag * float(
        np.sin(np.deg2rad(settings.placement_uncertainty_deg))
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
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Sensor poses looking at surface points ``xy`` (n, 2) plate frame.

    Returns ``(pos_mm (n, 3), R_plate_sensor (n, 3, 3), surface_pt_mm (n, 3), normal (n, 3))``: the
    sensor z axis along minus the normal (tilted ``tilt_deg`` towards ``-outward`` for edge passes),
    the sensor y axis along ``sign * travel`` and the laser line (x) across it.
    """
    h, gx, gy = surface.height_and_gradient(xy[:, 0], xy[:, 1])
    n = _unit(np.column_stack([-gx, -gy, np.ones_like(gx)]))
    pts = np.column_stack([xy, h])
    z = -n
    if outward_xy is not None and tilt_deg > 0:
        o = np.broadcast_to(np.array([outward_xy[0], outward_xy[1], 0.0]), n.shape)
        o = _unit(o - np.sum(o * n, axis=1, keepdims=True) * n)
        a = np.deg2rad(tilt_deg)
        # looking in from outside and above, so the vertical thickness face is lit
        z = _unit(-n * np.cos(a) - o * np.sin(a))
    t3 = np.broadcast_to(np.array([travel_xy[0], travel_xy[1], 0.0]), z.shape)
    y = sign * _unit(t3 - np.sum(t3 * z, axis=1, keepdims=True) * z)
    x = np.cross(y, z)
    R = np.stack([x, y, z], axis=2)
    return pts - standoff_mm * z, R, pts, n


def _check_depth(
    surface: DesignSurface,
    label: str,
    pos: np.ndarray,
    R: np.ndarray,
    settings: PlannerSettings,
    margin_mm: float,
) -> None:
    """Refuse when the laser line, at any waypoint, would leave the depth range on the curved surface
    (plate-frame poses; the placement uncertainty moves the surface under the line by up to
    |gradient| x margin)."""
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
        i, k = np.argwhere(bad)[0]
        raise PlanRefused(
            f"the laser line would leave the depth range: predicted depth {depth[i, k]:.1f} +/- "
            f"{spread[i, k]:.1f} mm at {u[k]:+.1f} mm along the line",
            pass_label=label,
            point_index=int(i),
            limit=f"depth range [{settings.depth_min_mm}, {settings.depth_max_mm}] mm",
        )


def _samples(a: float, b: float, step: float) -> np.ndarray:
    n = max(2, int(np.ceil(abs(b - a) / step)) + 1)
    return np.linspace(a, b, n)


def _slerp_frames(R0: np.ndarray, R1: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Rotations (m, 3, 3) on the geodesic from R0 to R1 at fractions ``u`` (m,)."""
    dR = R0.T @ R1
    angle = float(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1.0, 1.0)))
    if angle < 1e-9:
        return np.broadcast_to(R0, (u.size, 3, 3)).copy()
    if np.pi - angle < 1e-6:
        # half turn: the axis is the eigenvector of dR for eigenvalue 1
        w, vecs = np.linalg.eigh(dR + dR.T)
        axis = vecs[:, np.argmax(w)]
    else:
        axis = np.array([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]]) / (2 * np.sin(angle))
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    th = u * angle
    Rs = (
        np.eye(3)[None]
        + np.sin(th)[:, None, None] * K[None]
        + (1 - np.cos(th))[:, None, None] * (K @ K)[None]
    )
    return R0[None] @ Rs


def _rotation_angle_deg(R0: np.ndarray, R1: np.ndarray) -> float:
    return float(np.rad2deg(np.arccos(np.clip((np.trace(R0.T @ R1) - 1) / 2, -1.0, 1.0))))


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
    rot = _rotation_angle_deg(R0, R1)
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
    return Segment(kind=kind, label=label, pos_mm=pos, R_base_sensor=_slerp_frames(R0, R1, u))


def build_segments(
    surface: DesignSurface, placement: Placement, settings: PlannerSettings, *, sign: float = 1.0
) -> tuple[list[Segment], float]:
    """The ordered segments of a scan (base frame) and the placement margin used (mm).

    Order: approach, raster passes (serpentine) with links, links to and along the four edge passes
    (nearest edge first, around the plate), retract. ``sign`` (+1 / -1) picks which way the sensor's
    y axis points along the raster passes; the joint path tries both.

    Raises:
        PlanRefused: the line would leave the depth range somewhere.
    """
    margin = placement_margin_mm(surface, settings)
    L, W = surface.size_mm
    along_x = L >= W
    a2 = np.array([1.0, 0.0]) if along_x else np.array([0.0, 1.0])
    c2 = np.array([0.0, 1.0]) if along_x else np.array([1.0, 0.0])
    lo_a, hi_a = (surface.x_min_mm, surface.x_max_mm) if along_x else (surface.y_min_mm, surface.y_max_mm)
    lo_c, hi_c = (surface.y_min_mm, surface.y_max_mm) if along_x else (surface.x_min_mm, surface.x_max_mm)
    width = hi_c - lo_c + 2 * margin
    w = settings.line_width_mm
    n_pass = 1 if width <= w else int(np.ceil((width - w) / settings.pass_step_mm)) + 1
    first, last = lo_c - margin + w / 2, hi_c + margin - w / 2
    centres = np.array([0.5 * (lo_c + hi_c)]) if n_pass == 1 else np.linspace(first, last, n_pass)

    sweeps: list[tuple[str, str, np.ndarray, np.ndarray]] = []  # (kind, label, pos, R) plate frame
    for i, c in enumerate(centres):
        a0, a1 = (lo_a - margin, hi_a + margin) if i % 2 == 0 else (hi_a + margin, lo_a - margin)
        s = _samples(a0, a1, settings.waypoint_step_mm)
        xy = s[:, None] * a2[None] + c * c2[None]
        pos, R, _, _ = _sensor_frames(surface, xy, a2, sign, settings.standoff_mm)
        label = f"scan {i + 1}"
        _check_depth(surface, label, pos, R, settings, margin)
        sweeps.append(("scan", label, pos, R))

    if settings.edge_passes:
        corners = np.array(
            [
                [surface.x_min_mm, surface.y_min_mm],
                [surface.x_max_mm, surface.y_min_mm],
                [surface.x_max_mm, surface.y_max_mm],
                [surface.x_min_mm, surface.y_max_mm],
            ]
        )
        outward = np.array([[0.0, -1.0], [1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]])
        run = settings.placement_uncertainty_mm + w / 2
        end_xy = sweeps[-1][2][-1, :2]
        best = None
        for start in range(4):
            for ccw in (True, False):
                order = [(start + k) % 4 for k in range(4)] if ccw else [(start - k) % 4 for k in range(4)]
                e0 = order[0]
                p_from, p_to = (
                    (corners[e0], corners[(e0 + 1) % 4]) if ccw else (corners[(e0 + 1) % 4], corners[e0])
                )
                d = _unit(p_to - p_from)
                dist = float(np.linalg.norm(p_from - run * d - end_xy))
                if best is None or dist < best[0]:
                    best = (dist, order, ccw)
        _, order, ccw = best
        prev_x = sweeps[-1][3][-1, :, 0]
        for k, e in enumerate(order):
            p_from, p_to = (corners[e], corners[(e + 1) % 4]) if ccw else (corners[(e + 1) % 4], corners[e])
            d = _unit(p_to - p_from)
            s = _samples(-run, float(np.linalg.norm(p_to - p_from)) + run, settings.waypoint_step_mm)
            xy = p_from[None] + s[:, None] * d[None]
            # the sensor's line direction is kept as close as possible to the previous pass's (less wrist roll)
            options = [
                _sensor_frames(surface, xy, d, sg, settings.standoff_mm, outward[e], settings.edge_tilt_deg)
                for sg in (1.0, -1.0)
            ]
            pos, R, _, _ = max(options, key=lambda o: float(o[1][0, :, 0] @ prev_x))
            prev_x = R[-1, :, 0]
            sweeps.append(("edge", f"edge {k + 1}", pos, R))

    segments: list[Segment] = []
    p0, R0 = sweeps[0][2][0], sweeps[0][3][0]
    up0 = -R0[:, 2]
    s = np.linspace(
        settings.approach_mm, 0.0, max(3, int(np.ceil(settings.approach_mm / settings.waypoint_step_mm)) + 1)
    )
    segments.append(
        Segment(
            "approach",
            "approach",
            p0[None] + s[:, None] * up0[None],
            np.broadcast_to(R0, (s.size, 3, 3)).copy(),
        )
    )
    n_link = 0
    for j, (kind, label, pos, R) in enumerate(sweeps):
        if j > 0:
            n_link += 1
            prev = segments[-1]
            segments.append(
                _link(
                    surface,
                    f"link {n_link}",
                    "link",
                    prev.pos_mm[-1],
                    prev.R_base_sensor[-1],
                    pos[0],
                    R[0],
                    settings,
                    settings.link_clearance_mm,
                )
            )
        segments.append(Segment(kind, label, pos, R))
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
    ``coverage_cell_mm``; a cell over the surface is seen when it holds at least one return. The same
    rays are cast against the plate moved to four corners of the placement uncertainty (shift and
    rotation) for ``worst_fraction``.
    """
    sweeps = [s for s in segments if s.is_sweep]
    if not sweeps:
        raise PlanInputError("segments: no sweep to predict coverage from")
    parts = [_resample_sweep(s, settings.coverage_profile_step_mm) for s in sweeps]
    pos = np.concatenate([p[0] for p in parts])
    x = np.concatenate([p[1] for p in parts])
    z = np.concatenate([p[2] for p in parts])
    u = np.linspace(-settings.line_width_mm / 2, settings.line_width_mm / 2, settings.coverage_rays)
    dirs = _unit(settings.standoff_mm * z[:, None, :] + u[None, :, None] * x[:, None, :]).reshape(-1, 3)
    origins = np.repeat(pos, u.size, axis=0)
    zrep = np.repeat(z, u.size, axis=0)
    rays = o3d.core.Tensor(np.hstack([origins, dirs]).astype(np.float32))
    cos_max = np.cos(np.deg2rad(settings.max_incidence_deg))

    cell = settings.coverage_cell_mm
    nx = max(1, int(np.ceil((surface.x_max_mm - surface.x_min_mm) / cell)))
    ny = max(1, int(np.ceil((surface.y_max_mm - surface.y_min_mm) / cell)))
    cx = surface.x_min_mm + (np.arange(nx) + 0.5) * (surface.x_max_mm - surface.x_min_mm) / nx
    cy = surface.y_min_mm + (np.arange(ny) + 0.5) * (surface.y_max_mm - surface.y_min_mm) / ny
    CX, CY = np.meshgrid(cx, cy, indexing="ij")
    surface_cells = surface.inside(CX.ravel(), CY.ravel()).reshape(nx, ny)
    total = int(surface_cells.sum())
    if total == 0:
        raise PlanInputError("design: no footprint cell lies over the surface")

    def fraction(pl: Placement) -> tuple[float, int]:
        T = placement_transform(pl)
        scene = _raycasting_scene(design.transformed(T))
        hit = scene.cast_rays(rays)
        t = hit["t_hit"].numpy().astype(np.float64)
        nrm = hit["primitive_normals"].numpy().astype(np.float64)
        ok = np.isfinite(t)
        depth = t * np.sum(dirs * zrep, axis=1)
        cos_inc = np.abs(np.sum(nrm * dirs, axis=1))
        ok &= (depth >= settings.depth_min_mm) & (depth <= settings.depth_max_mm) & (cos_inc >= cos_max)
        p = origins[ok] + t[ok, None] * dirs[ok]
        local = (p - T[:3, 3]) @ T[:3, :3]  # base -> plate frame
        ix = np.floor((local[:, 0] - surface.x_min_mm) / (surface.x_max_mm - surface.x_min_mm) * nx).astype(
            np.int64
        )
        iy = np.floor((local[:, 1] - surface.y_min_mm) / (surface.y_max_mm - surface.y_min_mm) * ny).astype(
            np.int64
        )
        keep = (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)
        seen = np.zeros((nx, ny), dtype=bool)
        seen[ix[keep], iy[keep]] = True
        n_seen = int((seen & surface_cells).sum())
        return n_seen / total, n_seen

    frac, n_seen = fraction(placement)
    worst = frac
    du, dd = settings.placement_uncertainty_mm, settings.placement_uncertainty_deg
    if du > 0 or dd > 0:
        for sx, sy, sa in ((1, 1, 1), (-1, -1, -1), (1, -1, -1), (-1, 1, 1)):
            moved = Placement.on_bed(
                placement.x_mm + sx * du,
                placement.y_mm + sy * du,
                placement.yaw_deg + sa * dd,
                z_mm=placement.z_mm,
            )
            worst = min(worst, fraction(moved)[0])
    log.debug("coverage_predicted", fraction=frac, worst=worst, rays=int(origins.shape[0]))
    return CoverageReport(
        fraction=frac,
        worst_fraction=worst,
        cells_total=total,
        cells_seen=n_seen,
        cell_mm=cell,
        profiles=int(pos.shape[0]),
        rays=int(origins.shape[0]),
    )
