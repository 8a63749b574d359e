"""The plate as a finite-element plate loaded by the inherent deformation of heating lines.

Bending: Kirchhoff plate, Morley triangles (scikit-fem), ``M = D (kappa - kappa_inh)``; membrane:
plane stress, linear triangles, ``N = A (eps - eps_inh)``. On a flat plate the two do not couple
(linear theory), so they are two small solves with the same mesh. A heating line is a band whose
inherent curvature and strain integrate across it to the line's bend and shrinkage
(``coefficients.InherentDeformation``); the band is smoothed to a Gaussian of the same integral so the
response does not depend on where the band falls in the mesh. The plate is free: the rigid motions
are held by three corners (bending) and a corner plus a direction (membrane), and a caller compares
shapes after removing a best-fit plane, as the resting fit does.

Frames and units: plate frame in mm (x along the plate's length, y across, z up out of the face that
lies up on the bed, ``top``), deflection ``w_mm`` along z.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu
from scipy.spatial import cKDTree
from scipy.special import erf
from skfem import Basis, BilinearForm, ElementTriMorley, ElementTriP1, ElementVector, MeshTri, asm
from skfem.helpers import dd, ddot, sym_grad, trace

from analysis.forming.coefficients import InherentDeformation, Material


@dataclass(frozen=True)
class HeatingLine:
    """One straight heating line in the plate frame, with what it leaves (per unit length).

    ``face`` is ``"top"`` (the face up on the bed) or ``"bottom"``; heating a face bends the plate
    toward it.
    """

    start_plate_mm: tuple[float, float]
    end_plate_mm: tuple[float, float]
    face: str
    deformation: InherentDeformation

    def __post_init__(self) -> None:
        if self.face not in ("top", "bottom"):
            raise ValueError(f"face must be 'top' or 'bottom', not {self.face!r}")
        if math.dist(self.start_plate_mm, self.end_plate_mm) <= 0:
            raise ValueError(f"a heating line needs two distinct ends, got {self.start_plate_mm}")


def _band_weights(
    points_mm: np.ndarray, start_mm: np.ndarray, end_mm: np.ndarray, sigma_mm: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Across-line density (1/mm, integrates to 1 across) at ``points_mm`` (2, ...), tapered at the
    ends with the same width; and the line's unit tangent and normal."""
    d = end_mm - start_mm
    length = float(np.hypot(*d))
    t = d / length
    n = np.array([-t[1], t[0]])
    rel = points_mm - start_mm.reshape((2,) + (1,) * (points_mm.ndim - 1))
    s = np.tensordot(t, rel, axes=1)  # along, from the start
    q = np.tensordot(n, rel, axes=1)  # across
    across = np.exp(-0.5 * (q / sigma_mm) ** 2) / (math.sqrt(2.0 * math.pi) * sigma_mm)
    along = 0.5 * (erf(s / (math.sqrt(2.0) * sigma_mm)) - erf((s - length) / (math.sqrt(2.0) * sigma_mm)))
    return across * along, t, n


