"""Designs as shipyards hand them over: IGES and STEP B-spline surfaces, read through OpenCASCADE.

A hull design system exports a shell plate as one or more NURBS faces (IGES entity 128, bounded
or trimmed as 143 / 144; STEP ``B_SPLINE_SURFACE_WITH_KNOTS`` in an ``ADVANCED_FACE``), in ship
coordinates, in the file's units. :func:`read_cad` turns such a file into a :class:`CadDesign`:

* the faces sewn into one plate (a file holding several plates that do not touch is refused),
* units from the file (IGES global section's units flag, STEP ``SI_UNIT`` with its prefix or a
  ``CONVERSION_BASED_UNIT``) converted into millimetres,
* the plate's own frame (its base plane and long edge; see :func:`plate_frame_from_surface`),
* every face as an exact NURBS patch evaluated with numpy (:class:`NurbsPatch`: points, first
  derivatives, normals), so that templates are cut from the surface itself
  (:meth:`CadDesign.vertical_heights`) and points can be projected onto it (:meth:`CadDesign.project`),
* a tessellation (:attr:`CadDesign.mesh`) for registration, with its chord error measured against
  the exact surface (:attr:`CadDesign.chord_error_mm`),
* the outline sampled from the faces' own free boundary and the four corners at its vertices.

An unusable file raises :class:`DesignError` with one line naming the file and what is wrong.
:func:`read_design` is the one entry point for every design format (PLY, STL and OBJ meshes too).
"""

from __future__ import annotations

import re
from collections import Counter
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np
import structlog

from analysis.design.mesh import MeshError, TriMesh, load_mesh
from analysis.design.outline import (  # noqa: F401 - canonical_corner_order_in_plane: analysis.design.moulded's
    OutlineError,
    canonical_corner_order_in_plane,
    frame_design_mesh,
    outline_corners,
    plate_frame_from_surface,
)
from analysis.design.plates import canonical_corner_order

log = structlog.get_logger(__name__)

CAD_SUFFIXES = (".igs", ".iges", ".stp", ".step")
MESH_SUFFIXES = (".ply", ".stl", ".obj")
DESIGN_SUFFIXES = MESH_SUFFIXES + CAD_SUFFIXES

# IGES global parameter 14 (units flag) -> (name, millimetres per unit); flag 3 names the unit in 15
IGES_UNITS: dict[int, tuple[str, float]] = {
    1: ("inch", 25.4), 2: ("mm", 1.0), 4: ("foot", 304.8), 5: ("mile", 1609344.0), 6: ("m", 1000.0),
    7: ("km", 1.0e6), 8: ("mil", 0.0254), 9: ("micron", 1.0e-3), 10: ("cm", 10.0),
    11: ("microinch", 2.54e-5),
}  # fmt: skip
IGES_UNIT_NAMES = {"IN": 1, "INCH": 1, "MM": 2, "FT": 4, "MI": 5, "M": 6, "KM": 7, "MIL": 8, "UM": 9,
                   "MICRON": 9, "CM": 10, "UIN": 11}  # fmt: skip
STEP_PREFIX_MM = {"$": 1000.0, ".MILLI.": 1.0, ".CENTI.": 10.0, ".DECI.": 100.0, ".KILO.": 1.0e6,
                  ".MICRO.": 1.0e-3}  # fmt: skip
STEP_PREFIX_NAME = {"$": "m", ".MILLI.": "mm", ".CENTI.": "cm", ".DECI.": "dm", ".KILO.": "km",
                    ".MICRO.": "micron"}  # fmt: skip
STEP_CONVERSION_MM = {"INCH": 25.4, "FOOT": 304.8, "FEET": 304.8, "MILLIMETRE": 1.0, "METRE": 1000.0}
# IGES entity types that carry a surface or a face (what a design's faces come from)
IGES_SURFACE_TYPES = {108, 114, 118, 120, 122, 128, 140, 143, 144, 186, 190, 192, 194, 196, 198, 510, 514}
STEP_FACE_TYPES = ("ADVANCED_FACE", "FACE_SURFACE")


class DesignError(MeshError):
    """A design file that cannot be used; the message is one line naming the file and the problem."""


# ------------------------------------------------------------------------------- file inspection


@dataclass(frozen=True)
class FileFacts:
    """What the file says about itself before OpenCASCADE reads it.

    fmt: "IGES" | "STEP"; units: the file's length unit ("m", "mm", ...); mm_per_unit: its size;
    entities: entity counts by type (IGES type numbers as strings, STEP entity names);
    surfaces: how many faces the file declares (IGES surface entities, STEP faces).
    """

    fmt: str
    units: str
    mm_per_unit: float
    entities: dict[str, int]
    surfaces: int


def _iges_fields(text: str) -> list[str]:
    """The global section's parameters (Hollerith strings unwrapped), in order."""
    pd, rd = ",", ";"
    pos = 0
    fields: list[str] = []
    holl = re.compile(r"\s*(\d+)H")
    while pos < len(text):
        m = holl.match(text, pos)
        if m:
            n = int(m.group(1))
            value = text[m.end() : m.end() + n]
            pos = m.end() + n
        else:
            end = pos
            while end < len(text) and text[end] not in (pd, rd):
                end += 1
            value = text[pos:end].strip()
            pos = end
        fields.append(value)
        if len(fields) == 1 and value and len(value) == 1 and m:
            pd = value
        if len(fields) == 2 and value and len(value) == 1 and m:
            rd = value
        if pos >= len(text) or text[pos] == rd:
            break
        pos += 1  # the delimiter
    return fields


