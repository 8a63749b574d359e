"""The yard's template table: parsing the CSV and laying its templates on the plate's corners."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from analysis.design.template_table import (
    TableTemplate,
    TemplateTableError,
    parse_template_table,
    read_template_table,
)
from analysis.templates import DetectionLayout, TemplateError, detection_lines, line_name

RECT = np.array([[0.0, 0.0, 0.0], [1200.0, 0.0, 0.0], [1200.0, 800.0, 0.0], [0.0, 800.0, 0.0]])
NO_LAYOUT = {"transverse_count": 0, "longitudinal_count": 0, "diagonals": False}

TABLE = """# AVEVA cross templates, plate P-17
name,edge,distance_mm,angle_deg
FR101,0-3,150.0,90
FR102,1-2,300,90
LT-A,0-1,200,90.0
SKEW,x,600,60
"""


def test_parse_accepts_columns_aliases_and_separators() -> None:
    rows = parse_template_table(TABLE)
    assert rows[0] == TableTemplate("FR101", "0-3", 150.0, 90.0)
    assert rows[3] == TableTemplate("SKEW", "0-3", 600.0, 60.0)
    semi = parse_template_table("Template; From; Distance; Angle\nA;Y;12,5;90\n")
    assert semi == (TableTemplate("A", "0-1", 12.5, 90.0),)
    no_angle = parse_template_table("name,from,distance_mm\nB,3-2,40\n")
    assert no_angle == (TableTemplate("B", "3-2", 40.0, 90.0),)


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ("name,distance_mm,angle_deg\nA,100,90\n", "missing column 'edge'"),
        ("name,edge,distance_mm\nA,aft,100\n", "line 2: unknown edge 'aft'"),
        ("name,edge,distance_mm\nA,0-3,ten\n", "line 2: distance 'ten' is not a number"),
        ("name,edge,distance_mm\nA,0-3,nan\n", "is not a finite number"),
        ("name,edge,distance_mm\nA,0-3,-5\n", "is negative"),
        ("name,edge,distance_mm,angle_deg\nA,0-3,5,10\n", "angle 10 deg is outside 30..150"),
        ("name,edge,distance_mm\nA,0-3,5\nA,0-3,6\n", "line 3: template 'A' appears twice"),
        ("name,edge,distance_mm\nA,0-3\n", "line 2: 2 fields"),
        ("name,edge,distance_mm\n", "no template rows"),
        ("", "empty"),
    ],
)
def test_bad_tables_are_refused_with_their_reason(text: str, reason: str) -> None:
    with pytest.raises(TemplateTableError, match=r"^t\.csv: ") as exc:
        parse_template_table(text, "t.csv")
    assert reason in str(exc.value)
    assert "\n" not in str(exc.value)


def test_unreadable_file_is_one_line(tmp_path) -> None:
    with pytest.raises(TemplateTableError, match="cannot read the template table"):
        read_template_table(tmp_path / "missing.csv")


def test_table_lines_lie_where_the_table_says_and_keep_its_names() -> None:
    layout = DetectionLayout(**NO_LAYOUT, templates=parse_template_table(TABLE))
    lines = detection_lines(RECT, layout)
    assert [line_name(ln) for ln in lines] == ["FR101", "FR102", "LT-A", "SKEW"]
    fr101, fr102, lta, skew = lines
    assert fr101.family == "transverse" and np.allclose(fr101.start_mm, [150, 0, 0])
    assert np.allclose(fr101.end_mm, [150, 800, 0])
    assert np.allclose(fr102.start_mm, [900, 0, 0]) and np.allclose(fr102.end_mm, [900, 800, 0])
    assert lta.family == "longitudinal" and np.allclose(lta.start_mm, [0, 200, 0])
    assert np.allclose(lta.end_mm, [1200, 200, 0])
    # 60 degrees from the length edge: 800 mm across, 800 / tan(60) along
    assert np.allclose(skew.start_mm, [600, 0, 0])
    assert np.allclose(skew.end_mm, [600 + 800 / np.tan(np.radians(60)), 800, 0])
    # added to the equal spacing, which keeps its names
    both = detection_lines(RECT, DetectionLayout(templates=layout.templates))
    assert [line_name(ln) for ln in both][:2] == ["T1", "T2"] and len(both) == 14 + 7 + 2 + 4


def test_a_distance_off_the_plate_or_a_template_leaving_it_is_refused() -> None:
    off = DetectionLayout(**NO_LAYOUT, templates=(TableTemplate("FR9", "0-1", 950.0),))
    with pytest.raises(TemplateError, match="template FR9: 950 mm from edge 0-1 lies outside the plate"):
        detection_lines(RECT, off)
    leaves = DetectionLayout(**NO_LAYOUT, templates=(TableTemplate("S", "0-3", 1100.0, 45.0),))
    with pytest.raises(TemplateError, match="leaves the plate"):
        detection_lines(RECT, leaves)


@settings(max_examples=40, deadline=None)
@given(
    d=st.floats(0.0, 1.0),
    angle=st.floats(80.0, 100.0),
    edge=st.sampled_from(["0-3", "1-2", "0-1", "3-2"]),
    rot=st.floats(-np.pi, np.pi),
)
def test_square_templates_follow_the_plate_at_any_placement(
    d: float, angle: float, edge: str, rot: float
) -> None:
    """A table line's start lies on its measuring edge at the distance, its end on the opposite edge,
    wherever the plate lies on the bed (the line is laid in the plate's own frame)."""
    c, s = np.cos(rot), np.sin(rot)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    corners = RECT @ R.T + [300.0, -40.0, 12.0]
    across = 1200.0 if edge in ("0-3", "1-2") else 800.0
    other = 800.0 if across == 1200.0 else 1200.0
    dist = 0.1 * across + d * 0.8 * across
    # a slanted template must end on the opposite edge, not beyond the plate's corners
    assume(
        abs(other / np.tan(np.radians(angle))) + dist <= across
        and dist - abs(other / np.tan(np.radians(angle))) >= 0
    )
    (line,) = detection_lines(
        corners, DetectionLayout(**NO_LAYOUT, templates=(TableTemplate("X", edge, dist, angle),))
    )
    i0 = int(edge[0])
    assert np.isclose(np.linalg.norm(line.start_mm - corners[i0]), dist)
    direction = (line.end_mm - line.start_mm) / np.linalg.norm(line.end_mm - line.start_mm)
    i1 = {"0-3": 1, "1-2": 0, "0-1": 3, "3-2": 0}[edge]
    edge_dir = (corners[i1] - corners[i0]) / np.linalg.norm(corners[i1] - corners[i0])
    assert np.isclose(np.degrees(np.arccos(abs(direction @ edge_dir))), min(angle, 180 - angle), atol=1e-6)
