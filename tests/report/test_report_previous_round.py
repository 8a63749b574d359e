"""The report's "Previous round" section: the plate's previous round's figures per line, by line name."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from analysis.report.html_page import render_html
from analysis.report.load import PreviousLine, PreviousRound, load_results
from analysis.report.write import write_report
from analysis.templates import DetectionLayout
from tests.support.results_fixture import write_synthetic_results

SMALL = DetectionLayout(
    transverse_offsets_mm=(300.0, 900.0), longitudinal_offsets_mm=(300.0,), diagonals=False
)


def _previous(names: list[str]) -> PreviousRound:
    lines = tuple(
        PreviousLine(name=n, zmax_mm=4.25 + k, sz_avg_mm=1.5 + k, passed=k % 2 == 1)
        for k, n in enumerate(names)
    )
    return PreviousRound(
        round=2, job_id="job-prev-7", created_utc="2026-11-30T09:00:00Z", verdict="fail", lines=lines
    )


def _html(tmp_path: Path, previous: PreviousRound | None) -> tuple[str, list[str]]:
    write_synthetic_results(tmp_path, n_points=2000, layout=SMALL, plate_id="P-9")
    data = load_results(tmp_path)
    names = [ln.name for ln in data.report.lines]
    svgs = {"top": "<svg></svg>", "coverage": "<svg></svg>"} | {
        f"line{k}": "<svg></svg>" for k in range(len(names))
    }
    return render_html(data, [], svgs, previous), names


def _row(html: str, name: str) -> str:
    section = html.split('<section id="previous-round"', 1)[1].split("</section>", 1)[0]
    return section.split(f'<tr data-line="{name}">', 1)[1].split("</tr>", 1)[0]


def test_a_first_round_shows_no_previous_round(tmp_path: Path) -> None:
    html, _ = _html(tmp_path, None)
    assert 'id="previous-round"' not in html and "Previous round" not in html


def test_the_previous_round_is_shown_per_line_matched_by_name(tmp_path: Path) -> None:
    html, names = _html(tmp_path, None)
    assert len(names) >= 3
    # the previous round knew the first line and the last, plus a line this round does not have
    prev = _previous([names[0], "X9", names[-1]])
    html, _ = _html(tmp_path, prev)
    assert '<section id="previous-round" data-round="3">' in html
    assert "This is round 3 of plate P-9; round 2: job job-prev-7" in html
    first = _row(html, names[0])
    assert "<td>4.25</td><td>1.50</td>" in first and first.endswith("FAIL</td>")
    last = _row(html, names[-1])
    assert "<td>6.25</td><td>3.50</td>" in last and last.endswith('<td class="t">FAIL</td>')  # k = 2: failed
    middle = _row(html, names[1])  # no match in the previous round: dashes
    assert middle.endswith('<td>—</td><td>—</td><td class="t">—</td>')
    assert 'data-line="X9"' not in html.split('id="previous-round"', 1)[1].split("</section>", 1)[0]


@pytest.mark.process  # pdftotext
def test_the_pdf_carries_the_previous_round_page(tmp_path: Path) -> None:
    truth = write_synthetic_results(tmp_path, n_points=2000, layout=SMALL, plate_id="P-9")
    names = [ln.name for ln in truth.report.lines]
    write_report(tmp_path, _previous(names[:1]))
    text = subprocess.run(
        ["pdftotext", "-layout", str(tmp_path / "report.pdf"), "-"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    page = next(p for p in text.split("\f") if "Previous round" in p)
    assert "Round 3 of plate P-9; round 2: job job-prev-7" in page
    assert "4.25" in page and "1.50" in page
    assert 'id="previous-round"' in (tmp_path / "report.html").read_text(encoding="utf-8")
