"""A design's outline, corners and own frame, found from the design itself (mesh or CAD surface).

A yard's surface arrives in ship coordinates: a side-shell plate stands near vertical, metres
above the keel, and its outline is rarely a rectangle (parallelograms, trapezoids, edges bowed in
plan). The same three steps serve a triangle mesh (PLY, STL, OBJ) and a CAD design
(:mod:`analysis.design.cad`, which samples its outline from the faces' free boundary):

1. **Outline.** The closed boundary curve of the surface: for a mesh, its edges used by one
   triangle (:func:`mesh_free_edges`, the one place that finds them) chained into loops
   (:func:`mesh_boundary_loops`).
2. **Corners.** Where the outline turns most (:func:`outline_corners`): the turning angle at each
   outline point between the chords to the points a fixed arc length before and after it, the four
   largest turns kept apart from each other. Corner angles of 60 to 120 degrees turn the outline by
   120 to 60 degrees; an edge bowed by 2 % of its length turns it by a few degrees over its whole
   length, so neither right angles nor straight edges are assumed.
3. **Frame.** :func:`plate_frame_from_surface`: the base plane is the least-squares plane through
   the surface, x runs along the long edges; :func:`frame_design_mesh` moves a mesh into that frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import structlog

from analysis.design.mesh import MeshError, TriMesh
from analysis.design.plates import canonical_corner_order

__all__ = [
    "FramedMesh",
    "OutlineError",
    "canonical_corner_order_in_plane",
    "design_corners_from_mesh",
    "frame_design_mesh",
    "mesh_boundary_loops",
    "mesh_free_edges",
    "outline_corners",
    "plate_frame",
    "plate_frame_from_surface",
]

log = structlog.get_logger(__name__)

CORNER_MIN_TURN_DEG = 20.0  # a corner of at most 160 degrees turns the outline by at least 20


class OutlineError(MeshError):
    """A design whose outline has no four corners: a closed solid, a round plate, a bad boundary."""


def mesh_free_edges(mesh: TriMesh) -> tuple[np.ndarray, np.ndarray]:
    """The mesh's free edges (each used by one triangle only): ``(edges (m, 2), opposite (m,))``.

    edges: vertex indices, each edge in its triangle's own direction (so each boundary loop runs one
    way round), in triangle order (every triangle's edge 0-1, then 1-2, then 2-0); opposite: the
    third vertex of the triangle each edge belongs to (the side the surface lies on). Every free
    edge is listed: the outer outline, holes' edges and the edges of every separate piece. Empty
    (0, 2) and (0,) arrays for a closed mesh.
    """
    tri = mesh.triangles
    n = len(mesh.vertices_mm)
    e = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]).astype(np.int64)
    opposite = np.concatenate([tri[:, 2], tri[:, 0], tri[:, 1]]).astype(np.int64)
    key = np.sort(e, axis=1)
    _, inv, counts = np.unique(key[:, 0] * n + key[:, 1], return_inverse=True, return_counts=True)
    once = counts[inv.ravel()] == 1
    return e[once], opposite[once]


def mesh_boundary_loops(mesh: TriMesh) -> list[np.ndarray]:
    """Closed loops of the mesh's boundary (:func:`mesh_free_edges` chained), as vertex index arrays.

    Each loop lists its vertices in order, without repeating the first one, longest loop first.
    A boundary vertex shared by two loops (a pinched mesh) ends one loop and starts the next.
    """
    directed, _ = mesh_free_edges(mesh)
    if len(directed) == 0:
        return []
    nxt = {int(a): int(b) for a, b in directed}
    loops: list[np.ndarray] = []
    left = set(nxt)
    # each loop starts at the smallest vertex left: one sorted walk, not a min() over the set per
    # loop (quadratic in a triangle soup, where every triangle is a loop: an STL of 240 000)
    for start in sorted(nxt):
        if start not in left:
            continue
        loop = [start]
        left.discard(start)
        v = nxt[start]
        while v != start and v in left:
            loop.append(v)
            left.discard(v)
            v = nxt[v]
        if len(loop) >= 3:
            loops.append(np.asarray(loop, dtype=np.int64))
    loops.sort(key=lambda lp: -len(lp))
    return loops


def outline_corners(
    samples_mm: np.ndarray, up: np.ndarray, candidates: np.ndarray | None = None
) -> np.ndarray:
    """Indices (4,) into ``samples_mm`` of a closed outline's four corners, in outline order.

    samples_mm: (k, 3) points along the closed outline, in order. up: (3,) the base plane's normal
    (turning angles are measured in that plane). candidates: optional (k,) bool, the samples that
    may be corners (a CAD wire's vertices); default every sample.
    The turning angle at a sample is taken between the chords to the points 0.5 % of the
    perimeter before and after it (a mesh's jagged boundary or a bowed edge's gentle curve turns
    little over that span); the largest turn wins, the outline within 2 % of the perimeter of it is
    set aside (a strip up to about 20 times longer than wide keeps its short edges), four times. When fewer than four turns exceed 20 degrees (rounded corners) the
    points farthest out along the footprint's diagonals are taken instead.
    Raises :class:`OutlineError` when no four distinct corners are found.
    """
    P = np.asarray(samples_mm, dtype=np.float64)
    k = len(P)
    if P.ndim != 2 or P.shape[1] != 3 or k < 4:
        raise OutlineError(f"an outline needs (k >= 4, 3) points, got shape {P.shape}")
    z = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    h = P - np.outer(P @ z, z)
    seg = np.linalg.norm(np.roll(h, -1, axis=0) - h, axis=1)
    s = np.r_[0.0, np.cumsum(seg)]  # arc length at each sample, s[k] = perimeter
    per = float(s[-1])
    if per <= 0:
        raise OutlineError("the outline has zero length")
    span = 0.005 * per

    def at(arc: np.ndarray) -> np.ndarray:  # points of the closed outline at arc lengths (any value)
        a = np.mod(arc, per)
        j = np.clip(np.searchsorted(s, a, side="right") - 1, 0, k - 1)
        w = ((a - s[j]) / np.where(seg[j] > 0, seg[j], 1.0))[:, None]
        return h[j] + w * (h[(j + 1) % k] - h[j])

    d_in = h - at(s[:-1] - span)
    d_out = at(s[:-1] + span) - h
    cosang = np.einsum("ij,ij->i", d_in, d_out) / (
        np.linalg.norm(d_in, axis=1) * np.linalg.norm(d_out, axis=1) + 1e-300
    )
    turn = np.degrees(np.arccos(np.clip(cosang, -1.0, 1.0)))
    if candidates is not None:
        turn = np.where(np.asarray(candidates, dtype=bool), turn, -1.0)
    picks: list[int] = []
    free = np.ones(k, dtype=bool)
    for _ in range(4):
        j = int(np.argmax(np.where(free, turn, -1.0)))
        if turn[j] < CORNER_MIN_TURN_DEG or not free[j]:
            break
        picks.append(j)
        gap = np.abs(s[:-1] - s[j])
        free &= np.minimum(gap, per - gap) > 4.0 * span
    if len(picks) < 4:
        xy = h - h.mean(axis=0)
        _, _, axes = np.linalg.svd(xy, full_matrices=False)
        uv = xy @ axes[:2].T
        uv /= np.abs(uv).max(axis=0)
        picks = [int(np.argmax(uv @ np.array(d))) for d in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
        if len(set(picks)) < 4:
            raise OutlineError("cannot find four distinct corners on the design's boundary")
    return np.sort(np.asarray(picks, dtype=np.int64))


def canonical_corner_order_in_plane(corners_mm: np.ndarray, up: np.ndarray) -> np.ndarray:
    """:func:`canonical_corner_order` seen from ``up`` instead of +z (corners in any frame)."""
    z = up / np.linalg.norm(up)
    a = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = a - (a @ z) * z
    x /= np.linalg.norm(x)
    R = np.vstack([x, np.cross(z, x), z])
    local = corners_mm @ R.T
    return canonical_corner_order(local) @ R


def _surface_up(vertices_mm: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(normal (3,), mean (3,)) of the area-weighted least-squares plane through a triangulated
    surface, the normal turned to the side the triangles' normals point to."""
    tv = vertices_mm[triangles]
    nrm = np.cross(tv[:, 1] - tv[:, 0], tv[:, 2] - tv[:, 0])
    area = 0.5 * np.linalg.norm(nrm, axis=1)
    cen = tv.mean(axis=1)
    if not area.sum() > 0:  # every triangle degenerate: no plane; leave the refusal to the caller's checks
        return np.array([0.0, 0.0, 1.0]), vertices_mm.mean(axis=0)
    mean = (cen * area[:, None]).sum(axis=0) / area.sum()
    X = (cen - mean) * np.sqrt(area)[:, None]
    n_sum = nrm.sum(axis=0)
    sv = vt = None
    if len(X) >= 3:  # full_matrices=False: U of a large mesh would be n x n
        _, sv, vt = np.linalg.svd(X, full_matrices=False)
    if sv is None or sv[1] <= 1e-9 * sv[0] or not sv[0] > 0:
        # fewer than three triangles, or their centres on one line: the plane through the centres
        # is undetermined, the area-weighted normal is the best estimate (a single flat facet's own)
        z = n_sum / np.linalg.norm(n_sum) if np.linalg.norm(n_sum) > 0 else np.array([0.0, 0.0, 1.0])
    else:
        z = vt[2]
    if n_sum @ z < 0:
        z = -z
    return z, mean


def plate_frame_from_surface(
    vertices_mm: np.ndarray, triangles: np.ndarray, corners_mm: np.ndarray
) -> np.ndarray:
    """4x4 transform file frame -> design frame, found from the plate itself.

    z: the normal of the area-weighted least-squares plane through the surface (the plate's base
    plane), turned to the side the surface's normals point to (the design side up); x: along the
    long edges, mean of the two long edges' directions in that plane; origin: the corners' centre
    projected onto the plane (the callers then move it along z onto the surface). A plate already
    lying in its file's frame (base plane within 0.5 degrees of +z, corners centred on the origin
    within 1 mm) keeps that frame: the identity.
    """
    z, mean = _surface_up(vertices_mm, triangles)
    c = canonical_corner_order_in_plane(corners_mm, z)
    centre = c.mean(axis=0)
    if z[2] > np.cos(np.radians(0.5)) and np.linalg.norm(centre[:2]) < 1.0:
        return np.eye(4)
    e_a = c[1] - c[0]
    e_b = c[2] - c[3]
    x = (e_a / np.linalg.norm(e_a) + e_b / np.linalg.norm(e_b)) / 2
    x -= (x @ z) * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.vstack([x, y, z])
    origin = centre - ((centre - mean) @ z) * z
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ origin
    return T


def _mesh_outline(mesh: TriMesh) -> np.ndarray:
    """(k, 3) the mesh's outer boundary loop (the longest), in order."""
    loops = mesh_boundary_loops(mesh)
    if not loops:
        raise OutlineError("the design mesh has no open boundary: is it a closed solid, not a top surface?")
    return mesh.vertices_mm[loops[0]]


def design_corners_from_mesh(design: TriMesh, up: np.ndarray | None = None) -> np.ndarray:
    """(4, 3) corners of a design mesh's outline in the project's order (corner 0 = reference).

    up: the base plane's normal (default +z, the design frame's): the corners are ordered as seen
    from it. Any convex four-sided outline (corner angles 60 to 120 degrees, bowed edges) works.
    """
    up = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, dtype=np.float64)
    outline = _mesh_outline(design)
    return canonical_corner_order_in_plane(outline[outline_corners(outline, up)], up)


def _height_over_origin(mesh: TriMesh) -> float | None:
    """z of the mesh above (0, 0) (barycentric in the triangle holding it), None if it misses."""
    tv = mesh.triangle_vertices_mm
    a, b, c = tv[:, 0, :2], tv[:, 1, :2], tv[:, 2, :2]
    v0, v1 = b - a, c - a
    den = v0[:, 0] * v1[:, 1] - v0[:, 1] * v1[:, 0]
    ok = np.abs(den) > 1e-12
    den = np.where(ok, den, 1.0)
    w1 = (-a[:, 0] * v1[:, 1] + a[:, 1] * v1[:, 0]) / den
    w2 = (v0[:, 0] * -a[:, 1] - v0[:, 1] * -a[:, 0]) / den
    hit = np.flatnonzero(ok & (w1 >= -1e-9) & (w2 >= -1e-9) & (w1 + w2 <= 1 + 1e-9))
    if len(hit) == 0:
        return None
    i = hit[0]
    return float(tv[i, 0, 2] + w1[i] * (tv[i, 1, 2] - tv[i, 0, 2]) + w2[i] * (tv[i, 2, 2] - tv[i, 0, 2]))


@dataclass(frozen=True)
class FramedMesh:
    """A design mesh moved into its own plate frame.

    mesh: the design frame's mesh (x along the long edges, z the base plane's normal, origin on the
    surface over the corners' centre). corners_mm: (4, 3) its corners in the project's order.
    T_design_file: 4x4, file coordinates (mm) -> design frame; the identity for a mesh already
    lying in its own frame.
    """

    mesh: TriMesh
    corners_mm: np.ndarray
    T_design_file: np.ndarray


def frame_design_mesh(mesh: TriMesh) -> FramedMesh:
    """The plate's base plane, frame and corners from a design mesh in any pose (ship coordinates).

    The same frame :mod:`analysis.design.cad` finds for a CAD design (:func:`plate_frame_from_surface`).
    Raises :class:`OutlineError` for a mesh without a four-cornered open boundary.
    """
    z, _ = _surface_up(mesh.vertices_mm, mesh.triangles)
    outline = _mesh_outline(mesh)
    corners_file = outline[outline_corners(outline, z)]
    T = plate_frame_from_surface(mesh.vertices_mm, mesh.triangles, corners_file)
    if np.array_equal(T, np.eye(4)):
        framed = mesh
    else:
        framed = mesh.transformed(T)
        foot = _height_over_origin(framed)
        if foot is not None:
            shift = np.eye(4)
            shift[2, 3] = -foot
            T = shift @ T
            framed = mesh.transformed(T)
        log.debug("design_framed", tilt_deg=round(float(np.degrees(np.arccos(np.clip(z[2], -1, 1)))), 3),
                 origin_file_mm=np.round(np.linalg.inv(T)[:3, 3], 3).tolist())  # fmt: skip
    corners = corners_file @ T[:3, :3].T + T[:3, 3]
    return FramedMesh(framed, canonical_corner_order(corners), T)


def plate_frame(design_corners: np.ndarray) -> np.ndarray:
    """4x4 transform design frame -> plate frame (origin corner 0, x along edge 0->1, z up)."""
    x = design_corners[1, :2] - design_corners[0, :2]
    x = np.array([x[0], x[1], 0.0]) / np.linalg.norm(x)
    z = np.array([0.0, 0.0, 1.0])
    y = np.cross(z, x)
    R = np.vstack([x, y, z])  # rows: plate axes in design coordinates
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ np.array([*design_corners[0, :2], 0.0])
    return T