@dataclass
class PlateModel:
    """A rectangular plate ``length_mm`` x ``width_mm`` x ``thickness_mm`` meshed at ``element_mm``,
    with its factorised stiffnesses, ready for many load cases.

    Build one with ``PlateModel.build``; ``deflection`` and ``influence`` answer w at given points.
    """

    length_mm: float
    width_mm: float
    thickness_mm: float
    element_mm: float
    material: Material
    mesh: MeshTri
    bending_basis: Basis
    membrane_basis: Basis
    _bending_free: np.ndarray
    _bending_lu: object
    _membrane_free: np.ndarray
    _membrane_lu: object
    _qp_mm: np.ndarray  # (2, nelems, nqp)
    _hess: list[np.ndarray]  # per local dof: (2, 2, nelems, nqp)
    _probes: dict[bytes, sp.csr_matrix] = field(default_factory=dict)

    @staticmethod
    def build(
        length_mm: float,
        width_mm: float,
        thickness_mm: float,
        material: Material,
        element_mm: float | None = None,
    ) -> PlateModel:
        """Mesh and factorise. ``element_mm`` defaults to a size that keeps the plate near 6000
        triangles (20 mm at the least): fine enough for lines 50 mm apart, fast after every scan."""
        if min(length_mm, width_mm, thickness_mm) <= 0:
            raise ValueError(f"plate {length_mm} x {width_mm} x {thickness_mm} mm must be positive")
        if element_mm is None:
            element_mm = max(20.0, math.sqrt(length_mm * width_mm / 3000.0))
        nx = max(4, round(length_mm / element_mm))
        ny = max(4, round(width_mm / element_mm))
        mesh = MeshTri.init_tensor(np.linspace(0.0, length_mm, nx + 1), np.linspace(0.0, width_mm, ny + 1))
        e_mpa, nu, h = material.youngs_modulus_mpa, material.poisson_ratio, thickness_mm
        d_nmm = e_mpa * h**3 / (12.0 * (1.0 - nu**2))

        bending_basis = Basis(mesh, ElementTriMorley(), intorder=4)

        @BilinearForm
        def bending(u, v, w):
            return d_nmm * ((1.0 - nu) * ddot(dd(u), dd(v)) + nu * trace(dd(u)) * trace(dd(v)))

        kb = asm(bending, bending_basis).tocsc()
        corners = [
            int(np.argmin(np.hypot(mesh.p[0] - x, mesh.p[1] - y)))
            for x, y in ((0.0, 0.0), (length_mm, 0.0), (0.0, width_mm))
        ]
        fixed_b = bending_basis.nodal_dofs[0, corners]
        free_b = np.setdiff1d(np.arange(bending_basis.N), fixed_b)
        lu_b = _factorise(kb[free_b][:, free_b])

        membrane_basis = Basis(mesh, ElementVector(ElementTriP1()), intorder=2)
        lam = e_mpa * nu / (1.0 - nu**2)  # plane stress
        mu = e_mpa / (2.0 * (1.0 + nu))

        @BilinearForm
        def membrane(u, v, w):
            eu, ev = sym_grad(u), sym_grad(v)
            return h * (2.0 * mu * ddot(eu, ev) + lam * trace(eu) * trace(ev))

        km = asm(membrane, membrane_basis).tocsc()
        c0, c1 = corners[0], corners[1]
        fixed_m = np.array(
            [
                membrane_basis.nodal_dofs[0, c0],
                membrane_basis.nodal_dofs[1, c0],
                membrane_basis.nodal_dofs[1, c1],
            ]
        )
        free_m = np.setdiff1d(np.arange(membrane_basis.N), fixed_m)
        lu_m = _factorise(km[free_m][:, free_m])

        qp = bending_basis.global_coordinates().value
        hess = [np.asarray(bending_basis.basis[i][0].hess) for i in range(len(bending_basis.basis))]
        return PlateModel(
            length_mm,
            width_mm,
            thickness_mm,
            float(element_mm),
            material,
            mesh,
            bending_basis,
            membrane_basis,
            free_b,
            lu_b,
            free_m,
            lu_m,
            qp,
            hess,
        )

    @property
    def band_sigma_mm(self) -> float:
        """Width (standard deviation, mm) of the smoothed band: resolved by the quadrature."""
        return 0.6 * self.element_mm

    def _curvature_load(self, lines: list[HeatingLine]) -> np.ndarray:
        """The bending right-hand side of ``lines``: int D [(1-nu) K_inh : H(phi) + nu tr K tr H(phi)]."""
        rhs = np.zeros(self.bending_basis.N)
        for line in lines:
            rhs += self._line_load(line)
        return rhs

    def _line_load(self, line: HeatingLine) -> np.ndarray:
        """One line's bending right-hand side, integrated only over the elements its band reaches
        (the band's Gaussian and its tapered ends are below 1e-14 of their peak 8 widths away)."""
        nu = self.material.poisson_ratio
        d_nmm = self.material.youngs_modulus_mpa * self.thickness_mm**3 / (12.0 * (1.0 - nu**2))
        start = np.asarray(line.start_plate_mm, float)
        end = np.asarray(line.end_plate_mm, float)
        pad = 8.0 * self.band_sigma_mm + 1.5 * self.element_mm  # an element's points lie near its centre
        lo, hi = np.minimum(start, end) - pad, np.maximum(start, end) + pad
        centre = self._qp_mm.mean(axis=2)  # (2, nelems)
        near = np.flatnonzero(np.all((centre >= lo[:, None]) & (centre <= hi[:, None]), axis=0))
        dens, t, n = _band_weights(self._qp_mm[:, near], start, end, self.band_sigma_mm)
        sign = 1.0 if line.face == "top" else -1.0
        ka = sign * line.deformation.bend_across_rad * dens  # curvature across the line, 1/mm
        kl = sign * line.deformation.bend_along_rad * dens
        kxx = ka * n[0] * n[0] + kl * t[0] * t[0]
        kyy = ka * n[1] * n[1] + kl * t[1] * t[1]
        kxy = ka * n[0] * n[1] + kl * t[0] * t[1]
        dx = self.bending_basis.dx[near]
        tr = kxx + kyy
        rhs = np.zeros(self.bending_basis.N)
        for i, hess in enumerate(self._hess):
            h = hess[:, :, near]
            integrand = (1.0 - nu) * (kxx * h[0, 0] + 2.0 * kxy * h[0, 1] + kyy * h[1, 1]) + nu * tr * (
                h[0, 0] + h[1, 1]
            )
            rhs += np.bincount(
                self.bending_basis.element_dofs[i, near],
                d_nmm * (integrand * dx).sum(axis=1),
                minlength=rhs.size,
            )
        return rhs

    def _solve_bending(self, rhs: np.ndarray) -> np.ndarray:
        w = np.zeros(rhs.shape)
        w[self._bending_free] = self._bending_lu.solve(rhs[self._bending_free])
        return w

    def deflection_mm(self, lines: list[HeatingLine], points_mm: np.ndarray) -> np.ndarray:
        """Deflection ``w`` (mm, up) at ``points_mm`` (n, 2) after heating ``lines``, three corners held."""
        w = self._solve_bending(self._curvature_load(lines))
        return self.probe(points_mm) @ w

    def probe(self, points_mm: np.ndarray) -> sp.csr_matrix:
        """The (n, dofs) matrix that evaluates a bending solution at ``points_mm`` (n, 2) inside the plate."""
        points_mm = np.asarray(points_mm, float)
        if points_mm.ndim != 2 or points_mm.shape[1] != 2:
            raise ValueError(f"points_mm must be (n, 2), got {points_mm.shape}")
        key = points_mm.tobytes()
        if key not in self._probes:  # finding the points' elements is the slow part: once per point set
            inside = np.clip(points_mm, [1e-6, 1e-6], [self.length_mm - 1e-6, self.width_mm - 1e-6])
            self._probes = {key: _probe_matrix(self.bending_basis, inside)}
        return self._probes[key]

    def influence_mm(self, lines: list[HeatingLine], points_mm: np.ndarray) -> np.ndarray:
        """Deflection at ``points_mm`` (n, 2) of each line alone: (n, len(lines)), one solve with many
        right-hand sides on the factorised stiffness."""
        if not lines:
            return np.zeros((len(points_mm), 0))
        rhs = np.stack([self._line_load(line) for line in lines], axis=1)
        w = np.zeros_like(rhs)
        # SuperLU solves column by column: the right-hand sides in Fortran order spare it a copy
        w[self._bending_free] = self._bending_lu.solve(np.asfortranarray(rhs[self._bending_free]))
        return self.probe(points_mm) @ w

    def in_plane_mm(self, lines: list[HeatingLine], points_mm: np.ndarray) -> np.ndarray:
        """In-plane displacement (n, 2) in mm at ``points_mm`` after the lines' shrinkage."""
        e_mpa, nu, h = self.material.youngs_modulus_mpa, self.material.poisson_ratio, self.thickness_mm
        lam = e_mpa * nu / (1.0 - nu**2)
        mu = e_mpa / (2.0 * (1.0 + nu))
        mb = self.membrane_basis
        qp = mb.global_coordinates().value
        exx = np.zeros(qp.shape[1:])
        eyy = np.zeros_like(exx)
        exy = np.zeros_like(exx)
        for line in lines:
            dens, t, n = _band_weights(
                qp,
                np.asarray(line.start_plate_mm, float),
                np.asarray(line.end_plate_mm, float),
                self.band_sigma_mm,
            )
            ea = -line.deformation.shrink_across_mm * dens  # strain across, negative: shrinkage
            el = -line.deformation.shrink_along_mm * dens
            exx += ea * n[0] * n[0] + el * t[0] * t[0]
            eyy += ea * n[1] * n[1] + el * t[1] * t[1]
            exy += ea * n[0] * n[1] + el * t[0] * t[1]
        tr = exx + eyy
        sxx = h * (2 * mu * exx + lam * tr)
        syy = h * (2 * mu * eyy + lam * tr)
        sxy = h * 2 * mu * exy
        rhs = np.zeros(mb.N)
        for i in range(len(mb.basis)):
            g = np.asarray(mb.basis[i][0].grad)  # (2 components, 2 derivatives, nelems, nqp)
            sym_xy = 0.5 * (g[0, 1] + g[1, 0])
            integrand = sxx * g[0, 0] + syy * g[1, 1] + 2.0 * sxy * sym_xy
            rhs += np.bincount(mb.element_dofs[i], (integrand * mb.dx).sum(axis=1), minlength=rhs.size)
        u = np.zeros(mb.N)
        u[self._membrane_free] = self._membrane_lu.solve(rhs[self._membrane_free])
        pts = np.clip(
            np.asarray(points_mm, float), [1e-6, 1e-6], [self.length_mm - 1e-6, self.width_mm - 1e-6]
        )
        probe = _probe_matrix(mb, pts)
        return (probe @ u).reshape(2, -1).T  # rows: every point's x, then every point's y


