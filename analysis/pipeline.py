"""The inspection pipeline, read like section 2 of the paper.

    cloud --segment--> plate top surface --boundary--> corners
          --register--> design resting on the plate (coarse, ICP, non-penetrating)
          --templates--> detection lines cut through design and measurement
          --metrics--> six figures per line, judged against the tolerances

:func:`inspect_cloud` runs it on arrays and returns an :class:`Inspection`; :func:`write_results`
stores it as a results directory (``report.json``, ``report.csv``, ``results.npz``, ``cloud.ply``),
the input of the human-facing report (:mod:`analysis.report`). :func:`analyse_job` is the entry
point analysis workers call.

Frames: the measured frame is the scan's (robot base / bed, z up, mm). The design frame is the
design mesh's own (x along the plate's length, y along its width, z up). The plate frame used for
positions people look up on the plate has its origin at the reference corner (corner 0), x along
edge 0->1 (the length), y along edge 0->3, both horizontal in the design frame.

The measured surface is reconstructed as a height field on a grid of the measured frame's XY
plane (the mean of the points in each cell; a plate lying on a bed is a graph over that plane),
triangulated between neighbouring filled cells. The cell is sized so that it averages about 16
scan points (about 1.6 mm at HD8 density), which divides the sensor noise by 4, and the grid keeps
the cost linear in the number of points where a Delaunay triangulation of millions would not be.

ICP runs on that reconstructed surface. The non-penetrating fit rests the design on patch
estimates of the plate whose noise bias is bounded (``analysis.register.rest_surface``: the noise measured
from the data, patch means of the gaps to the design sized so the highest patch error stays below
0.25 sigma with 99 % confidence): rested on raw points or 16-point cell means, the design floated on
the highest noise excursion (1.75 sigma) and every Zmax read that much too high. The sections are
smoothed at the cell means' noise. ``penetration_points`` counts resting-surface points below the
design (0 after the fit); ``raw_points_below_4sigma`` reports raw points more than 4 noise sigmas
below it. ``template_fit`` chooses one template for the plate (rigid, the paper's 3D fit) or one
per line (``analysis.template_fit``, the paper's 2D case); docs/metrology.md has the details.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import structlog

from analysis.boundary import BoundaryError, BoundaryResult, find_corners
from analysis.cloud_io import ORGANISATION, ScanCloud, write_cloud_ply
from analysis.contracts.job import (
    AnalysisJob,
    CompareLine,
    DesignReport,
    LineFitReport,
    LineNotScanned,
    LineReport,
    RegistrationReport,
    Report,
    ReportInputs,
    RestSurfaceReport,
    ScanCoverage,
    SurfaceReport,
    TemplateFitCompare,
)
from analysis.contracts.placement import Placement, placement_transform
from analysis.contracts.results import LineSeries, ResultsArrays, write_report_json
from analysis.contracts.settings import TEMPLATE_FITS, InspectionSettings
from analysis.design.cad import read_design
from analysis.design.cad_surface import CadDesign
from analysis.design.mesh import MeshError, TriMesh
from analysis.design.moulded import design_as_laid
from analysis.design.outline import design_corners_from_mesh, frame_design_mesh, plate_frame
from analysis.export import DESIGN_FRAME, write_lines_ship
from analysis.metrics import LineMetrics, Verdict, judge, line_metrics
from analysis.register.fit import RegistrationResult, register, register_from_placement
from analysis.register.height_field import HeightField, height_field_from_mesh
from analysis.register.onesided import deflection_gaps
from analysis.register.rest_surface import RestSurface, rest_surface
from analysis.register.transforms import RegistrationError, apply_transform, invert_transform
from analysis.report.csv_table import write_csv
from analysis.segment import PassCells, SegmentResult, pass_cells, segment_plate
from analysis.template_fit import (
    LineFitResult,
    TemplateFitError,
    check_mode,
    fit_line_template,
    line_rest_samples,
)
from analysis.templates import (
    TemplateCut,
    cut_templates,
    cut_templates_exact,
    detection_lines,
    line_name,
)

log = structlog.get_logger(__name__)

MAX_MAP_POINTS = 300_000
HOLE_CELL_MM = 5.0


class InspectionError(ValueError):
    """The inputs cannot be inspected: no plate, a design that does not fit the plate, no line."""


@dataclass
class Inspection:
    """One plate inspected: the report and the arrays behind it.

    report: the report (``report.json``, :class:`~analysis.contracts.job.Report`).
    plate_points_mm: (n, 3) top-surface points in the measured frame; deviation_mm: (n,) their
    signed deviation d = z_design - z_measured (>= 0: the plate lies below the template).
    surface_points_mm, surface_deviation_mm: the same for the reconstructed surface (cell means).
    cuts: one TemplateCut per judged line (measured frame), in report order.
    """

    report: Report
    plate_points_mm: np.ndarray
    deviation_mm: np.ndarray
    surface_points_mm: np.ndarray
    surface_deviation_mm: np.ndarray
    T_measured_design: np.ndarray
    T_plate_design: np.ndarray
    plate_size_mm: tuple[float, float]
    cuts: list[TemplateCut]
    coverage_holes_xy_mm: np.ndarray
    segment: SegmentResult
    boundary: BoundaryResult | None  # None: a partial scan in which no edge was found whole
    registration: RegistrationResult
    verdict: Verdict
    timings_s: dict[str, float] = field(default_factory=dict)


# ---------------------------------------------------------------------------------------- helpers


def _side_lengths(corners: np.ndarray) -> tuple[float, float]:
    xy = corners[:, :2]
    d = np.linalg.norm(np.roll(xy, -1, axis=0) - xy, axis=1)
    return float((d[0] + d[2]) / 2), float((d[1] + d[3]) / 2)


def _check_size(design_c: np.ndarray, measured_c: np.ndarray, tol: float) -> None:
    dl, dw = _side_lengths(design_c)
    ml, mw = _side_lengths(measured_c)
    if abs(ml - dl) > tol * dl or abs(mw - dw) > tol * dw:
        raise InspectionError(
            f"the design does not match the plate: the plate measures {ml:.0f} x {mw:.0f} mm, "
            f"the design is {dl:.0f} x {dw:.0f} mm (more than {tol:.0%} apart)"
        )


#: a detection line of a partial scan is judged when the scan covers this share of its length (a
#: complete scan's lines miss a few millimetres at the plate's edges); shorter ones are reported as
#: not scanned, never judged on the part that was seen
PARTIAL_LINE_COVERAGE = 0.9
#: how far the seen part of a partial scan may reach beyond the design placed where the scan was
#: planned (the placement's uncertainty): farther, the cloud is not a part of this plate
PARTIAL_FOOTPRINT_MARGIN_MM = 50.0
PARTIAL_HINT = (
    "; a scan cut short covers only part of the plate: analyse it with the placement the scan was "
    "planned from (`cellctl inspect --placement`, a job's own re-analysis does) to report what it covered"
)


def _partial_scan(design_c: np.ndarray, measured: np.ndarray, nominal: np.ndarray, tol: float) -> bool:
    """The measured plate is a part of the design's plate, as a scan cut short leaves it: ``measured``,
    its four corners (then no side may be longer than the design's, beyond ``tol``) or its points
    (when no corner was found), lies inside the design's outline placed by ``nominal`` (4x4 design
    -> measured), grown by the placement's uncertainty (a thousandth of the points may lie out)."""
    if len(measured) == 4:
        dl, dw = _side_lengths(design_c)
        ml, mw = _side_lengths(measured)
        if ml > (1 + tol) * dl or mw > (1 + tol) * dw:
            return False
    measured_c = measured
    inv = invert_transform(nominal)
    m_design = measured_c @ inv[:3, :3].T + inv[:3, 3]
    outline = design_c[:, :2]

    def cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:  # z of the 2-D cross product
        return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]

    orient = np.sign(cross(outline[1] - outline[0], outline[2] - outline[1]))
    for a, b in zip(outline, np.roll(outline, -1, axis=0), strict=True):
        edge = b - a
        # signed distance of each corner from the edge, positive inside (counter-clockwise outline)
        dist = orient * cross(edge, m_design[:, :2] - a) / max(float(np.linalg.norm(edge)), 1e-9)
        if float(np.quantile(dist, 0.001)) < -PARTIAL_FOOTPRINT_MARGIN_MM:
            return False
    return True


