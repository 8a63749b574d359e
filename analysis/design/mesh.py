"""Triangle meshes in millimetres: the one mesh type the analysis passes around.

A plain container of numpy arrays (trimesh's habit), with file I/O through open3d for
PLY, STL and OBJ so that a design exported from a CAD package loads as it is.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np


class MeshError(ValueError):
    """A mesh file that cannot be used: unreadable, empty, or of the wrong shape."""


@dataclass(frozen=True)
class TriMesh:
    """A triangle mesh.

    vertices_mm: (n, 3) float64, millimetres.
    triangles: (m, 3) int64, indices into ``vertices_mm``.
    """

    vertices_mm: np.ndarray
    triangles: np.ndarray

    def __post_init__(self) -> None:
        v = np.ascontiguousarray(self.vertices_mm, dtype=np.float64)
        t = np.ascontiguousarray(self.triangles, dtype=np.int64)
        if v.ndim != 2 or v.shape[1] != 3:
            raise MeshError(f"vertices_mm must be (n, 3), got {v.shape}")
        if t.ndim != 2 or t.shape[1] != 3:
            raise MeshError(f"triangles must be (m, 3), got {t.shape}")
        if t.size and (t.min() < 0 or t.max() >= len(v)):
            raise MeshError("triangle index out of range of vertices_mm")
        object.__setattr__(self, "vertices_mm", v)
        object.__setattr__(self, "triangles", t)

    @property
    def triangle_vertices_mm(self) -> np.ndarray:
        """(m, 3, 3) float64: the three corners of every triangle."""
        return self.vertices_mm[self.triangles]

    def triangle_normals(self) -> np.ndarray:
        """(m, 3) float64 unit normals (right-hand rule on the vertex order)."""
        tv = self.triangle_vertices_mm
        n = np.cross(tv[:, 1] - tv[:, 0], tv[:, 2] - tv[:, 0])
        length = np.linalg.norm(n, axis=1, keepdims=True)
        return n / np.where(length > 0, length, 1.0)

    def triangle_areas_mm2(self) -> np.ndarray:
        """(m,) float64 triangle areas in mm^2."""
        tv = self.triangle_vertices_mm
        return 0.5 * np.linalg.norm(np.cross(tv[:, 1] - tv[:, 0], tv[:, 2] - tv[:, 0]), axis=1)

    def transformed(self, T: np.ndarray) -> TriMesh:
        """The mesh moved by the 4x4 homogeneous transform ``T`` (mm)."""
        T = np.asarray(T, dtype=np.float64)
        if T.shape != (4, 4):
            raise MeshError(f"transform must be 4x4, got {T.shape}")
        return TriMesh(self.vertices_mm @ T[:3, :3].T + T[:3, 3], self.triangles)


def _read_ply_mesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (n, 3) and triangles (m, 3) of a PLY, read with plyfile (polygons fanned into triangles).

    open3d's PLY reader trusts the file: a binary PLY whose face lists disagree with its bytes
    crashed the process (segmentation fault, found by tests/fuzz). plyfile raises instead.
    """
    from plyfile import PlyData, PlyElementParseError

    from analysis.cloud_io import ply_header_overclaims

    # parsers believe the header and spend minutes on a tiny file claiming 10^8 vertices
    overclaim = ply_header_overclaims(path)
    if overclaim:
        raise MeshError(f"{path}: {overclaim}")
    try:
        try:  # all triangles (what cellctl and most CAD exports write): read as one array, checked
            ply = PlyData.read(str(path), known_list_len={"face": _TRIANGLE_LISTS})
        except PlyElementParseError as exc:
            if exc.message != "unexpected list length" and "end-of-file" not in exc.message:
                raise
            ply = PlyData.read(str(path))  # polygons of other sizes: list by list
        vert = ply["vertex"].data
        v = np.column_stack([np.asarray(vert[c], dtype=np.float64) for c in ("x", "y", "z")])
        faces = ply["face"].data
        name = next(n for n in _TRIANGLE_LISTS if n in (faces.dtype.names or ()))
        column = faces[name]
        if column.dtype != object:  # the triangles' (m, 3) array
            t = np.asarray(column, dtype=np.int64).reshape(-1, 3)
            return v, t
        polys = [np.asarray(f, dtype=np.int64) for f in column]
    except (KeyError, StopIteration):
        raise MeshError(f"{path}: PLY lacks vertex x, y, z or face vertex_indices") from None
    except Exception as exc:  # plyfile's own errors, truncated data: one line naming the file
        raise MeshError(f"{path}: unreadable PLY file ({type(exc).__name__}: {str(exc)[:200]})") from None
    tris = [np.column_stack([np.full(len(f) - 2, f[0]), f[1:-1], f[2:]]) for f in polys if len(f) >= 3]
    t = np.concatenate(tris) if tris else np.zeros((0, 3), dtype=np.int64)
    return v, t


