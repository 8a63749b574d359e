"""One face's surface as an exact tensor-product NURBS patch, evaluated with numpy: points and first
derivatives on whole arrays of parameters (:class:`NurbsPatch`), its B-spline basis by Cox-de Boor.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


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