def _line_coverage(cut: TemplateCut) -> float:
    """Share of the line's length (plate edge to plate edge) where the scan has the plate."""
    length = float(np.linalg.norm((cut.line.end_mm - cut.line.start_mm)[:2]))
    if length <= 0 or len(cut.s_mm) < 2:
        return 0.0
    step = float(np.median(np.diff(cut.s_mm)))
    seen = np.isfinite(cut.measured_h_mm) & np.isfinite(cut.design_h_mm)
    return min(1.0, float(np.count_nonzero(seen)) * step / length)


def _xy_cells(points_mm: np.ndarray, cell_mm: float) -> tuple[np.ndarray, int, int]:
    """The XY cell of every point, counted from the points' lowest corner: (flat index ``i * ny +
    j`` (n,), nx, ny). Column by column (a reduction along axis 0 of an (n, 2) view is 20x slower)."""
    i, j = (np.floor((points_mm[:, k] - points_mm[:, k].min()) / cell_mm).astype(np.int64) for k in (0, 1))
    nx, ny = int(i.max()) + 1, int(j.max()) + 1
    i *= ny
    i += j
    return i, nx, ny


def _hole_fraction(points_mm: np.ndarray, cell_mm: float) -> float:
    """Empty cells lying between filled ones (left and right, or above and below), per filled cell."""
    flat, nx, ny = _xy_cells(points_mm, cell_mm)
    occ = (np.bincount(flat, minlength=nx * ny) > 0).reshape(nx, ny)
    inner = ~occ[1:-1, 1:-1]
    holes = inner & ((occ[:-2, 1:-1] & occ[2:, 1:-1]) | (occ[1:-1, :-2] & occ[1:-1, 2:]))
    return float(holes.sum() / max(occ.sum(), 1))


def surface_cell_mm(
    points_mm: np.ndarray, area_mm2: float, finest_mm: float, min_points: int = 16, max_holes: float = 0.01
) -> float:
    """The height-grid cell size for the measured surface.

    Large enough that a cell averages about ``min_points`` scan points (the noise of a cell mean is
    the sensor noise / sqrt(min_points), so the template rests on the plate, not on its noise), and
    large enough that the scan leaves no holes between filled cells (a coarse scan needs larger
    cells, else section planes fall through). Never finer than ``finest_mm``.
    """
    density = len(points_mm) / max(area_mm2, 1.0)
    cell = max(finest_mm, float(np.sqrt(min_points / max(density, 1e-9))))
    for _ in range(12):
        if _hole_fraction(points_mm, cell) <= max_holes:
            break
        cell *= 1.25
    return cell


