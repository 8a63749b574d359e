"""The heating plan of an analysed job: read from its results directory, written beside report.json.

What the planner needs is in the results: the deviation after the resting fit on the plate frame's
map points (``results.npz`` ``plate_xy_mm`` / ``plate_deviation_mm``, d = design - measured), the
plate's size, and its thickness (report.json ``design.thickness_mm`` when the design was moulded
down, else ``[forming] thickness_mm``). The sections of the report's lines (``results.npz``
``line{k}_*``) give the predicted Zmax of each line after the round: its measured heights moved by
the predicted deflection, the design rested again on the heated plate (the non-penetrating fit,
linearised to a plane), judged by :mod:`analysis.metrics` under the report's tolerances.

The model is a flat plate: the design's curvature is not in it (docs/forming.md, assumptions).

:func:`write_job_plan` never raises for a plan that cannot be made: ``heating-plan.json`` then holds
``status: no_plan`` and the reason.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from analysis.contracts.job import Report
from analysis.contracts.results import ReportError, ResultsArrays, read_report, read_results_arrays
from analysis.forming.coefficients import DEFAULT_TABLE, Coefficients, inherent_deformation
from analysis.forming.plan_file import (
    DISABLED,
    HEATING_PLAN_FILE,
    HeatingPlanFile,
    PlanLine,
    PlanModel,
    PredictedRound,
    write_heating_plan,
)
from analysis.forming.rules import PlanSettings
from analysis.metrics import MetricsError, judge, judge_line, line_metrics
from analysis.register.onesided import solve_onesided_qp

__all__ = ["HEATING_PLAN_DXF", "MAX_PLAN_POINTS", "JobPlan", "plan_job", "write_job_plan"]

#: the DXF's name in a results directory
HEATING_PLAN_DXF = "heating-plan.dxf"
#: map points the plan is made on (a regular subset of results.npz's; the planner fits fewer still)
MAX_PLAN_POINTS = 20_000
#: fewer map points than this: no plan (the deviation is not known well enough)
MIN_PLAN_POINTS = 100

MODEL_NAME = (
    "inherent strain (Ueda; Jang, Seo & Ko): Kirchhoff plate (Morley) and membrane, scikit-fem, "
    "flat rectangular plate"
)


@dataclass(frozen=True)
class JobPlan:
    """What :func:`write_job_plan` wrote: the plan and its files (``dxf`` None without a plan)."""

    plan: HeatingPlanFile
    json_path: Path
    dxf_path: Path | None


def _now_utc() -> str:
    return datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


def _no_plan(reason: str, report: Report | None = None) -> HeatingPlanFile:
    return HeatingPlanFile(
        status="no_plan",
        reason=reason,
        job_id=report.job_id if report else "",
        plate_id=report.plate_id if report else "",
        created_utc=_now_utc(),
    )


def _subset(n: int, most: int) -> np.ndarray:
    return np.arange(0, n, max(1, math.ceil(n / most)))


def _line_points(report: Report, arrays: ResultsArrays) -> list[tuple[int, np.ndarray] | None]:
    """Each report line's section sample positions in the plate frame (m, 2), with its index; None
    where the line has no section or no ends."""
    out: list[tuple[int, np.ndarray] | None] = []
    for k, (line, series) in enumerate(zip(report.lines, arrays.lines, strict=True)):
        if series is None or line.start_plate_mm is None or line.end_plate_mm is None:
            out.append(None)
            continue
        a, b = np.asarray(line.start_plate_mm, float), np.asarray(line.end_plate_mm, float)
        u = (b - a) / max(float(np.hypot(*(b - a))), 1e-9)
        out.append((k, a + np.outer(series.s_mm, u)))
    return out


def _predicted(
    report: Report, arrays: ResultsArrays, line_heat: list[np.ndarray | None]
) -> tuple[dict[str, float | None], str]:
    """Each line's Zmax after the round (by name), its section's measured heights moved by
    ``line_heat`` (mm, per sample), and the verdict under the report's tolerances."""
    zmax: dict[str, float | None] = {}
    judged = []
    for k, line in enumerate(report.lines):
        series, heat = arrays.lines[k], line_heat[k]
        if series is None or heat is None:
            zmax[line.name] = None
            judged.append(line.passed)
            continue
        try:
            m = line_metrics(
                series.s_mm, series.design_z_mm, series.measured_z_mm + heat, noise_mm=line.noise_mm,
                family=line.family, index=line.index,
            )  # fmt: skip
        except MetricsError:
            zmax[line.name] = None
            judged.append(line.passed)
            continue
        zmax[line.name] = round(m.zmax_mm, 4)
        judged.append(judge_line(m, report.tolerances).passed)
    # a plate with no line judged keeps the judge's rule: no line, no pass
    verdict = judge([], report.tolerances).verdict if not judged else ("pass" if all(judged) else "fail")
    return zmax, verdict