#: the face list property's names, each read as 3 indices on the fast path of :func:`_read_ply_mesh`
_TRIANGLE_LISTS = {"vertex_indices": 3, "vertex_index": 3}


def _check_binary_stl(path: Path) -> None:
    """A binary STL's size is fixed by its triangle count; refuse one whose bytes disagree before
    open3d reads it (it trusts the count)."""
    with path.open("rb") as f:
        head = f.read(84)
    size = path.stat().st_size
    if head[:5].lower() == b"solid" and b"facet" in path.read_bytes()[:4096]:
        return  # ASCII STL
    if len(head) < 84:
        raise MeshError(f"{path}: binary STL shorter than its 84-byte header")
    n = int.from_bytes(head[80:84], "little")
    if size != 84 + 50 * n:
        raise MeshError(
            f"{path}: binary STL declares {n} triangles ({84 + 50 * n} bytes) but has {size} bytes"
        )


def load_mesh(path: str | Path) -> TriMesh:
    """Read a triangle mesh (PLY, STL or OBJ, millimetres) with one clear error when unusable."""
    path = Path(path)
    if not path.is_file():
        raise MeshError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if suffix not in {".ply", ".stl", ".obj"}:
        raise MeshError(f"{path}: unsupported mesh format {path.suffix!r} (use .ply, .stl or .obj)")
    if suffix == ".ply":
        v, t = _read_ply_mesh(path)
    else:
        import open3d as o3d

        if suffix == ".stl":
            _check_binary_stl(path)
        m = o3d.io.read_triangle_mesh(str(path))
        v = np.asarray(m.vertices)
        t = np.asarray(m.triangles)
    if len(v) == 0 or len(t) == 0:
        raise MeshError(f"{path}: no triangles in the file (empty or unreadable)")
    if not np.isfinite(v).all():
        raise MeshError(f"{path}: non-finite vertex coordinates")
    try:
        return TriMesh(v, t)
    except MeshError as exc:  # TriMesh's own checks (an index beyond the vertices) do not know the file
        raise MeshError(f"{path}: {exc}") from None


def save_mesh(mesh: TriMesh, path: str | Path) -> Path:
    """Write ``mesh`` as PLY, STL or OBJ (by suffix); returns the path."""
    import open3d as o3d

    path = Path(path)
    m = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(mesh.vertices_mm),
        o3d.utility.Vector3iVector(mesh.triangles.astype(np.int32)),
    )
    if path.suffix.lower() == ".stl":
        m.compute_triangle_normals()
    if not o3d.io.write_triangle_mesh(str(path), m, write_ascii=False):
        raise MeshError(f"{path}: could not write mesh")
    return path


def principal_extents_mm(vertices_mm: np.ndarray) -> np.ndarray:
    """(3,) extents of a point set along its principal axes, largest first (mm): a plate's length,
    width and rise whatever its pose (a plate in ship coordinates may stand on edge)."""
    v = np.asarray(vertices_mm, dtype=np.float64)
    c = v - v.mean(axis=0)
    _, _, axes = np.linalg.svd(c[:: max(1, len(c) // 20000)], full_matrices=False)
    return np.sort(np.ptp(c @ axes.T, axis=0))[::-1]


def surface_mismatch(formed: TriMesh, design: TriMesh, tolerance: float = 0.1) -> str | None:
    """Why a formed plate's surface is not the plate of ``design`` (both in the same frame, mm), or None.

    The two must agree in length and width within ``tolerance`` (a share) + 20 mm, and their
    bounding boxes' centres lie within ``tolerance`` of the design's length + 20 mm: a formed plate
    departs from its design by millimetres, a wrong file or a file in other units or another frame
    by far more.
    """
    ef, ed = principal_extents_mm(formed.vertices_mm), principal_extents_mm(design.vertices_mm)
    for k, what in ((0, "length"), (1, "width")):
        if abs(ef[k] - ed[k]) > tolerance * ed[k] + 20.0:
            return f"the formed plate's {what} is {ef[k]:.1f} mm, the design's {ed[k]:.1f} mm"
    cf = (formed.vertices_mm.min(axis=0) + formed.vertices_mm.max(axis=0)) / 2
    cd = (design.vertices_mm.min(axis=0) + design.vertices_mm.max(axis=0)) / 2
    gap = float(np.linalg.norm(cf - cd))
    if gap > tolerance * ed[0] + 20.0:
        return f"the formed plate lies {gap:.1f} mm from the design (not in the design file's frame?)"
    return None
