"""What a design file gives the analysis, checked before a plate is scanned against it.

:func:`check_design` reads any design (IGES, STEP or a mesh) and states what the inspection will
use: units, faces, size, corners, area, smallest radius of curvature, the detection lines with
their names and positions from the reference corner, and, given the plate thickness, where the
other side's corners lie (the design offset by the thickness along its normals).
:func:`preview_png` draws the surface in plan with its outline, corners and lines.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from analysis.design.cad import read_design
from analysis.design.cad_surface import CadDesign
from analysis.design.mesh import TriMesh
from analysis.pipeline import design_corners_from_mesh, plate_frame
from analysis.templates import DetectionLayout, DetectionLine, detection_lines, line_name


@dataclass
class DesignCheck:
    """The check's result: ``summary`` (JSON-ready), the design and the lines it would use."""

    summary: dict[str, Any]
    design: TriMesh | CadDesign
    corners_mm: np.ndarray
    lines: list[DetectionLine]


def _side_lengths(corners: np.ndarray) -> tuple[float, float]:
    d = np.linalg.norm(np.roll(corners[:, :2], -1, axis=0) - corners[:, :2], axis=1)
    return float((d[0] + d[2]) / 2), float((d[1] + d[3]) / 2)


def offset_corners_mm(design: CadDesign, thickness_mm: float) -> np.ndarray:
    """(4, 3) corners of the plate's other side: the design's corners moved by ``thickness_mm``
    against the surface normal (the design side's normal points up, the other side lies below)."""
    face, uv = design.nearest_parameters(design.corners_mm)  # a corner is a tessellation vertex
    return design.corners_mm - thickness_mm * design.normals(face, uv)


def check_design(
    path: str | Path, layout: DetectionLayout | None = None, thickness_mm: float | None = None
) -> DesignCheck:
    """Read ``path`` and describe it; raises the reader's error (a one-line ``MeshError``)."""
    design = read_design(path)
    layout = layout or DetectionLayout()
    if isinstance(design, CadDesign):
        summary = design.summary()
        corners = design.corners_mm
    else:
        corners = design_corners_from_mesh(design)
        length, width = _side_lengths(corners)
        summary = {
            "file": str(path),
            "format": Path(path).suffix.lstrip(".").upper() + " mesh",
            "file_units": "mm",
            "faces": None,
            "size_mm": [round(length, 3), round(width, 3)],
            "area_mm2": round(float(design.triangle_areas_mm2().sum()), 1),
            "corners_mm": np.round(corners, 4).tolist(),
            "tessellation": {"triangles": len(design.triangles)},
        }
    lines = detection_lines(corners, layout)
    T_plate = plate_frame(corners)
    records = []
    for line in lines:
        ends = np.vstack([line.start_mm, line.end_mm]) @ T_plate[:3, :3].T + T_plate[:3, 3]
        records.append(
            {
                "name": line_name(line),
                "family": line.family,
                "position_mm": round(line.position_mm, 2),
                "start_plate_mm": np.round(ends[0, :2], 2).tolist(),
                "end_plate_mm": np.round(ends[1, :2], 2).tolist(),
                "length_mm": round(line.chord_mm, 2),
            }
        )
    summary["lines"] = records
    if thickness_mm is not None:
        if not (np.isfinite(thickness_mm) and thickness_mm > 0):
            raise ValueError(f"--thickness: must be a positive number of mm, got {thickness_mm!r}")
        summary["thickness_mm"] = thickness_mm
        if isinstance(design, CadDesign):
            other = offset_corners_mm(design, thickness_mm)
            length, width = _side_lengths(other)
            summary["other_side"] = {
                "corners_mm": np.round(other, 4).tolist(),
                "size_mm": [round(length, 3), round(width, 3)],
            }
    return DesignCheck(summary, design, corners, lines)


def preview_png(check: DesignCheck, path: str | Path, max_triangles: int = 60000) -> Path:
    """Plan view of the design (height in colour), its outline, corners and detection lines."""
    design = check.design
    mesh = design.mesh if isinstance(design, CadDesign) else design
    fig = Figure(figsize=(9, 6.5), dpi=110)
    ax = fig.add_subplot(1, 1, 1)
    tri = mesh.triangles
    if len(tri) > max_triangles:
        tri = tri[np.random.default_rng(0).choice(len(tri), max_triangles, replace=False)]
    v = mesh.vertices_mm
    art = ax.tripcolor(v[:, 0], v[:, 1], tri, v[:, 2], shading="gouraud", cmap="viridis")
    fig.colorbar(art, ax=ax, label="height z (mm, design frame)", shrink=0.8)
    if isinstance(design, CadDesign):
        b = np.vstack([design.boundary_mm, design.boundary_mm[:1]])
        ax.plot(b[:, 0], b[:, 1], color="black", lw=1.2)
    c = check.corners_mm
    ax.plot(c[:, 0], c[:, 1], "o", color="red", ms=5)
    for k, p in enumerate(c):
        ax.annotate(f"C{k}", p[:2], textcoords="offset points", xytext=(4, 4), color="red", fontsize=9)
    colours = {"transverse": "white", "longitudinal": "orange", "diagonal": "magenta"}
    for line in check.lines:
        ends = np.vstack([line.start_mm, line.end_mm])
        ax.plot(ends[:, 0], ends[:, 1], color=colours[line.family], lw=0.8)
        name = line_name(line)
        ax.annotate(name, ends[0, :2], fontsize=6, color=colours[line.family],
                    textcoords="offset points", xytext=(-2, -9))  # fmt: skip
    s = check.summary
    ax.set_title(
        f"{Path(s['file']).name}: {s['format']}, {s.get('faces') or 'mesh'} face(s), "
        f"{s['size_mm'][0]:.1f} x {s['size_mm'][1]:.1f} mm, {len(check.lines)} lines",
        fontsize=10,
    )
    ax.set_xlabel("x (mm, design frame)")
    ax.set_ylabel("y (mm, design frame)")
    ax.set_aspect("equal")
    path = Path(path)
    fig.savefig(path, format="png")
    return path
