"""The coefficients of line heating and the inherent deformation one heating line leaves.

A heating line of heat input ``Q`` (J/mm) on a plate ``h`` mm thick leaves four numbers (Ueda's
inherent deformation, as Vega, Osawa, Rashed & Murakawa define it): the shrinkage across and along
the line, ``delta = int(eps dy dz) / h`` (mm), and the bending across and along,
``theta = int(eps (z - h/2) dy dz) / (h^3 / 12)`` (rad). The inherent strain ``eps`` lives in the
mechanical-melting zone (Jang, Seo & Ko): the half-disc under the torch whose peak temperature
exceeded ``T_m``. docs/forming.md derives the law; ``line_heating.toml`` holds the numbers the yard
edits.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

#: the table shipped with the code; a yard's own copy is passed to ``load_coefficients``
DEFAULT_TABLE = Path(__file__).with_name("line_heating.toml")


class Material(BaseModel):
    """A plate material's properties the law needs (room temperature, handbook values)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    youngs_modulus_mpa: float = Field(gt=0)
    poisson_ratio: float = Field(gt=0, lt=0.5)
    expansion_per_k: float = Field(gt=0)
    volumetric_heat_j_per_mm3_k: float = Field(gt=0)
    yield_strength_mpa: float = Field(gt=0)
    mechanical_melting_rise_k: float = Field(gt=0)


class Process(BaseModel):
    """The torch and the factors that turn the zone's free thermal strain into inherent strain."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    torch_efficiency: float = Field(gt=0, le=1)
    torch_power_w: float = Field(gt=0)
    transverse_strain_factor: float = Field(gt=0, le=2)
    longitudinal_strain_factor: float = Field(ge=0, le=5)
    heat_input_min_j_per_mm: float = Field(gt=0)
    heat_input_max_j_per_mm: float = Field(gt=0)

    @model_validator(mode="after")
    def _range(self) -> Process:
        if self.heat_input_max_j_per_mm <= self.heat_input_min_j_per_mm:
            raise ValueError("heat_input_max_j_per_mm must exceed heat_input_min_j_per_mm")
        return self


class Coefficients(BaseModel):
    """The whole table: materials by name and the process."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    material: dict[str, Material]
    process: Process

    def for_material(self, name: str) -> Material:
        """The named material, or a ``KeyError`` naming the ones the table has."""
        try:
            return self.material[name]
        except KeyError:
            raise KeyError(
                f"material {name!r} not in the table (has: {', '.join(sorted(self.material))})"
            ) from None


def load_coefficients(path: Path | str = DEFAULT_TABLE) -> Coefficients:
    """Read and validate a coefficient table (TOML)."""
    with open(path, "rb") as f:
        return Coefficients.model_validate(tomllib.load(f))


@dataclass(frozen=True)
class InherentDeformation:
    """What one heating line leaves, per unit of its length, in its own axes (across, along).

    ``bend_across_rad`` is the angle the two sides turn toward the heated face; the shrinkages are
    how much the plate shortens across the line and (per unit width of the band's effect) along it.
    """

    heat_input_j_per_mm: float
    thickness_mm: float
    zone_radius_mm: float
    shrink_across_mm: float
    shrink_along_mm: float
    bend_across_rad: float
    bend_along_rad: float


def _zone_moments(radius_mm: float, thickness_mm: float, n: int = 400) -> tuple[float, float]:
    """Area (mm^2) of the half-disc of ``radius_mm`` under the heated face clipped to the thickness,
    and its first moment about the mid-plane (mm^3, positive toward the heated face)."""
    depth = min(radius_mm, thickness_mm)
    z = (np.arange(n) + 0.5) * (depth / n)  # depth below the heated face, midpoint rule
    width = 2.0 * np.sqrt(np.maximum(radius_mm**2 - z**2, 0.0))
    dz = depth / n
    area = float(width.sum() * dz)
    moment = float((width * (thickness_mm / 2.0 - z)).sum() * dz)
    return area, moment


def zone_radius_mm(heat_input_j_per_mm: float, material: Material) -> float:
    """Radius of the mechanical-melting zone: where the peak temperature of an instantaneous line
    source ``Q`` on a half-space, ``2 Q / (pi e rho_c r^2)``, reaches ``T_m``."""
    return math.sqrt(
        2.0
        * heat_input_j_per_mm
        / (math.pi * math.e * material.volumetric_heat_j_per_mm3_k * material.mechanical_melting_rise_k)
    )


def inherent_deformation(
    heat_input_j_per_mm: float, thickness_mm: float, material: Material, process: Process
) -> InherentDeformation:
    """The four inherent deformations of one line of heat input ``Q`` on a plate ``h`` thick."""
    if heat_input_j_per_mm <= 0 or thickness_mm <= 0:
        raise ValueError(f"heat input {heat_input_j_per_mm} J/mm and thickness {thickness_mm} mm must be > 0")
    r = zone_radius_mm(heat_input_j_per_mm, material)
    area, moment = _zone_moments(r, thickness_mm)
    eps_across = (
        process.transverse_strain_factor * material.expansion_per_k * material.mechanical_melting_rise_k
    )
    eps_along = process.longitudinal_strain_factor * material.yield_strength_mpa / material.youngs_modulus_mpa
    h = thickness_mm
    return InherentDeformation(
        heat_input_j_per_mm=heat_input_j_per_mm,
        thickness_mm=h,
        zone_radius_mm=r,
        shrink_across_mm=eps_across * area / h,
        shrink_along_mm=eps_along * area / h,
        bend_across_rad=eps_across * moment * 12.0 / h**3,
        bend_along_rad=eps_along * moment * 12.0 / h**3,
    )


def torch_speed_mm_s(heat_input_j_per_mm: float, process: Process) -> float:
    """The torch speed that gives ``Q``: ``v = efficiency * power / Q``."""
    return process.torch_efficiency * process.torch_power_w / heat_input_j_per_mm


def peak_bend_heat_input_j_per_mm(thickness_mm: float, material: Material, process: Process) -> float:
    """The heat input of the largest angular distortion on this thickness, searched in the process's
    range: beyond it more heat bends less (the whole thickness heats)."""
    q = np.geomspace(process.heat_input_min_j_per_mm, process.heat_input_max_j_per_mm, 200)
    bends = [inherent_deformation(float(x), thickness_mm, material, process).bend_across_rad for x in q]
    return float(q[int(np.argmax(bends))])


def heat_input_for_bend(
    bend_rad: float, thickness_mm: float, material: Material, process: Process
) -> float | None:
    """The least heat input that bends ``bend_rad`` across (the rising branch), or None when no heat
    input in the process's range bends that much."""
    q_lo = process.heat_input_min_j_per_mm
    q_hi = peak_bend_heat_input_j_per_mm(thickness_mm, material, process)

    def bend(q: float) -> float:
        return inherent_deformation(q, thickness_mm, material, process).bend_across_rad

    if bend(q_hi) < bend_rad:
        return None
    if bend(q_lo) >= bend_rad:
        return q_lo
    for _ in range(50):
        mid = 0.5 * (q_lo + q_hi)
        if bend(mid) < bend_rad:
            q_lo = mid
        else:
            q_hi = mid
    return q_hi
