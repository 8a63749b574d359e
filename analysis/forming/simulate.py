"""Simulated heating: a heating plan applied to a formed plate's mesh with a forming model that is
**not** the planner's, so that a loop of scan -> plan -> heat is not judged by its own model.

What differs from the planner (:mod:`analysis.forming.planner` on :class:`PlateModel`):

- the discretisation: another element size (``ELEMENT_RATIO`` of the planner's, so the nodes never
  coincide) and the mesh's diagonals the other way (the model is built on the plate mirrored across
  its length, y -> W - y, the lines mirrored onto it and the answer mirrored back);
- the coefficients: the bend (across and along) and the shrinkage (across and along) each scaled by
  a factor drawn uniformly in ``1 +- coefficient_spread`` (default 25 %), one per plan: a model
  error the next round has to see and correct;
- the line positions: each end of each line moved by up to ``position_spread_mm`` (default 5 mm) in
  x and y, as a crew marks and follows chalk lines, kept inside the plate.

The draw is seeded and recorded (:class:`HeatDraw`) in the output's sidecar JSON.

Frames: the plan's positions, and the points :func:`heat_points` moves, are in the plate frame of
report.json's lines (mm from the reference corner, x along edge 0 -> 1, y along 0 -> 3, z up); a
mesh is framed and moved by :mod:`analysis.heat_mesh` (``analysis.forming`` imports nothing else of
analysis). The model is a flat plate (as the planner's): the formed plate's curvature is not in it.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from analysis.forming.coefficients import InherentDeformation, inherent_deformation
from analysis.forming.plan_file import HeatingPlanFile
from analysis.forming.plate_model import HeatingLine, PlateModel

__all__ = [
    "COEFFICIENT_SPREAD",
    "ELEMENT_RATIO",
    "POSITION_SPREAD_MM",
    "SIZE_TOLERANCE_MM",
    "HeatDraw",
    "HeatError",
    "SimulatedRound",
    "draw_perturbation",
    "heat_points",
]

#: coefficients off by up to this fraction
COEFFICIENT_SPREAD = 0.25
#: line ends off by up to this (mm, in x and in y)
POSITION_SPREAD_MM = 5.0
#: the simulator's element size over the planner's
ELEMENT_RATIO = 0.7
#: the mesh's plate and the plan's may differ by this much in length or width (mm)
SIZE_TOLERANCE_MM = 10.0


class HeatError(ValueError):
    """A plan that cannot be applied to this mesh (no lines, another plate, a mesh without corners)."""


@dataclass(frozen=True)
class SimulatedRound:
    """The points' displacement (n, 3; mm, plate frame), the draw, and the simulator's element size."""

    displacement_mm: np.ndarray
    draw: HeatDraw
    element_mm: float

    def sidecar(self) -> dict:
        """What an output's sidecar JSON records of the round: the model and the draw."""
        return {
            "model": "inherent strain, Kirchhoff plate (Morley) and membrane, scikit-fem, flat plate; "
            f"mesh mirrored across the length, element size {ELEMENT_RATIO:g} x the planner's "
            "(simulated heating, analysis/forming/simulate.py)",
            "element_mm": round(self.element_mm, 3),
            "max_deflection_mm": round(float(np.abs(self.displacement_mm[:, 2]).max()), 4),
            "draw": self.draw.to_dict(),
        }


@dataclass(frozen=True)
class HeatDraw:
    """The perturbation of one simulated round: the seed, the factors on the bend and on the
    shrinkage, and each line's ends as heated (plate frame, mm)."""

    seed: int
    coefficient_spread: float
    position_spread_mm: float
    bend_factor: float
    shrink_factor: float
    lines: dict[str, tuple[tuple[float, float], tuple[float, float]]]

    def to_dict(self) -> dict:
        d = asdict(self)
        d["lines"] = {
            k: {"start_plate_mm": list(a), "end_plate_mm": list(b)} for k, (a, b) in self.lines.items()
        }
        return d