def _factorise(k: sp.spmatrix) -> object:
    """LU of a symmetric positive definite stiffness (rigid motions held): a minimum-degree ordering
    of K + K^T and no pivoting off the diagonal (SuperLU's symmetric mode) has half the fill of its
    default column ordering, so the many-right-hand-side solve of the planner's influence takes
    about a third of the time (6000 x 2000 at 63 mm: 0.8 M entries against 1.7 M)."""
    return splu(k.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})


def _containing_triangles(mesh: MeshTri, points_mm: np.ndarray) -> np.ndarray:
    """The triangle holding each point (n, 2): the nearest centroids' triangles, checked by
    barycentric coordinates (skfem's own finder tests every point against every candidate, which is
    quadratic in the number of points)."""
    tri = mesh.p[:, mesh.t]  # (2, 3, nt)
    tree = cKDTree(tri.mean(axis=1).T)
    k = min(8, mesh.t.shape[1])
    _, cand = tree.query(points_mm, k=k)  # (n, k)
    a, b, c = tri[:, 0, cand], tri[:, 1, cand], tri[:, 2, cand]  # (2, n, k)
    v0, v1, v2 = b - a, c - a, points_mm.T[:, :, None] - a
    det = v0[0] * v1[1] - v0[1] * v1[0]
    l1 = (v2[0] * v1[1] - v2[1] * v1[0]) / det
    l2 = (v0[0] * v2[1] - v0[1] * v2[0]) / det
    slack = np.minimum(np.minimum(l1, l2), 1.0 - l1 - l2)  # >= 0 inside
    best = np.argmax(slack, axis=1)
    if np.any(slack[np.arange(len(points_mm)), best] < -1e-9):
        raise ValueError("a point lies outside the plate's mesh")
    return cand[np.arange(len(points_mm)), best]


