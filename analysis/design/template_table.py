"""A yard's template table: the cross templates of one plate, as a CSV (docs/designs.md).

Modelled on the bending-template output of hull design systems (AVEVA Hull's cross templates):
one row per template with its name, the plate edge it is measured from, the distance from that
edge and the template's angle. :func:`read_template_table` turns the file into
:class:`TableTemplate` rows for :class:`~analysis.templates.DetectionLayout`;
whether a distance lies on the plate is checked when the lines are laid on the corners
(:func:`analysis.templates.detection_lines`).
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

__all__ = [
    "EDGE_ALIASES",
    "MAX_NAME_CHARS",
    "MAX_ROWS",
    "TableTemplate",
    "TemplateEdge",
    "TemplateTableError",
    "name_problem",
    "parse_template_table",
    "read_template_table",
    "row_problem",
]

TemplateEdge = Literal["0-3", "1-2", "0-1", "3-2"]


@dataclass(frozen=True)
class TableTemplate:
    """One row of a yard's template table (docs/designs.md).

    name: the yard's template name (the report's line name). edge: the plate edge it is measured
    from, named by its corners (``"0-3"``: the width edge through the reference corner, so the
    distance runs along the length; ``"1-2"`` the opposite width edge; ``"0-1"`` the length edge
    through the reference corner; ``"3-2"`` the opposite length edge). distance_mm: from that edge,
    along the adjacent edge from the corner named first, in the base plane. angle_deg: in plan,
    between the template and the edge the distance runs along (90: square to it).
    """

    name: str
    edge: TemplateEdge
    distance_mm: float
    angle_deg: float = 90.0


MAX_ROWS = 200
MAX_NAME_CHARS = 40
MAX_DISTANCE_MM = 100_000.0  # 100 m: beyond any plate
# accepted spellings of each column (case and surrounding blanks ignored)
COLUMNS = {
    "name": ("name", "template", "template_name"),
    "edge": ("edge", "from", "reference", "measured_from"),
    "distance_mm": ("distance_mm", "distance", "dist_mm"),
    "angle_deg": ("angle_deg", "angle"),
}
# edge names: by their corners, or the plate frame axis the distance runs along
EDGE_ALIASES = {
    "0-3": "0-3", "3-0": "0-3", "x": "0-3",
    "1-2": "1-2", "2-1": "1-2",
    "0-1": "0-1", "1-0": "0-1", "y": "0-1",
    "3-2": "3-2", "2-3": "3-2",
}  # fmt: skip


class TemplateTableError(ValueError):
    """A template table that cannot be used; the message names the file, the line and the problem."""


def name_problem(name: str) -> str | None:
    """Why ``name`` cannot be a template's name (None: it can). A name is 1 to 40 printable ASCII
    characters without quotes or backslashes (yards name templates ``FR34``, ``T-07 +200``): it
    goes into reports and file names as it is, and a trigger's size stays bounded whatever JSON
    encoder sends it (no escapes longer than two bytes)."""
    if not name or name != name.strip():
        return f"template name {name!r} is empty or starts or ends with a blank"
    if len(name) > MAX_NAME_CHARS:
        return f"template name {name[:20]!r}... has {len(name)} characters, at most {MAX_NAME_CHARS}"
    bad = sorted({ch for ch in name if not (" " <= ch <= "~") or ch in '"\\'})
    if bad:
        return f"template name {name!r} holds {''.join(bad)!r}: printable ASCII without quotes or backslashes only"
    return None


def row_problem(row: TableTemplate) -> str | None:
    """Why a template row cannot be used (None: it can): its name (:func:`name_problem`), a distance
    outside 0..100 000 mm, an angle outside 30..150 degrees. The one rule for a CSV's rows and a
    trigger's."""
    problem = name_problem(row.name)
    if problem:
        return problem
    if not (math.isfinite(row.distance_mm) and 0.0 <= row.distance_mm <= MAX_DISTANCE_MM):
        return f"template {row.name}: distance {row.distance_mm:g} mm is outside 0..{MAX_DISTANCE_MM:g} mm"
    if not (math.isfinite(row.angle_deg) and 30.0 <= row.angle_deg <= 150.0):
        return f"template {row.name}: angle {row.angle_deg:g} deg is outside 30..150 deg (90: square to the edge)"
    return None


