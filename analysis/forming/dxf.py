"""``heating-plan.dxf``: the plan's lines drawn in the plate frame, for the crew to mark the plate
(chalk, or a projector that reads DXF).

Millimetres (``$INSUNITS`` 4), the plate frame of report.json: the reference corner at (0, 0), x
along the plate's length, y across, seen from above as the plate lies. Layers: ``PLATE`` (the
outline), ``REFERENCE`` (the corner's mark and its words), ``HEAT_TOP`` and ``HEAT_BOTTOM`` (one
LINE per heating line, on the layer of its face) and ``HEAT_LABELS`` (each line's id and order at
its start). A bottom-face line keeps the top's coordinates: the crew mirrors it when turning the
plate over (the layer's description says so).
"""

from __future__ import annotations

from pathlib import Path

import ezdxf
from ezdxf import units

from analysis.forming.plan_file import HeatingPlanFile

__all__ = ["FACE_LAYERS", "write_plan_dxf"]

#: the layer of each face's lines
FACE_LAYERS = {"top": "HEAT_TOP", "bottom": "HEAT_BOTTOM"}

# AutoCAD colour index: red for the face up, blue for the face down
_LAYERS = {
    "PLATE": (7, "plate outline, plate frame mm, reference corner at (0, 0)"),
    "REFERENCE": (3, "the reference corner of report.json's lines"),
    "HEAT_TOP": (1, "heating lines on the face up as the plate lies"),
    "HEAT_BOTTOM": (5, "heating lines on the face down: coordinates seen from above, mirror when turned"),
    "HEAT_LABELS": (7, "line id and order, at each line's start"),
}


def write_plan_dxf(plan: HeatingPlanFile, length_mm: float, width_mm: float, path: str | Path) -> Path:
    """Write the plan's lines and the plate's outline (``length_mm`` x ``width_mm``) to ``path``
    (atomically: a temporary file renamed)."""
    doc = ezdxf.new("R2010", setup=True)
    doc.units = units.MM
    for name, (colour, description) in _LAYERS.items():
        doc.layers.add(name, color=colour).description = description
    msp = doc.modelspace()
    msp.add_lwpolyline(
        [(0.0, 0.0), (length_mm, 0.0), (length_mm, width_mm), (0.0, width_mm)],
        close=True,
        dxfattribs={"layer": "PLATE"},
    )
    text_mm = max(10.0, min(length_mm, width_mm) / 40.0)
    mark = 2.0 * text_mm
    msp.add_circle((0.0, 0.0), mark / 2, dxfattribs={"layer": "REFERENCE"})
    msp.add_line((0.0, 0.0), (mark, 0.0), dxfattribs={"layer": "REFERENCE"})
    msp.add_line((0.0, 0.0), (0.0, mark), dxfattribs={"layer": "REFERENCE"})
    msp.add_text(
        "REF (0, 0): x along, y across",
        height=text_mm * 0.8,
        dxfattribs={"layer": "REFERENCE", "insert": (mark * 0.6, -1.6 * text_mm)},
    )
    for line in plan.lines:
        start, end = tuple(line.start_plate_mm), tuple(line.end_plate_mm)
        msp.add_line(start, end, dxfattribs={"layer": FACE_LAYERS[line.face]})
        msp.add_text(
            f"{line.id} #{line.order} {line.face}",
            height=text_mm,
            dxfattribs={
                "layer": "HEAT_LABELS",
                "insert": (start[0] + 0.3 * text_mm, start[1] + 0.3 * text_mm),
            },
        )
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    doc.saveas(tmp)
    tmp.replace(path)
    return path