def height_grid_mesh(points_mm: np.ndarray, cell_mm: float) -> TriMesh:
    """The measured surface as a height field: mean z per XY cell, triangulated between neighbours.

    points_mm: (n, 3) top-surface points (z up). Two triangles per 2x2 block of filled cells.
    """
    flat, nx, ny = _xy_cells(points_mm, cell_mm)
    count = np.bincount(flat, minlength=nx * ny)
    filled = count > 0
    mean = np.zeros((nx * ny, 3))
    for k in range(3):
        mean[:, k] = np.bincount(flat, weights=points_mm[:, k], minlength=nx * ny)
    mean[filled] /= count[filled, None]
    vid = np.full(nx * ny, -1, dtype=np.int64)
    vid[filled] = np.arange(int(filled.sum()))
    grid = vid.reshape(nx, ny)
    a, b = grid[:-1, :-1].ravel(), grid[1:, :-1].ravel()
    c, d = grid[1:, 1:].ravel(), grid[:-1, 1:].ravel()
    tris = []
    for t in (np.column_stack([a, b, c]), np.column_stack([a, c, d])):
        tris.append(t[(t >= 0).all(axis=1)])
    return TriMesh(mean[filled], np.concatenate(tris))


def _coverage_holes(design: TriMesh, seen_xy_design: np.ndarray, cell_mm: float) -> tuple[float, np.ndarray]:
    """Fraction of the design's footprint cells holding at least one measured point, and the holes."""
    V = design.vertices_mm
    lo = V[:, :2].min(axis=0)
    shape = np.maximum(np.ceil((V[:, :2].max(axis=0) - lo) / cell_mm).astype(int), 1)
    # Footprint cells: those a design triangle's centroid falls in (the design mesh is fine enough).
    cen = design.triangle_vertices_mm[:, :, :2].mean(axis=1)
    fp = np.zeros(shape, dtype=bool)
    ij = np.clip(((cen - lo) / cell_mm).astype(int), 0, shape - 1)
    fp[ij[:, 0], ij[:, 1]] = True
    seen = np.zeros(shape, dtype=bool)
    inside = np.all((seen_xy_design >= lo) & (seen_xy_design < lo + shape * cell_mm), axis=1)
    ij = ((seen_xy_design[inside] - lo) / cell_mm).astype(int)
    seen[np.clip(ij[:, 0], 0, shape[0] - 1), np.clip(ij[:, 1], 0, shape[1] - 1)] = True
    holes = fp & ~seen
    frac = float((fp & seen).sum() / max(fp.sum(), 1))
    hi, hj = np.nonzero(holes)
    centres = lo + (np.column_stack([hi, hj]) + 0.5) * cell_mm
    return frac, centres


def _subsample_index(n: int, k: int, seed: int = 0) -> np.ndarray:
    if n <= k:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, size=k, replace=False))


def _line_figures(
    cuts: list[TemplateCut], fits: list[LineFitResult | None], noise_mm: float
) -> tuple[list[LineMetrics], list[TemplateCut], list[LineFitResult | None]]:
    """The six figures of every cut that has enough samples (the others are logged and skipped)."""
    metrics: list[LineMetrics] = []
    kept: list[TemplateCut] = []
    kept_fits: list[LineFitResult | None] = []
    for cut, fit in zip(cuts, fits, strict=True):
        try:
            m = line_metrics(
                cut.s_mm, cut.design_h_mm, cut.measured_h_mm, noise_mm=noise_mm,
                family=cut.line.family, index=cut.line.index, position_mm=cut.line.position_mm,
            )  # fmt: skip
        except ValueError as exc:
            log.warning("line_skipped", family=cut.line.family, index=cut.line.index, reason=str(exc))
            continue
        metrics.append(m)
        kept.append(cut)
        kept_fits.append(fit)
    return metrics, kept, kept_fits


def _per_line_cuts(
    cuts: list[TemplateCut], points_mm: np.ndarray, gaps_mm: np.ndarray, noise_mm: float
) -> tuple[list[TemplateCut], list[LineFitResult | None]]:
    """Each cut with its design section rested on its own line (``analysis.template_fit``)."""
    out: list[TemplateCut] = []
    fits: list[LineFitResult | None] = []
    for cut in cuts:
        try:
            r = line_rest_samples(points_mm, gaps_mm, cut.line, cut.s_mm, cut.design_h_mm, noise_mm)
            fit = fit_line_template(cut.s_mm, cut.design_h_mm, r.s_mm, r.h_mm)
        except (TemplateFitError, RegistrationError) as exc:
            log.warning("per_line_fit_skipped", family=cut.line.family, index=cut.line.index, reason=str(exc))
            continue
        moved = fit.moved_heights(cut.s_mm, cut.design_h_mm, cut.s_mm)
        out.append(TemplateCut(cut.line, cut.s_mm, moved, cut.measured_h_mm))
        fits.append(fit)
    return out, fits


# --------------------------------------------------------------------------------------- pipeline


@dataclass
class PreparedDesign:
    """What the inspection needs of the design alone (:func:`prepare_design`): the face the sensor
    sees in its own frame, its corners, and its height field (``field`` a future while it is being
    rasterised). Made before the scan's last profile when the cloud is streamed."""

    mesh: TriMesh
    cad: CadDesign | None
    T_design_file: np.ndarray | None
    corners_mm: np.ndarray
    field: Any  # HeightField, or a concurrent.futures.Future of one

    def height_field(self) -> HeightField:
        f = self.field
        return f.result() if hasattr(f, "result") else f


