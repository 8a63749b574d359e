"""A results directory loaded for the report (:func:`load_results`), and the previous round of the
same plate it is compared with (:class:`PreviousRound`).
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from analysis.contracts.job import LineReport, Report
from analysis.contracts.results import LineSeries, ReportError, read_report, read_results_arrays
from analysis.forming.plan_file import HEATING_PLAN_FILE, HeatingPlanFile, read_heating_plan


@dataclass(frozen=True)
class ResultsData:
    """A results directory, loaded and checked (:func:`load_results`).

    report: report.json (lines carry a ``name``, derived from family and index if absent).
    plate_xy_mm: (n, 2) float64 positions from the reference corner; plate_deviation_mm: (n,) float64.
    plate_size_mm: (2,) length, width. lines: one :class:`LineSeries` per report line, or None where
    the results hold no section for it. holes_xy_mm: (h, 2) centres of unseen design cells.
    heating_plan: heating-plan.json when the directory has one that reads (docs/forming.md).
    """

    results_dir: Path
    report: Report
    plate_xy_mm: np.ndarray
    plate_deviation_mm: np.ndarray
    plate_size_mm: np.ndarray
    lines: list[LineSeries | None]
    holes_xy_mm: np.ndarray
    heating_plan: HeatingPlanFile | None = None


@dataclass(frozen=True)
class PreviousLine:
    """One line of the previous round: its name (``T1``, ``L2``, ``D1``), Zmax and SZ-average (mm),
    and whether it passed."""

    name: str
    zmax_mm: float
    sz_avg_mm: float
    passed: bool


@dataclass(frozen=True)
class PreviousRound:
    """The plate's previous forming round (the caller finds it; this module reads no job directory).

    round: its number among the plate's analysed rounds (1 = the first); this report is round + 1.
    """

    round: int
    job_id: str
    created_utc: str
    verdict: str
    lines: tuple[PreviousLine, ...]


def previous_by_line(report: Report, previous: PreviousRound) -> list[tuple[LineReport, PreviousLine | None]]:
    """This report's lines, each with the previous round's line of the same name (None: no match)."""
    by_name = {ln.name: ln for ln in previous.lines}
    return [(ln, by_name.get(ln.name)) for ln in report.lines]


def load_results(results_dir: str | Path) -> ResultsData:
    """Read and check ``report.json`` and ``results.npz`` of a results directory, and its
    ``heating-plan.json`` when there is one that reads
    (:func:`analysis.contracts.results.read_report`, :func:`analysis.contracts.results.read_results_arrays`).

    Raises :class:`ReportError` naming the file and the field or array at fault.
    """
    d = Path(results_dir)
    if not d.is_dir():
        raise ReportError(f"{d}: not a results directory (no such directory)")
    report = read_report(d / "report.json")
    arrays = read_results_arrays(d / "results.npz", n_lines=len(report.lines))
    plan = None
    if (d / HEATING_PLAN_FILE).is_file():
        with contextlib.suppress(ValueError):  # a plan that does not read never costs the report
            plan = read_heating_plan(d)
    return ResultsData(
        d, report, arrays.plate_xy_mm, arrays.plate_deviation_mm, arrays.plate_size_mm, arrays.lines,
        arrays.holes_xy_mm, plan,
    )  # fmt: skip
