"""Design surfaces of curved hull plates and the forming-error fields that make a formed plate.

Conventions (shared by ``synth``, ``segment``, ``boundary``, ``register``, ``templates``):

* **Design plate frame.** x runs along the plate's length, y along its width, z up. The origin is the
  centre of the design's XY footprint, which is the rectangle ``[-L/2, L/2] x [-W/2, W/2]``
  (``L = length_mm >= W = width_mm``). ``length_mm`` and ``width_mm`` are therefore footprint
  (projected) sizes, not arc lengths. The design mesh is the plate's *top* (scanned) surface
  ``z = height(x, y)``; the bottom is ``thickness_mm`` below it along z and the thickness faces are
  the vertical planes over the footprint's edges.
* **Heights.** Every shape has ``height(0, 0) = 0``. The sail is a dish (synclastic, both curvatures
  positive, edges higher than the centre), the saddle is anticlastic, the twisted plate is the
  hyperbolic paraboloid ``z = k x y``, the cylinder bends about the y axis.
* **Corners.** ``design_corners`` returns (4, 3) mm ordered counter-clockwise seen from +z, starting
  at the reference corner ``(-L/2, -W/2)``: c0 (-,-), c1 (+,-), c2 (+,+), c3 (-,+). Edge k runs from
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

from analysis.mesh import TriMesh, load_mesh

__all__ = [
    "EdgeSpringback",
    "FormingError",
    "GaussianBump",
    "PlateError",
    "PlateKind",
    "PlateSpec",
    "canonical_corner_order",
    "default_forming_error",
    "design_corners",
    "design_height_mm",
    "design_mesh",
    "formed_corners",
    "formed_height_mm",
    "forming_dz_mm",
    "load_design",
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
    """

    kind: PlateKind = "sail"
    length_mm: float = 1200.0
    width_mm: float = 800.0
    thickness_mm: float = 15.0
    radius_x_mm: float = 4000.0
    radius_y_mm: float = 3000.0
    twist_per_mm: float = 4.0e-5

    def __post_init__(self) -> None:
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


@dataclass(frozen=True)
class FormingError:
    """A forming-error field: ``dz(x, y)`` added to the design height (design frame, mm).

    bumps: Gaussian dents and bumps.
    springback: optional edge spring-back.
    bend_fraction: global bend error, the fraction by which the design's height relative to its
        centre is over-bent (> 0) or under-bent (< 0): dz = bend_fraction * height(x, y).
    """

    bumps: tuple[GaussianBump, ...] = ()
    springback: EdgeSpringback | None = None
    bend_fraction: float = 0.0

    def to_dict(self) -> dict:
        """Plain JSON-ready dict (the truth file's ``forming_error``)."""
        return {
            "bumps": [asdict(b) for b in self.bumps],
            "springback": asdict(self.springback) if self.springback else None,
            "bend_fraction": self.bend_fraction,
        }

    @classmethod
    def from_dict(cls, d: dict) -> FormingError:
        """Inverse of :meth:`to_dict`."""
        sb = d.get("springback")
        return cls(
            bumps=tuple(GaussianBump(**b) for b in d.get("bumps", [])),
            springback=EdgeSpringback(**sb) if sb else None,
            bend_fraction=float(d.get("bend_fraction", 0.0)),
        )

    @property
    def is_zero(self) -> bool:
        """True when the field is identically zero."""
        return (
            all(b.amplitude_mm == 0 for b in self.bumps)
            and (self.springback is None or self.springback.amplitude_mm == 0)
            and self.bend_fraction == 0
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
        hl, hw = spec.length_mm / 2, spec.width_mm / 2
        # Distances to the four edges; outside the footprint they go negative and the field keeps
        # growing smoothly, which the ray caster needs for its Newton steps near the edges.
        e_xp, e_xm = np.exp(np.minimum(-(hl - x) / s, 30.0)), np.exp(np.minimum(-(hl + x) / s, 30.0))
        e_yp, e_ym = np.exp(np.minimum(-(hw - y) / s, 30.0)), np.exp(np.minimum(-(hw + y) / s, 30.0))
        dz += a * (e_xp + e_xm + e_yp + e_ym)
        if with_gradient:
            gx += a * (e_xp - e_xm) / s
            gy += a * (e_yp - e_ym) / s
    if error.bend_fraction != 0:
        dz += error.bend_fraction * design_height_mm(spec, x, y)
        if with_gradient:
            hx, hy = _design_gradient(spec, x, y)
            gx += error.bend_fraction * hx
            gy += error.bend_fraction * hy
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


def design_mesh(spec: PlateSpec, *, pitch_mm: float = 5.0, error: FormingError | None = None) -> TriMesh:
    """The design top surface as a regular triangle mesh in the design frame (mm).

    pitch_mm: grid spacing; the grid always includes the footprint's edges exactly.
    error: when given, the formed surface instead of the design.
    """
    if not pitch_mm > 0:
        raise PlateError(f"pitch_mm: must be positive, got {pitch_mm!r}")
    nx = max(2, int(np.ceil(spec.length_mm / pitch_mm)) + 1)
    ny = max(2, int(np.ceil(spec.width_mm / pitch_mm)) + 1)
    xs = np.linspace(-spec.length_mm / 2, spec.length_mm / 2, nx)
    ys = np.linspace(-spec.width_mm / 2, spec.width_mm / 2, ny)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    Z = formed_height_mm(spec, error, X, Y) if error is not None else design_height_mm(spec, X, Y)
    vertices = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
    idx = np.arange(nx * ny).reshape(nx, ny)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    # (a, b, c) and (a, c, d): counter-clockwise seen from +z, so the normals point up.
    triangles = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    return TriMesh(vertices, triangles)


def design_corners(spec: PlateSpec) -> np.ndarray:
    """(4, 3) float64 mm: the design's top corners, counter-clockwise from +z, from (-L/2, -W/2)."""
    hl, hw = spec.length_mm / 2, spec.width_mm / 2
    xy = np.array([[-hl, -hw], [hl, -hw], [hl, hw], [-hl, hw]])
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
    """Load a design top-surface mesh (PLY, STL or OBJ, mm); see :func:`analysis.mesh.load_mesh`."""
    return load_mesh(path)
