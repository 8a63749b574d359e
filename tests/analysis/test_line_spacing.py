"""Detection lines scaled to the plate: the paper's spacing rule ("auto" counts) and a template table."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from analysis.design.template_table import TableTemplate
from analysis.templates import DetectionLayout, TemplateError, detection_lines, paper_line_count
from cellctl.analysis_job import inspection_settings
from cellctl.config import CellConfig

AUTO = DetectionLayout(transverse_count=None, longitudinal_count=None)


def _corners(length: float, width: float) -> np.ndarray:
    return np.array([[0, 0, 0], [length, 0, 0], [length, width, 0], [0, width, 0]], dtype=float)


def _families(lines) -> dict[str, list]:
    out: dict[str, list] = {"transverse": [], "longitudinal": [], "diagonal": []}
    for ln in lines:
        out[ln.family].append(ln)
    return out


def test_the_papers_plate_keeps_its_lines() -> None:
    """1200 x 800: "auto" is the paper's 14 at 80 mm and 7 at 100 mm, the same lines as the explicit layout."""
    auto = detection_lines(_corners(1200, 800), AUTO)
    explicit = detection_lines(_corners(1200, 800), DetectionLayout())
    assert [(ln.family, ln.position_mm) for ln in auto] == [(ln.family, ln.position_mm) for ln in explicit]
    fam = _families(auto)
    assert (len(fam["transverse"]), len(fam["longitudinal"]), len(fam["diagonal"])) == (14, 7, 2)


def test_a_measured_side_slightly_short_keeps_the_count() -> None:
    fam = _families(detection_lines(_corners(1199.6, 799.5), AUTO))
    assert (len(fam["transverse"]), len(fam["longitudinal"])) == (14, 7)


def test_a_long_plate_gets_the_paper_spacing_over_its_whole_length() -> None:
    """6000 x 2000: 74 transverse lines every 80 mm from 80 to 5920 mm, 19 longitudinal every 100 mm."""
    fam = _families(detection_lines(_corners(6000, 2000), AUTO))
    t = np.array([ln.position_mm for ln in fam["transverse"]])
    lo = np.array([ln.position_mm for ln in fam["longitudinal"]])
    assert len(t) == 74 and len(lo) == 19
    assert np.allclose(np.diff(t), 80.0) and t[0] == pytest.approx(80.0) and t[-1] == pytest.approx(5920.0)
    assert (
        np.allclose(np.diff(lo), 100.0) and lo[0] == pytest.approx(100.0) and lo[-1] == pytest.approx(1900.0)
    )
    # every transverse line crosses the full width, every longitudinal the full length
    assert all(ln.chord_mm == pytest.approx(2000.0) for ln in fam["transverse"])
    assert all(ln.chord_mm == pytest.approx(6000.0) for ln in fam["longitudinal"])


def test_today_an_explicit_count_stays_in_the_middle() -> None:
    """An explicit count is kept as given (the layout of a cell that fixed it)."""
    fam = _families(detection_lines(_corners(6000, 2000), DetectionLayout()))
    t = [ln.position_mm for ln in fam["transverse"]]
    assert len(t) == 14 and t[0] == pytest.approx(2480.0)


@settings(max_examples=60, deadline=None)
@given(side=st.floats(50.0, 20000.0), spacing=st.floats(20.0, 500.0))
def test_paper_count_leaves_a_spacing_at_each_end(side: float, spacing: float) -> None:
    n = paper_line_count(side, spacing)
    assert n >= 1
    if n > 1:
        margin = (side - (n - 1) * spacing) / 2.0
        assert margin >= spacing * (1 - 0.05) - 1e-9  # one spacing (less the measurement slack)
        assert margin < 1.5 * spacing + 0.05 * spacing + 1e-9  # and no room for another pair


def test_paper_count_refuses_nonsense() -> None:
    with pytest.raises(TemplateError):
        paper_line_count(0.0, 80.0)
    with pytest.raises(TemplateError):
        paper_line_count(1000.0, -1.0)


def test_a_template_table_replaces_the_auto_lines() -> None:
    table = (
        TableTemplate("FR1", "0-3", 1500.0),
        TableTemplate("FR2", "0-3", 4500.0),
        TableTemplate("LK", "0-1", 700.0),
    )
    lines = detection_lines(
        _corners(6000, 2000), DetectionLayout(None, 80.0, None, 100.0, True, templates=table)
    )
    assert [ln.name for ln in lines if ln.name] == ["FR1", "FR2", "LK"]
    assert len(lines) == 3 + 2  # the table's and the diagonals, no spaced lines
    # an explicit count keeps the old rule: the spaced lines, then the table's
    fixed = detection_lines(_corners(6000, 2000), DetectionLayout(3, 80.0, 0, 100.0, False, templates=table))
    assert [ln.name or ln.family for ln in fixed] == ["transverse"] * 3 + ["FR1", "FR2", "LK"]


def test_config_auto_reaches_the_layout() -> None:
    cfg = CellConfig.model_validate({"cell": {"id": "c1"}})
    assert cfg.analysis.transverse_count == "auto" and cfg.analysis.longitudinal_count == "auto"
    layout = inspection_settings(cfg.analysis).layout
    assert layout.transverse_count is None and layout.longitudinal_count is None
    fixed = CellConfig.model_validate({"cell": {"id": "c1"}, "analysis": {"transverse_count": 5}})
    assert inspection_settings(fixed.analysis).layout.transverse_count == 5
    with pytest.raises(ValueError):
        CellConfig.model_validate({"cell": {"id": "c1"}, "analysis": {"transverse_count": "many"}})