def prepare_design(
    design: TriMesh | CadDesign, settings: InspectionSettings, pool: ThreadPoolExecutor | None = None
) -> PreparedDesign:
    """The design's part of the inspection, independent of the cloud: framed into its own plate frame
    (a mesh in ship coordinates), turned to the face the sensor sees (``settings.design_side``), its
    corners, and its height field (rasterised on ``pool`` when given: numpy releases the GIL, so it
    runs on the second core while the scan is segmented)."""
    T_design_file = None
    if isinstance(design, TriMesh):  # a mesh in ship coordinates: into its own plate frame first
        framed = frame_design_mesh(design)
        design, T_design_file = framed.mesh, framed.T_design_file
    # the face the sensor sees: the design itself, or its other side when laid moulded side down
    design = design_as_laid(design, settings.design_side, settings.thickness_mm)
    cad = design if isinstance(design, CadDesign) else None
    mesh = cad.mesh if cad is not None else design
    field: Any = (
        pool.submit(height_field_from_mesh, mesh, settings.design_grid_mm)
        if pool is not None
        else height_field_from_mesh(mesh, settings.design_grid_mm)
    )
    corners = cad.corners_mm if cad is not None else design_corners_from_mesh(mesh)
    return PreparedDesign(mesh, cad, T_design_file, corners, field)


