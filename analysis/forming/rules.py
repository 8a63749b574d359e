"""The crew's rules for a round of line heating, and the settings a plan is made with.

Apart from the planner so that ``cellctl.config`` (the ``[forming]`` section of cell.toml) and the
contract of ``heating-plan.json`` read them without importing the FE model (scikit-fem).
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from analysis.forming.coefficients import DEFAULT_TABLE, Coefficients, load_coefficients

__all__ = ["HeatingRules", "PlanSettings"]


class HeatingRules(BaseModel):
    """The crew's rules for one round: where lines may go, how many, on which faces."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    min_spacing_mm: float = Field(default=80.0, gt=0, description="least distance between two parallel lines")
    edge_margin_mm: float = Field(default=30.0, ge=0, description="no line nearer an edge than this")
    max_lines_per_round: int = Field(default=12, ge=1, le=100)
    candidate_step_mm: float = Field(default=40.0, gt=0, description="grid of candidate positions")
    allow_bottom_face: bool = Field(default=True, description="the crew may turn the plate over")
    target_fraction: float = Field(
        default=0.3, gt=0, lt=1, description="a round is enough when the predicted RMS falls below this share"
    )
    material: str = "mild_steel"


class PlanSettings(HeatingRules):
    """The rules and what else a plan from an analysed job needs (cell.toml ``[forming]``).

    thickness_mm: the plate's thickness when the report does not carry one (a moulded-down design
    does). element_mm: the FE model's element ("auto": about 3000 squares, 20 mm at the least).
    heat_input_min_j_per_mm / heat_input_max_j_per_mm: the crew's heat-input range (None: the
    coefficient table's); it must lie inside the table's. coefficients_file: the yard's own table
    (None: the one shipped, ``analysis/forming/line_heating.toml``).
    """

    thickness_mm: float = Field(default=15.0, gt=0, le=200)
    element_mm: Annotated[float, Field(ge=5, le=500)] | Literal["auto"] = "auto"
    heat_input_min_j_per_mm: Annotated[float, Field(gt=0)] | None = None
    heat_input_max_j_per_mm: Annotated[float, Field(gt=0)] | None = None
    coefficients_file: Path | None = None

    @model_validator(mode="after")
    def _range_and_material(self) -> PlanSettings:
        lo, hi = self.heat_input_min_j_per_mm, self.heat_input_max_j_per_mm
        if lo is not None and hi is not None and hi <= lo:
            raise ValueError(f"heat_input_max_j_per_mm ({hi:g}) must exceed heat_input_min_j_per_mm ({lo:g})")
        self.coefficients()  # the table read, the material and the range checked against it
        return self

    def rules(self) -> HeatingRules:
        """The crew's rules alone (what the planner takes)."""
        return HeatingRules.model_validate(self.model_dump(include=set(HeatingRules.model_fields)))

    def coefficients(self) -> Coefficients:
        """The coefficient table with the crew's heat-input range; ValueError naming the problem
        when the material is not in it or the range lies outside the table's."""
        path = self.coefficients_file or DEFAULT_TABLE
        try:
            table = load_coefficients(path)
        except OSError as exc:
            raise ValueError(f"coefficients_file {path}: {exc.strerror or exc}") from None
        except (tomllib.TOMLDecodeError, ValidationError) as exc:
            raise ValueError(f"coefficients_file {path}: not a coefficient table: {exc}") from None
        if self.material not in table.material:
            raise ValueError(
                f"material {self.material!r} is not in the coefficient table {path.name} "
                f"(has: {', '.join(sorted(table.material))})"
            )
        p = table.process
        lo = self.heat_input_min_j_per_mm or p.heat_input_min_j_per_mm
        hi = self.heat_input_max_j_per_mm or p.heat_input_max_j_per_mm
        if hi <= lo or lo < p.heat_input_min_j_per_mm or hi > p.heat_input_max_j_per_mm:
            raise ValueError(
                f"heat-input range {lo:g}-{hi:g} J/mm is not inside the coefficient table's "
                f"{p.heat_input_min_j_per_mm:g}-{p.heat_input_max_j_per_mm:g} J/mm (its range of validity)"
            )
        process = p.model_copy(update={"heat_input_min_j_per_mm": lo, "heat_input_max_j_per_mm": hi})
        return table.model_copy(update={"process": process})
