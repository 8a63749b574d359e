"""A CAD design's exact surface in the design frame (:class:`CadDesign`): points and normals of its
NURBS faces, points projected onto it, the vertical cut of a template (:meth:`CadDesign.vertical_heights`),
its size and curvature, and the ``design check`` summary. :mod:`analysis.design.cad` reads it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from analysis.design.cad_facts import FileFacts
from analysis.design.mesh import TriMesh
from analysis.design.nurbs import NurbsPatch


@dataclass
class CadDesign:
    """A design read from an IGES or STEP file, in the design frame (mm).

    mesh: the tessellation (for registration, height fields, the planner); triangle_face: (m,)
    face index of every triangle; triangle_uv: (m, 3, 2) the surface parameters of its corners.
    faces: one :class:`NurbsPatch` per face. corners_mm: (4, 3) from the free boundary's vertices,
    in the project's order (:func:`analysis.design.plates.canonical_corner_order`). boundary_mm: (k, 3)
    the outline sampled from the boundary curves, in order. T_design_file: 4x4 file (ship)
    coordinates in mm -> design frame. chord_error_mm: the largest distance between the
    tessellation and the exact surface, measured at the triangles' centroids and edge midpoints.
    offset_mm: the surface the templates are cut from is the faces' offset by this much along
    :meth:`normals` (0: the faces themselves; the other side of a turned-over plate, see
    :mod:`analysis.design.moulded`); ``mesh`` and ``corners_mm`` are then those of the offset surface.
    """

    path: Path
    facts: FileFacts
    faces: list[NurbsPatch]
    mesh: TriMesh
    triangle_face: np.ndarray
    triangle_uv: np.ndarray
    corners_mm: np.ndarray
    boundary_mm: np.ndarray
    T_design_file: np.ndarray
    deflection_mm: float
    chord_error_mm: float
    area_mm2: float
    timings_s: dict[str, float] = field(default_factory=dict)
    offset_mm: float = 0.0

    # -- exact surface ------------------------------------------------------------------------
    def evaluate(self, face: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Points, d/du and d/dv at ``uv`` (n, 2) on faces ``face`` (n,): three (n, 3) arrays, mm."""
        face = np.asarray(face, dtype=np.int64)
        S = np.empty((len(face), 3))
        Su, Sv = np.empty_like(S), np.empty_like(S)
        for f in np.unique(face):
            sel = face == f
            S[sel], Su[sel], Sv[sel] = self.faces[f].evaluate(uv[sel, 0], uv[sel, 1])
        return S, Su, Sv

    def normals(self, face: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """(n, 3) unit surface normals (du x dv, oriented like the tessellation's triangles)."""
        _, Su, Sv = self.evaluate(face, uv)
        n = np.cross(Su, Sv)
        return n / np.linalg.norm(n, axis=1, keepdims=True) * self._orientation[face][:, None]

    def _offset_points(self, face: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`evaluate` of the surface the templates are cut from (offset by ``offset_mm``)."""
        S, Su, Sv = self.evaluate(face, uv)
        if self.offset_mm:
            n = np.cross(Su, Sv)
            n *= (self._orientation[face] / np.linalg.norm(n, axis=1))[:, None]
            S = S + self.offset_mm * n
        return S, Su, Sv

    @cached_property
    def _orientation(self) -> np.ndarray:
        """+1 or -1 per face: the sign that turns du x dv into the tessellation's (up) side."""
        centroid_uv = self.triangle_uv.mean(axis=1)
        _, Su, Sv = self.evaluate(self.triangle_face, centroid_uv)
        dots = np.einsum("ij,ij->i", np.cross(Su, Sv), self.mesh.triangle_normals())
        sign = np.ones(len(self.faces))
        for f in range(len(self.faces)):
            sel = self.triangle_face == f
            if sel.any() and np.sum(dots[sel]) < 0:
                sign[f] = -1.0
        return sign

    @cached_property
    def _tree(self):
        from scipy.spatial import cKDTree

        return cKDTree(self.mesh.triangle_vertices_mm.reshape(-1, 3))

    def nearest_parameters(self, points_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The face and (u, v) of the tessellation vertex nearest each point: Newton's start."""
        _, k = self._tree.query(points_mm)
        return self.triangle_face[k // 3], self.triangle_uv.reshape(-1, 2)[k]

    def project(
        self,
        points_mm: np.ndarray,
        iterations: int = 12,
        seeds: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Closest points of the exact surface to ``points_mm`` (n, 3): (feet (n, 3), distance (n,)).

        Gauss-Newton on the foot-point condition from the nearest tessellation vertex (or from
        ``seeds``: faces (n,) and parameters (n, 2)), the parameters kept inside the face's bounds.
        Distances are unsigned, mm.
        """
        p = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
        face, uv = seeds if seeds is not None else self.nearest_parameters(p)
        uv = np.array(uv, dtype=np.float64)
        for _ in range(iterations):
            S, Su, Sv = self.evaluate(face, uv)
            J = np.stack([Su, Sv], axis=2)  # (n, 3, 2)
            JtJ = np.einsum("nki,nkj->nij", J, J)
            rhs = np.einsum("nki,nk->ni", J, p - S)
            step = _damped_solve(JtJ, rhs)
            uv += step
            self._clamp(face, uv)
            if np.abs(step).max() < 1e-12 * max(1.0, float(np.abs(uv).max())):
                break
        S, _, _ = self.evaluate(face, uv)
        return S, np.linalg.norm(p - S, axis=1)

    def _clamp(self, face: np.ndarray, uv: np.ndarray) -> None:
        for f in np.unique(face):
            sel = face == f
            uv[sel, 0] = np.clip(uv[sel, 0], *self.faces[f].u_range)
            uv[sel, 1] = np.clip(uv[sel, 1], *self.faces[f].v_range)

    def vertical_heights(
        self, origins_mm: np.ndarray, direction: np.ndarray, iterations: int = 12
    ) -> np.ndarray:
        """Where the lines ``origin + t * direction`` meet the exact surface: (n, 3) points, NaN where
        a line misses every face. The cut of a template: one line per sample of a detection line.

        Newton on S(u, v) - origin - t * direction = 0 (3 unknowns, exact Jacobian) from the nearest
        tessellation vertex; a line whose solution leaves its seed face's bounds is retried from the
        faces of its neighbours' solutions.
        """
        o = np.asarray(origins_mm, dtype=np.float64).reshape(-1, 3)
        d = np.asarray(direction, dtype=np.float64) / np.linalg.norm(direction)
        face, uv = self.nearest_parameters(o)
        out = np.full_like(o, np.nan)
        todo = np.ones(len(o), dtype=bool)
        for _attempt in range(3):
            idx = np.nonzero(todo)[0]
            if not len(idx):
                break
            f, w = face[idx], uv[idx].copy()
            t = np.einsum("ij,j->i", self._offset_points(f, w)[0] - o[idx], d)
            for _ in range(iterations):
                # on an offset surface the Jacobian leaves out offset * dN: Newton becomes a
                # contraction by about offset / radius per step (0.005 for 15 mm on a 3 m radius)
                S, Su, Sv = self._offset_points(f, w)
                J = np.stack([Su, Sv, np.broadcast_to(-d, Su.shape)], axis=2)
                F = S - o[idx] - t[:, None] * d
                if np.abs(F).max() < 1e-9:  # converged everywhere (quadratically, from a near seed)
                    break
                Jt = np.swapaxes(J, 1, 2)
                step = _damped_solve(Jt @ J, -np.einsum("nij,nj->ni", Jt, F))
                w += step[:, :2]
                t += step[:, 2]
                self._clamp(f, w)
            S, _, _ = self._offset_points(f, w)
            F = S - o[idx] - t[:, None] * d
            ok = np.linalg.norm(F, axis=1) < 1e-6
            out[idx[ok]] = S[ok]
            todo[idx[ok]] = False
            # retry the misses from another face: the one a neighbouring line landed on
            done = np.nonzero(~todo)[0]
            miss = np.nonzero(todo)[0]
            if not len(done) or not len(miss):
                break
            near = done[np.clip(np.searchsorted(done, miss), 0, len(done) - 1)]
            if np.array_equal(face[miss], face[near]):
                break
            face[miss], uv[miss] = face[near], uv[near]
        return out

    # -- summary ------------------------------------------------------------------------------
    def size_mm(self) -> tuple[float, float]:
        """Mean lengths of the long and the short edge pair of the corners, in the base plane."""
        xy = self.corners_mm[:, :2]
        d = np.linalg.norm(np.roll(xy, -1, axis=0) - xy, axis=1)
        return float((d[0] + d[2]) / 2), float((d[1] + d[3]) / 2)

    def smallest_radius_mm(self, n: int = 41) -> float:
        """The smallest principal radius of curvature over an n x n parameter grid of every face."""
        best = np.inf
        for patch in self.faces:
            u = np.linspace(*patch.u_range, n)
            v = np.linspace(*patch.v_range, n)
            U, V = (a.ravel() for a in np.meshgrid(u, v, indexing="ij"))
            h = 1e-4 * np.array([patch.u_range[1] - patch.u_range[0], patch.v_range[1] - patch.v_range[0]])
            U = np.clip(U, patch.u_range[0] + h[0], patch.u_range[1] - h[0])
            V = np.clip(V, patch.v_range[0] + h[1], patch.v_range[1] - h[1])
            S, Su, Sv = patch.evaluate(U, V)
            _, Suu, Suv = (a - b for a, b in zip(patch.evaluate(U + h[0], V), (S, Su, Sv), strict=True))
            _, Svu, Svv = (a - b for a, b in zip(patch.evaluate(U, V + h[1]), (S, Su, Sv), strict=True))
            Suu, Suv, Svv = Suu / h[0], (Suv / h[0] + Svu / h[1]) / 2, Svv / h[1]
            nrm = np.cross(Su, Sv)
            jac = np.linalg.norm(nrm, axis=1)
            regular = jac > 1e-6 * np.median(jac)  # a patch side collapsed to a point has no curvature
            nrm /= np.where(regular, jac, 1.0)[:, None]
            E, F, G = (np.einsum("ij,ij->i", a, b) for a, b in ((Su, Su), (Su, Sv), (Sv, Sv)))
            L, M, N = (np.einsum("ij,ij->i", a, nrm) for a in (Suu, Suv, Svv))
            K = (L * N - M * M) / (E * G - F * F)
            H = (E * N - 2 * F * M + G * L) / (2 * (E * G - F * F))
            kmax = np.where(regular, np.abs(H) + np.sqrt(np.maximum(H * H - K, 0.0)), 0.0)
            best = min(best, float(1.0 / max(kmax.max(), 1e-15)))
        return best

    def summary(self) -> dict:
        """A JSON-ready description (the ``design check`` output)."""
        length, width = self.size_mm()
        return {
            "file": str(self.path),
            "format": self.facts.fmt,
            "file_units": self.facts.units,
            "mm_per_file_unit": self.facts.mm_per_unit,
            "faces": len(self.faces),
            "rational_faces": sum(p.rational for p in self.faces),
            "size_mm": [round(length, 3), round(width, 3)],
            "area_mm2": round(self.area_mm2, 1),
            "corners_mm": np.round(self.corners_mm, 4).tolist(),
            "corners_file_mm": np.round(
                _apply(np.linalg.inv(self.T_design_file), self.corners_mm), 4
            ).tolist(),
            "T_design_file": np.round(self.T_design_file, 9).tolist(),
            "smallest_radius_mm": round(self.smallest_radius_mm(), 1),
            "tessellation": {
                "triangles": len(self.mesh.triangles),
                "deflection_mm": self.deflection_mm,
                "chord_error_mm": round(self.chord_error_mm, 5),
            },
            "entities": self.facts.entities,
            "timings_s": self.timings_s,
        }


def _damped_solve(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Batched solve of (n, k, k) normal equations, lightly damped: at a pole of a patch (a side
    collapsed to a point) the Jacobian is singular and the step must stay finite."""
    eps = 1e-12 * np.trace(A, axis1=1, axis2=2)[:, None, None] + 1e-300
    return np.linalg.solve(A + eps * np.eye(A.shape[1]), b[..., None])[..., 0]


def _apply(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p @ T[:3, :3].T + T[:3, 3]