def inspect_cloud(
    cloud: ScanCloud,
    design: TriMesh | CadDesign | PreparedDesign,
    settings: InspectionSettings | None = None,
    *,
    plate_id: str = "",
    job_id: str = "",
    cell_id: str = "",
    inputs: ReportInputs | None = None,
    nominal_placement: Placement | None = None,
    passes: dict[int, PassCells] | None = None,
) -> Inspection:
    """Inspect one scanned plate against its design; see the module docstring for the stages.

    Raises InspectionError (and the stages' own ValueError subclasses: NoPlateError,
    BoundaryError, RegistrationError, TemplateError, MetricsError) with a message a user can act on.
    nominal_placement: the design frame's placement on the bed as the operator laid the plate;
    optional, it decides which corner is the reference when the design is symmetric under a half
    turn (else the bed convention decides, see register()). The report records it under ``inputs``.
    inputs: what the caller records of the inputs (the design's name, how the placement was found);
    the cloud's size and ``nominal_placement`` are filled in here.
    design: a mesh, or a CAD design (:mod:`analysis.design.cad`): then registration runs on its
    tessellation, the corners come from the face's own boundary and the templates are cut from
    the exact surface. ``settings.design_side`` ``moulded_down``: the plate lies turned over, the
    design is offset by ``settings.thickness_mm`` first (:func:`analysis.design.moulded.design_as_laid`).
    Or a :class:`PreparedDesign` made beforehand for these settings (a streamed cloud: the design's
    part was done during the scan). passes: the cells of the passes already segmented
    (:func:`analysis.segment.pass_cells`, by pass id; :class:`CloudStream`).
    """
    settings = settings or InspectionSettings()
    timings: dict[str, float] = {}
    t = time.perf_counter()

    def lap(stage: str) -> None:
        nonlocal t
        now = time.perf_counter()
        timings[stage] = round(now - t, 4)
        t = now

    with ThreadPoolExecutor(1, thread_name_prefix="design-field") as pool:
        prepared = design if isinstance(design, PreparedDesign) else prepare_design(design, settings, pool)
        lap("design")
        seg = segment_plate(cloud, passes=passes)
        lap("segment")
        try:
            bnd: BoundaryResult | None = find_corners(seg.points_mm)
        except BoundaryError:
            if nominal_placement is None:
                raise
            bnd = None  # a few passes of a scan cut short: no edge of the plate seen whole
        lap("boundary")
        surface: HeightField = prepared.height_field()
    design, cad, T_design_file = prepared.mesh, prepared.cad, prepared.T_design_file
    design_c = prepared.corners_mm
    nominal = placement_transform(nominal_placement) if nominal_placement is not None else None
    partial = False
    try:
        if bnd is None:
            raise InspectionError("the plate's edges were not found in the scan")
        _check_size(design_c, bnd.corners_mm, settings.size_tolerance)
    except InspectionError as exc:
        # a scan cut short (interrupted, re-analysed from its raw files) saw part of the plate: with
        # the placement it was planned from, report what it saw; else the plain refusal
        seen = seg.points_mm[:: max(1, len(seg.points_mm) // 100_000)] if bnd is None else bnd.corners_mm
        if nominal is None or not _partial_scan(design_c, seen, nominal, settings.size_tolerance):
            raise InspectionError(f"{exc}{PARTIAL_HINT if nominal is None else ''}") from None
        partial = True
        log.warning("partial_scan", reason=str(exc), design_mm=[round(v) for v in _side_lengths(design_c)])
    cell_mm = surface_cell_mm(
        seg.points_mm, seg.plate_area_mm2, settings.grid_mm, settings.min_points_per_cell
    )
    measured_mesh = height_grid_mesh(seg.points_mm, cell_mm)
    lap("surface")
    # The fits run on the reconstructed surface (cell means): every cell of the plate, denoised.
    rests: list[RestSurface] = []

    def rest_on(T_icp: np.ndarray) -> np.ndarray:
        # the design rests on patch estimates of the plate with a bounded noise bias
        rests.append(rest_surface(surface, seg.points_mm, T_icp, target_sigmas=settings.rest_target_sigmas,
                                  max_cell_mm=settings.rest_max_cell_mm))  # fmt: skip
        return rests[-1].points_mm

    if partial:  # the corners were not all seen: the placement's, the surface's height and tilt
        assert nominal is not None
        reg = register_from_placement(
            surface, measured_mesh.vertices_mm, design_c, nominal, rest_points=rest_on
        )
    else:
        reg = register(
            surface,
            measured_mesh.vertices_mm,
            design_c,
            bnd.corners_mm,
            nominal_transform=nominal,
            rest_points=rest_on,
        )
    rest = rests[-1]
    lap("register")

    T = reg.transform  # design -> measured
    if partial:  # the lines of the whole plate, where the registered design's corners lie
        measured_c = design_c @ T[:3, :3].T + T[:3, 3]
    else:
        measured_c = np.roll(bnd.corners_mm, -reg.coarse.shift, axis=0)
    lines = detection_lines(measured_c, settings.layout)
    if cad is not None:
        cuts = cut_templates_exact(cad, T, measured_mesh, lines, step_mm=settings.sample_step_mm)
    else:
        cuts = cut_templates(design.transformed(T), measured_mesh, lines, step_mm=settings.sample_step_mm)
    not_scanned: list[LineNotScanned] = []
    if partial:  # a line the scan did not cover is reported as such, not judged on the part seen
        seen = {(c.line.family, c.line.index): _line_coverage(c) for c in cuts}
        not_scanned = [
            LineNotScanned(name=line_name(ln), family=ln.family, index=ln.index,
                           scanned_fraction=round(seen.get((ln.family, ln.index), 0.0), 3))
            for ln in lines if seen.get((ln.family, ln.index), 0.0) < PARTIAL_LINE_COVERAGE
        ]  # fmt: skip
        cuts = [c for c in cuts if seen[(c.line.family, c.line.index)] >= PARTIAL_LINE_COVERAGE]
    elif not cuts:
        raise InspectionError("no detection line crosses both the design and the scanned plate")
    lap("templates")

    # The sections are cut from cell means: their noise is the points' over the root of a cell's
    # count (estimated from the data; the sections' own second differences miss it, the mesh being
    # linear between its nodes, and the splines would follow the noise)
    section_noise = rest.noise_mm / np.sqrt(len(seg.points_mm) / max(len(measured_mesh.vertices_mm), 1))
    gaps, _, _, valid = deflection_gaps(surface, seg.points_mm, T, geometry=False)
    mode = check_mode(settings.template_fit)
    modes = [mode] + ([m for m in TEMPLATE_FITS if m != mode] if settings.template_fit_compare else [])
    judged: dict[str, tuple[Verdict, list[TemplateCut], list[LineFitResult | None]]] = {}
    for fit_mode in modes:
        fit_cuts, fits = (
            (cuts, [None] * len(cuts))
            if fit_mode == "rigid"
            else _per_line_cuts(cuts, seg.points_mm, np.where(valid, gaps, np.nan), rest.noise_mm)
        )
        metrics, kept, kept_fits = _line_figures(fit_cuts, fits, section_noise)
        if not metrics and not partial:
            raise InspectionError("no detection line has enough scanned samples to be evaluated")
        judged[fit_mode] = (judge(metrics, settings.tolerances), kept, kept_fits)
    verdict, kept, kept_fits = judged[mode]
    if partial:  # lines skipped for too few samples were not scanned either
        judged_keys = {(c.line.family, c.line.index) for c in kept}
        named = {(x.family, x.index) for x in not_scanned}
        not_scanned += [
            LineNotScanned(name=line_name(c.line), family=c.line.family, index=c.line.index, scanned_fraction=0.0)
            for c in cuts if (c.line.family, c.line.index) not in judged_keys | named
        ]  # fmt: skip
    lap("metrics")

    deviation = np.where(valid, gaps, np.nan)
    s_gaps, _, _, s_valid = deflection_gaps(surface, measured_mesh.vertices_mm, T, geometry=False)
    surface_deviation = np.where(s_valid, s_gaps, np.nan)
    sigma = max(seg.noise_sigma_mm, 1e-6)
    raw_below = int(np.count_nonzero(valid & (gaps < -4.0 * sigma)))
    T_design_measured = invert_transform(T)
    # Coverage from the reconstructed surface: its cells are finer than the hole cells.
    surf_design = measured_mesh.vertices_mm @ T_design_measured[:3, :3].T + T_design_measured[:3, 3]
    coverage, holes_design = _coverage_holes(design, surf_design[:, :2], HOLE_CELL_MM)
    T_plate_design = plate_frame(design_c)
    holes_plate = holes_design @ T_plate_design[:2, :2].T + T_plate_design[:2, 3]
    lap("deviation_map")

    T_plate_measured = T_plate_design @ T_design_measured
    line_records: list[LineReport] = []
    for m, cut, line_fit in zip(verdict.lines, kept, kept_fits, strict=True):
        ends = np.vstack([cut.line.start_mm, cut.line.end_mm])
        ends_plate = ends @ T_plate_measured[:3, :3].T + T_plate_measured[:3, 3]
        line_records.append(
            LineReport.model_validate(
                {
                    **m.as_dict(),
                    "name": line_name(cut.line),
                    "start_plate_mm": [round(float(v), 2) for v in ends_plate[0, :2]],
                    "end_plate_mm": [round(float(v), 2) for v in ends_plate[1, :2]],
                    "noise_mm": m.noise_mm,
                    "line_fit": None if line_fit is None else LineFitReport(**line_fit.as_dict()),
                }
            )
        )

    plate_l, plate_w = _side_lengths(design_c)
    # a partial scan never passes: it fails on a line that fails, else it is incomplete
    verdict_text = verdict.verdict
    if partial:  # even with every line seen for 90 % of its length: the rest was not
        verdict_text = "fail" if verdict.failed else "incomplete"
    compare = None
    for other in modes[1:]:
        v, other_cuts, _ = judged[other]
        compare = TemplateFitCompare(
            template_fit=other,
            verdict=v.verdict,
            lines=[  # named as the main table names them (a template table's names, else T3, L1, ...)
                CompareLine(name=line_name(cut.line), family=m.family, index=m.index, sz_avg_mm=m.sz_avg_mm,
                            zmax_mm=m.zmax_mm, cmax_per_mm=m.cmax_per_mm, grade=m.grade, passed=m.passed)
                for m, cut in zip(v.lines, other_cuts, strict=True)
            ],
        )  # fmt: skip
    timings["total"] = round(sum(v for k, v in timings.items() if k != "total"), 4)
    given = inputs or ReportInputs(points=0)
    report = Report(
        plate_id=plate_id,
        job_id=job_id,
        cell_id=cell_id,
        created_utc=datetime.now(UTC).isoformat(timespec="seconds"),
        verdict=verdict_text,
        standard=settings.tolerances.standard,
        template_fit=mode,
        template_fit_compare=compare,
        registration=RegistrationReport(
            coarse_rms_mm=reg.coarse_rms_mm,
            icp_rms_mm=reg.icp.rms_mm,
            nonpen_rms_mm=reg.nonpenetrating.rms_mm,
            penetration_points=reg.penetration_points,
            penetration_points_before=reg.nonpenetrating.penetrating_before,
            surface_points=len(measured_mesh.vertices_mm),
            surface_cell_mm=cell_mm,
            raw_points_below_4sigma=raw_below,
            rest_surface=RestSurfaceReport(**rest.as_dict()),
            transform=T.tolist(),
            corner_shift=reg.coarse.shift,
            candidates_icp_rms_mm={str(k): v for k, v in reg.candidates.items()},
        ),
        corners_mm=measured_c.tolist(),
        plate_size_mm=[plate_l, plate_w],
        lines=line_records,
        tolerances=settings.tolerances,
        coverage=ScanCoverage(
            fraction=coverage,
            holes_mm2=float(len(holes_design) * HOLE_CELL_MM**2),
            partial=partial,
            lines_not_scanned=not_scanned,
        ),
        surface=SurfaceReport(
            points=len(seg.points_mm),
            noise_sigma_mm=seg.noise_sigma_mm,
            max_deviation_mm=float(np.nanmax(deviation)) if np.isfinite(deviation).any() else None,
        ),
        inputs=given.model_copy(update={"points": len(cloud), "placement": nominal_placement}),
        design=_design_record(cad, T_design_file).model_copy(
            update={
                "side": settings.design_side,
                "thickness_mm": settings.thickness_mm if settings.design_side == "moulded_down" else None,
            }
        ),
        timings_s=timings,
    )
    log.info("inspected", verdict=verdict.verdict, lines=len(line_records), worst_zmax_mm=round(verdict.worst_zmax_mm, 3),
             total_s=timings["total"])  # fmt: skip
    return Inspection(
        report=report,
        plate_points_mm=seg.points_mm,
        deviation_mm=deviation,
        surface_points_mm=measured_mesh.vertices_mm,
        surface_deviation_mm=surface_deviation,
        T_measured_design=T,
        T_plate_design=T_plate_design,
        plate_size_mm=(plate_l, plate_w),
        cuts=kept,
        coverage_holes_xy_mm=holes_plate,
        segment=seg,
        boundary=bnd,
        registration=reg,
        verdict=verdict,
        timings_s=timings,
    )


def _design_record(cad: CadDesign | None, T_design_file: np.ndarray | None = None) -> DesignReport:
    """What the report says about the design: a mesh (and how it was moved into its own frame, if
    it was given in another pose), or the CAD file's format, units and faces."""
    if cad is None:
        moved = T_design_file is not None and not np.array_equal(T_design_file, np.eye(4))
        return DesignReport(kind="mesh", T_design_file=T_design_file.tolist() if moved else None)
    return DesignReport(
        kind="cad",
        format=cad.facts.fmt,
        file_units=cad.facts.units,
        faces=len(cad.faces),
        chord_error_mm=round(cad.chord_error_mm, 5),
        templates="exact surface",
        T_design_file=cad.T_design_file.tolist(),
    )


# ------------------------------------------------------------------------------------ results dir


def _moved_float32(T: np.ndarray, points_mm: np.ndarray, block: int = 1 << 20) -> np.ndarray:
    """(n, 3) float32 ``points_mm`` (n, 3) moved by the 4x4 ``T``: transformed in float64 a block at a
    time and stored in the file's float32 (the same values as a float64 transform cast at the end,
    without its 24 bytes a point)."""
    out = np.empty((len(points_mm), 3), np.float32)
    for lo in range(0, len(points_mm), block):
        out[lo : lo + block] = apply_transform(T, points_mm[lo : lo + block])
    return out


def write_results(ins: Inspection, out_dir: str | Path) -> dict[str, Path]:
    """Store an inspection as a results directory; returns the written files by name.

    cloud.ply holds the plate's points in the design frame (registered), with their deviation
    (``scalar_deviation``, float32 mm, NaN where off the design); lines-ship.csv the judged lines'
    ends in the design file's frame (:mod:`analysis.export`).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files: dict[str, Path] = {}
    T_dm = invert_transform(ins.T_measured_design)
    pts_design = _moved_float32(T_dm, ins.plate_points_mm)
    files["cloud.ply"] = write_cloud_ply(
        ScanCloud(pts_design), out / "cloud.ply", extra={"scalar_deviation": ins.deviation_mm.astype(np.float32)},
        comment=f"cellctl registered cloud; frame: {DESIGN_FRAME.text()}; scalar_deviation mm "
        "(z_design - z_measured), NaN off the design",
    )  # fmt: skip
    # the judged lines' ends in the design file's frame (the ship's coordinates), for the yard's CAD
    ends = np.array([[c.line.start_mm, c.line.end_mm] for c in ins.cuts], dtype=np.float64).reshape(-1, 3)
    files["lines-ship.csv"] = write_lines_ship(
        out / "lines-ship.csv", ins.report, apply_transform(T_dm, ends)
    )

    # The map shows the reconstructed surface (denoised cell means), not single noisy points.
    T_pm = ins.T_plate_design @ T_dm
    surf_plate = ins.surface_points_mm @ T_pm[:3, :3].T + T_pm[:3, 3]
    idx = _subsample_index(len(surf_plate), MAX_MAP_POINTS)
    ok = np.isfinite(ins.surface_deviation_mm[idx])
    arrays = ResultsArrays(
        plate_xy_mm=surf_plate[idx][ok, :2],
        plate_deviation_mm=ins.surface_deviation_mm[idx][ok],
        plate_size_mm=np.asarray(ins.plate_size_mm, dtype=np.float64),
        lines=[
            LineSeries(cut.s_mm, cut.design_h_mm, cut.measured_h_mm, cut.design_h_mm - cut.measured_h_mm)
            for cut in ins.cuts
        ],
        holes_xy_mm=ins.coverage_holes_xy_mm,
    )
    files["results.npz"] = arrays.save(out / "results.npz")
    files["report.csv"] = write_csv(ins.report, out / "report.csv")
    # report.json last: its presence marks a complete results directory.
    write_report_json(ins.report, out / "report.json")
    files["report.json"] = out / "report.json"
    return files


# ------------------------------------------------------------------------------------- worker API


def _read_job_design(job: AnalysisJob) -> TriMesh | CadDesign:
    try:
        return read_design(job.design)
    except MeshError as exc:
        raise InspectionError(str(exc)) from None


def _inspect_job(cloud: ScanCloud, design: TriMesh | CadDesign | PreparedDesign, job: AnalysisJob,
                 passes: dict[int, PassCells] | None = None) -> Report:  # fmt: skip
    ins = inspect_cloud(
        cloud, design, job.settings, nominal_placement=job.placement,
        plate_id=job.plate_id, job_id=job.job_id, cell_id=job.cell_id,
        inputs=ReportInputs(points=0, design=job.design, placement_found=job.placement_found), passes=passes,
    )  # fmt: skip
    if job.out_dir:
        write_results(ins, job.out_dir)
    return ins.report


def analyse_job(cloud: ScanCloud, job: AnalysisJob) -> Report:
    """Worker entry point: ``cloud`` the scan (organised or not), ``job`` the job's parameters
    (design, nominal placement, settings, ``out_dir``).

    Returns the :class:`~analysis.contracts.job.Report`; with ``out_dir`` also
    writes the results directory there. ``analyse_job.stream`` is the same analysis for a cloud
    that arrives in chunks (:class:`CloudStream`).
    """
    return _inspect_job(cloud, _read_job_design(job), job)


def concat_clouds(chunks: list[ScanCloud]) -> ScanCloud:
    """Clouds one after the other (all organised, or none; times kept only when every one has them)."""
    if not chunks:
        raise InspectionError("the cloud is empty: no chunk arrived")
    if len(chunks) == 1:
        return chunks[0]
    cat = lambda name: np.concatenate([getattr(c, name) for c in chunks])  # noqa: E731
    organised = all(c.organised for c in chunks)
    return ScanCloud(
        cat("xyz_mm"),
        *((cat("pass_id"), cat("profile_index"), cat("point_index")) if organised else (None, None, None)),
        t_s=cat("t_s") if all(c.t_s is not None for c in chunks) else None,
    )


class GrowingCloud:
    """The chunks of a stream concatenated as they arrive, into arrays that grow by half (amortised:
    each point is copied about three times over the scan, while the scan runs), so the end of the
    stream costs a view and not a copy of the whole cloud. The same arrays as :func:`concat_clouds`
    of the chunks: organised only when every chunk is, times only when every chunk has them. The
    cloud's arrays are views of the buffers, which hold up to half again as many rows."""

    _FIELDS = ("xyz_mm", *ORGANISATION, "t_s")

    def __init__(self) -> None:
        self._n = 0
        self._chunks = 0
        self._arrays: dict[str, np.ndarray | None] = dict.fromkeys(self._FIELDS)
        self._dropped: set[str] = set()

    def append(self, chunk: ScanCloud) -> None:
        m = len(chunk)
        self._chunks += 1
        for name in self._FIELDS:
            a = getattr(chunk, name)
            if a is None or name in self._dropped:
                self._dropped.add(name)
                self._arrays[name] = None
                continue
            buf = self._arrays[name]
            if buf is None or len(buf) < self._n + m:
                grown = np.empty((max(self._n + m, int(1.5 * self._n), 1024), *a.shape[1:]), a.dtype)
                if buf is not None:
                    grown[: self._n] = buf[: self._n]
                buf = self._arrays[name] = grown
            buf[self._n : self._n + m] = a
        self._n += m

    @property
    def fields(self) -> frozenset[str]:
        """The fields the cloud keeps (a chunk without times drops them from the whole cloud)."""
        return frozenset(f for f in self._FIELDS if f not in self._dropped)

    def cloud(self) -> ScanCloud:
        if self._chunks == 0:
            raise InspectionError("the cloud is empty: no chunk arrived")
        n, a = self._n, self._arrays
        organised = all(name not in self._dropped for name in ORGANISATION)
        xyz = a["xyz_mm"]
        assert xyz is not None
        return ScanCloud(
            xyz[:n],
            *((a[k][:n] for k in ORGANISATION) if organised else (None, None, None)),  # type: ignore[index]
            t_s=None if "t_s" in self._dropped else a["t_s"][:n],  # type: ignore[index]
        )


class CloudStream:
    """The analysis of a cloud that arrives in chunks while the plate is scanned (the daemon cuts
    the scan's rows, in time order, where a pass ends): whatever does not need the whole cloud is
    done as the chunks arrive, :meth:`finish` runs the rest.

    At the start the design is read, framed and rasterised (on a second thread); :meth:`add` takes
    the chunks in order and segments each pass they complete into cells and regions
    (:func:`analysis.segment.pass_cells`; pass 0, which files the transit of the whole scan, waits
    for the end, and a pass seen again in a later chunk is made again at the end) and copies them
    onto the end of the cloud so far (:class:`GrowingCloud`), so :meth:`finish` holds the chunks
    concatenated -- the cloud the daemon would have sent whole, point for point -- and
    runs :func:`inspect_cloud` with the prepared design and those cells: the same functions on the
    same arrays as the whole-cloud analysis, so the figures are its figures.

    :meth:`ahead` runs that analysis before the stream has ended, once the sender says every pass
    is in (the arm still retracts, and the rows of the retract seldom hold a point): its report
    stands if the rest of the stream adds no point and changes no field of the cloud -- the cloud
    :meth:`finish` would analyse is then the same arrays -- else :meth:`finish` analyses again."""

    def __init__(self, job: AnalysisJob) -> None:
        self.job = job
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="design-field")
        self.prepared = prepare_design(_read_job_design(job), job.settings, self._pool)
        self._cloud = GrowingCloud()
        self._cells: dict[int, PassCells | None] = {}
        self._seen: set[int] = set()
        self._points = 0
        # the report made by ahead() and the cloud it was made of: (points, fields kept), report
        self._ahead: tuple[tuple[int, frozenset[str]], Report] | None = None
        self.timings_s: dict[str, float] = {"pass_cells": 0.0}

    def add(self, chunk: ScanCloud) -> None:
        """The next chunk of the cloud (in order); the passes in it segmented into cells."""
        t0 = time.perf_counter()
        self._cloud.append(chunk)
        offset, self._points = self._points, self._points + len(chunk)
        if self._ahead is not None and self._ahead[0] != self._state():
            self._ahead = None  # the cloud changed: the report made ahead is not its report
            self.timings_s["ahead_dropped"] = 1.0
        if chunk.organised and len(chunk):
            pid = chunk.pass_id
            for k in np.unique(pid).tolist():
                if k in self._seen:  # a pass across chunks: its cells are made from the whole cloud
                    self._cells.pop(k, None)
                    continue
                self._seen.add(k)
                if k == 0:
                    continue  # the transit of the whole scan is filed under pass 0
                local = np.nonzero(pid == k)[0]
                self._cells[k] = pass_cells(
                    chunk.xyz_mm[local], chunk.profile_index[local], chunk.point_index[local], local + offset
                )
        self.timings_s["pass_cells"] += round(time.perf_counter() - t0, 4)

    @property
    def points(self) -> int:
        return self._points

    def _state(self) -> tuple[int, frozenset[str]]:
        return self._points, self._cloud.fields

    def _analyse(self) -> Report:
        t0 = time.perf_counter()
        cloud = self._cloud.cloud()
        self.prepared.height_field()  # raises the rasterisation's error, if any
        self.timings_s["concat"] = round(time.perf_counter() - t0, 4)
        cells = {k: c for k, c in self._cells.items() if c is not None}
        return _inspect_job(cloud, self.prepared, self.job, cells)

    def ahead(self) -> None:
        """Every pass is in: analyse the cloud so far now, ahead of the stream's end. The report is
        kept for :meth:`finish` while no later chunk changes the cloud; an analysis that fails here
        is left to :meth:`finish`, which runs it again and raises its error."""
        t0 = time.perf_counter()
        state = self._state()
        try:
            report = self._analyse()
        except Exception as exc:
            log.info("analysis_ahead_failed", job_id=self.job.job_id, error=str(exc)[:200])
            return
        self._ahead = (state, report)
        self.timings_s["ahead"] = round(time.perf_counter() - t0, 4)

    def finish(self) -> Report:
        """The report of the whole cloud (and the results directory with ``job.out_dir``): the one
        made by :meth:`ahead` when the cloud has not changed since, else made now."""
        try:
            if self._ahead is not None and self._ahead[0] == self._state():
                self.timings_s["ahead_kept"] = 1.0
                return self._ahead[1]
            return self._analyse()
        finally:
            self.close()

    def close(self) -> None:
        """Drop the chunks and stop the design thread (a cancelled stream)."""
        self._cloud = GrowingCloud()
        self._cells = {}
        self._ahead = None
        self._pool.shutdown(wait=False, cancel_futures=True)


analyse_job.stream = CloudStream  # type: ignore[attr-defined]