def draw_perturbation(
    plan: HeatingPlanFile,
    length_mm: float,
    width_mm: float,
    seed: int,
    *,
    coefficient_spread: float = COEFFICIENT_SPREAD,
    position_spread_mm: float = POSITION_SPREAD_MM,
) -> HeatDraw:
    """The seeded draw: factors in ``1 +- coefficient_spread``, each end moved by up to
    ``position_spread_mm`` in x and y (clipped to the plate)."""
    if not 0.0 <= coefficient_spread < 1.0 or position_spread_mm < 0:
        raise HeatError(
            f"spreads must be 0 <= coefficients < 1 and positions >= 0, got {coefficient_spread}, {position_spread_mm}"
        )
    rng = np.random.default_rng(seed)
    bend, shrink = 1.0 + coefficient_spread * rng.uniform(-1.0, 1.0, 2)
    hi = np.array([length_mm, width_mm])
    lines = {}
    for line in plan.lines:
        ends = np.array([line.start_plate_mm, line.end_plate_mm], float)
        ends = np.clip(ends + rng.uniform(-position_spread_mm, position_spread_mm, (2, 2)), 0.0, hi)
        lines[line.id] = (tuple(float(v) for v in ends[0]), tuple(float(v) for v in ends[1]))
    return HeatDraw(seed, coefficient_spread, position_spread_mm, float(bend), float(shrink), lines)


def _scaled(d: InherentDeformation, bend: float, shrink: float) -> InherentDeformation:
    return InherentDeformation(
        heat_input_j_per_mm=d.heat_input_j_per_mm,
        thickness_mm=d.thickness_mm,
        zone_radius_mm=d.zone_radius_mm,
        shrink_across_mm=d.shrink_across_mm * shrink,
        shrink_along_mm=d.shrink_along_mm * shrink,
        bend_across_rad=d.bend_across_rad * bend,
        bend_along_rad=d.bend_along_rad * bend,
    )


def heat_points(
    plan: HeatingPlanFile,
    points_plate_mm: np.ndarray,
    plate_size_mm: tuple[float, float],
    seed: int = 0,
    *,
    coefficient_spread: float = COEFFICIENT_SPREAD,
    position_spread_mm: float = POSITION_SPREAD_MM,
) -> SimulatedRound:
    """How the plate's points ``points_plate_mm`` (n, 2 or 3; plate frame) move (n, 3; mm) when the
    plan's lines are heated, by the mismatched model; ``plate_size_mm`` the plate's length and width
    as measured on the plate being heated.

    HeatError when the plan has no lines or was made for another plate size (beyond
    ``SIZE_TOLERANCE_MM``).
    """
    if plan.status != "plan" or plan.model is None:
        raise HeatError(f"the plan holds no plan: {plan.reason or 'status ' + plan.status}")
    if not plan.lines:
        why = "; ".join(plan.notes) if plan.notes else "the planner chose none"
        raise HeatError(f"the plan has no heating lines ({why})")
    m = plan.model
    length_mm, width_mm = plate_size_mm
    if abs(length_mm - m.length_mm) > SIZE_TOLERANCE_MM or abs(width_mm - m.width_mm) > SIZE_TOLERANCE_MM:
        raise HeatError(
            f"the plan is for a {m.length_mm:g} x {m.width_mm:g} mm plate, the mesh's is "
            f"{length_mm:.1f} x {width_mm:.1f} mm (more than {SIZE_TOLERANCE_MM:g} mm apart)"
        )
    draw = draw_perturbation(
        plan, m.length_mm, m.width_mm, seed,
        coefficient_spread=coefficient_spread, position_spread_mm=position_spread_mm,
    )  # fmt: skip
    element_mm = ELEMENT_RATIO * m.element_mm
    model = PlateModel.build(
        m.length_mm, m.width_mm, m.thickness_mm, m.material_properties, element_mm=element_mm
    )

    def mirror(p: np.ndarray) -> np.ndarray:  # y -> W - y: the model's mesh diagonals the other way
        return np.column_stack([p[:, 0], m.width_mm - p[:, 1]])

    heated = []
    for line in plan.lines:
        a, b = draw.lines[line.id]
        if math.dist(a, b) <= 0:
            continue
        d = inherent_deformation(line.heat_input_j_mm, m.thickness_mm, m.material_properties, m.process)
        a_m, b_m = mirror(np.array([a, b]))
        heated.append(
            HeatingLine(tuple(a_m), tuple(b_m), line.face, _scaled(d, draw.bend_factor, draw.shrink_factor))
        )
    pts = mirror(np.asarray(points_plate_mm, float)[:, :2])
    w = model.deflection_mm(heated, pts)
    uv = model.in_plane_mm(heated, pts)
    uv[:, 1] *= -1.0  # back from the mirrored plate
    return SimulatedRound(np.column_stack([uv, w]), draw, element_mm)