def _probe_matrix(basis: Basis, points_mm: np.ndarray) -> sp.csr_matrix:
    """The (components * n, dofs) matrix that evaluates a solution of ``basis`` at ``points_mm`` (n, 2)
    (as skfem's ``CellBasis.probes``, with the point location above)."""
    x = points_mm.T
    cells = _containing_triangles(basis.mesh, points_mm)
    ref = basis.mapping.invF(x[:, :, np.newaxis], tind=cells)
    phis = np.array(
        [basis.elem.gbasis(basis.mapping, ref, k, tind=cells)[0] for k in range(basis.Nbfun)]
    ).flatten()
    comp = int(np.prod(basis._base_tensor_order))
    rows = np.tile(np.arange(comp * x.shape[1], dtype=np.int64), basis.Nbfun)
    cols = basis.element_dofs[:, np.tile(cells, comp)].flatten()
    return sp.coo_matrix((phis, (rows, cols)), shape=(comp * x.shape[1], basis.N)).tocsr()


def remove_plane(points_mm: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``values`` (n,) or (n, k) minus their least-squares plane a + b x + c y over ``points_mm`` (n, 2):
    the rigid motion a resting fit takes out."""
    a = np.column_stack([np.ones(len(points_mm)), points_mm[:, 0], points_mm[:, 1]])
    coef, *_ = np.linalg.lstsq(a, values, rcond=None)
    return values - a @ coef