def _rested_change_mm(
    xy: np.ndarray, d_mm: np.ndarray, w_mm: np.ndarray, pts: np.ndarray, w_pts_mm: np.ndarray
) -> np.ndarray:
    """How far the measured heights at ``pts`` (m, 2) move up after the round and the next resting
    fit: the deflection ``w_pts_mm`` less the plane by which the design rests again on the heated
    plate. The rest is the non-penetrating fit's (on or above every map point, as close as possible
    in least squares; :func:`analysis.register.onesided.solve_onesided_qp`), linearised to a plane
    a + b x + c y over the map points ``xy`` (n, 2) whose deviation was ``d_mm`` (design - measured)
    and moves by ``-w_mm``."""

    def basis(p: np.ndarray) -> np.ndarray:  # metres: a well-conditioned QP
        return np.column_stack([np.ones(len(p)), p * 1e-3])

    x, _, _ = solve_onesided_qp(basis(xy), d_mm - w_mm, np.array([1.0, 0.0, 0.0]), 0.0)
    return w_pts_mm - basis(pts) @ x


def plan_job(results_dir: str | Path, settings: PlanSettings, *, enabled: bool = True) -> HeatingPlanFile:
    """The heating plan of the analysed job in ``results_dir`` (never raises for a plan that cannot
    be made: the file says why)."""
    d = Path(results_dir)
    t0 = time.perf_counter()
    try:
        report = read_report(d / "report.json")
    except ReportError as exc:
        return _no_plan(f"the results cannot be read: {exc}")
    if not enabled:
        return _no_plan(DISABLED, report)
    try:
        arrays = read_results_arrays(d / "results.npz", n_lines=len(report.lines))
    except ReportError as exc:
        return _no_plan(f"the results cannot be read: {exc}", report)
    tol = report.tolerances
    if report.lines and all(ln.zmax_mm <= tol.deviation_standard_mm for ln in report.lines):
        return _no_plan(
            f"every line is within the standard range ({tol.deviation_standard_mm:g} mm): nothing to heat",
            report,
        )
    ok = np.all(np.isfinite(arrays.plate_xy_mm), axis=1) & np.isfinite(arrays.plate_deviation_mm)
    if int(ok.sum()) < MIN_PLAN_POINTS:
        return _no_plan(f"only {int(ok.sum())} map points with a deviation: too few to plan on", report)
    try:
        coefficients = settings.coefficients()
    except ValueError as exc:
        return _no_plan(f"the coefficient table: {exc}", report)
    length_mm, width_mm = (float(v) for v in arrays.plate_size_mm)
    thickness_from = "report" if report.design.thickness_mm else "config"
    thickness_mm = float(report.design.thickness_mm or settings.thickness_mm)
    xy, dev = arrays.plate_xy_mm[ok], arrays.plate_deviation_mm[ok]
    keep = _subset(len(xy), MAX_PLAN_POINTS)
    xy, dev = xy[keep], dev[keep]
    try:
        plan = _plan(report, arrays, xy, dev, length_mm, width_mm, thickness_mm, coefficients, settings)
    except (ValueError, ArithmeticError, MemoryError, RuntimeError, np.linalg.LinAlgError) as exc:
        return _no_plan(f"the planner failed: {type(exc).__name__}: {exc}", report)
    lines, notes, predicted, element_mm = plan
    material = coefficients.for_material(settings.material)
    return HeatingPlanFile(
        status="plan",
        job_id=report.job_id,
        plate_id=report.plate_id,
        created_utc=_now_utc(),
        lines=lines,
        notes=notes,
        predicted=predicted,
        model=PlanModel(
            name=MODEL_NAME,
            element_mm=element_mm,
            length_mm=length_mm,
            width_mm=width_mm,
            thickness_mm=thickness_mm,
            thickness_from=thickness_from,
            coefficients_file=str(settings.coefficients_file or DEFAULT_TABLE),
            material=settings.material,
            material_properties=material,
            process=coefficients.process,
            rules=settings.rules(),
        ),
        planning_s=round(time.perf_counter() - t0, 3),
    )


