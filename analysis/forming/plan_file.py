"""``heating-plan.json``: the line-heating plan of an analysed job, beside its report.json.

Written by :func:`analysis.heating_plan.write_job_plan` (after every analysis, and by ``cellctl
heat-plan``), read by the HMI and the report. Every position is in the plate frame of report.json's
lines: mm from the reference corner, x along the plate's length, y across, as the plate lies (seen
from above; a bottom-face line keeps these coordinates: the crew mirrors them when the plate is
turned over). A plan that could not be made is a file too: ``status`` ``no_plan`` and its ``reason``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from analysis.forming.coefficients import Material, Process
from analysis.forming.rules import HeatingRules

__all__ = [
    "DISABLED",
    "HEATING_PLAN_FILE",
    "HeatingPlanFile",
    "PlanLine",
    "PlanModel",
    "PredictedRound",
    "read_heating_plan",
    "write_heating_plan",
]

#: the file's name in a results directory
HEATING_PLAN_FILE = "heating-plan.json"
#: the reason of a plan turned off
DISABLED = "line-heating plans are off in cell.toml ([forming] enabled = false)"

Vec2 = Annotated[list[float], Field(min_length=2, max_length=2)]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class PlanLine(_Strict):
    """One heating line, in the order the crew heats it.

    bend_deg: the predicted angle across the line (positive: the two sides turn toward the heated
    face); shrink_mm: the predicted shrinkage across it.
    """

    id: str
    order: Annotated[int, Field(ge=1)]
    start_plate_mm: Vec2
    end_plate_mm: Vec2
    face: Literal["top", "bottom"]
    heat_input_j_mm: Annotated[float, Field(gt=0)]
    torch_speed_mm_s: Annotated[float, Field(gt=0)]
    bend_deg: float
    shrink_mm: float

    def sentence(self) -> str:
        """The crew's one sentence: ``H3: top face, (120, 40) to (120, 760), 8 mm/s``."""
        (x0, y0), (x1, y1) = self.start_plate_mm, self.end_plate_mm
        return (
            f"{self.id}: {self.face} face, ({x0:.0f}, {y0:.0f}) to ({x1:.0f}, {y1:.0f}), "
            f"{self.torch_speed_mm_s:.0f} mm/s"
        )


class PredictedRound(_Strict):
    """The plate after the round, as the model predicts it: each report line's Zmax by name (mm,
    None where the results hold no section of the line) and the verdict under the report's
    tolerances; the deviation's RMS and largest value over the plate before and after (mm, the
    best-fit plane removed, as the resting fit does)."""

    zmax_mm: dict[str, float | None]
    verdict: Literal["pass", "fail"]
    rms_before_mm: float
    rms_after_mm: float
    max_before_mm: float
    max_after_mm: float


class PlanModel(_Strict):
    """What the plan was computed with: the forming model, the plate as modelled, the coefficients
    (the material's and the process's, the crew's heat-input range applied) and the crew's rules."""

    name: str
    element_mm: float
    length_mm: float
    width_mm: float
    thickness_mm: float
    thickness_from: Literal["report", "config"]
    coefficients_file: str
    material: str
    material_properties: Material
    process: Process
    rules: HeatingRules


class HeatingPlanFile(_Strict):
    """``heating-plan.json``. ``status`` ``plan``: ``lines`` (possibly none, ``notes`` then say why),
    ``predicted``, ``model``; ``no_plan``: ``reason`` says why no plan was made."""

    status: Literal["plan", "no_plan"]
    reason: str | None = None
    job_id: str = ""
    plate_id: str = ""
    created_utc: str = ""
    lines: list[PlanLine] = []
    notes: list[str] = []
    predicted: PredictedRound | None = None
    model: PlanModel | None = None
    planning_s: float | None = None


def write_heating_plan(plan: HeatingPlanFile, path: str | Path) -> Path:
    """The file written atomically (a temporary file renamed)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(plan.model_dump(mode="json"), indent=2, allow_nan=False), encoding="utf-8")
    tmp.replace(path)
    return path


def read_heating_plan(path: str | Path) -> HeatingPlanFile:
    """Read ``heating-plan.json`` (a file, or a results directory holding one); ValueError naming the
    file and the problem when it is missing or not a plan."""
    p = Path(path)
    if p.is_dir():
        p = p / HEATING_PLAN_FILE
    try:
        return HeatingPlanFile.model_validate_json(p.read_bytes())
    except FileNotFoundError:
        raise ValueError(f"{p}: missing") from None
    except ValidationError as exc:
        first = exc.errors(include_url=False)[0]
        where = ".".join(str(x) for x in first["loc"]) or "(top level)"
        raise ValueError(f"{p}: {where}: {first['msg']}") from None
