"""The locate run's plans and verdicts: where the passes go, how the cloud is read, when a given
placement is refused.

The passes are planned by the scan planner (:func:`cellctl.planning.plan_scan`, its public API) as
the coverage of a flat "bed plate" at the locate height (:func:`locate_height_mm`: ``[locate]
standoff_mm`` above the design's highest edge) minus the planner's own standoff: the planner then flies the sensor, looking straight down, at the
locate height; its pass step is the locate pass spacing (line width = spacing, no overlap), no
edge passes, no placement margin, at the locate speed. The planner runs its passes along the longer
side of what it covers, so two plans make the two families: the whole bed (passes along its longer
side) and the square on its shorter side at its middle, turned a quarter (passes across). Every
edge of a plate lying on the bed is crossed by one family or the other.

The passes across are planned from the first fit where there is one (:func:`across_plans`): the
passes along pin the plate's yaw and where it lies along the bed (from the edges they cross), and
leave it sliding across. Where a pass across the bed meets the design's outline then depends on
that fit only, not on the slide, so each pass across flies at the height of the outline it will
cross (``[locate] standoff_mm`` above it) rather than above the design's highest edge: on a deep
plate (a 6 m sail whose long edges fall 225 mm from its corners to their middles, under a sensor
that sees 60 mm) one height for the whole bed cannot see them all. ``[locate] across_passes``
passes at 20 .. 80 % of the plate's extent along the bed, each across the whole bed, each its own
plan. :func:`next_locate_plans` is the order of the run.

The cloud is read by :mod:`analysis.register.locate`; this module only turns ``[locate]`` into its settings
and decides on a given placement.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import structlog

from analysis.contracts.placement import Placement, placement_transform
from analysis.design.mesh import TriMesh
from analysis.design.outline import mesh_free_edges
from analysis.design.plates import design_mesh, plate_spec
from analysis.register.locate import LocateResult, LocateSettings, placement_offset
from cellctl.config import CellConfig
from cellctl.planning import (
    PlanInputError,
    PlannerSettings,
    PlanRefused,
    ScanPlan,
    plan_scan,
    start_corner_near,
)

__all__ = [
    "LocatePlan",
    "across_plans",
    "design_min_width_mm",
    "face_down_refusal",
    "given_placement_refusal",
    "locate_height_mm",
    "locate_plans",
    "locate_settings",
    "needs_across",
    "next_locate_plans",
]

log = structlog.get_logger(__name__)

# how far beyond the laser line's half width a pass across counts the outline as its own (mm):
# the first fit's yaw and position along the bed are good to about a millimetre
_ACROSS_STRIP_MARGIN_MM = 25.0
# the passes across run this far beyond the bed's sides, so that they start and end off any plate
_ACROSS_OVERRUN_MM = 50.0
# the sensor's lean along a pass across, beyond the cell's sweep_pitch_deg, tried in turn (deg)
_ACROSS_EXTRA_PITCH_DEG = (0.0, 10.0, 20.0)


@dataclass(frozen=True)
class LocatePlan:
    """One run of locate passes: its name, its plan, the planner settings it was made with, and the
    world z range (lowest, highest) the sensor measures on its passes (where an edge point is the
    surface leaving the range, not the plate's edge)."""

    name: str
    plan: ScanPlan
    settings: PlannerSettings
    range_z_mm: tuple[float, float]
    across: bool

    @classmethod
    def of(
        cls, cfg: CellConfig, name: str, plan: ScanPlan, settings: PlannerSettings, *, across: bool
    ) -> LocatePlan:
        """``plan``'s locate plan (``across``: passes across the bed, the run's second part), its
        range from its passes' sensor poses (a leaning sensor sees its depth range foreshortened in z)."""
        las = cfg.laser
        pos = np.concatenate([seg.pos_mm for seg in plan.passes])
        axis_z = np.concatenate([seg.R_base_sensor[:, 2, 2] for seg in plan.passes])  # < 0: looking down
        lo = float(np.min(pos[:, 2] + las.depth_max_mm * axis_z))
        hi = float(np.max(pos[:, 2] + las.depth_min_mm * axis_z))
        return cls(name, plan, settings, (lo, hi), across)


def _flat(length_mm: float, width_mm: float) -> TriMesh:
    return design_mesh(plate_spec("flat", length_mm=length_mm, width_mm=width_mm), pitch_mm=50.0)


def locate_height_mm(cfg: CellConfig, design: TriMesh) -> float:
    """World z of the sensor origin on the locate passes: ``[locate] standoff_mm`` above the design's
    highest edge (the plate lying at ``[scan] placement_z_mm``), so that its edges are in the depth
    range below; never nearer than the sensor's ``depth_min_mm`` to the design's highest point."""
    edge_z = float(design_outline_z_mm(design).max())
    top_z = float(design.vertices_mm[:, 2].max())
    clear = max(edge_z + cfg.locate.standoff_mm, top_z + cfg.laser.depth_min_mm)
    return cfg.scan.placement_z_mm + clear


def design_outline_z_mm(design: TriMesh) -> np.ndarray:
    """Heights (design frame, mm) of the vertices on the design's outline: every free edge's
    (:func:`analysis.design.outline.mesh_free_edges`, holes' edges included); every vertex's for a closed
    mesh (no free edge)."""
    return design.vertices_mm[_outline_vertices(design), 2]


def _outline_vertices(design: TriMesh) -> np.ndarray:
    """Indices of the vertices on the design's outline (every vertex for a closed mesh)."""
    edges, _ = mesh_free_edges(design)
    return np.unique(edges) if len(edges) else np.arange(len(design.vertices_mm))


def _planner_settings(cfg: CellConfig) -> PlannerSettings:
    """The scan planner's settings for locate passes: flat, at the locate speed, no edge passes."""
    loc = cfg.locate
    return PlannerSettings.from_config(cfg).with_(
        line_width_mm=loc.pass_spacing_mm,
        overlap_fraction=0.0,
        speed_mm_s=loc.speed_mm_s,
        edge_passes=False,
        placement_uncertainty_mm=0.0,
        placement_uncertainty_deg=0.0,
        # the locate passes span the whole bed: a turnaround flown beyond its ends would leave the
        # arm's reach (the default bed: joint 3 at 73.02 deg on link 2); they stop and go, as before
        flying_turns=False,
        # each locate plan is a strip of the bed whose passes run along it, as the run intends
        pass_axis="longer",
    )


def _bed(cfg: CellConfig) -> tuple[np.ndarray, np.ndarray, int]:
    """(bed's lower corner, its upper corner, the index of its longer axis: 0 x, 1 y)."""
    lo, hi = np.asarray(cfg.locate.bed_min_xy_mm), np.asarray(cfg.locate.bed_max_xy_mm)
    return lo, hi, int(np.argmax(hi - lo))


def locate_plans(cfg: CellConfig, design: TriMesh) -> list[LocatePlan]:
    """The two families of locate passes for ``design`` at the locate height: along the whole bed,
    and across the square at its middle (raises the planner's PlanRefused / PlanInputError)."""
    return [_along_plan(cfg, design), _across_square_plan(cfg, design)]


#: the passes along cross every plate lying on the bed at least this many times
LOCATE_MIN_CROSSINGS = 2
#: ... each crossing this far inside the plate's narrowest extent (mm): the laser line's width
_CROSSING_MARGIN_MM = 50.0


def design_min_width_mm(design: TriMesh) -> float:
    """The design's narrowest extent in plan (mm): the least width of its outline over directions
    (1 deg apart, less 0.1 % for the directions between)."""
    xy = design.vertices_mm[_outline_vertices(design), :2]
    a = np.deg2rad(np.arange(180.0))
    widths = np.ptp(xy @ np.stack([np.cos(a), np.sin(a)]), axis=0)
    return float(widths.min()) * 0.999


def _fewest_passes(bed_width_mm: float, spacing_mm: float, plate_width_mm: float) -> tuple[int, float]:
    """How many passes along the bed, and the planner's line width (their step) for them: the
    fewest that cross every lay of a plate ``plate_width_mm`` across (its narrowest extent, less the
    crossing margin; wholly on the bed) at least :data:`LOCATE_MIN_CROSSINGS` times, where that is
    fewer than ``[locate] pass_spacing_mm`` gives; else those (``spacing_mm``).

    The planner puts n passes of line width w at ``linspace(w / 2, B - w / 2, n)`` across the bed
    (B wide, n = ceil((B - w) / w) + 1); a plate's extent across is an interval at least its width
    long inside [0, B], and the passes it certainly covers are counted over every such interval."""
    n_cfg = 1 if bed_width_mm <= spacing_mm else int(np.ceil((bed_width_mm - spacing_mm) / spacing_mm)) + 1
    w_plate = plate_width_mm - 2 * _CROSSING_MARGIN_MM
    if w_plate <= 0 or w_plate > bed_width_mm:
        return n_cfg, spacing_mm
    starts = np.linspace(0.0, bed_width_mm - w_plate, 2001)
    for n in range(LOCATE_MIN_CROSSINGS, n_cfg):
        w = bed_width_mm / n * (1 + 1e-9)
        centres = np.linspace(w / 2, bed_width_mm - w / 2, n)
        inside = (centres[None] >= starts[:, None]) & (centres[None] <= starts[:, None] + w_plate)
        if inside.sum(axis=1).min() >= LOCATE_MIN_CROSSINGS:
            return n, w
    return n_cfg, spacing_mm


def _bed_family(
    cfg: CellConfig, design: TriMesh, name: str, square: bool, start_axes: np.ndarray | None = None
) -> LocatePlan:
    settings = _planner_settings(cfg)
    lo, hi, long_axis = _bed(cfg)
    centre, size = (lo + hi) / 2, hi - lo
    if not square:
        # the fewest passes along that still cross the plate twice, wherever it lies (a 6 m plate on
        # a 2.1 m wide bed: 2 passes where 350 mm spacing made 6)
        n, w = _fewest_passes(float(size.min()), cfg.locate.pass_spacing_mm, design_min_width_mm(design))
        settings = settings.with_(line_width_mm=w)
        log.debug("locate_along_passes", passes=n, step_mm=round(w, 1))
    # the "bed plate"'s top lies the planner's standoff below the locate height
    z = _bed_plate_z_mm(locate_height_mm(cfg, design), settings)
    yaw_long = 0.0 if long_axis == 0 else 90.0
    L, W = float(size.max()), float(size.min())
    # the square: the planner's passes along its x, turned a quarter (across the bed)
    mesh, yaw = (_flat(W, W), yaw_long + 90.0) if square else (_flat(L, W), yaw_long)
    placement = Placement.on_bed(float(centre[0]), float(centre[1]), yaw, z_mm=z)
    if start_axes is not None:
        # the passes start at the bed's corner nearest the arm, as the scan's do (the shortest
        # move to the run's start); an arm the planner cannot place leaves its default corner
        try:
            settings = settings.with_(start_corner=start_corner_near(mesh, placement, settings, start_axes))
        except PlanInputError as exc:
            log.warning("locate_start_corner_unknown", reason=str(exc))
    plan = plan_scan(mesh, placement, settings, with_coverage=False)
    return LocatePlan.of(cfg, name, plan, settings, across=square)


def _bed_plate_z_mm(sensor_z_mm: float, settings: PlannerSettings) -> float:
    """The z of the flat "bed plate" the planner covers so that the sensor flies at ``sensor_z_mm``:
    the planner puts it its standoff from the surface along its axis, leaning ``sweep_pitch_deg``."""
    return sensor_z_mm - settings.standoff_mm * float(np.cos(np.deg2rad(settings.sweep_pitch_deg)))


def _along_plan(cfg: CellConfig, design: TriMesh, start_axes: np.ndarray | None = None) -> LocatePlan:
    return _bed_family(cfg, design, "locate along", square=False, start_axes=start_axes)


def _across_square_plan(cfg: CellConfig, design: TriMesh) -> LocatePlan:
    return _bed_family(cfg, design, "locate across", square=True)


def _world_design(cfg: CellConfig, design: TriMesh, found: LocateResult) -> tuple[np.ndarray, np.ndarray]:
    """(outline vertices, all vertices) of ``design`` in the world under the fit ``found``, its z
    taken at ``[scan] placement_z_mm`` as the locate height's (a first fit's z is only as good as
    its slide)."""
    pl = found.placement.model_copy(
        update={"pos_mm": [found.placement.x_mm, found.placement.y_mm, cfg.scan.placement_z_mm]}
    )
    T = placement_transform(pl)
    world = design.vertices_mm @ T[:3, :3].T + T[:3, 3]
    return world[_outline_vertices(design)], world


def across_plans(
    cfg: CellConfig, design: TriMesh, found: LocateResult, start_near_xy_mm: np.ndarray | None = None
) -> list[LocatePlan]:
    """Passes across the bed planned from a first fit (see the module docstring): ``[locate]
    across_passes`` passes at 20 .. 80 % of the plate's extent along the bed, each over the whole
    bed's width and ``_ACROSS_OVERRUN_MM`` beyond, flown ``[locate] standoff_mm`` above the highest
    outline point in its strip (never nearer than ``[laser] depth_min_mm`` to the design there);
    one plan each. ``start_near_xy_mm``: where the arm is (the last run's end, world x-y): the
    passes go from the nearest, each starting at the bed's side nearer the previous one's end.

    Raises:
        PlanRefused, PlanInputError: the planner's, for a pass it cannot fly.
    """
    loc, las = cfg.locate, cfg.laser
    settings = _planner_settings(cfg)
    lo, hi, long_axis = _bed(cfg)
    u = np.eye(2)[long_axis]  # along the bed (the first family's passes)
    v_axis = 1 - long_axis
    outline, vertices = _world_design(cfg, design, found)
    w_out, w_all = outline[:, :2] @ u, vertices[:, :2] @ u
    n = loc.across_passes
    fractions = np.array([0.5]) if n == 1 else np.linspace(0.2, 0.8, n)
    positions = float(w_out.min()) + fractions * float(np.ptp(w_out))
    half = las.line_width_mm / 2 + _ACROSS_STRIP_MARGIN_MM
    heights = []
    for s in positions:
        edge = outline[np.abs(w_out - s) <= half, 2]
        top = vertices[np.abs(w_all - s) <= half, 2]
        edge_top = float(edge.max()) if len(edge) else float(outline[:, 2].max())
        heights.append(max(edge_top + loc.standoff_mm, float(top.max(initial=edge_top)) + las.depth_min_mm))
    # the flat strip's x (its one pass, which the planner flies from its -x end) along +v, or -v
    yaw_up = 0.0 if v_axis == 0 else 90.0
    # the sensor's lean along these passes: the cell's, then more where the wrist would pass near its
    # singularity (a pass across the bed runs towards the arm's base, lower than the passes along)
    pitches = [p for p in (settings.sweep_pitch_deg + d for d in _ACROSS_EXTRA_PITCH_DEG) if p < 45.0]
    # one after the other from where the arm is: the nearest pass first, each starting at the end of
    # the bed nearer the previous one's end (the move to a pass's start is a straight line in joint
    # space: from the far corner of the bed it can dip below the workspace box)
    prev = None if start_near_xy_mm is None else np.asarray(start_near_xy_mm, dtype=np.float64)
    order = (
        np.arange(n)
        if prev is None or abs(prev @ u - positions[0]) <= abs(prev @ u - positions[-1])
        else np.arange(n)[::-1]
    )
    out = []
    for k in order:
        s_k, h = float(positions[k]), heights[k]
        centre = np.empty(2)
        centre[long_axis] = s_k
        centre[v_axis] = (lo[v_axis] + hi[v_axis]) / 2
        up_first = prev is None or abs(prev[v_axis] - lo[v_axis]) <= abs(prev[v_axis] - hi[v_axis])
        # the way it runs: up (+v) or down; the strip turned half a turn leans the sensor the other way
        ways = [
            (yaw_up, not up_first),
            (yaw_up + 180.0, up_first),
            (yaw_up, up_first),
            (yaw_up + 180.0, not up_first),
        ]
        refused: PlanRefused | None = None
        for (yaw, reverse), pitch, overrun in itertools.product(
            ways, list(pitches), (_ACROSS_OVERRUN_MM, 0.0)
        ):
            st = settings.with_(sweep_pitch_deg=pitch, passes_reversed=reverse)
            placement = Placement.on_bed(float(centre[0]), float(centre[1]), yaw, z_mm=_bed_plate_z_mm(h, st))
            # past the bed's sides by the overrun, or (at the end of the arm's reach) the bed only
            strip = _flat(float(hi[v_axis] - lo[v_axis]) + 2 * overrun, las.line_width_mm)
            try:
                plan = plan_scan(strip, placement, st, with_coverage=False)
            except PlanRefused as exc:
                refused = exc
                continue
            out.append(LocatePlan.of(cfg, f"locate across {len(out) + 1}", plan, st, across=True))
            pitches.insert(0, pitches.pop(pitches.index(pitch)))  # the next pass tries it first
            prev = plan.passes[-1].pos_mm[-1, :2]
            break
        else:
            assert refused is not None
            raise refused
    return out


def next_locate_plans(
    cfg: CellConfig,
    design: TriMesh,
    run: list[LocatePlan],
    found: LocateResult | None,
    start_axes: np.ndarray | None = None,
) -> list[LocatePlan]:
    """The locate plans to run next, given those ``run`` so far and the fit of their clouds
    (None: no fit yet, or it failed); ``[]``: the run is over.

    First the family along the bed, from the bed's corner nearest the arm when ``start_axes`` (the
    arm's axes as the controller reports them: (6,) deg, or (7,) the track's mm first) is given. Then, when :func:`needs_across` says so (or there is no fit),
    passes across: planned from the first fit (:func:`across_plans`) where there is one, else (or
    when the planner refuses them) the square family at the bed's middle. Nothing after passes
    across.

    Raises:
        PlanRefused, PlanInputError: the planner's, for the families over the bed.
    """
    if not run:
        return [_along_plan(cfg, design, start_axes)]
    if any(lp.across for lp in run):
        return []
    if found is not None and not needs_across(cfg, found):
        return []
    if found is not None:
        try:
            return across_plans(cfg, design, found, run[-1].plan.passes[-1].pos_mm[-1, :2])
        except (PlanRefused, PlanInputError) as exc:
            log.warning(
                "locate_across_planned_refused", reason=str(exc), fallback="locate across the bed's middle"
            )
    return [_across_square_plan(cfg, design)]


def locate_settings(cfg: CellConfig, design: TriMesh, yaw_hint_deg: float | None) -> LocateSettings:
    """:class:`analysis.register.locate.LocateSettings` of ``[locate]``, the sensor range at the locate height."""
    loc, las = cfg.locate, cfg.laser
    h = locate_height_mm(cfg, design)
    z = design.vertices_mm[:, 2]
    z0 = cfg.scan.placement_z_mm
    return LocateSettings(
        bed_z_mm=loc.bed_z_mm,
        min_height_mm=loc.min_height_mm,
        plate_z_mm=(z0 + float(z.min()) - loc.plate_band_mm, z0 + float(z.max()) + loc.plate_band_mm),
        # passes at the locate height; a LocatePlan's own range_z_mm where passes fly at their own
        range_z_mm=(h - las.depth_max_mm, h - las.depth_min_mm),
        yaw_hint_deg=yaw_hint_deg,
        convention_yaw_deg=loc.convention_yaw_deg,
        allow_face_down=loc.allow_face_down,
        max_rms_mm=loc.max_rms_mm,
    )


def needs_across(cfg: CellConfig, found: LocateResult) -> bool:
    """Whether the passes across should run after those along: the first fit slides along one
    direction, or the plate's outline (taken as its design's x / y edges) lies within ``[locate]
    across_within_deg`` of square to the first passes. An edge crossed square-on is seen only to a
    profile's spacing along the pass (a step of 1 mm at 225 mm/s and 200 Hz): a short plate's yaw
    then needs the edges the other family crosses."""
    if not found.constrained:
        return True
    lo, hi = np.asarray(cfg.locate.bed_min_xy_mm), np.asarray(cfg.locate.bed_max_xy_mm)
    pass_yaw = 0.0 if (hi - lo)[0] >= (hi - lo)[1] else 90.0
    d = (found.placement.yaw_deg - pass_yaw) % 90.0
    return min(d, 90.0 - d) < cfg.locate.across_within_deg


def given_placement_refusal(cfg: CellConfig, found: LocateResult, given: Placement) -> str | None:
    """Why a given placement is refused (the operator reads it), or None when it holds."""
    loc = cfg.locate
    d_mm, d_deg = placement_offset(found.placement, given)
    if d_mm <= loc.max_offset_mm and d_deg <= loc.max_angle_deg:
        return None
    f = found.placement
    return (
        f"the given placement (x {given.x_mm:.1f}, y {given.y_mm:.1f} mm, yaw {given.yaw_deg:.2f} deg) is "
        f"{d_mm:.1f} mm and {d_deg:.2f} deg from where the plate was found (x {f.x_mm:.1f}, "
        f"y {f.y_mm:.1f} mm, yaw {f.yaw_deg:.2f} deg; outline fit RMS {found.rms_mm:.2f} mm); "
        f"[locate] allows {loc.max_offset_mm:g} mm / {loc.max_angle_deg:g} deg. Check how the plate lies, "
        "or trigger without a placement to scan it where it was found"
    )


def face_down_refusal(found: LocateResult) -> str | None:
    """Why a plate found face down cannot be scanned, or None."""
    if not found.face_down:
        return None
    return (
        "the plate lies face down (its outline fits the design only mirrored): turn it over, or give "
        "design_side = moulded_down with its thickness"
    )