def iges_facts(path: Path, data: bytes) -> FileFacts:
    """Check an IGES file's fixed layout and read its units and entity counts (no geometry)."""
    lines = data.decode("latin-1").splitlines()
    sections: dict[str, list[str]] = {k: [] for k in "SGDPT"}
    for k, line in enumerate(lines):
        if not line.strip():
            continue
        if len(line) < 73 or line[72] not in sections:
            if k == len(lines) - 1:
                raise DesignError(f"{path}: truncated IGES file (its last line, {k + 1}, is cut off)")
            raise DesignError(
                f"{path}: corrupted IGES file (line {k + 1} is not an 80-column S/G/D/P/T record)"
            )
        sections[line[72]].append(line[:72])
    if not sections["D"] or not sections["G"]:
        raise DesignError(f"{path}: not an IGES file (no global or directory section)")
    if not sections["T"]:
        raise DesignError(f"{path}: truncated IGES file (the terminate section is missing)")
    counts = re.findall(r"([SGDP])\s*(\d+)", sections["T"][0])
    for letter, n in counts:
        if int(n) != len(sections[letter]):
            raise DesignError(
                f"{path}: truncated or corrupted IGES file (the terminate section counts {int(n)} "
                f"{letter} lines, the file has {len(sections[letter])})"
            )
    if len(sections["D"]) % 2:
        raise DesignError(f"{path}: corrupted IGES file (odd number of directory lines)")
    try:
        types = Counter(int(d[:8]) for d in sections["D"][::2])
    except ValueError:
        raise DesignError(f"{path}: corrupted IGES file (a directory entry has no entity type)") from None
    g = _iges_fields("".join(sections["G"]))
    flag_text = g[13].strip() if len(g) > 13 else ""
    name = g[14].strip().upper() if len(g) > 14 else ""
    if not flag_text:
        raise DesignError(f"{path}: units missing (the IGES global section has no units flag)")
    try:
        flag = int(float(flag_text))
    except ValueError:
        raise DesignError(f"{path}: corrupted IGES global section (units flag {flag_text!r})") from None
    if flag == 3:
        flag = IGES_UNIT_NAMES.get(name, 0)
    if flag not in IGES_UNITS:
        raise DesignError(f"{path}: units missing or unknown (IGES units flag {flag_text}, name {name!r})")
    unit, mm = IGES_UNITS[flag]
    surfaces = sum(n for t, n in types.items() if t in IGES_SURFACE_TYPES)
    # a trimmed surface (143/144) or a face (510) wraps its 128: count the outermost only
    wrappers = types.get(143, 0) + types.get(144, 0) + types.get(510, 0)
    if wrappers:
        surfaces = wrappers + sum(types.get(t, 0) for t in (108, 114, 118, 120, 122, 140) if t != 128)
    else:
        surfaces = types.get(128, 0) + sum(types.get(t, 0) for t in (108, 114, 118, 120, 122, 140))
    return FileFacts("IGES", unit, mm, {str(t): n for t, n in sorted(types.items())}, surfaces)


def step_facts(path: Path, data: bytes) -> FileFacts:
    """Check a STEP Part 21 file's frame and read its length unit and entity counts (no geometry)."""
    text = data.decode("latin-1")
    head = text.lstrip()[:64].upper()
    if not head.startswith("ISO-10303-21"):
        raise DesignError(f"{path}: not a STEP file (no ISO-10303-21 header)")
    if "END-ISO-10303-21" not in text[-4096:].upper():
        raise DesignError(f"{path}: truncated STEP file (no END-ISO-10303-21 at its end)")
    names = Counter(m.group(1).upper() for m in re.finditer(r"#\d+\s*=\s*([A-Za-z_0-9]+)\s*\(", text))
    mm = unit = None
    for stmt in re.findall(r"#\d+\s*=\s*\(([^;]*LENGTH_UNIT[^;]*)\)\s*;", text, flags=re.IGNORECASE):
        si = re.search(r"SI_UNIT\s*\(\s*(\$|\.\w+\.)\s*,\s*\.METRE\.\s*\)", stmt, flags=re.IGNORECASE)
        conv = re.search(r"CONVERSION_BASED_UNIT\s*\(\s*'([^']*)'", stmt, flags=re.IGNORECASE)
        if si and si.group(1).upper() in STEP_PREFIX_MM:
            mm, unit = STEP_PREFIX_MM[si.group(1).upper()], STEP_PREFIX_NAME[si.group(1).upper()]
        elif conv and conv.group(1).upper() in STEP_CONVERSION_MM:
            mm, unit = STEP_CONVERSION_MM[conv.group(1).upper()], conv.group(1).lower()
        if mm is not None:
            break
    if mm is None:
        raise DesignError(f"{path}: units missing (no length unit in the STEP file)")
    faces = sum(names.get(n, 0) for n in STEP_FACE_TYPES)
    return FileFacts("STEP", unit, mm, dict(sorted(names.items())), faces)


# ---------------------------------------------------------------------------------- NURBS patches