def _number(text: str, what: str, where: str) -> float:
    try:
        value = float(text.strip().replace(",", ".") if text.count(",") == 1 and "." not in text else text)
    except ValueError:
        raise TemplateTableError(f"{where}: {what} {text.strip()!r} is not a number") from None
    if not math.isfinite(value):
        raise TemplateTableError(f"{where}: {what} {text.strip()!r} is not a finite number")
    return value


def parse_template_table(text: str, source: str = "template table") -> tuple[TableTemplate, ...]:
    """Rows of a template table given as text (comma- or semicolon-separated, a header line first;
    blank lines and lines starting with ``#`` are skipped). Raises :class:`TemplateTableError`."""
    lines = [
        (n, ln) for n, ln in enumerate(text.splitlines(), 1) if ln.strip() and not ln.lstrip().startswith("#")
    ]
    if not lines:
        raise TemplateTableError(f"{source}: empty (no header line)")
    head_no, head = lines[0]
    delim = ";" if head.count(";") > head.count(",") else ","
    header = [h.strip().lower() for h in next(csv.reader([head], delimiter=delim))]
    col: dict[str, int] = {}
    for key, names in COLUMNS.items():
        found = [i for i, h in enumerate(header) if h in names]
        if found:
            col[key] = found[0]
        elif key != "angle_deg":
            raise TemplateTableError(
                f"{source}: line {head_no}: missing column {key!r} (accepted: {', '.join(names)}; "
                f"the header has {', '.join(header) or 'nothing'})"
            )
    rows: list[TableTemplate] = []
    seen: set[str] = set()
    for n, ln in lines[1:]:
        where = f"{source}: line {n}"
        cells = next(csv.reader(io.StringIO(ln), delimiter=delim))
        if len(cells) <= max(col.values()):
            raise TemplateTableError(f"{where}: {len(cells)} fields, the header has {len(header)}")
        name = cells[col["name"]].strip()
        if not name:
            raise TemplateTableError(f"{where}: the template has no name")
        if name in seen:
            raise TemplateTableError(f"{where}: template {name!r} appears twice")
        seen.add(name)
        raw_edge = cells[col["edge"]].strip().lower()
        if raw_edge not in EDGE_ALIASES:
            raise TemplateTableError(
                f"{where}: unknown edge {cells[col['edge']].strip()!r} "
                f"(one of 0-3, 1-2, 0-1, 3-2, or the axis x, y)"
            )
        distance = _number(cells[col["distance_mm"]], "distance", where)
        if distance < 0:
            raise TemplateTableError(f"{where}: distance {distance:g} mm is negative")
        angle = _number(cells[col["angle_deg"]], "angle", where) if "angle_deg" in col else 90.0
        if not 30.0 <= angle <= 150.0:
            raise TemplateTableError(
                f"{where}: angle {angle:g} deg is outside 30..150 deg (90: square to the edge)"
            )
        row = TableTemplate(name, EDGE_ALIASES[raw_edge], distance, angle)  # type: ignore[arg-type]
        if (problem := row_problem(row)) is not None:
            raise TemplateTableError(f"{where}: {problem}")
        rows.append(row)
    if not rows:
        raise TemplateTableError(f"{source}: no template rows after the header")
    if len(rows) > MAX_ROWS:
        raise TemplateTableError(f"{source}: {len(rows)} templates, at most {MAX_ROWS}")
    return tuple(rows)


def read_template_table(path: str | Path) -> tuple[TableTemplate, ...]:
    """:func:`parse_template_table` of a file; a missing or unreadable file is a TemplateTableError."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise TemplateTableError(f"{p}: cannot read the template table: {reason}") from None
    return parse_template_table(text, str(p))
