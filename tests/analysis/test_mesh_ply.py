"""Design meshes read from PLY (analysis.design.mesh.load_mesh): the triangles-only fast path and the
polygon path give the same mesh, polygons are fanned, and damaged files get one clear error."""

from __future__ import annotations

import numpy as np
import plyfile
import pytest

from analysis.design.mesh import MeshError, load_mesh


def _write_ply(path, vertices, faces, *, text=False, name="vertex_indices"):
    v = np.array([tuple(p) for p in vertices], dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    f = np.empty(len(faces), dtype=[(name, "O")])
    f[name] = [np.asarray(face, dtype=np.int32) for face in faces]
    els = [plyfile.PlyElement.describe(v, "vertex"), plyfile.PlyElement.describe(f, "face")]
    plyfile.PlyData(els, text=text).write(str(path))
    return path


def _grid(n=6):
    xs, ys = np.meshgrid(np.arange(n) * 10.0, np.arange(n) * 10.0)
    verts = np.column_stack([xs.ravel(), ys.ravel(), 0.01 * xs.ravel() ** 1.5])
    quads = [(i * n + j, i * n + j + 1, (i + 1) * n + j + 1, (i + 1) * n + j) for i in range(n - 1) for j in range(n - 1)]  # fmt: skip
    return verts, quads


@pytest.mark.parametrize("text", [False, True])
@pytest.mark.parametrize("name", ["vertex_indices", "vertex_index"])
def test_triangles_read_in_the_files_order_binary_or_text(tmp_path, text, name):
    verts, quads = _grid()
    tris = [t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))]
    mesh = load_mesh(_write_ply(tmp_path / "t.ply", verts, tris, text=text, name=name))
    np.testing.assert_array_equal(mesh.triangles, np.asarray(tris))
    np.testing.assert_allclose(mesh.vertices_mm, verts.astype(np.float32))


def test_quads_and_mixed_polygons_are_fanned_into_the_same_triangles(tmp_path):
    verts, quads = _grid()
    faces = [quads[0][:3], *quads[1:]]  # a triangle first: the fast path's length check refuses the rest
    mesh = load_mesh(_write_ply(tmp_path / "q.ply", verts, faces))
    want = [faces[0]] + [t for a, b, c, d in faces[1:] for t in ((a, b, c), (a, c, d))]
    np.testing.assert_array_equal(mesh.triangles, np.asarray(want))
    all_quads = load_mesh(_write_ply(tmp_path / "q4.ply", verts, quads))
    assert len(all_quads.triangles) == 2 * len(quads)


def test_a_truncated_binary_triangle_file_is_one_clear_error(tmp_path):
    verts, quads = _grid()
    tris = [t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))]
    path = _write_ply(tmp_path / "t.ply", verts, tris)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) - 7])
    with pytest.raises(MeshError, match=r"t\.ply"):
        load_mesh(path)
