"""Design surfaces of curved hull plates and the forming-error fields that make a formed plate.

Conventions (shared by ``synth``, ``segment``, ``boundary``, ``register``, ``templates``):

* **Design plate frame.** x runs along the plate's length, y along its width, z up. The origin is the
  centre of the design's XY footprint, by default the rectangle ``[-L/2, L/2] x [-W/2, W/2]``
  (``L = length_mm >= W = width_mm``); a parallelogram, trapezoid or bowed outline
  (``corner_angle_deg``, ``top_length_mm``, ``bow_mm``) has its corners' mean there. ``length_mm``
  and ``width_mm`` are footprint (projected) sizes, not arc lengths. The design mesh is the plate's *top* (scanned) surface
  ``z = height(x, y)``; the bottom is ``thickness_mm`` below it along z and the thickness faces are
  the vertical planes over the footprint's edges.
* **Heights.** Every shape has ``height(0, 0) = 0``. The sail is a dish (synclastic, both curvatures
  positive, edges higher than the centre), the saddle is anticlastic, the twisted plate is the
  hyperbolic paraboloid ``z = k x y``, the cylinder bends about the y axis.
* **Corners.** ``design_corners`` returns (4, 3) mm ordered counter-clockwise seen from +z, starting
  at the reference corner ``(-L/2, -W/2)``: c0 (-,-), c1 (+,-), c2 (+,+), c3 (-,+) (any outline:
  c0 -> c1 is edge 0 along +x, c3 -> c2 the opposite length edge). Edge k runs from
  corner k to corner k+1, so edges 0 and 2 are the long edges and edge 0 runs along +x.
  ``boundary.find_corners`` orders measured corners the same way (corner 0 starts a long edge,
  see :func:`canonical_corner_order`), so design and measured corners correspond up to a half turn
  (an index shift of 2): the plate's near-symmetry that registration resolves by trying both.
* **Forming error.** A formed plate is the design plus a vertical displacement field ``dz(x, y)``
  in the design frame (:class:`FormingError`). The footprint is unchanged, so ground truth for any
  figure along a detection line is ``dz`` sampled on that line.

All lengths are millimetres, all angles degrees unless a name says otherwise.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Literal

import numpy as np

from analysis.design.mesh import TriMesh, load_mesh

__all__ = [
    "EdgeSpringback",
    "FormingError",
    "GaussianBump",
    "HeightGrid",
    "OutlineEdge",
    "PlateError",
    "PlateKind",
    "PlateSpec",
    "canonical_corner_order",
    "default_forming_error",
    "design_corners",
    "design_height_mm",
    "design_mesh",
    "edge_inward_distances",
    "footprint_bounds",
    "footprint_contains",
    "footprint_grid",
    "formed_corners",
    "formed_height_mm",
    "forming_dz_mm",
    "is_rectangle",
    "load_design",
    "outline_corners_xy",
    "outline_edges",
    "plate_spec",
    "surface_gradient",
]

PlateKind = Literal["sail", "saddle", "twisted", "cylinder", "flat"]
PLATE_KINDS: tuple[str, ...] = ("sail", "saddle", "twisted", "cylinder", "flat")


class PlateError(ValueError):
    """A plate or forming-error description that cannot describe a real plate."""


@dataclass(frozen=True)
class PlateSpec:
    """Size and shape of a design plate (mm).

    radius_x_mm: bending radius of sections along x (sail, saddle, cylinder).
    radius_y_mm: bending radius of sections along y (sail, saddle).
    twist_per_mm: k of ``z = k x y`` for the twisted plate (1/mm).
    Outline (default: the rectangle ``length_mm x width_mm``): edge 0 (corner 0 -> 1) runs along +x
    and is ``length_mm`` long, the opposite edge 2 is parallel to it ``width_mm`` away (in plan) and
    ``top_length_mm`` long (default ``length_mm``: a parallelogram; else a trapezoid), the corner
    angle at corner 0 is ``corner_angle_deg`` (60-120). ``bow_mm``: per edge, the sagitta of a
    parabolic bow in plan (positive outward) over the edge's chord. The corners' mean is the origin.
    """

    kind: PlateKind = "sail"
    length_mm: float = 1200.0
    width_mm: float = 800.0
    thickness_mm: float = 15.0
    radius_x_mm: float = 4000.0
    radius_y_mm: float = 3000.0
    twist_per_mm: float = 4.0e-5
    corner_angle_deg: float = 90.0
    top_length_mm: float | None = None
    bow_mm: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        object.__setattr__(self, "bow_mm", tuple(float(b) for b in self.bow_mm))
        if len(self.bow_mm) != 4 or not np.isfinite(self.bow_mm).all():
            raise PlateError(f"bow_mm: four finite edge bows (mm) expected, got {self.bow_mm!r}")
        if not 60.0 <= self.corner_angle_deg <= 120.0:
            raise PlateError(f"corner_angle_deg: {self.corner_angle_deg!r} is outside 60-120 degrees")
        if self.top_length_mm is not None and not (
            np.isfinite(self.top_length_mm) and self.top_length_mm > 0
        ):
            raise PlateError(f"top_length_mm: must be a positive finite number, got {self.top_length_mm!r}")
        if self.kind not in PLATE_KINDS:
            raise PlateError(f"kind: unknown plate kind {self.kind!r} (one of {', '.join(PLATE_KINDS)})")
        for name in ("length_mm", "width_mm", "thickness_mm", "radius_x_mm", "radius_y_mm"):
            value = getattr(self, name)
            if not np.isfinite(value) or value <= 0:
                raise PlateError(f"{name}: must be a positive finite number, got {value!r}")
        if self.width_mm > self.length_mm:
            raise PlateError(
                f"width_mm: {self.width_mm} exceeds length_mm {self.length_mm}; x runs along the length"
            )
        if self.kind == "cylinder" and self.radius_x_mm <= self.length_mm / 2:
            raise PlateError(f"radius_x_mm: {self.radius_x_mm} too small for a {self.length_mm} mm cylinder")
        if not np.isfinite(self.twist_per_mm):
            raise PlateError("twist_per_mm: must be finite")

    def to_dict(self) -> dict:
        """Plain JSON-ready dict."""
        return asdict(self)


def plate_spec(kind: str = "sail", **overrides: float) -> PlateSpec:
    """A :class:`PlateSpec` of ``kind`` with the project's defaults (the paper's 1200 x 800 x 15 sail).

    Shape defaults per kind: sail Rx 4000 / Ry 3000 mm (about 72 mm of depth); saddle Rx 4000 /
    Ry 3000 mm; twisted k = 4e-5 /mm (19 mm corner lift); cylinder Rx 2500 mm.
    """
    base: dict = {"kind": kind}
    if kind == "cylinder":
        base["radius_x_mm"] = 2500.0
    base.update(overrides)
    return PlateSpec(**base)


@dataclass(frozen=True)
class GaussianBump:
    """A Gaussian bump (``amplitude_mm > 0``, up) or dent (``< 0``, down) at (x_mm, y_mm), design frame."""

    x_mm: float
    y_mm: float
    amplitude_mm: float
    sigma_mm: float

    def __post_init__(self) -> None:
        if not self.sigma_mm > 0:
            raise PlateError(f"sigma_mm: must be positive, got {self.sigma_mm!r}")
        for name in ("x_mm", "y_mm", "amplitude_mm"):
            if not np.isfinite(getattr(self, name)):
                raise PlateError(f"{name}: must be finite")


@dataclass(frozen=True)
class EdgeSpringback:
    """Edge spring-back: each edge lifts by ``amplitude_mm`` (negative: drops), decaying inward.

    dz = amplitude * sum over the 4 edges of exp(-distance_to_edge / decay_mm); a corner, close to
    two edges, lifts by about twice the amplitude, as a sprung-back corner does.
    """

    amplitude_mm: float
    decay_mm: float = 80.0

    def __post_init__(self) -> None:
        if not self.decay_mm > 0:
            raise PlateError(f"decay_mm: must be positive, got {self.decay_mm!r}")
        if not np.isfinite(self.amplitude_mm):
            raise PlateError("amplitude_mm: must be finite")


@dataclass(frozen=True, eq=False)
class HeightGrid:
    """A sampled height field ``dz`` (mm) on a regular grid of the design frame: ``values_mm[i, j]``
    at ``(x0_mm + i * step_mm, y0_mm + j * step_mm)``, interpolated by a bicubic spline (a twist, or
    what simulated heating rounds left, benchmarks/forming_loop.py). Outside the grid the spline's
    end pieces go on (keep the grid a little larger than the footprint). Compared by identity."""

    x0_mm: float
    y0_mm: float
    step_mm: float
    values_mm: np.ndarray

    def __post_init__(self) -> None:
        v = np.asarray(self.values_mm, dtype=np.float64)
        if v.ndim != 2 or min(v.shape) < 4 or not np.isfinite(v).all():
            raise PlateError(f"values_mm: a finite (nx >= 4, ny >= 4) grid expected, got shape {v.shape}")
        if not (np.isfinite(self.step_mm) and self.step_mm > 0):
            raise PlateError(f"step_mm: must be positive, got {self.step_mm!r}")
        object.__setattr__(self, "values_mm", v)
        from scipy.interpolate import RectBivariateSpline

        xs = self.x0_mm + self.step_mm * np.arange(v.shape[0])
        ys = self.y0_mm + self.step_mm * np.arange(v.shape[1])
        object.__setattr__(self, "_spline", RectBivariateSpline(xs, ys, v, kx=3, ky=3))

    @classmethod
    def sample(
        cls, fn, x_range_mm: tuple[float, float], y_range_mm: tuple[float, float], step_mm: float
    ) -> HeightGrid:
        """``fn(x, y)`` (mm, design frame, arrays) sampled over the ranges."""
        nx = max(4, int(np.ceil((x_range_mm[1] - x_range_mm[0]) / step_mm)) + 1)
        ny = max(4, int(np.ceil((y_range_mm[1] - y_range_mm[0]) / step_mm)) + 1)
        X, Y = np.meshgrid(
            x_range_mm[0] + step_mm * np.arange(nx), y_range_mm[0] + step_mm * np.arange(ny), indexing="ij"
        )
        return cls(x_range_mm[0], y_range_mm[0], step_mm, np.asarray(fn(X, Y), dtype=np.float64))

    def points_mm(self) -> np.ndarray:
        """The grid's nodes (nx * ny, 2), in ``values_mm.ravel()`` order."""
        nx, ny = self.values_mm.shape
        X, Y = np.meshgrid(
            self.x0_mm + self.step_mm * np.arange(nx),
            self.y0_mm + self.step_mm * np.arange(ny),
            indexing="ij",
        )
        return np.column_stack([X.ravel(), Y.ravel()])

    def plus(self, dz_mm: np.ndarray) -> HeightGrid:
        """The same grid with ``dz_mm`` (values at :meth:`points_mm`) added."""
        return HeightGrid(
            self.x0_mm, self.y0_mm, self.step_mm, self.values_mm + np.reshape(dz_mm, self.values_mm.shape)
        )

    def at(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(dz, d dz/dx, d dz/dy)`` at (x, y) (any matching shapes)."""
        sp = self._spline  # type: ignore[attr-defined]
        xf, yf = x.ravel(), y.ravel()
        return tuple(sp.ev(xf, yf, dx=dx, dy=dy).reshape(x.shape) for dx, dy in ((0, 0), (1, 0), (0, 1)))  # type: ignore[return-value]

    def to_dict(self) -> dict:
        return {
            "x0_mm": self.x0_mm,
            "y0_mm": self.y0_mm,
            "step_mm": self.step_mm,
            "values_mm": self.values_mm.tolist(),
        }


@dataclass(frozen=True)
class FormingError:
    """A forming-error field: ``dz(x, y)`` added to the design height (design frame, mm).

    bumps: Gaussian dents and bumps.
    springback: optional edge spring-back.
    bend_fraction: global bend error, the fraction by which the design's height relative to its
        centre is over-bent (> 0) or under-bent (< 0): dz = bend_fraction * height(x, y).
    grid: optional sampled field added on top (:class:`HeightGrid`: a twist, a heated round).
    """

    bumps: tuple[GaussianBump, ...] = ()
    springback: EdgeSpringback | None = None
    bend_fraction: float = 0.0
    grid: HeightGrid | None = None

    def to_dict(self) -> dict:
        """Plain JSON-ready dict (the truth file's ``forming_error``)."""
        return {
            "bumps": [asdict(b) for b in self.bumps],
            "springback": asdict(self.springback) if self.springback else None,
            "bend_fraction": self.bend_fraction,
            "grid": self.grid.to_dict() if self.grid is not None else None,
        }

    @classmethod
    def from_dict(cls, d: dict) -> FormingError:
        """Inverse of :meth:`to_dict`."""
        sb = d.get("springback")
        return cls(
            bumps=tuple(GaussianBump(**b) for b in d.get("bumps", [])),
            springback=EdgeSpringback(**sb) if sb else None,
            bend_fraction=float(d.get("bend_fraction", 0.0)),
            grid=HeightGrid(**d["grid"]) if d.get("grid") else None,
        )

    @property
    def is_zero(self) -> bool:
        """True when the field is identically zero."""
        return (
            all(b.amplitude_mm == 0 for b in self.bumps)
            and (self.springback is None or self.springback.amplitude_mm == 0)
            and self.bend_fraction == 0
            and (self.grid is None or not np.any(self.grid.values_mm))
        )


NO_FORMING_ERROR = FormingError()


def default_forming_error(spec: PlateSpec) -> FormingError:
    """The forming error ``synth`` applies without ``--deform``: one dent, one bump, mild spring-back.

    Sized relative to the plate so it applies to any size: a 2.5 mm dent at (+L/4, -W/8), a 1.5 mm
    bump at (-L/5, +W/5), 1 mm edge spring-back decaying over 60 mm.
    """
    L, W = spec.length_mm, spec.width_mm
    return FormingError(
        bumps=(
            GaussianBump(L / 4, -W / 8, -2.5, min(L, W) / 12),
            GaussianBump(-L / 5, W / 5, 1.5, min(L, W) / 10),
        ),
        springback=EdgeSpringback(1.0, 60.0),
    )


def design_height_mm(spec: PlateSpec, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
    """Design top-surface height z (mm) at design-frame (x, y) (mm, any broadcastable shapes)."""
    x = np.asarray(x_mm, dtype=np.float64)
    y = np.asarray(y_mm, dtype=np.float64)
    if spec.kind == "sail":
        return x * x / (2 * spec.radius_x_mm) + y * y / (2 * spec.radius_y_mm)
    if spec.kind == "saddle":
        return x * x / (2 * spec.radius_x_mm) - y * y / (2 * spec.radius_y_mm)
    if spec.kind == "twisted":
        return spec.twist_per_mm * x * y
    if spec.kind == "cylinder":
        r = spec.radius_x_mm
        return r - np.sqrt(np.maximum(r * r - x * x, 0.0))
    return np.zeros(np.broadcast_shapes(x.shape, y.shape))


def _design_gradient(spec: PlateSpec, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    if spec.kind == "sail":
        return x / spec.radius_x_mm, y / spec.radius_y_mm
    if spec.kind == "saddle":
        return x / spec.radius_x_mm, -y / spec.radius_y_mm
    if spec.kind == "twisted":
        return spec.twist_per_mm * y, spec.twist_per_mm * x
    if spec.kind == "cylinder":
        r = spec.radius_x_mm
        return x / np.sqrt(np.maximum(r * r - x * x, 1e-9)), np.zeros_like(y)
    return np.zeros_like(x), np.zeros_like(y)


def forming_dz_mm(
    spec: PlateSpec, error: FormingError, x_mm: np.ndarray, y_mm: np.ndarray, *, with_gradient: bool = False
) -> np.ndarray | tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertical forming displacement dz (mm) at design-frame (x, y) (mm).

    With ``with_gradient`` returns ``(dz, d dz/dx, d dz/dy)``.
    """
    x, y = np.broadcast_arrays(np.asarray(x_mm, dtype=np.float64), np.asarray(y_mm, dtype=np.float64))
    dz = np.zeros(x.shape)
    gx = np.zeros(x.shape)
    gy = np.zeros(x.shape)
    for b in error.bumps:
        dx, dy = x - b.x_mm, y - b.y_mm
        g = b.amplitude_mm * np.exp(-(dx * dx + dy * dy) / (2 * b.sigma_mm**2))
        dz += g
        if with_gradient:
            gx -= g * dx / b.sigma_mm**2
            gy -= g * dy / b.sigma_mm**2
    if error.springback is not None and error.springback.amplitude_mm != 0:
        a, s = error.springback.amplitude_mm, error.springback.decay_mm
        # Distances to the four edges; outside the footprint they go negative and the field keeps
        # growing smoothly, which the ray caster needs for its Newton steps near the edges.
        for dist, ddx, ddy in edge_inward_distances(spec, x, y):
            ex = np.exp(np.minimum(-dist / s, 30.0))
            dz += a * ex
            if with_gradient:
                gx -= a * ex * ddx / s
                gy -= a * ex * ddy / s
    if error.bend_fraction != 0:
        dz += error.bend_fraction * design_height_mm(spec, x, y)
        if with_gradient:
            hx, hy = _design_gradient(spec, x, y)
            gx += error.bend_fraction * hx
            gy += error.bend_fraction * hy
    if error.grid is not None:
        gz, ggx, ggy = error.grid.at(x, y)
        dz += gz
        if with_gradient:
            gx += ggx
            gy += ggy
    if with_gradient:
        return dz, gx, gy
    return dz


def formed_height_mm(spec: PlateSpec, error: FormingError, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
    """Formed top-surface height (mm): design height plus the forming error, design frame."""
    return design_height_mm(spec, x_mm, y_mm) + forming_dz_mm(spec, error, x_mm, y_mm)


def surface_gradient(
    spec: PlateSpec, error: FormingError, x_mm: np.ndarray, y_mm: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Formed height and its gradient at design-frame (x, y): ``(z_mm, dz/dx, dz/dy)``."""
    x = np.asarray(x_mm, dtype=np.float64)
    y = np.asarray(y_mm, dtype=np.float64)
    dz, gx, gy = forming_dz_mm(spec, error, x, y, with_gradient=True)
    hx, hy = _design_gradient(spec, x, y)
    return design_height_mm(spec, x, y) + dz, hx + gx, hy + gy


# ------------------------------------------------------------------------------------- outline


def is_rectangle(spec: PlateSpec) -> bool:
    """True for the plain ``length_mm x width_mm`` rectangle (the default outline)."""
    return (
        spec.corner_angle_deg == 90.0
        and spec.top_length_mm in (None, spec.length_mm)
        and not any(spec.bow_mm)
    )


def outline_corners_xy(spec: PlateSpec) -> np.ndarray:
    """(4, 2) the outline's corners in plan (design frame, mm), counter-clockwise from corner 0."""
    L, W = spec.length_mm, spec.width_mm
    top = spec.length_mm if spec.top_length_mm is None else spec.top_length_mm
    if is_rectangle(spec):
        return np.array([[-L / 2, -W / 2], [L / 2, -W / 2], [L / 2, W / 2], [-L / 2, W / 2]])
    shear = W / np.tan(np.radians(spec.corner_angle_deg))
    x0 = -(L + 2 * shear + top) / 4  # the corners' mean on the origin
    return np.array([[x0, -W / 2], [x0 + L, -W / 2], [x0 + shear + top, W / 2], [x0 + shear, W / 2]])


@dataclass(frozen=True)
class OutlineEdge:
    """Edge k of the outline in plan: ``p(s) = a + s e + bow(s) n`` for ``s`` in [0, chord_mm].

    a: (2,) corner k; e: (2,) unit chord direction to corner k + 1; n: (2,) unit outward normal of
    the chord; bow(s) = k s (chord - s) with k = 4 sagitta / chord^2 (parabolic bow, 0 at the corners).
    """

    a: np.ndarray
    e: np.ndarray
    n: np.ndarray
    chord_mm: float
    k_per_mm: float

    def bow(self, s: np.ndarray) -> np.ndarray:
        """Outward offset (mm) of the edge from its chord at chord coordinate s (0 beyond the chord)."""
        sc = np.clip(s, 0.0, self.chord_mm)
        return self.k_per_mm * sc * (self.chord_mm - sc)

    def slope(self, s: np.ndarray) -> np.ndarray:
        """d bow / ds (0 beyond the chord)."""
        inside = (s >= 0.0) & (s <= self.chord_mm)
        return np.where(inside, self.k_per_mm * (self.chord_mm - 2.0 * s), 0.0)

    def point(self, s: np.ndarray) -> np.ndarray:
        """(m, 2) edge points at chord coordinates s (straight continuation beyond the chord)."""
        s = np.atleast_1d(np.asarray(s, dtype=np.float64))
        return self.a + np.outer(s, self.e) + np.outer(self.bow(s), self.n)

    def outward(self, s: np.ndarray) -> np.ndarray:
        """(m, 2) unit outward normals of the edge curve at s."""
        s = np.atleast_1d(np.asarray(s, dtype=np.float64))
        v = self.n[None, :] - self.slope(s)[:, None] * self.e[None, :]
        return v / np.linalg.norm(v, axis=1, keepdims=True)


def outline_edges(spec: PlateSpec) -> tuple[OutlineEdge, ...]:
    """The outline's four edges, edge k from corner k to corner k + 1."""
    c = outline_corners_xy(spec)
    out = []
    for k in range(4):
        a, b = c[k], c[(k + 1) % 4]
        chord = float(np.linalg.norm(b - a))
        e = (b - a) / chord
        out.append(OutlineEdge(a, e, np.array([e[1], -e[0]]), chord, 4.0 * spec.bow_mm[k] / chord**2))
    return tuple(out)


def edge_inward_distances(
    spec: PlateSpec, x_mm: np.ndarray, y_mm: np.ndarray
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per edge: (inward distance (mm) from the edge curve, measured across its chord, and its x and
    y derivatives) at design-frame (x, y); positive inside. A point is on the plate when all four
    are >= 0."""
    x = np.asarray(x_mm, dtype=np.float64)
    y = np.asarray(y_mm, dtype=np.float64)
    out = []
    for ed in outline_edges(spec):
        s = (x - ed.a[0]) * ed.e[0] + (y - ed.a[1]) * ed.e[1]
        c = (x - ed.a[0]) * ed.n[0] + (y - ed.a[1]) * ed.n[1]
        sl = ed.slope(s)
        out.append((ed.bow(s) - c, sl * ed.e[0] - ed.n[0], sl * ed.e[1] - ed.n[1]))
    return out


def footprint_contains(spec: PlateSpec, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
    """True where design-frame (x, y) lies on the plate's footprint (edges included)."""
    if is_rectangle(spec):
        return (np.abs(x_mm) <= spec.length_mm / 2) & (np.abs(y_mm) <= spec.width_mm / 2)
    inside = np.ones(np.broadcast_shapes(np.shape(x_mm), np.shape(y_mm)), dtype=bool)
    for d, _, _ in edge_inward_distances(spec, x_mm, y_mm):
        inside &= d >= -1e-9
    return inside


def footprint_bounds(spec: PlateSpec) -> tuple[float, float, float, float]:
    """(x_min, x_max, y_min, y_max) of the footprint, bowed edges included (mm)."""
    pts = np.concatenate([ed.point(np.linspace(0.0, ed.chord_mm, 65)) for ed in outline_edges(spec)])
    return float(pts[:, 0].min()), float(pts[:, 0].max()), float(pts[:, 1].min()), float(pts[:, 1].max())


def footprint_grid(spec: PlateSpec, nu: int, nv: int) -> tuple[np.ndarray, np.ndarray]:
    """(X, Y) (nu, nv) a grid over the footprint reaching its edges exactly (design frame, mm).

    A rectangle: the regular grid. Any other outline: the Coons patch of its four edge curves
    (u along edges 0 and 2, v along edges 3 and 1), so the grid's border lies on the outline.
    """
    u = np.linspace(0.0, 1.0, nu)
    v = np.linspace(0.0, 1.0, nv)
    if is_rectangle(spec):
        X, Y = np.meshgrid(spec.length_mm * (u - 0.5), spec.width_mm * (v - 0.5), indexing="ij")
        return X, Y
    e0, e1, e2, e3 = outline_edges(spec)
    c = outline_corners_xy(spec)
    bottom = e0.point(u * e0.chord_mm)
    top = e2.point((1.0 - u) * e2.chord_mm)
    left = e3.point((1.0 - v) * e3.chord_mm)
    right = e1.point(v * e1.chord_mm)
    U, V = u[:, None, None], v[None, :, None]
    P = (
        (1 - V) * bottom[:, None] + V * top[:, None] + (1 - U) * left[None] + U * right[None]
        - ((1 - U) * (1 - V) * c[0] + U * (1 - V) * c[1] + U * V * c[2] + (1 - U) * V * c[3])
    )  # fmt: skip
    return P[..., 0], P[..., 1]


def design_mesh(spec: PlateSpec, *, pitch_mm: float = 5.0, error: FormingError | None = None) -> TriMesh:
    """The design top surface as a regular triangle mesh in the design frame (mm).

    pitch_mm: grid spacing; the grid always includes the footprint's edges exactly.
    error: when given, the formed surface instead of the design.
    """
    if not pitch_mm > 0:
        raise PlateError(f"pitch_mm: must be positive, got {pitch_mm!r}")
    edges = outline_edges(spec)
    nx = max(2, int(np.ceil(max(edges[0].chord_mm, edges[2].chord_mm) / pitch_mm)) + 1)
    ny = max(2, int(np.ceil(max(edges[1].chord_mm, edges[3].chord_mm) / pitch_mm)) + 1)
    X, Y = footprint_grid(spec, nx, ny)
    Z = formed_height_mm(spec, error, X, Y) if error is not None else design_height_mm(spec, X, Y)
    vertices = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
    idx = np.arange(nx * ny).reshape(nx, ny)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    # (a, b, c) and (a, c, d): counter-clockwise seen from +z, so the normals point up.
    triangles = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    return TriMesh(vertices, triangles)


def design_corners(spec: PlateSpec) -> np.ndarray:
    """(4, 3) float64 mm: the design's top corners, counter-clockwise from +z, from the reference
    corner (``(-L/2, -W/2)`` for a rectangle)."""
    xy = outline_corners_xy(spec)
    return np.column_stack([xy, design_height_mm(spec, xy[:, 0], xy[:, 1])])


def formed_corners(spec: PlateSpec, error: FormingError) -> np.ndarray:
    """(4, 3) float64 mm: the formed plate's top corners, same order as :func:`design_corners`."""
    c = design_corners(spec)
    c[:, 2] = formed_height_mm(spec, error, c[:, 0], c[:, 1])
    return c


def canonical_corner_order(corners_mm: np.ndarray) -> np.ndarray:
    """Reorder four plate corners to the project's convention (returns (4, 3), a copy).

    Counter-clockwise seen from +z; corner 0 starts a long edge (edge 0 = corner 0 -> corner 1, the
    longer of the two edge pairs by mean length), and of the two long edges the one whose XY
    direction is closest to the frame's +x axis (direction angle in (-90 deg, 90 deg]). For a design
    in its own frame this reproduces :func:`design_corners`; for a measured plate it fixes the
    order up to the plate's half-turn symmetry.

    corners_mm: (4, 3) corners in cyclic order (either sense).
    """
    c = np.asarray(corners_mm, dtype=np.float64)
    if c.shape != (4, 3):
        raise PlateError(f"corners_mm must be (4, 3), got {c.shape}")
    xy = c[:, :2]
    signed_area = 0.5 * np.sum(xy[:, 0] * np.roll(xy[:, 1], -1) - np.roll(xy[:, 0], -1) * xy[:, 1])
    if signed_area < 0:
        c = c[::-1]
    lengths = np.linalg.norm(np.roll(c, -1, axis=0) - c, axis=1)
    start = 0 if lengths[0] + lengths[2] >= lengths[1] + lengths[3] else 1
    d = c[(start + 1) % 4, :2] - c[start, :2]
    angle = np.arctan2(d[1], d[0])
    if not (-np.pi / 2 < angle <= np.pi / 2 + 1e-12):
        start += 2
    return np.roll(c, -start, axis=0).copy()


def load_design(path) -> TriMesh:
    """Load a design top-surface mesh (PLY, STL or OBJ, mm); see :func:`analysis.design.mesh.load_mesh`."""
    return load_mesh(path)