def _basis(knots: np.ndarray, degree: int, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """B-spline basis values and first derivatives at ``x``: two (n, len(knots) - degree - 1) arrays.

    Cox-de Boor on whole arrays, one loop over the degree. ``x`` is clamped into the knot range; the
    last non-empty span is closed on the right so the end parameter evaluates.
    """
    t = knots
    lo, hi = t[degree], t[-degree - 1]
    x = np.clip(np.asarray(x, dtype=np.float64), lo, hi)[:, None]
    span_ok = t[1:] > t[:-1]
    N = ((t[:-1] <= x) & (x < t[1:])).astype(np.float64)
    last = np.nonzero(span_ok)[0][-1]
    N[:, last] = np.where(x[:, 0] >= t[last + 1], 1.0, N[:, last])
    dN = np.zeros_like(N)
    for d in range(1, degree + 1):
        m = len(t) - 1 - d
        den_l = t[d : d + m] - t[:m]
        den_r = t[d + 1 : d + 1 + m] - t[1 : 1 + m]
        inv_l = np.divide(1.0, den_l, out=np.zeros_like(den_l), where=den_l > 0)
        inv_r = np.divide(1.0, den_r, out=np.zeros_like(den_r), where=den_r > 0)
        if d == degree:
            dN = d * (N[:, :m] * inv_l - N[:, 1 : 1 + m] * inv_r)
        N = (x - t[:m]) * inv_l * N[:, :m] + (t[d + 1 : d + 1 + m] - x) * inv_r * N[:, 1 : 1 + m]
    return N, dN


@dataclass(frozen=True)
class NurbsPatch:
    """One face's surface as a tensor-product NURBS, in millimetres (the design frame).

    poles_mm: (nu, nv, 3); weights: (nu, nv) (all 1 for a polynomial surface);
    knots_u, knots_v: flat knot sequences (multiplicities expanded); degree_u, degree_v;
    u_range, v_range: the face's parameter bounds (its trimming box).
    """

    poles_mm: np.ndarray
    weights: np.ndarray
    knots_u: np.ndarray
    knots_v: np.ndarray
    degree_u: int
    degree_v: int
    u_range: tuple[float, float]
    v_range: tuple[float, float]

    @property
    def rational(self) -> bool:
        return bool(np.ptp(self.weights) > 1e-12)

    def evaluate(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Points and first derivatives at parameters (u, v): three (n, 3) arrays, mm."""
        Nu, dNu = _basis(self.knots_u, self.degree_u, u)
        Nv, dNv = _basis(self.knots_v, self.degree_v, v)
        nu, nv = self.weights.shape
        # homogeneous poles (w x, w y, w z, w): u by a matrix product, then v per point
        Pw = np.concatenate([self.poles_mm * self.weights[..., None], self.weights[..., None]], axis=2)
        Pw = Pw.reshape(nu, nv * 4)
        G = (Nu @ Pw).reshape(-1, nv, 4)
        Gu = (dNu @ Pw).reshape(-1, nv, 4)
        H = np.einsum("nj,njc->nc", Nv, G)
        Hu = np.einsum("nj,njc->nc", Nv, Gu)
        Hv = np.einsum("nj,njc->nc", dNv, G)
        A, W = H[:, :3], H[:, 3:]
        Au, Wu = Hu[:, :3], Hu[:, 3:]
        Av, Wv = Hv[:, :3], Hv[:, 3:]
        S = A / W
        return S, (Au - S * Wu) / W, (Av - S * Wv) / W

    def transformed(self, T: np.ndarray) -> NurbsPatch:
        """The patch moved by the 4x4 transform ``T`` (NURBS are affine invariant: move the poles)."""
        P = self.poles_mm @ T[:3, :3].T + T[:3, 3]
        return NurbsPatch(P, self.weights, self.knots_u, self.knots_v, self.degree_u, self.degree_v,
                          self.u_range, self.v_range)  # fmt: skip

    def in_domain(self, u: np.ndarray, v: np.ndarray, tol: float = 1e-9) -> np.ndarray:
        (u0, u1), (v0, v1) = self.u_range, self.v_range
        tu, tv = tol * max(u1 - u0, 1.0), tol * max(v1 - v0, 1.0)
        return (u >= u0 - tu) & (u <= u1 + tu) & (v >= v0 - tv) & (v <= v1 + tv)


# ------------------------------------------------------------------------------------ the design


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


# ------------------------------------------------------------------------------------ OCC reading


def _quiet_occ() -> None:
    """OpenCASCADE prints progress to stdout; a command's stdout is for its own output."""
    from OCP.Message import Message, Message_Gravity

    printers = Message.DefaultMessenger_s().Printers()
    for k in range(1, printers.Length() + 1):
        printers.Value(k).SetTraceLevel(Message_Gravity.Message_Fail)


def _read_shape(path: Path, facts: FileFacts):
    """The file's shape through OpenCASCADE's IGES or STEP reader, in millimetres."""
    from OCP.IFSelect import IFSelect_RetDone
    from OCP.IGESControl import IGESControl_Reader
    from OCP.Interface import Interface_Static
    from OCP.STEPControl import STEPControl_Reader

    _quiet_occ()
    Interface_Static.SetCVal_s("xstep.cascade.unit", "MM")
    reader = IGESControl_Reader() if facts.fmt == "IGES" else STEPControl_Reader()
    status = reader.ReadFile(str(path))
    if status != IFSelect_RetDone:
        raise DesignError(f"{path}: corrupted {facts.fmt} file (OpenCASCADE cannot parse it)")
    if facts.fmt == "IGES":
        reader.SetReadVisible(True)
    reader.TransferRoots()
    if reader.NbShapes() == 0:
        raise DesignError(f"{path}: no surface ({_entity_list(facts)})")
    return reader.OneShape()


def _entity_list(facts: FileFacts) -> str:
    items = sorted(facts.entities.items(), key=lambda kv: -kv[1])[:6]
    prefix = "entities " if facts.fmt == "IGES" else ""
    return prefix + ", ".join(f"{k} x{n}" for k, n in items)


def _faces(shape) -> list:
    from OCP.TopAbs import TopAbs_FACE
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopoDS import TopoDS

    out = []
    ex = TopExp_Explorer(shape, TopAbs_FACE)
    while ex.More():
        out.append(TopoDS.Face(ex.Current()))
        ex.Next()
    return out


def _sew(faces: list, tol_mm: float):
    """Sew the faces into shells; returns (sewn shape, number of connected plates)."""
    from OCP.BRepBuilderAPI import BRepBuilderAPI_Sewing
    from OCP.TopAbs import TopAbs_SHELL
    from OCP.TopExp import TopExp_Explorer

    sew = BRepBuilderAPI_Sewing(tol_mm)
    for f in faces:
        sew.Add(f)
    sew.Perform()
    shape = sew.SewedShape()
    shells = 0
    ex = TopExp_Explorer(shape, TopAbs_SHELL)
    while ex.More():
        shells += 1
        ex.Next()
    free_faces = len(_faces(shape)) - sum(len(_faces(s)) for s in _shells(shape))
    return shape, max(shells, 1 if len(faces) == 1 else 0) + free_faces


def _shells(shape) -> list:
    from OCP.TopAbs import TopAbs_SHELL
    from OCP.TopExp import TopExp_Explorer

    out = []
    ex = TopExp_Explorer(shape, TopAbs_SHELL)
    while ex.More():
        out.append(ex.Current())
        ex.Next()
    return out


def _as_nurbs(shape, faces: list) -> tuple:
    """Faces on planes, cylinders, offsets... converted to NURBS faces (their pcurves follow), so
    that the tessellation's parameters are the NURBS patch's. A shape of B-spline faces is kept."""
    from OCP.BRep import BRep_Tool
    from OCP.BRepBuilderAPI import BRepBuilderAPI_NurbsConvert
    from OCP.Geom import Geom_BSplineSurface

    if all(isinstance(BRep_Tool.Surface_s(f), Geom_BSplineSurface) for f in faces):
        return shape, faces
    converted = BRepBuilderAPI_NurbsConvert(shape, True).Shape()
    return converted, _faces(converted)


def _patch(face, path: Path) -> NurbsPatch:
    """The face's surface as a NURBS patch with the face's parameter bounds (file frame, mm)."""
    from OCP.BRep import BRep_Tool
    from OCP.BRepTools import BRepTools
    from OCP.Geom import Geom_BSplineSurface
    from OCP.GeomConvert import GeomConvert

    u0, u1, v0, v1 = BRepTools.UVBounds_s(face)
    surf = BRep_Tool.Surface_s(face)  # in the face's own coordinates: its location moves it
    bs = surf if isinstance(surf, Geom_BSplineSurface) else None
    if bs is None:
        try:
            from OCP.Geom import Geom_RectangularTrimmedSurface

            bs = GeomConvert.SurfaceToBSplineSurface_s(Geom_RectangularTrimmedSurface(surf, u0, u1, v0, v1))
        except Exception as exc:  # OCC's Standard_Failure: a surface kind it cannot convert
            raise DesignError(
                f"{path}: unsupported surface {type(surf).__name__} ({str(exc)[:80]})"
            ) from None
    bs = bs.Copy()  # OCP hands back the concrete type; the copy may be made non-periodic
    if bs.IsUPeriodic():
        bs.SetUNotPeriodic()
    if bs.IsVPeriodic():
        bs.SetVNotPeriodic()
    nu, nv = bs.NbUPoles(), bs.NbVPoles()
    poles = np.array([[(p.X(), p.Y(), p.Z()) for p in (bs.Pole(i, j) for j in range(1, nv + 1))]
                      for i in range(1, nu + 1)])  # fmt: skip
    weights = np.array([[bs.Weight(i, j) for j in range(1, nv + 1)] for i in range(1, nu + 1)])
    ku = np.array([bs.UKnotSequence().Value(i) for i in range(1, bs.UKnotSequence().Length() + 1)])
    kv = np.array([bs.VKnotSequence().Value(i) for i in range(1, bs.VKnotSequence().Length() + 1)])
    trsf = face.Location().Transformation()
    T = np.eye(4)
    T[:3, :] = [[trsf.Value(i, j) for j in range(1, 5)] for i in range(1, 4)]
    patch = NurbsPatch(poles, weights, ku, kv, bs.UDegree(), bs.VDegree(), (u0, u1), (v0, v1))
    return patch if np.allclose(T, np.eye(4)) else patch.transformed(T)


def _untrimmed(face, patch: NurbsPatch) -> bool:
    """True when the face is its patch's whole parameter rectangle: one wire, every edge's curve on
    the surface lying on one side of the rectangle (no trimming curve inside it)."""
    from OCP.BRepAdaptor import BRepAdaptor_Curve2d
    from OCP.TopAbs import TopAbs_EDGE, TopAbs_WIRE
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopoDS import TopoDS

    wires = TopExp_Explorer(face, TopAbs_WIRE)
    n_wires = 0
    while wires.More():
        n_wires += 1
        wires.Next()
    if n_wires != 1:
        return False
    (u0, u1), (v0, v1) = patch.u_range, patch.v_range
    tol_u, tol_v = 1e-9 * max(u1 - u0, 1e-9), 1e-9 * max(v1 - v0, 1e-9)
    ex = TopExp_Explorer(face, TopAbs_EDGE)
    while ex.More():
        c = BRepAdaptor_Curve2d(TopoDS.Edge(ex.Current()), face)
        pts = [c.Value(t) for t in np.linspace(c.FirstParameter(), c.LastParameter(), 5)]
        u = np.array([p.X() for p in pts])
        v = np.array([p.Y() for p in pts])
        on_side = (
            np.all(np.abs(u - u0) < tol_u) or np.all(np.abs(u - u1) < tol_u)
            or np.all(np.abs(v - v0) < tol_v) or np.all(np.abs(v - v1) < tol_v)
        )  # fmt: skip
        if not on_side:
            return False
        ex.Next()
    return True


def _grid_tessellation(patch: NurbsPatch, chord_mm: float, max_nodes: int = 400_000):
    """A patch's whole parameter rectangle as a grid mesh with chord error about ``chord_mm``.

    The grid is refined once from a 17 x 17 trial: the midpoints' departure from the chords falls
    with the square of the spacing. Returns (vertices, triangles, uv (n, 2)); triangles are
    counter-clockwise in (u, v) (du x dv side).
    """
    (u0, u1), (v0, v1) = patch.u_range, patch.v_range

    def departure(nu: int, nv: int) -> tuple[float, float, float, float]:
        u = np.linspace(u0, u1, nu)
        v = np.linspace(v0, v1, nv)
        U, V = np.meshgrid(u, v, indexing="ij")
        S = patch.evaluate(U.ravel(), V.ravel())[0].reshape(nu, nv, 3)
        Um, Vm = np.meshgrid((u[:-1] + u[1:]) / 2, v, indexing="ij")
        Su = patch.evaluate(Um.ravel(), Vm.ravel())[0].reshape(nu - 1, nv, 3)
        Um, Vm = np.meshgrid(u, (v[:-1] + v[1:]) / 2, indexing="ij")
        Sv = patch.evaluate(Um.ravel(), Vm.ravel())[0].reshape(nu, nv - 1, 3)
        Um, Vm = np.meshgrid((u[:-1] + u[1:]) / 2, (v[:-1] + v[1:]) / 2, indexing="ij")
        Sc = patch.evaluate(Um.ravel(), Vm.ravel())[0].reshape(nu - 1, nv - 1, 3)
        dc = np.linalg.norm(Sc - (S[:-1, :-1] + S[1:, 1:]) / 2, axis=2).max()  # the cell's diagonal
        du = max(np.linalg.norm(Su - (S[:-1] + S[1:]) / 2, axis=2).max(), dc)
        dv = max(np.linalg.norm(Sv - (S[:, :-1] + S[:, 1:]) / 2, axis=2).max(), dc)
        len_u = np.linalg.norm(np.diff(S, axis=0), axis=2).sum(axis=0).max()
        len_v = np.linalg.norm(np.diff(S, axis=1), axis=2).sum(axis=1).max()
        return float(du), float(dv), float(len_u), float(len_v)

    n0 = 17
    du, dv, len_u, len_v = departure(n0, n0)
    # fine enough for the chord error, and no cell longer than 20 mm on a plate (a hull's patch:
    # 1 % of its length), so seeds and section extents stay local
    cell = max(20.0, 0.01 * max(len_u, len_v))
    nu = int(np.clip(max(np.ceil((n0 - 1) * np.sqrt(du / chord_mm)), np.ceil(len_u / cell)) + 1, 2, 4000))
    nv = int(np.clip(max(np.ceil((n0 - 1) * np.sqrt(dv / chord_mm)), np.ceil(len_v / cell)) + 1, 2, 4000))
    if nu * nv > max_nodes:
        scale = np.sqrt(max_nodes / (nu * nv))
        nu, nv = max(2, int(nu * scale)), max(2, int(nv * scale))
    u = np.linspace(u0, u1, nu)
    v = np.linspace(v0, v1, nv)
    U, V = np.meshgrid(u, v, indexing="ij")
    uv = np.column_stack([U.ravel(), V.ravel()])
    S = patch.evaluate(uv[:, 0], uv[:, 1])[0]
    idx = np.arange(nu * nv).reshape(nu, nv)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    tri = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    return S, tri, uv


def _tessellate(faces: list, patches: list[NurbsPatch], deflection_mm: float):
    """(vertices (n, 3), triangles (m, 3), triangle face (m,), triangle uv (m, 3, 2)), file frame.

    A face that is its patch's whole parameter rectangle is gridded in numpy at a fifth of the
    deflection (exact nodes, fast); a trimmed face is meshed by OpenCASCADE within the deflection.
    """
    from OCP.BRep import BRep_Tool
    from OCP.BRepMesh import BRepMesh_IncrementalMesh
    from OCP.TopAbs import TopAbs_REVERSED
    from OCP.TopLoc import TopLoc_Location

    verts, tris, tface, tuv = [], [], [], []
    offset = 0
    for k, (face, patch) in enumerate(zip(faces, patches, strict=True)):
        if _untrimmed(face, patch):
            pts, t, uv = _grid_tessellation(patch, deflection_mm / 5.0)
        else:
            BRepMesh_IncrementalMesh(face, deflection_mm, False, 0.1, False)
            loc = TopLoc_Location()
            tri = BRep_Tool.Triangulation_s(face, loc)
            if tri is None or tri.NbTriangles() == 0:
                continue
            trsf = loc.Transformation()
            n = tri.NbNodes()
            pts = []
            for i in range(1, n + 1):
                p = tri.Node(i).Transformed(trsf)
                pts.append((p.X(), p.Y(), p.Z()))
            pts = np.asarray(pts)
            uv = np.array([(tri.UVNode(i).X(), tri.UVNode(i).Y()) for i in range(1, n + 1)])
            t = np.array([tri.Triangle(i).Get() for i in range(1, tri.NbTriangles() + 1)], dtype=np.int64) - 1
        if face.Orientation() == TopAbs_REVERSED:
            t = t[:, [0, 2, 1]]
        verts.append(pts)
        tris.append(t + offset)
        tface.append(np.full(len(t), k))
        tuv.append(uv[t])
        offset += len(pts)
    if not tris:
        raise DesignError("the surface could not be tessellated")
    return np.concatenate(verts), np.concatenate(tris), np.concatenate(tface), np.concatenate(tuv)


def _weld(vertices: np.ndarray, triangles: np.ndarray, tol_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Merge coincident vertices (the faces' shared edges) so the mesh is one connected surface."""
    key = np.round(vertices / tol_mm).astype(np.int64)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    return vertices[first], inverse.reshape(-1)[triangles]


def _free_edges(shape) -> list:
    """Edges of the shape used by one face only: the plate's outline (seams excluded)."""
    from OCP.BRep import BRep_Tool
    from OCP.OCP.collections import (
        IndexedDataMap_TopoDS_Shape_List_TopoDS_Shape_TopTools_ShapeMapHasher as EdgeFaces,
    )
    from OCP.TopAbs import TopAbs_EDGE, TopAbs_FACE
    from OCP.TopExp import TopExp
    from OCP.TopoDS import TopoDS

    emap = EdgeFaces()
    TopExp.MapShapesAndAncestors_s(shape, TopAbs_EDGE, TopAbs_FACE, emap)
    out = []
    for k in range(1, emap.Extent() + 1):
        edge = TopoDS.Edge(emap.FindKey(k))
        faces = emap.FindFromIndex(k)
        if faces.Size() == 1 and not BRep_Tool.Degenerated_s(edge):
            face = TopoDS.Face(faces.First())
            if not BRep_Tool.IsClosed_s(edge, face):  # a periodic face's seam is not outline
                out.append(edge)
    return out


def _boundary(shape, path: Path) -> list[tuple[np.ndarray, np.ndarray]]:
    """The free boundary as closed loops: per loop (samples (k, 3), vertex flags (k,) bool), the
    boundary curves sampled every 2 mm or finer, chained end to end."""
    from OCP.BRepAdaptor import BRepAdaptor_Curve
    from OCP.GCPnts import GCPnts_AbscissaPoint

    pieces = []
    for edge in _free_edges(shape):
        c = BRepAdaptor_Curve(edge)
        a, b = c.FirstParameter(), c.LastParameter()
        length = GCPnts_AbscissaPoint.Length_s(c)
        n = int(np.clip(np.ceil(length / 2.0), 8, 4000))
        pts = []
        for tt in np.linspace(a, b, n + 1):
            p = c.Value(float(tt))
            pts.append((p.X(), p.Y(), p.Z()))
        pieces.append(np.asarray(pts))
    if not pieces:
        raise DesignError(f"{path}: the surface has no free boundary (a closed solid, not a plate surface)")
    size = max(float(np.ptp(np.concatenate(pieces), axis=0).max()), 1.0)
    loops = []
    left = list(range(len(pieces)))
    while left:
        loop = [pieces[left.pop(0)]]
        while left:
            end = loop[-1][-1]
            ends = np.array([[np.linalg.norm(pieces[i][0] - end), np.linalg.norm(pieces[i][-1] - end)]
                             for i in left])  # fmt: skip
            k, side = np.unravel_index(int(np.argmin(ends)), ends.shape)
            if ends[k, side] > 1e-3 * size:
                break
            piece = pieces[left.pop(int(k))]
            loop.append(piece if side == 0 else piece[::-1])
        samples = np.concatenate([p[:-1] for p in loop])
        flags = np.concatenate([np.arange(len(p) - 1) == 0 for p in loop])
        loops.append((samples, flags))
    return loops


def read_cad(
    path: str | Path,
    deflection_mm: float | None = None,
    sew_tol_mm: float | None = None,
    *,
    one_plate: bool = True,
    isolated: bool = True,
    timeout_s: float = 300.0,
) -> CadDesign:
    """Read an IGES or STEP design (see :func:`read_cad_in_process` for the parameters).

    isolated: read in a forked child process. OpenCASCADE's translators trust the file: a
    corrupted STEP entity crashed the whole process (segmentation fault), as open3d did on a bad
    PLY. A :class:`CadDesign` is plain arrays, so the child pickles it back through a pipe; a
    child that dies or runs past ``timeout_s`` refuses the file with one line.
    """
    if not isolated:
        return read_cad_in_process(path, deflection_mm, sew_tol_mm, one_plate=one_plate)
    import OCP.BRepMesh
    import OCP.IGESControl
    import OCP.STEPControl  # noqa: F401 - loaded once here, inherited by every forked reader

    design = _in_child(
        lambda: read_cad_in_process(path, deflection_mm, sew_tol_mm, one_plate=one_plate, quiet=True),
        path,
        timeout_s,
    )
    log.info("design_read", file=str(path), fmt=design.facts.fmt, units=design.facts.units,
             faces=len(design.faces), triangles=len(design.mesh.triangles),
             chord_error_mm=round(design.chord_error_mm, 5))  # fmt: skip
    return design


def _in_child(work, path: str | Path, timeout_s: float):
    """Run ``work()`` in a forked child; its result or exception comes back pickled."""
    import os
    import pickle
    import select
    import signal
    import time

    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: never returns into the caller's code
        import faulthandler

        faulthandler.disable()  # a crash is reported by the parent in one line, not as a dump
        os.close(r)
        code = 0
        try:
            try:
                payload = pickle.dumps(("ok", work()))
            except DesignError as exc:
                payload = pickle.dumps(("error", str(exc)))
            except Exception as exc:  # a reader bug still ends in one line, with its type
                payload = pickle.dumps(
                    ("error", f"{path}: the CAD reader failed ({type(exc).__name__}: {exc})")
                )
            with os.fdopen(w, "wb") as f:
                f.write(payload)
        except BaseException:  # the child must exit, whatever happened
            code = 1
        os._exit(code)
    os.close(w)
    chunks: list[bytes] = []
    deadline = time.monotonic() + timeout_s
    try:
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                os.kill(pid, signal.SIGKILL)
                raise DesignError(f"{path}: the CAD reader did not finish within {timeout_s:.0f} s")
            ready, _, _ = select.select([r], [], [], min(left, 1.0))
            if ready:
                chunk = os.read(r, 1 << 20)
                if not chunk:
                    break
                chunks.append(chunk)
    finally:
        os.close(r)
        _, status = os.waitpid(pid, 0)
    if os.WIFSIGNALED(status) or not chunks:
        kind = Path(path).suffix.lstrip(".").upper()
        why = f"signal {os.WTERMSIG(status)}" if os.WIFSIGNALED(status) else f"exit {os.WEXITSTATUS(status)}"
        raise DesignError(f"{path}: corrupted {kind} file (the CAD reader crashed on it: {why})")
    kind, value = pickle.loads(b"".join(chunks))
    if kind == "error":
        raise DesignError(value)
    return value


def read_cad_in_process(
    path: str | Path,
    deflection_mm: float | None = None,
    sew_tol_mm: float | None = None,
    *,
    one_plate: bool = True,
    quiet: bool = False,
) -> CadDesign:
    """Read an IGES or STEP design into a :class:`CadDesign` (design frame, mm), in this process.

    deflection_mm: the tessellation's chord tolerance; default 0.01 mm (half the sensor noise) for a plate up to 5 m
    across, 1e-5 of the diagonal beyond (a whole hull). sew_tol_mm: gap up to which faces sharing an
    edge are sewn into one plate (default 0.05 mm, 1e-5 of the diagonal for a whole hull).
    one_plate: refuse a file whose faces form several separate pieces (a whole hull's patches may
    overlap and be read with False). Raises :class:`DesignError` (one line) for an unusable file.
    """
    import time

    path = Path(path)
    timings: dict[str, float] = {}
    t0, c0 = time.perf_counter(), time.process_time()
    if not path.is_file():
        raise DesignError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if suffix not in CAD_SUFFIXES:
        raise DesignError(f"{path}: not an IGES or STEP file (suffix {path.suffix!r})")
    data = path.read_bytes()
    if not data.strip():
        raise DesignError(f"{path}: empty file")
    facts = iges_facts(path, data) if suffix in (".igs", ".iges") else step_facts(path, data)
    shape = _read_shape(path, facts)
    faces = _faces(shape)
    if not faces:
        kinds = _entity_list(facts)
        if facts.surfaces:
            raise DesignError(f"{path}: unsupported entity: no face could be made from {kinds}")
        raise DesignError(f"{path}: no surface in the file ({kinds})")
    if facts.surfaces and len(faces) < facts.surfaces:
        raise DesignError(
            f"{path}: {facts.surfaces - len(faces)} of {facts.surfaces} surfaces could not be read "
            f"(corrupted or unsupported entity; {_entity_list(facts)})"
        )
    timings["read"] = time.perf_counter() - t0
    t = time.perf_counter()
    from OCP.Bnd import Bnd_Box
    from OCP.BRepBndLib import BRepBndLib

    box = Bnd_Box()
    BRepBndLib.Add_s(shape, box)
    diag = box.CornerMin().Distance(box.CornerMax())
    if sew_tol_mm is None:
        sew_tol_mm = max(0.05, 1e-5 * diag)
    if len(faces) > 1:
        shape, plates = _sew(faces, sew_tol_mm)
        faces = _faces(shape)
        if plates > 1 and one_plate:
            raise DesignError(
                f"{path}: several disjoint plates ({plates} separate pieces among {len(faces)} faces); "
                "give one plate per file"
            )
    shape, faces = _as_nurbs(shape, faces)
    patches = [_patch(f, path) for f in faces]
    timings["sew"] = time.perf_counter() - t
    t = time.perf_counter()
    if deflection_mm is None:
        deflection_mm = 0.01 if diag <= 5000.0 else 1e-5 * diag
    try:
        V, Tr, tface, tuv = _tessellate(faces, patches, deflection_mm)
    except DesignError as exc:
        raise DesignError(f"{path}: {exc}") from None
    V, Tr = _weld(V, Tr, min(1e-3, sew_tol_mm))
    timings["tessellate"] = time.perf_counter() - t
    t = time.perf_counter()
    wires = _boundary(shape, path)
    samples, vflag = max(wires, key=lambda w: np.ptp(w[0], axis=0).sum())
    mesh_file = TriMesh(V, Tr)
    up = mesh_file.triangle_normals().T @ mesh_file.triangle_areas_mm2()
    up /= max(np.linalg.norm(up), 1e-300)
    try:
        corners_file = samples[outline_corners(samples, up, candidates=vflag)]
    except OutlineError as exc:
        raise DesignError(f"{path}: {exc}") from None
    T = plate_frame_from_surface(V, Tr, corners_file)

    def framed(T: np.ndarray) -> CadDesign:
        mesh = mesh_file.transformed(T)
        return CadDesign(
            path=path, facts=facts, faces=[p.transformed(T) for p in patches], mesh=mesh,
            triangle_face=tface, triangle_uv=tuv, corners_mm=canonical_corner_order(_apply(T, corners_file)),
            boundary_mm=_apply(T, samples), T_design_file=T, deflection_mm=float(deflection_mm),
            chord_error_mm=0.0, area_mm2=float(mesh.triangle_areas_mm2().sum()), timings_s=timings,
        )  # fmt: skip

    design = framed(T)
    if not np.array_equal(T, np.eye(4)):
        # the origin on the surface itself, over the corners' centre (as a mesh's design frame has it)
        foot = design.vertical_heights(np.zeros((1, 3)), np.array([0.0, 0.0, 1.0]))[0]
        if np.isfinite(foot).all():
            shift = np.eye(4)
            shift[2, 3] = -foot[2]
            design = framed(shift @ T)
    design.chord_error_mm = measured_chord_error_mm(design)
    timings["boundary"] = time.perf_counter() - t
    timings["cpu"] = time.process_time() - c0  # the reader's own CPU time (a forked child's too)
    if not quiet:  # a forked child does not log: another thread may have held the log's lock
        log.info("design_read", file=str(path), fmt=facts.fmt, units=facts.units, faces=len(patches),
                 triangles=len(design.mesh.triangles), chord_error_mm=round(design.chord_error_mm, 5))  # fmt: skip
    return design


def measured_chord_error_mm(design: CadDesign, max_triangles: int = 5000) -> float:
    """The largest distance between the tessellation and the exact surface (mm), measured where a
    triangle departs most from its surface: its centroid and its edge midpoints (a subsample of at
    most ``max_triangles`` triangles)."""
    m = len(design.mesh.triangles)
    idx = np.arange(m) if m <= max_triangles else np.random.default_rng(0).choice(m, max_triangles, False)
    tv = design.mesh.triangle_vertices_mm[idx]
    tuv = design.triangle_uv[idx]
    face = design.triangle_face[idx]
    worst = 0.0
    for wts in ((1 / 3, 1 / 3, 1 / 3), (0.5, 0.5, 0.0), (0.0, 0.5, 0.5), (0.5, 0.0, 0.5)):
        w = np.asarray(wts)
        p = np.einsum("k,nkc->nc", w, tv)
        _, dist = design.project(p, iterations=6, seeds=(face, np.einsum("k,nkc->nc", w, tuv)))
        worst = max(worst, float(dist.max()))
    return worst


def read_design(path: str | Path) -> TriMesh | CadDesign:
    """Any design file: IGES / STEP -> :class:`CadDesign`; PLY / STL / OBJ -> :class:`TriMesh` (mm)."""
    suffix = Path(path).suffix.lower()
    if suffix in CAD_SUFFIXES:
        return read_cad(path)
    if suffix in MESH_SUFFIXES:
        # a mesh in ship coordinates is moved into its own plate frame, as a CAD design is
        try:
            return frame_design_mesh(load_mesh(path)).mesh
        except OutlineError as exc:
            raise DesignError(f"{path}: {exc}") from None
    raise DesignError(
        f"{path}: unsupported design format {Path(path).suffix!r} (use {', '.join(DESIGN_SUFFIXES)})"
    )


def design_mesh_of(design: TriMesh | CadDesign) -> TriMesh:
    """The triangle mesh of a design (a CAD design's tessellation)."""
    return design.mesh if isinstance(design, CadDesign) else design


def design_mesh_from_file(path: str | Path) -> TriMesh:
    """The design's triangle mesh from any design file, in the design frame (the planner's input)."""
    return design_mesh_of(read_design(path))