def _plan(
    report: Report,
    arrays: ResultsArrays,
    xy: np.ndarray,
    d_mm: np.ndarray,
    length_mm: float,
    width_mm: float,
    thickness_mm: float,
    coefficients: Coefficients,
    settings: PlanSettings,
) -> tuple[list[PlanLine], list[str], PredictedRound, float]:
    # the FE model is imported here: reading a plan (the HMI, the report) never pays for scikit-fem
    from analysis.forming.planner import plan_heating
    from analysis.forming.plate_model import HeatingLine, PlateModel

    material = coefficients.for_material(settings.material)
    element = None if settings.element_mm == "auto" else float(settings.element_mm)
    model = PlateModel.build(length_mm, width_mm, thickness_mm, material, element_mm=element)
    # the planner takes measured - design, up as the plate lies; results.npz holds d = design - measured
    plan = plan_heating(
        xy, -d_mm, length_mm, width_mm, thickness_mm, coefficients, settings.rules(), model=model
    )
    lines = [
        PlanLine(
            id=f"H{p.order}",
            order=p.order,
            start_plate_mm=[round(v, 1) for v in p.start_plate_mm],
            end_plate_mm=[round(v, 1) for v in p.end_plate_mm],
            face=p.face,  # type: ignore[arg-type]
            heat_input_j_mm=round(p.heat_input_j_per_mm, 1),
            torch_speed_mm_s=round(p.torch_speed_mm_s, 2),
            bend_deg=round(p.bend_deg, 4),
            shrink_mm=round(p.shrink_mm, 4),
        )
        for p in plan.lines
    ]
    # the round as the crew heats it: the deflection at the map points and on every line's section,
    # the deflection's plane over the plate taken out (the next resting fit takes it out)
    heated = [
        HeatingLine(
            tuple(p.start_plate_mm),
            tuple(p.end_plate_mm),
            p.face,
            inherent_deformation(p.heat_input_j_per_mm, thickness_mm, material, coefficients.process),
        )
        for p in plan.lines
    ]
    have = [x for x in _line_points(report, arrays) if x is not None]
    line_heat: list[np.ndarray | None] = [None] * len(report.lines)
    if have:
        pts = np.concatenate([p for _, p in have])
        w = np.zeros(len(pts))
        if heated:
            w = _rested_change_mm(
                xy, d_mm, model.deflection_mm(heated, xy), pts, model.deflection_mm(heated, pts)
            )
        for (k, _), part in zip(have, np.split(w, np.cumsum([len(p) for _, p in have])[:-1]), strict=True):
            line_heat[k] = part
    zmax, verdict = _predicted(report, arrays, line_heat)
    predicted = PredictedRound(
        zmax_mm=zmax, verdict=verdict,  # type: ignore[arg-type]
        rms_before_mm=round(plan.rms_before_mm, 4), rms_after_mm=round(plan.rms_after_mm, 4),
        max_before_mm=round(plan.max_before_mm, 4), max_after_mm=round(plan.max_after_mm, 4),
    )  # fmt: skip
    return lines, plan.notes, predicted, float(plan.element_mm)


def write_job_plan(results_dir: str | Path, settings: PlanSettings, *, enabled: bool = True) -> JobPlan:
    """Make the plan of the job in ``results_dir`` and write ``heating-plan.json`` (always) and
    ``heating-plan.dxf`` (with a plan) there. FileNotFoundError when ``results_dir`` is no directory
    (there is nowhere to write); OSError when the disk refuses."""
    d = Path(results_dir)
    if not d.is_dir():
        raise FileNotFoundError(f"{d}: not a results directory (no such directory)")
    plan = plan_job(d, settings, enabled=enabled)
    dxf_path: Path | None = None
    stale = d / HEATING_PLAN_DXF
    if plan.status == "plan" and plan.model is not None:
        from analysis.forming.dxf import write_plan_dxf

        dxf_path = write_plan_dxf(plan, plan.model.length_mm, plan.model.width_mm, stale)
    elif stale.exists():  # a DXF of an earlier plan must not be marked from
        stale.unlink()
    json_path = write_heating_plan(plan, d / HEATING_PLAN_FILE)
    return JobPlan(plan, json_path, dxf_path)
