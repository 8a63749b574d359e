"""The whole registration: every coarse candidate, ICP from each, the one-sided fit of the best.

:func:`register` runs the three stages (:mod:`~analysis.register.coarse`,
:mod:`~analysis.register.icp`, :mod:`~analysis.register.onesided`) on the design's
:class:`~analysis.register.height_field.HeightField`, trying every cyclic shift of the measured
corners and keeping the one whose ICP fit is best (this resolves the 180 degree turn of a nearly
symmetric plate); :func:`register_from_placement` starts from the operator's nominal placement
instead of the corners.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import structlog

from analysis.design.mesh import TriMesh
from analysis.register.coarse import CoarseResult, _check_corners, _snap_to_cloud, coarse_register
from analysis.register.height_field import HeightField, height_field_from_mesh
from analysis.register.icp import BOUNDARY_WEIGHT, IcpResult, _subsample, icp_point_to_plane
from analysis.register.onesided import NonPenetratingResult, deflection_gaps, grid_average, nonpenetrating_fit
from analysis.register.transforms import RegistrationError, _check_points, _check_transform

log = structlog.get_logger(__name__)


TIE_RELATIVE = 0.01  # candidate ICP fits within 1 % (plus TIE_ABSOLUTE_MM) of the best are a tie
TIE_ABSOLUTE_MM = 0.002


# --------------------------------------------------------------------------------------------------
# the whole registration


@dataclass(frozen=True)
class RegistrationResult:
    """Coarse fit, ICP and non-penetrating fit of one design onto one measured plate.

    transform: (4, 4) design -> measured, mm (the non-penetrating pose).
    coarse: the coarse fit of the chosen corner correspondence; icp: the ICP from it.
    nonpenetrating: the final one-sided fit. candidates: ICP RMS (mm) per corner shift tried.
    """

    transform: np.ndarray
    coarse: CoarseResult
    coarse_rms_mm: float
    icp: IcpResult
    nonpenetrating: NonPenetratingResult
    candidates: dict[int, float] = field(default_factory=dict)

    @property
    def penetration_points(self) -> int:
        return self.nonpenetrating.penetrating_after


def coarse_candidates(
    design_corners_mm: np.ndarray,
    measured_corners_mm: np.ndarray,
    *,
    design_points_mm: np.ndarray | None = None,
    measured_points_mm: np.ndarray | None = None,
    max_corner_rms_mm: float | None = None,
) -> list[CoarseResult]:
    """Coarse fits for all four cyclic corner correspondences, best corner RMS first.

    With ``max_corner_rms_mm`` the candidates whose corners cannot be matched (a 90 degree shift on
    an oblong plate) are dropped; by default the bound is the best RMS plus 10 % of the plate's
    shorter side, which always keeps the 180 degree twin of a rectangle.
    """
    D = _check_corners("design_corners_mm", design_corners_mm)
    M = _check_corners("measured_corners_mm", measured_corners_mm)

    def snapped(c: np.ndarray, cloud: np.ndarray | None) -> np.ndarray:
        # the edge midpoints do not depend on the shift: snap them once; a 200,000-point share of
        # the cloud places them to its spacing, which is all the coarse fit needs
        if cloud is not None and len(cloud) > 200_000:
            cloud = cloud[:: len(cloud) // 200_000]
        n = np.cross(c[2] - c[0], c[3] - c[1])
        return _snap_to_cloud(0.5 * (c + np.roll(c, -1, axis=0)), cloud, n)

    mid_D, mid_M = snapped(D, design_points_mm), snapped(M, measured_points_mm)
    cands = [
        coarse_register(D, M, shift=k, design_midpoints_mm=mid_D, measured_midpoints_mm=mid_M)
        for k in range(4)
    ]
    cands.sort(key=lambda c: c.corner_rms_mm)
    if max_corner_rms_mm is None:
        D = np.asarray(design_corners_mm, dtype=np.float64)
        side = float(min(np.linalg.norm(D[1] - D[0]), np.linalg.norm(D[2] - D[1])))
        max_corner_rms_mm = cands[0].corner_rms_mm + 0.1 * side
    return [c for c in cands if c.corner_rms_mm <= max_corner_rms_mm]


def coarse_fit_rms(surface: HeightField, measured_points_mm: np.ndarray, T: np.ndarray) -> float:
    """RMS vertical distance (mm) of the measured points to the design surface at pose ``T``."""
    s, _, _, valid = deflection_gaps(surface, measured_points_mm, T)
    return float(np.sqrt(np.mean(s[valid] ** 2))) if valid.any() else float("inf")


def register(
    design: TriMesh | HeightField,
    measured_points_mm: np.ndarray,
    design_corners_mm: np.ndarray,
    measured_corners_mm: np.ndarray,
    *,
    up: np.ndarray = np.array([0.0, 0.0, 1.0]),
    grid_step_mm: float = 1.0,
    icp_points: int = 100_000,
    boundary_weight: float = BOUNDARY_WEIGHT,
    nonpen_cell_mm: float | None = None,
    rest_points: Callable[[np.ndarray], np.ndarray] | None = None,
    nominal_transform: np.ndarray | None = None,
    seed: int = 0,
) -> RegistrationResult:
    """Coarse fit (all corner shifts), ICP per candidate, best ICP kept, then the non-penetrating fit.

    design: the design mesh (top surface, design plate frame, z up) or its height field.
    measured_points_mm: (n, 3) plate top-surface points, measured frame.
    design_corners_mm, measured_corners_mm: (4, 3), counter-clockwise from +z.
    The candidates' ICP runs on a 20,000-point subsample; the winner is refined on ``icp_points``.
    ICP and the non-penetrating fit keep the plate anchored in its own plane by the matched corners
    (``boundary_weight``, see :func:`icp_point_to_plane`); 0 turns that off.
    ``nominal_transform``: the operator's nominal placement (4x4 design -> measured); it only
    breaks ties between equally good fits of a symmetric design (which corner is the reference).
    ``nonpen_cell_mm``: None rests the design on every measured point; a cell size (1 mm for HD8
    scans) rests it on the :func:`grid_average` cell means instead -- the noise no longer lifts
    the design and 10^7 points cost what 10^6 do; penetration is then counted on the cell means.
    ``rest_points``: given the ICP pose (4x4 design -> measured), the (m, 3) points the design
    rests on instead (``analysis.register.rest_surface``: patch estimates with a bounded noise bias);
    penetration is then counted on those.
    """
    P = _check_points("measured_points_mm", measured_points_mm, 6)
    surface = design if isinstance(design, HeightField) else height_field_from_mesh(design, grid_step_mm)
    design_vertices = surface.points_mm()
    cands = coarse_candidates(
        design_corners_mm, measured_corners_mm, design_points_mm=design_vertices, measured_points_mm=P
    )
    trials: dict[int, tuple[float, CoarseResult, IcpResult]] = {}
    D = np.asarray(design_corners_mm, dtype=np.float64)
    matched = {
        c.shift: np.roll(np.asarray(measured_corners_mm, dtype=np.float64), -c.shift, axis=0) for c in cands
    }
    for cand in cands:
        try:
            icp = icp_point_to_plane(
                surface,
                P,
                cand.transform,
                max_points=20_000,
                max_iterations=30,
                seed=seed,
                design_corners_mm=D,
                measured_corners_mm=matched[cand.shift],
                boundary_weight=boundary_weight,
            )
        except RegistrationError:
            continue
        trials[cand.shift] = (icp.rms_mm, cand, icp)
    if not trials:
        raise RegistrationError(
            "no corner correspondence gives an ICP fit: the cloud does not match the design"
        )
    # A design symmetric under a half turn fits both ways equally well: the corner labelling (and with
    # it the line numbering) must then not depend on noise. Ties go to the candidate whose rotation is
    # nearest the nominal placement when one is given, else to the lowest shift (the measured corners'
    # own order: corner 0 starts the long edge pointing along the bed's +x).
    best_rms = min(v[0] for v in trials.values())
    tied = [k for k, v in trials.items() if v[0] <= best_rms * (1.0 + TIE_RELATIVE) + TIE_ABSOLUTE_MM]
    if nominal_transform is not None and len(tied) > 1:
        R_nom = _check_transform("nominal_transform", nominal_transform)[:3, :3]
        best_shift = min(tied, key=lambda k: (-float(np.trace(R_nom.T @ trials[k][1].transform[:3, :3])), k))
    else:
        best_shift = min(tied)
    _, coarse, icp0 = trials[best_shift]
    anchor = dict(
        design_corners_mm=D, measured_corners_mm=matched[best_shift], boundary_weight=boundary_weight
    )
    icp = icp_point_to_plane(surface, P, icp0.transform, max_points=icp_points, seed=seed, **anchor)
    coarse_rms = coarse_fit_rms(surface, _subsample(P, 20_000, seed), coarse.transform)
    if rest_points is not None:
        P_np = _check_points("rest_points", rest_points(icp.transform), 6)
    else:
        P_np = P if nonpen_cell_mm is None else grid_average(P, nonpen_cell_mm)
    npf = nonpenetrating_fit(surface, P_np, icp.transform, up=up, **anchor)
    log.info(
        "registered",
        shift=best_shift,
        candidates={k: round(v[0], 4) for k, v in trials.items()},
        coarse_rms_mm=round(coarse_rms, 3),
        icp_rms_mm=round(icp.rms_mm, 4),
        penetrating_before=npf.penetrating_before,
        penetrating_after=npf.penetrating_after,
    )
    return RegistrationResult(
        transform=npf.transform,
        coarse=coarse,
        coarse_rms_mm=coarse_rms,
        icp=icp,
        nonpenetrating=npf,
        candidates={k: v[0] for k, v in trials.items()},
    )


def register_from_placement(
    design: TriMesh | HeightField,
    measured_points_mm: np.ndarray,
    design_corners_mm: np.ndarray,
    nominal_transform: np.ndarray,
    *,
    up: np.ndarray = np.array([0.0, 0.0, 1.0]),
    grid_step_mm: float = 1.0,
    icp_points: int = 100_000,
    boundary_weight: float = BOUNDARY_WEIGHT,
    rest_points: Callable[[np.ndarray], np.ndarray] | None = None,
    seed: int = 0,
) -> RegistrationResult:
    """The registration of a scan that saw only part of the plate (a scan cut short): the plate's
    corners were not seen, so they are taken from the placement the scan was planned from.

    ``nominal_transform`` (4x4 design -> measured) is first lowered or raised onto the measured
    surface (the median vertical gap: a placement's height is the bed's, not the plate's top), which
    gives the corners the fits are anchored to; then ICP and the non-penetrating fit run as in
    :func:`register`. The in-plane pose is as good as the placement (the located one: about a
    millimetre); the height and tilt are the measured surface's. ``coarse`` is that corrected
    nominal pose (shift 0, corner RMS 0: the corners are the placement's).
    """
    P = _check_points("measured_points_mm", measured_points_mm, 6)
    surface = design if isinstance(design, HeightField) else height_field_from_mesh(design, grid_step_mm)
    T0 = _check_transform("nominal_transform", nominal_transform).copy()
    D = np.asarray(design_corners_mm, dtype=np.float64)
    sample = _subsample(P, 20_000, seed)
    gap, _, _, valid = deflection_gaps(surface, sample, T0, up=up, geometry=False)
    if not valid.any():
        raise RegistrationError(
            "the scanned part of the plate lies outside the design placed where the scan was planned"
        )
    T0[:3, 3] -= float(np.median(gap[valid])) * np.asarray(up, dtype=np.float64)
    M = D @ T0[:3, :3].T + T0[:3, 3]
    anchor = dict(design_corners_mm=D, measured_corners_mm=M, boundary_weight=boundary_weight)
    icp = icp_point_to_plane(surface, P, T0, max_points=icp_points, seed=seed, **anchor)
    coarse_rms = coarse_fit_rms(surface, sample, T0)
    P_np = _check_points("rest_points", rest_points(icp.transform), 6) if rest_points is not None else P
    npf = nonpenetrating_fit(surface, P_np, icp.transform, up=up, **anchor)
    log.info(
        "registered_from_placement",
        coarse_rms_mm=round(coarse_rms, 3),
        icp_rms_mm=round(icp.rms_mm, 4),
        penetrating_before=npf.penetrating_before,
        penetrating_after=npf.penetrating_after,
    )
    return RegistrationResult(
        transform=npf.transform,
        coarse=CoarseResult(T0, 0, 0.0, 0.0),
        coarse_rms_mm=coarse_rms,
        icp=icp,
        nonpenetrating=npf,
        candidates={0: icp.rms_mm},
    )
