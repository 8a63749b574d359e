"""Fixtures of the report tests: a results directory with known truth, reported once per session."""

from __future__ import annotations

from pathlib import Path

import pytest

from analysis.report.write import write_report
from analysis.templates import DetectionLayout
from tests.support.results_fixture import SyntheticResults, write_synthetic_results

# Lines through the dent (T4 at x = 900, L2 at y = 300), through the bump (T2, L3), and clear of both;
# eleven lines keep the session's one full render short while spanning several PDF pages of plots.
LAYOUT = DetectionLayout(
    transverse_offsets_mm=(150.0, 360.0, 600.0, 900.0, 1050.0),
    longitudinal_offsets_mm=(150.0, 300.0, 560.0, 700.0),
    diagonals=True,
)
# HTML-significant characters in the plate id must reach the page as text, never as markup.
PLATE_ID = 'HULL-07 <b>&"x"</b>'


@pytest.fixture(scope="session")
def reported(tmp_path_factory: pytest.TempPathFactory) -> tuple[SyntheticResults, list[Path]]:
    """A synthetic results directory (30,000 points, 11 lines) and the files write_report made."""
    out = tmp_path_factory.mktemp("results")
    truth = write_synthetic_results(out, n_points=30_000, layout=LAYOUT, plate_id=PLATE_ID)
    return truth, write_report(out)
