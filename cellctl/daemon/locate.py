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

The cloud is read by :mod:`analysis.locate`; this module only turns ``[locate]`` into its settings
and decides on a given placement.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from analysis.locate import LocateResult, LocateSettings, placement_offset
from analysis.mesh import TriMesh
from analysis.outline import mesh_free_edges
from analysis.placement import Placement
from analysis.plates import design_mesh, plate_spec
from cellctl.config import CellConfig
from cellctl.planning import PlannerSettings, ScanPlan, plan_scan

__all__ = [
    "LocatePlan",
    "face_down_refusal",
    "given_placement_refusal",
    "locate_height_mm",
    "locate_plans",
    "locate_settings",
    "needs_across",
]


@dataclass(frozen=True)
class LocatePlan:
    """One family of locate passes: its plan, the planner settings it was made with, its name."""

    name: str
    plan: ScanPlan
    settings: PlannerSettings


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
    (:func:`analysis.outline.mesh_free_edges`, holes' edges included); every vertex's for a closed
    mesh (no free edge)."""
    edges, _ = mesh_free_edges(design)
    return design.vertices_mm[np.unique(edges) if len(edges) else np.arange(len(design.vertices_mm)), 2]


def locate_plans(cfg: CellConfig, design: TriMesh) -> list[LocatePlan]:
    """The two families of locate passes for ``design`` (raises the planner's PlanRefused /
    PlanInputError)."""
    loc = cfg.locate
    base = PlannerSettings.from_config(cfg)
    settings = base.with_(
        line_width_mm=loc.pass_spacing_mm,
        overlap_fraction=0.0,
        speed_mm_s=loc.speed_mm_s,
        edge_passes=False,
        placement_uncertainty_mm=0.0,
        placement_uncertainty_deg=0.0,
        # the locate passes span the whole bed: a turnaround flown beyond its ends would leave the
        # arm's reach (the default bed: joint 3 at 73.02 deg on link 2); they stop and go, as before
        flying_turns=False,
    )
    lo, hi = np.asarray(loc.bed_min_xy_mm), np.asarray(loc.bed_max_xy_mm)
    centre = (lo + hi) / 2
    size = hi - lo
    long_axis = int(np.argmax(size))
    # the "bed plate"'s top lies the planner's standoff below the locate height
    z = locate_height_mm(cfg, design) - settings.standoff_mm
    yaw_long = 0.0 if long_axis == 0 else 90.0
    L, W = float(size.max()), float(size.min())
    families = [
        ("locate along", _flat(L, W), yaw_long),
        ("locate across", _flat(W, W), yaw_long + 90.0),  # a square: the planner's passes along its x
    ]
    out = []
    for name, mesh, yaw in families:
        placement = Placement.on_bed(float(centre[0]), float(centre[1]), yaw, z_mm=z)
        out.append(LocatePlan(name, plan_scan(mesh, placement, settings, with_coverage=False), settings))
    return out


def locate_settings(cfg: CellConfig, design: TriMesh, yaw_hint_deg: float | None) -> LocateSettings:
    """:class:`analysis.locate.LocateSettings` of ``[locate]``, the sensor range at the locate height."""
    loc, las = cfg.locate, cfg.laser
    h = locate_height_mm(cfg, design)
    z = design.vertices_mm[:, 2]
    z0 = cfg.scan.placement_z_mm
    return LocateSettings(
        bed_z_mm=loc.bed_z_mm,
        min_height_mm=loc.min_height_mm,
        plate_z_mm=(z0 + float(z.min()) - loc.plate_band_mm, z0 + float(z.max()) + loc.plate_band_mm),
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
