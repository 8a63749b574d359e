"""Triangle-mesh scenes for the sensor simulator and batched ray casting against them.

A scene is plain arrays: ``vertices_mm (n, 3) float`` and ``triangles (m, 3) int`` in the world frame,
millimetres. Builders here make the scenes the simulator needs: a plane, a step, and the cell scene
(plate with thickness: top, side walls, bottom; the bed and the supports it rests on).

Ray casting goes through open3d's ``RaycastingScene`` (Embree BVH), called once per batch of rays.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import open3d as o3d

__all__ = [
    "RayHits",
    "Scene",
    "SceneRaycaster",
    "box_scene",
    "cell_scene",
    "merge_scenes",
    "plane_scene",
    "plate_solid",
    "step_scene",
]


@dataclass(frozen=True)
class Scene:
    """A triangle mesh in the world frame.

    Attributes:
        vertices_mm: (n, 3) float64, mm.
        triangles: (m, 3) int64 vertex indices, counter-clockwise seen from outside (normal points out).
    """

    vertices_mm: np.ndarray
    triangles: np.ndarray

    def __post_init__(self) -> None:
        v = np.asarray(self.vertices_mm, dtype=np.float64)
        t = np.asarray(self.triangles, dtype=np.int64)
        if v.ndim != 2 or v.shape[1] != 3:
            raise ValueError(f"Scene.vertices_mm must be (n, 3), got {v.shape}")
        if t.ndim != 2 or t.shape[1] != 3:
            raise ValueError(f"Scene.triangles must be (m, 3), got {t.shape}")
        if t.size and (t.min() < 0 or t.max() >= len(v)):
            raise ValueError(f"Scene.triangles index outside [0, {len(v)})")
        object.__setattr__(self, "vertices_mm", v)
        object.__setattr__(self, "triangles", t)


def merge_scenes(scenes: Sequence[Scene]) -> Scene:
    """Concatenate meshes into one scene (indices are re-based)."""
    offsets = np.cumsum([0] + [len(s.vertices_mm) for s in scenes[:-1]])
    return Scene(
        np.concatenate([s.vertices_mm for s in scenes]),
        np.concatenate([s.triangles + off for s, off in zip(scenes, offsets, strict=True)]),
    )


def plane_scene(
    z_mm: float = 0.0, half_size_mm: float = 500.0, center_xy_mm: Sequence[float] = (0.0, 0.0)
) -> Scene:
    """A horizontal square at height ``z_mm``, normal +z, ``2 * half_size_mm`` wide."""
    cx, cy = center_xy_mm
    h = half_size_mm
    v = np.array(
        [[cx - h, cy - h, z_mm], [cx + h, cy - h, z_mm], [cx + h, cy + h, z_mm], [cx - h, cy + h, z_mm]]
    )
    return Scene(v, np.array([[0, 1, 2], [0, 2, 3]]))


def box_scene(min_mm: Sequence[float], max_mm: Sequence[float]) -> Scene:
    """An axis-aligned closed box between corners ``min_mm`` and ``max_mm`` (outward normals)."""
    x0, y0, z0 = min_mm
    x1, y1, z1 = max_mm
    v = np.array(
        [
            [x0, y0, z0],
            [x1, y0, z0],
            [x1, y1, z0],
            [x0, y1, z0],
            [x0, y0, z1],
            [x1, y0, z1],
            [x1, y1, z1],
            [x0, y1, z1],
        ]
    )
    t = np.array(
        [
            [0, 2, 1], [0, 3, 2],  # bottom (-z)
            [4, 5, 6], [4, 6, 7],  # top (+z)
            [0, 1, 5], [0, 5, 4],  # -y
            [2, 3, 7], [2, 7, 6],  # +y
            [1, 2, 6], [1, 6, 5],  # +x
            [3, 0, 4], [3, 4, 7],  # -x
        ]
    )  # fmt: skip
    return Scene(v, t)


def step_scene(
    step_x_mm: float = 0.0,
    low_z_mm: float = 0.0,
    high_z_mm: float = 10.0,
    half_size_mm: float = 300.0,
) -> Scene:
    """A step along y: the floor at ``low_z_mm`` for x < ``step_x_mm``, ``high_z_mm`` beyond, joined by a wall."""
    h = half_size_mm
    s = step_x_mm
    v = np.array(
        [
            [s - h, -h, low_z_mm], [s, -h, low_z_mm], [s, h, low_z_mm], [s - h, h, low_z_mm],
            [s, -h, high_z_mm], [s + h, -h, high_z_mm], [s + h, h, high_z_mm], [s, h, high_z_mm],
        ]
    )  # fmt: skip
    t = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7], [1, 4, 7], [1, 7, 2]])
    return Scene(v, t)


def _vertex_normals(v: np.ndarray, t: np.ndarray) -> np.ndarray:
    face_n = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])  # area weighted
    vn = np.zeros_like(v)
    for k in range(3):
        np.add.at(vn, t[:, k], face_n)
    norm = np.linalg.norm(vn, axis=1, keepdims=True)
    return vn / np.where(norm > 0, norm, 1.0)


def _boundary_edges(t: np.ndarray) -> np.ndarray:
    """(k, 2) directed boundary edges (as they appear in their single triangle)."""
    e = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    key = np.sort(e, axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return e[counts[inv.ravel()] == 1]


def plate_solid(top_vertices_mm: np.ndarray, top_triangles: np.ndarray, thickness_mm: float) -> Scene:
    """Close a plate's top-surface mesh into a solid: top, bottom (offset along -normal), side walls.

    Args:
        top_vertices_mm: (n, 3) float, top surface, mm; its triangles must face up (normals +z-ish).
        top_triangles: (m, 3) int.
        thickness_mm: plate thickness, measured along the vertex normals.

    Returns:
        A closed mesh with outward normals.
    """
    v = np.asarray(top_vertices_mm, dtype=np.float64)
    t = np.asarray(top_triangles, dtype=np.int64)
    if thickness_mm <= 0:
        raise ValueError(f"thickness_mm must be > 0, got {thickness_mm}")
    face_n = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    if face_n[:, 2].sum() < 0:
        t = t[:, ::-1]  # wound clockwise seen from above: the top must face up for the offset to go down
    bottom = v - _vertex_normals(v, t) * thickness_mm
    n = len(v)
    edges = _boundary_edges(t)
    a, b = edges[:, 0], edges[:, 1]
    # Top edge a->b runs counter-clockwise seen from above, so the wall quad (b, a, a', b') faces out.
    walls = np.concatenate([np.stack([b, a, a + n], 1), np.stack([b, a + n, b + n], 1)])
    tri = np.concatenate([t, t[:, ::-1] + n, walls])
    return Scene(np.concatenate([v, bottom]), tri)


@dataclass(frozen=True)
class RayHits:
    """Result of casting ``k`` rays.

    Attributes:
        t_mm: (k,) float distance along the (unit) ray to the first hit, mm; inf where nothing is hit.
        normal: (k, 3) float32 unit normal of the hit triangle, world frame (zeros where nothing is hit).
    """

    t_mm: np.ndarray
    normal: np.ndarray


class SceneRaycaster:
    """Batched first-hit ray casting against a :class:`Scene`.

    The mesh is shifted to its bounding-box centre before it goes to Embree (float32): coordinates of
    a 10 m plate would otherwise lose about 1 um of precision.
    """

    def __init__(self, scene: Scene, nthreads: int = 1) -> None:
        self.scene = scene
        lo = scene.vertices_mm.min(axis=0)
        hi = scene.vertices_mm.max(axis=0)
        self.shift_mm = (lo + hi) / 2.0
        self._nthreads = nthreads
        self._rc = o3d.t.geometry.RaycastingScene()
        self._rc.add_triangles(
            o3d.core.Tensor((scene.vertices_mm - self.shift_mm).astype(np.float32)),
            o3d.core.Tensor(scene.triangles.astype(np.uint32)),
        )

    def cast(self, origins_mm: np.ndarray, directions: np.ndarray) -> RayHits:
        """Cast rays in one call.

        Args:
            origins_mm: (k, 3) float, world frame, mm.
            directions: (k, 3) float, unit vectors, world frame.
        """
        k = len(origins_mm)
        rays = np.empty((k, 6), dtype=np.float32)
        rays[:, :3] = origins_mm - self.shift_mm
        rays[:, 3:] = directions
        return self.cast_shifted(rays)

    def cast_shifted(self, rays: np.ndarray) -> RayHits:
        """Cast prepared rays: (k, 6) float32 ``[origin - shift_mm, unit direction]`` (the fast path).

        ``t_mm`` comes back as float32 here (no copy).
        """
        out = self._rc.cast_rays(o3d.core.Tensor.from_numpy(rays), nthreads=self._nthreads)
        return RayHits(t_mm=out["t_hit"].numpy(), normal=out["primitive_normals"].numpy())


def cell_scene(
    top_vertices_mm: np.ndarray,
    top_triangles: np.ndarray,
    *,
    thickness_mm: float = 12.0,
    bed_z_mm: float | None = None,
    bed_margin_mm: float = 300.0,
    supports_xy_mm: np.ndarray | None = None,
    support_half_size_mm: float = 40.0,
) -> Scene:
    """The scene the cell's sensor sees: the plate as a solid, the supports under it and the bed.

    Args:
        top_vertices_mm: (n, 3) plate top surface in the world (robot base) frame, mm.
        top_triangles: (m, 3) its triangles, facing up.
        thickness_mm: plate thickness.
        bed_z_mm: height of the bed's top face; default 200 mm below the plate's lowest point.
        bed_margin_mm: how far the bed extends beyond the plate's footprint.
        supports_xy_mm: (k, 2) support centres; default a 3 x 3 grid over the plate's footprint.
            Each support is a square pillar from the bed up to the plate's underside.
        support_half_size_mm: half the pillar's side length.
    """
    plate = plate_solid(top_vertices_mm, top_triangles, thickness_mm)
    lo = plate.vertices_mm.min(axis=0)
    hi = plate.vertices_mm.max(axis=0)
    if bed_z_mm is None:
        bed_z_mm = float(lo[2]) - 200.0
    if supports_xy_mm is None:
        gx = np.linspace(lo[0], hi[0], 5)[1:-1]
        gy = np.linspace(lo[1], hi[1], 5)[1:-1]
        supports_xy_mm = np.stack(np.meshgrid(gx, gy), -1).reshape(-1, 2)
    supports_xy_mm = np.asarray(supports_xy_mm, dtype=np.float64).reshape(-1, 2)
    parts = [plate]
    if len(supports_xy_mm):
        rc = SceneRaycaster(plate)
        # A pillar reaches the lowest point of the underside over its footprint, so that it never
        # pokes through a curved plate; probe the corners and the centre from below.
        h = support_half_size_mm
        corners = np.array([[-h, -h], [h, -h], [h, h], [-h, h], [0.0, 0.0]])
        probe = (supports_xy_mm[:, None, :] + corners[None]).reshape(-1, 2)
        k = len(probe)
        hits = rc.cast(np.column_stack([probe, np.full(k, bed_z_mm)]), np.tile([0.0, 0.0, 1.0], (k, 1)))
        t = np.asarray(hits.t_mm, dtype=np.float64)
        under = np.where(np.isfinite(t), bed_z_mm + t, np.nan).reshape(-1, len(corners))
        for (cx, cy), zs in zip(supports_xy_mm, under, strict=True):
            if np.all(np.isnan(zs)):
                continue  # no plate above this support
            top = float(np.nanmin(zs))
            parts.append(box_scene((cx - h, cy - h, bed_z_mm), (cx + h, cy + h, top)))
    bed_lo = lo[:2] - bed_margin_mm
    bed_hi = hi[:2] + bed_margin_mm
    parts.append(box_scene((bed_lo[0], bed_lo[1], bed_z_mm - 50.0), (bed_hi[0], bed_hi[1], bed_z_mm)))
    return merge_scenes(parts)
