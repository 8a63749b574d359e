"""Digital templates: detection lines on the plate and section cuts of triangle meshes (paper 2.3.1).

A detection line is a vertical section plane (it contains the deflection direction ``up``) located
in the plate's own frame from its four corners, not from the bed's axes: transverse lines cross the
plate at given distances from the reference corner along the length edges, longitudinal lines run
at given distances along the width edges, diagonals join opposite corners. The same planes cut the
registered design mesh and the measured mesh; each cut is an ordered polyline, resampled every
``step_mm`` on a grid shared by design and measurement so the metrics compare like with like.

Corners: (4, 3) mm, counter-clockwise seen from +up, starting at the reference corner; edge 0->1
is a length edge (the design plate frame's x), edge 0->3 a width edge.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import structlog

from analysis.design.mesh import TriMesh
from analysis.design.template_table import TableTemplate

log = structlog.get_logger(__name__)


class TemplateError(ValueError):
    """Detection lines or section cuts that cannot be made: bad corners, bad layout, no intersection."""


# edge a table template is measured from -> (family, measuring edge p0->p1, opposite edge q0->q1)
_TABLE_EDGES: dict[str, tuple[str, tuple[int, int], tuple[int, int]]] = {
    "0-3": ("transverse", (0, 1), (3, 2)),
    "1-2": ("transverse", (1, 0), (2, 3)),
    "0-1": ("longitudinal", (0, 3), (1, 2)),
    "3-2": ("longitudinal", (3, 0), (2, 1)),
}


@dataclass(frozen=True)
class DetectionLayout:
    """Where the detection lines go (defaults: the paper's 1200 x 800 mm sail plate).

    Transverse lines are spaced along the length and centred on it; longitudinal lines are spaced
    along the width and centred on it; ``diagonals`` adds the two corner-to-corner lines. Explicit
    ``*_offsets_mm`` (distances from the reference corner) replace count and spacing. ``templates``
    (a yard's template table) adds one named line per row after those (set the counts to 0 and
    ``diagonals`` off to keep only the table's).

    A count of None is the paper's rule scaled to the plate (:func:`paper_line_count`): as many lines
    as fit at the spacing with one spacing left at each end (14 at 80 mm and 7 at 100 mm on the
    paper's 1200 x 800 mm plate, 74 and 19 on a 6000 x 2000 mm one); with a template table given,
    None means the table's lines only in that family's place (no spaced lines).
    """

    transverse_count: int | None = 14
    transverse_spacing_mm: float = 80.0
    longitudinal_count: int | None = 7
    longitudinal_spacing_mm: float = 100.0
    diagonals: bool = True
    transverse_offsets_mm: tuple[float, ...] | None = None
    longitudinal_offsets_mm: tuple[float, ...] | None = None
    templates: tuple[TableTemplate, ...] = ()


@dataclass(frozen=True)
class DetectionLine:
    """One detection line: a vertical section plane and its ends on the plate boundary.

    family: "transverse" | "longitudinal" | "diagonal"; index: 1-based within the family.
    start_mm, end_mm: (3,) ends on the boundary (corner chords), same frame as the corners.
    direction: (3,) unit, horizontal (perpendicular to ``up``), from start to end.
    normal: (3,) unit normal of the section plane (horizontal, perpendicular to ``direction``).
    position_mm: distance of the line from the reference corner along the edge it is spaced on
    (transverse: length edge, longitudinal: width edge; 0 for diagonals).
    chord_mm: horizontal distance from start to end.
    name: the line's name (a template table's; empty: the family letter and index name it).
    """

    family: str
    index: int
    start_mm: np.ndarray
    end_mm: np.ndarray
    direction: np.ndarray
    normal: np.ndarray
    up: np.ndarray
    position_mm: float
    chord_mm: float
    name: str = ""


FAMILY_LETTER = {"transverse": "T", "longitudinal": "L", "diagonal": "D"}


def line_name(line: DetectionLine) -> str:
    """The line's name: the template table's, else family letter and index (``T3``, ``L1``, ``D2``)."""
    return line.name or f"{FAMILY_LETTER.get(line.family, '?')}{line.index}"


def _unit(v: np.ndarray) -> np.ndarray:
    n = float(np.linalg.norm(v))
    if n < 1e-12:
        raise TemplateError("zero-length direction (coincident corners?)")
    return v / n


def _horizontal(v: np.ndarray, up: np.ndarray) -> np.ndarray:
    return v - (v @ up) * up


def _make_line(
    family: str, index: int, a: np.ndarray, b: np.ndarray, up: np.ndarray, position: float, name: str = ""
) -> DetectionLine:
    chord = _horizontal(b - a, up)
    direction = _unit(chord)
    normal = _unit(np.cross(direction, up))
    return DetectionLine(
        family, index, a, b, direction, normal, up, float(position), float(np.linalg.norm(chord)), name
    )


def _table_line(c: np.ndarray, up: np.ndarray, row: TableTemplate, index: int) -> DetectionLine:
    """The line of one template-table row: from the point at ``distance_mm`` along the measuring
    edge, at ``angle_deg`` to it in plan, to where it meets the opposite edge (corner chords)."""
    if row.edge not in _TABLE_EDGES:
        raise TemplateError(
            f"template {row.name}: unknown edge {row.edge!r} (one of {', '.join(_TABLE_EDGES)})"
        )
    family, (i0, i1), (j0, j1) = _TABLE_EDGES[row.edge]
    p0, p1, q0, q1 = c[i0], c[i1], c[j0], c[j1]
    edge_h = _horizontal(p1 - p0, up)
    length = float(np.linalg.norm(edge_h))
    if not 0.0 <= row.distance_mm <= length:
        raise TemplateError(
            f"template {row.name}: {row.distance_mm:g} mm from edge {row.edge} lies outside the plate "
            f"(it is {length:.1f} mm across that way)"
        )
    a = p0 + (row.distance_mm / length) * (p1 - p0)
    u = edge_h / length
    v = np.cross(up, u)  # u turned +90 degrees about up
    inward = 1.0 if _horizontal((q0 + q1) / 2 - p0, up) @ v > 0 else -1.0
    ang = np.radians(row.angle_deg)
    d = np.cos(ang) * u + inward * np.sin(ang) * v
    # a + t d = q0 + s e in plan; crossing both sides with d: s = -(d x w) / (d x e), w = q0 - a
    e = _horizontal(q1 - q0, up)
    w = _horizontal(q0 - a, up)
    den = float(np.cross(d, e) @ up)
    s = -float(np.cross(d, w) @ up) / den if abs(den) > 1e-12 else np.nan
    if not (np.isfinite(s) and -1e-9 <= s <= 1 + 1e-9):
        raise TemplateError(
            f"template {row.name}: at {row.angle_deg:g} deg from edge {row.edge} it leaves the plate "
            "before reaching the opposite edge"
        )
    return _make_line(family, index, a, q0 + s * (q1 - q0), up, row.distance_mm, row.name)


#: a measured side this much (of a spacing) short of a whole number of spacings still counts them:
#: the paper's 1200 mm side measured 1199.8 mm keeps its 14 lines at 80 mm
_COUNT_SLACK = 0.05


def paper_line_count(side_mm: float, spacing_mm: float) -> int:
    """Lines at ``spacing_mm`` along a side of ``side_mm`` by the paper's rule: one spacing from each
    end, then every spacing (the paper's 1200 x 800 mm plate: 14 at 80 mm, 7 at 100 mm; at least one,
    at the middle, on a side shorter than two spacings)."""
    if not (side_mm > 0 and spacing_mm > 0):
        raise TemplateError(f"side {side_mm} mm and spacing {spacing_mm} mm must be positive")
    return max(int(np.floor(side_mm / spacing_mm + _COUNT_SLACK)) - 1, 1)


def _offsets(
    count: int | None, spacing: float, explicit: tuple[float, ...] | None, length: float, name: str
) -> np.ndarray:
    if explicit is None and count is None:
        count = paper_line_count(length, spacing) if spacing > 0 else -1
    if explicit is not None:
        off = np.asarray(explicit, dtype=np.float64)
    else:
        if count < 0 or spacing <= 0:
            raise TemplateError(f"{name}: count must be >= 0 and spacing > 0, got {count}, {spacing}")
        off = (length - (count - 1) * spacing) / 2.0 + spacing * np.arange(count)
    if off.size and (off.min() < 0 or off.max() > length):
        raise TemplateError(
            f"{name} offsets {off.min():.1f}..{off.max():.1f} mm fall outside the edge of {length:.1f} mm"
        )
    return off


def detection_lines(
    corners_mm: np.ndarray,
    layout: DetectionLayout = DetectionLayout(),
    up: np.ndarray = np.array([0.0, 0.0, 1.0]),
) -> list[DetectionLine]:
    """Detection lines of ``layout`` located on the plate from its corners.

    corners_mm: (4, 3) mm, counter-clockwise from +up, reference corner first, edge 0->1 along
    the length. up: (3,) deflection direction. Distances along an edge are horizontal (the plate's
    base plane); a transverse line at offset a joins the points at a on the two length edges
    (0->1 and 3->2), so it follows the plate even when it is not a rectangle.
    """
    c = np.asarray(corners_mm, dtype=np.float64)
    if c.shape != (4, 3) or not np.isfinite(c).all():
        raise TemplateError(f"corners_mm must be a finite (4, 3) array, got shape {c.shape}")
    up = _unit(np.asarray(up, dtype=np.float64))
    if np.cross(c[2] - c[0], c[3] - c[1]) @ up <= 0:
        raise TemplateError("corners are not counter-clockwise seen from +up")
    h = c - np.outer(c @ up, up)  # corners projected on the base plane

    def along(p: np.ndarray, q: np.ndarray, dist: np.ndarray) -> np.ndarray:
        seg = q - p
        return p + np.outer(dist / np.linalg.norm(seg), seg)

    # positions measured on the horizontal projections, the 3-D ends on the corner chords
    len_a = float(np.linalg.norm(h[1] - h[0]))
    len_b = float(np.linalg.norm(h[2] - h[3]))
    wid_a = float(np.linalg.norm(h[3] - h[0]))
    wid_b = float(np.linalg.norm(h[2] - h[1]))
    lines: list[DetectionLine] = []
    # a template table given: the None ("auto") counts leave the lines to the table
    auto = 0 if layout.templates else None
    t_off = _offsets(
        auto if layout.transverse_count is None else layout.transverse_count,
        layout.transverse_spacing_mm,
        layout.transverse_offsets_mm,
        min(len_a, len_b),
        "transverse",
    )
    starts = along(c[0], c[1], t_off * np.linalg.norm(c[1] - c[0]) / len_a)
    ends = along(c[3], c[2], t_off * np.linalg.norm(c[2] - c[3]) / len_b)
    for k, (a, b, off) in enumerate(zip(starts, ends, t_off, strict=True)):
        lines.append(_make_line("transverse", k + 1, a, b, up, off))
    l_off = _offsets(
        auto if layout.longitudinal_count is None else layout.longitudinal_count,
        layout.longitudinal_spacing_mm,
        layout.longitudinal_offsets_mm,
        min(wid_a, wid_b),
        "longitudinal",
    )
    starts = along(c[0], c[3], l_off * np.linalg.norm(c[3] - c[0]) / wid_a)
    ends = along(c[1], c[2], l_off * np.linalg.norm(c[2] - c[1]) / wid_b)
    for k, (a, b, off) in enumerate(zip(starts, ends, l_off, strict=True)):
        lines.append(_make_line("longitudinal", k + 1, a, b, up, off))
    if layout.diagonals:
        lines.append(_make_line("diagonal", 1, c[0], c[2], up, 0.0))
        lines.append(_make_line("diagonal", 2, c[1], c[3], up, 0.0))
    for k, row in enumerate(layout.templates):
        lines.append(_table_line(c, up, row, k + 1))
    return lines


@dataclass(frozen=True)
class Section:
    """An ordered section polyline of a mesh cut by a detection line's plane.

    points_mm: (k, 3) intersection points, ordered by ``s_mm``.
    s_mm: (k,) horizontal position along the line, measured from the line's start.
    h_mm: (k,) height along ``up`` (the deflection coordinate).
    """

    points_mm: np.ndarray
    s_mm: np.ndarray
    h_mm: np.ndarray


def _along(points_mm: np.ndarray, origin: np.ndarray, vec: np.ndarray) -> np.ndarray:
    """(points - origin) . vec per point; by columns, as (n, 3) @ (3,) takes a slow path in numpy."""
    return (
        (points_mm[:, 0] - origin[0]) * vec[0]
        + (points_mm[:, 1] - origin[1]) * vec[1]
        + (points_mm[:, 2] - origin[2]) * vec[2]
    )


def cut_mesh(mesh: TriMesh, line: DetectionLine) -> Section:
    """Cut ``mesh`` with the line's section plane; vectorised over all triangles.

    Each mesh edge whose ends lie on different sides of the plane (a vertex on the plane counts as
    the positive side, so a shared vertex or edge yields one point, not two) gives one intersection
    point; shared edges and vertices on the plane are taken once. The points are ordered by their position along the line,
    which is the polyline order for a plate surface (a graph over the line).
    Raises :class:`TemplateError` if the plane misses the mesh.
    """
    V = mesh.vertices_mm
    d = _along(V, line.start_mm, line.normal)
    pos = d >= 0.0
    tri = mesh.triangles
    # a triangle crosses when one or two of its corners lie on the positive side (a count per
    # triangle: any / all along its rows took 8x as long)
    on = pos.view(np.int8)
    k = on[tri[:, 0]] + on[tri[:, 1]] + on[tri[:, 2]]
    crossing = (k != 0) & (k != 3)
    if not crossing.any():
        raise TemplateError(f"{line.family} line {line.index}: the section plane does not cut the mesh")
    t = tri[crossing]
    edges = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    edges = edges[pos[edges[:, 0]] != pos[edges[:, 1]]]
    edges = np.sort(edges, axis=1)
    # each edge once, in (lower, higher) vertex order: one integer key per edge
    _, once = np.unique(edges[:, 0] * len(V) + edges[:, 1], return_index=True)
    edges = edges[once]
    da, db = d[edges[:, 0]], d[edges[:, 1]]
    w = (da / (da - db))[:, None]
    pts = V[edges[:, 0]] + w * (V[edges[:, 1]] - V[edges[:, 0]])
    # a vertex lying on the plane ends several crossing edges: keep it once
    _, first = np.unique(np.round(pts, 9), axis=0, return_index=True)
    pts = pts[np.sort(first)]
    s = _along(pts, line.start_mm, line.direction)
    order = np.argsort(s, kind="stable")
    pts, s = pts[order], s[order]
    return Section(pts, s, _along(pts, np.zeros(3), line.up))


@dataclass(frozen=True)
class SampledSection:
    """A section resampled on the shared grid ``s_mm = k * step_mm`` (k integer) along its line.

    s_mm: (n,) positions; h_mm: (n,) heights along ``up``, NaN where the section has a hole wider
    than the allowed gap or no data.
    """

    s_mm: np.ndarray
    h_mm: np.ndarray


def sample_section(section: Section, step_mm: float = 1.0, max_gap_mm: float = 5.0) -> SampledSection:
    """Resample a section every ``step_mm`` on the grid of integer multiples of the step.

    Heights are linear between polyline points (the mesh is linear there); samples inside a hole
    of the polyline (missing returns in a scan) are NaN rather than a straight bridge. A hole is a
    step between polyline points wider than both ``max_gap_mm`` and three times the median step.
    """
    if step_mm <= 0:
        raise TemplateError(f"step_mm must be positive, got {step_mm}")
    s, h = section.s_mm, section.h_mm
    if len(s) < 2:
        return SampledSection(np.zeros(0), np.zeros(0))
    k0 = int(np.ceil(s[0] / step_mm - 1e-9))
    k1 = int(np.floor(s[-1] / step_mm + 1e-9))
    grid = step_mm * np.arange(k0, k1 + 1)
    hs = np.interp(grid, s, h)
    j = np.clip(np.searchsorted(s, grid), 1, len(s) - 1)
    spacing = np.diff(s)
    # a coarse mesh has wide but regular spacing; a hole is wide against the allowance and the mesh
    hole = (s[j] - s[j - 1]) > max(max_gap_mm, 3.0 * float(np.median(spacing)))
    hs[hole] = np.nan
    return SampledSection(grid, hs)


@dataclass(frozen=True)
class TemplateCut:
    """Design and measured sections of one detection line on a shared sampling grid.

    s_mm: (n,) positions along the line (mm from its start); design_h_mm, measured_h_mm: (n,)
    heights along ``up`` (NaN where that surface has no data).
    """

    line: DetectionLine
    s_mm: np.ndarray
    design_h_mm: np.ndarray
    measured_h_mm: np.ndarray


def cut_templates(
    design_mesh: TriMesh,
    measured_mesh: TriMesh,
    lines: list[DetectionLine],
    step_mm: float = 1.0,
    max_gap_mm: float = 5.0,
) -> list[TemplateCut]:
    """Cut the registered design and the measured mesh with every line; shared 1 mm sampling.

    design_mesh: the design already moved into the measurement frame (registration transform);
    measured_mesh: the reconstructed plate surface. Lines that miss either mesh are logged and
    skipped (a scan that does not reach a line must not stop the report).
    """
    out: list[TemplateCut] = []
    for line in lines:
        try:
            sd = sample_section(cut_mesh(design_mesh, line), step_mm, max_gap_mm=np.inf)
            sm = sample_section(cut_mesh(measured_mesh, line), step_mm, max_gap_mm=max_gap_mm)
        except TemplateError as exc:
            log.warning("template_line_skipped", family=line.family, index=line.index, reason=str(exc))
            continue
        cut = _joined_cut(line, sd, sm)
        if cut is not None:
            out.append(cut)
    return out


def _joined_cut(line: DetectionLine, sd: SampledSection, sm: SampledSection) -> TemplateCut | None:
    """Design and measured samples of one line on their common domain (None: they do not overlap)."""
    lo = max(sd.s_mm[0], sm.s_mm[0]) if len(sd.s_mm) and len(sm.s_mm) else 0.0
    hi = min(sd.s_mm[-1], sm.s_mm[-1]) if len(sd.s_mm) and len(sm.s_mm) else -1.0
    if hi <= lo:
        log.warning("template_line_skipped", family=line.family, index=line.index, reason="no common domain")
        return None
    grid = sd.s_mm[(sd.s_mm >= lo - 1e-9) & (sd.s_mm <= hi + 1e-9)]
    hd = sd.h_mm[np.searchsorted(sd.s_mm, grid - 1e-9)]
    hm = sm.h_mm[np.searchsorted(sm.s_mm, grid - 1e-9)]
    return TemplateCut(line, grid, hd, hm)


class ExactSurface(Protocol):
    """A design surface that can be cut exactly (:class:`analysis.design.cad_surface.CadDesign`)."""

    mesh: TriMesh

    def vertical_heights(self, origins_mm: np.ndarray, direction: np.ndarray) -> np.ndarray: ...


def exact_section(
    surface: ExactSurface,
    T_measured_design: np.ndarray,
    line: DetectionLine,
    step_mm: float = 1.0,
    mesh_measured: TriMesh | None = None,
) -> SampledSection:
    """The design's section along ``line`` (measured frame) sampled on the exact surface.

    The tessellation's cut gives the line's extent over the design (the face's own boundary, to
    the chord error); every sample of the shared ``step_mm`` grid inside it is then the exact
    intersection of the surface with the line through it along ``up``: a point of the section
    plane, so the section is the plane-surface intersection sampled where the metrics need it.
    mesh_measured: the tessellation already moved by ``T_measured_design`` (saves the move per line).
    """
    T = np.asarray(T_measured_design, dtype=np.float64)
    mesh_measured = mesh_measured if mesh_measured is not None else surface.mesh.transformed(T)
    approx = sample_section(cut_mesh(mesh_measured, line), step_mm, max_gap_mm=np.inf)
    if not len(approx.s_mm):
        return approx
    R, t = T[:3, :3], T[:3, 3]
    origins_m = line.start_mm + np.outer(approx.s_mm, line.direction)
    origins_d = (origins_m - t) @ R  # R^T (p - t), row-wise
    pts_d = surface.vertical_heights(origins_d, R.T @ line.up)
    pts_m = pts_d @ R.T + t
    return SampledSection(approx.s_mm, _along(pts_m, np.zeros(3), line.up))


def cut_templates_exact(
    surface: ExactSurface,
    T_measured_design: np.ndarray,
    measured_mesh: TriMesh,
    lines: list[DetectionLine],
    step_mm: float = 1.0,
    max_gap_mm: float = 5.0,
) -> list[TemplateCut]:
    """:func:`cut_templates` with the design side cut from the exact surface (:func:`exact_section`)."""
    out: list[TemplateCut] = []
    moved = surface.mesh.transformed(np.asarray(T_measured_design, dtype=np.float64))
    for line in lines:
        try:
            sd = exact_section(surface, T_measured_design, line, step_mm, moved)
            sm = sample_section(cut_mesh(measured_mesh, line), step_mm, max_gap_mm=max_gap_mm)
        except TemplateError as exc:
            log.warning("template_line_skipped", family=line.family, index=line.index, reason=str(exc))
            continue
        cut = _joined_cut(line, sd, sm)
        if cut is not None:
            out.append(cut)
    return out
