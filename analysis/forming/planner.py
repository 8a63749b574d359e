"""The heating planner's core: from where the plate is wrong to where to heat it.

Input: the deviation after the resting fit (measured minus design, mm, up as the plate lies) on
points of the plate frame, the plate's size and thickness, its material, and the crew's rules.
Output: straight heating lines (ends in plate mm, face, heat input and torch speed, order) that
minimise the deviation the forming model predicts after the round, and words when one round, or
heating at all, cannot do it.

The inverse solve: candidate lines on the rules' grid (across, along and both 45 deg diagonals, whole
and half lengths, both faces; lines of different directions may cross, parallel ones keep the least
spacing where their extents overlap); each candidate's influence on the deviation points from one factorised FE model (many
right-hand sides); a greedy selection (the candidate that most reduces the residual, refitted by
non-negative least squares over the chosen set) that keeps the least spacing, the edge margin and the
maximum number of lines; then each line's bend turned into the heat input that gives it, and the
round predicted again with the lines as they will be heated.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import nnls

from analysis.forming.coefficients import (
    Coefficients,
    heat_input_for_bend,
    inherent_deformation,
    peak_bend_heat_input_j_per_mm,
    torch_speed_mm_s,
)
from analysis.forming.plate_model import HeatingLine, PlateModel, remove_plane
from analysis.forming.rules import HeatingRules

__all__ = [
    "HeatingPlan",
    "HeatingRules",
    "PlannedLine",
    "in_plane_strain_given",
    "in_plane_strain_needed",
    "plan_heating",
]

#: deviation points the inverse solve fits (a regular subset of the scan's grid)
FIT_POINTS = 3000


@dataclass(frozen=True)
class PlannedLine:
    """One line of the plan, in the order the crew heats it."""

    order: int
    start_plate_mm: tuple[float, float]
    end_plate_mm: tuple[float, float]
    face: str
    heat_input_j_per_mm: float
    torch_speed_mm_s: float
    bend_deg: float
    shrink_mm: float


@dataclass
class HeatingPlan:
    """A round's plan: the lines, the predicted deviation after it, and what to tell the crew."""

    lines: list[PlannedLine]
    rms_before_mm: float
    rms_after_mm: float
    max_before_mm: float
    max_after_mm: float
    predicted_after_mm: np.ndarray
    element_mm: float
    notes: list[str] = field(default_factory=list)


_R = math.sqrt(0.5)
#: the candidates' directions as (unit tangent, unit normal): across the plate (constant x), along it
#: (constant y), and the two diagonals at +-45 deg (a twist z = k x y has its principal curvatures
#: there, on a plate of any aspect); a line's offset is its distance from the origin along the normal
_DIRECTIONS = (
    ((0.0, 1.0), (1.0, 0.0)),
    ((1.0, 0.0), (0.0, 1.0)),
    ((_R, _R), (-_R, _R)),
    ((_R, -_R), (_R, _R)),
)


@dataclass(frozen=True)
class _Candidate:
    start: tuple[float, float]
    end: tuple[float, float]
    face: str
    direction: int  # index into _DIRECTIONS
    offset_mm: float  # the line's signed distance from the origin along its direction's normal
    span: tuple[float, float]  # extent along the line (its tangent times the ends)


def _clipped(
    t: tuple[float, float], n: tuple[float, float], offset_mm: float, box: tuple[float, float, float, float]
) -> tuple[float, float] | None:
    """The extent (s0, s1) along tangent ``t`` of the line at ``offset_mm`` along normal ``n``
    inside ``box`` (x0, y0, x1, y1), or None when it misses the box."""
    base = (offset_mm * n[0], offset_mm * n[1])  # the line's point nearest the origin
    lo, hi = -math.inf, math.inf
    for k in (0, 1):
        a, b = box[k], box[k + 2]
        if abs(t[k]) < 1e-12:
            if not a - 1e-9 <= base[k] <= b + 1e-9:
                return None
            continue
        s0, s1 = (a - base[k]) / t[k], (b - base[k]) / t[k]
        lo, hi = max(lo, min(s0, s1)), min(hi, max(s0, s1))
    return (lo, hi) if hi > lo else None


def _candidates(length_mm: float, width_mm: float, rules: HeatingRules) -> list[_Candidate]:
    """Lines of every direction of ``_DIRECTIONS`` on the step from the edge margin, each whole
    (clipped to the margin's rectangle) and its two halves, on each face the rules allow. A diagonal
    shorter than the least spacing (a corner's stub) is left out."""
    m = rules.edge_margin_mm
    x0, x1 = (m, length_mm - m) if length_mm > 2 * m else (length_mm / 2, length_mm / 2)
    y0, y1 = (m, width_mm - m) if width_mm > 2 * m else (width_mm / 2, width_mm / 2)
    box = (x0, y0, x1, y1)
    out: list[_Candidate] = []
    faces = ("top", "bottom") if rules.allow_bottom_face else ("top",)
    for direction, (t, n) in enumerate(_DIRECTIONS):
        corners = [c[0] * n[0] + c[1] * n[1] for c in ((x0, y0), (x1, y0), (x0, y1), (x1, y1))]
        lo, hi = min(corners), max(corners)
        step = rules.candidate_step_mm
        if direction < 2:  # positions on the step from the margin (round numbers to chalk)
            offsets = np.arange(lo, hi + 1e-6, step) if hi > lo else np.array([lo])
        else:  # the diagonals on the step either side of the one through the plate's centre
            mid = 0.5 * (lo + hi)
            k = math.floor((hi - mid) / step + 1e-9)
            offsets = mid + step * np.arange(-k, k + 1)
        for off in offsets:
            extent = _clipped(t, n, float(off), box)
            if extent is None:
                continue
            a0, a1 = extent
            if direction >= 2 and a1 - a0 < rules.min_spacing_mm:
                continue
            spans = [(a0, a1), (a0, 0.5 * (a0 + a1)), (0.5 * (a0 + a1), a1)]
            for s0, s1 in spans:
                ends = [
                    (
                        float(np.clip(off * n[0] + s * t[0], x0, x1)),
                        float(np.clip(off * n[1] + s * t[1], y0, y1)),
                    )
                    for s in (s0, s1)
                ]
                for face in faces:
                    out.append(
                        _Candidate(ends[0], ends[1], face, direction, float(off), (float(s0), float(s1)))
                    )
    return out


def _conflicts_with(
    cand_arrays: tuple[np.ndarray, np.ndarray, np.ndarray], i: int, spacing_mm: float
) -> np.ndarray:
    """Which candidates conflict with candidate ``i``: parallel, closer than the spacing, their
    extents overlapping (the candidates as arrays of their direction, offset and span). Lines of
    different directions may cross: the rule of the least spacing is between parallel lines."""
    direction, offset, span = cand_arrays
    overlap = np.minimum(span[:, 1], span[i, 1]) - np.maximum(span[:, 0], span[i, 0])
    return (direction == direction[i]) & (np.abs(offset - offset[i]) < spacing_mm) & (overlap > 0)


def _without_overshoot(g: np.ndarray, bend_rad: np.ndarray, target: np.ndarray) -> list[int]:
    """The columns of ``g`` (n, k; per rad) to keep at ``bend_rad`` (k,): backward elimination of
    the line whose removal most lowers the residual against ``target`` (n,), while one does."""
    keep = list(range(len(bend_rad)))
    residual = target - g @ bend_rad
    while keep:
        contrib = g[:, keep] * bend_rad[keep]
        without = residual[:, None] + contrib
        norms = np.einsum("ij,ij->j", without, without)
        k = int(np.argmin(norms))
        if norms[k] >= float(residual @ residual) * (1 - 1e-3):
            break
        residual = without[:, k]
        del keep[k]
    return keep


def plan_heating(
    points_mm: np.ndarray,
    deviation_mm: np.ndarray,
    length_mm: float,
    width_mm: float,
    thickness_mm: float,
    coefficients: Coefficients,
    rules: HeatingRules | None = None,
    model: PlateModel | None = None,
) -> HeatingPlan:
    """Plan one round of line heating for the deviation ``deviation_mm`` (n,) at ``points_mm`` (n, 2).

    ``deviation_mm`` is measured minus design after the resting fit, up as the plate lies (a plate
    under-bent toward the top face has a positive deviation at its edges and negative in the middle).
    ``model`` may be passed when the same plate is planned again (the FE factorisation is reused).
    """
    rules = rules or HeatingRules()
    points_mm = np.asarray(points_mm, float)
    deviation_mm = np.asarray(deviation_mm, float)
    if points_mm.ndim != 2 or points_mm.shape[1] != 2 or deviation_mm.shape != (len(points_mm),):
        raise ValueError(
            f"points_mm (n, 2) and deviation_mm (n,) expected, got {points_mm.shape}, {deviation_mm.shape}"
        )
    if len(points_mm) < 3:
        raise ValueError("at least three deviation points are needed")
    material = coefficients.for_material(rules.material)
    process = coefficients.process
    model = model or PlateModel.build(length_mm, width_mm, thickness_mm, material)

    rms_before = float(np.sqrt(np.mean(remove_plane(points_mm, deviation_mm) ** 2)))
    max_before = float(np.max(np.abs(remove_plane(points_mm, deviation_mm))))

    # influence per unit bend: each candidate at the heat input of the largest bend, scaled by its bend
    q_ref = peak_bend_heat_input_j_per_mm(thickness_mm, material, process)
    ref = inherent_deformation(q_ref, thickness_mm, material, process)
    # positions finer than the mesh add nothing the model can tell apart
    step = max(rules.candidate_step_mm, model.element_mm)
    cands = _candidates(length_mm, width_mm, rules.model_copy(update={"candidate_step_mm": step}))
    # the fit needs the shape, not every scanned point: a regular subset of at most FIT_POINTS
    fit = np.arange(0, len(points_mm), max(1, len(points_mm) // FIT_POINTS))
    fit_points, target = points_mm[fit], remove_plane(points_mm[fit], -deviation_mm[fit])
    # one solve per line position: heating the bottom face is the top's response turned over
    tops = sorted({(c.start, c.end) for c in cands})
    col = {se: i for i, se in enumerate(tops)}
    g_top = model.influence_mm([HeatingLine(s, e, "top", ref) for s, e in tops], fit_points)
    g_top = remove_plane(fit_points, g_top) / ref.bend_across_rad  # (n, positions) per rad
    g = np.stack(
        [g_top[:, col[(c.start, c.end)]] * (1.0 if c.face == "top" else -1.0) for c in cands], axis=1
    )
    theta_min = inherent_deformation(
        process.heat_input_min_j_per_mm, thickness_mm, material, process
    ).bend_across_rad
    theta_max = ref.bend_across_rad

    cand_arrays = (
        np.array([c.direction for c in cands]),
        np.array([c.offset_mm for c in cands]),
        np.array([c.span for c in cands]).reshape(-1, 2),
    )
    chosen: list[int] = []
    amps = np.zeros(0)
    residual = target.copy()
    best_norm = float(np.linalg.norm(target))
    while len(chosen) < rules.max_lines_per_round:
        free = np.ones(len(cands), bool)
        for i in chosen:
            free &= ~_conflicts_with(cand_arrays, i, rules.min_spacing_mm)
            free[i] = False
        allowed = np.flatnonzero(free)
        if not allowed.size:
            break
        # score: the drop in residual norm if the candidate alone were added at its best amplitude
        ga = g[:, allowed]
        proj = residual @ ga
        norms = np.einsum("ij,ij->j", ga, ga) + 1e-30
        gain = np.where(proj > 0, proj**2 / norms, 0.0)
        k = int(np.argmax(gain))
        if gain[k] <= 1e-12 * best_norm**2:
            break
        trial = [*chosen, int(allowed[k])]
        trial_amps, rnorm = nnls(g[:, trial], target, maxiter=50 * len(trial))
        if rnorm >= best_norm * (1 - 1e-3):
            break
        chosen, amps, best_norm = trial, trial_amps, rnorm
        residual = target - g[:, chosen] @ amps
        keep = amps > 1e-9
        chosen, amps = [c for c, kk in zip(chosen, keep, strict=True) if kk], amps[keep]

    # the bends the crew can give: clipped to the process's range; more needs another round
    notes: list[str] = []
    planned: list[HeatingLine] = []
    planned_cols: list[int] = []
    for j, theta in zip(chosen, amps, strict=True):
        wanted = float(theta)
        if wanted < 0.5 * theta_min:
            continue
        q = heat_input_for_bend(min(max(wanted, theta_min), theta_max), thickness_mm, material, process)
        if q is None:
            q = q_ref
        planned.append(
            HeatingLine(
                cands[j].start,
                cands[j].end,
                cands[j].face,
                inherent_deformation(q, thickness_mm, material, process),
            )
        )
        planned_cols.append(j)
        if wanted > theta_max * 1.05:
            notes.append(
                f"a line at {cands[j].start}-{cands[j].end} needs {math.degrees(wanted):.2f} deg, more than one pass "
                f"gives ({math.degrees(theta_max):.2f} deg at {q_ref:.0f} J/mm): heat it again next round"
            )
    # a line raised to the least bend a pass gives can bend the plate past its design (a small
    # deviation on a long plate): leave out, one at a time, the lines whose absence fits better
    keep = _without_overshoot(
        g[:, planned_cols], np.array([line.deformation.bend_across_rad for line in planned]), target
    )
    if len(keep) < len(planned):
        notes.append(
            f"{len(planned) - len(keep)} line(s) left out: the least bend one pass gives "
            f"({math.degrees(theta_min):.2f} deg) would bend the plate past its design there"
        )
        planned = [planned[i] for i in keep]

    predicted_heat = (
        remove_plane(points_mm, model.deflection_mm(planned, points_mm))
        if planned
        else np.zeros(len(points_mm))
    )
    after = remove_plane(points_mm, deviation_mm + predicted_heat)
    rms_after = float(np.sqrt(np.mean(after**2)))
    max_after = float(np.max(np.abs(after)))

    # order: top face first (as the plate lies), then bottom after turning it; within a face from
    # the middle outward, so the plate's restraint stays symmetric
    centre = np.array([length_mm / 2, width_mm / 2])

    def order_key(line: HeatingLine) -> tuple[int, float]:
        mid = 0.5 * (np.asarray(line.start_plate_mm) + np.asarray(line.end_plate_mm))
        return (0 if line.face == "top" else 1, float(np.hypot(*(mid - centre))))

    planned.sort(key=order_key)
    out = [
        PlannedLine(
            order=i + 1,
            start_plate_mm=line.start_plate_mm,
            end_plate_mm=line.end_plate_mm,
            face=line.face,
            heat_input_j_per_mm=line.deformation.heat_input_j_per_mm,
            torch_speed_mm_s=torch_speed_mm_s(line.deformation.heat_input_j_per_mm, process),
            bend_deg=math.degrees(line.deformation.bend_across_rad),
            shrink_mm=line.deformation.shrink_across_mm,
        )
        for i, line in enumerate(planned)
    ]
    notes += _words(out, rms_before, rms_after, rules, points_mm, deviation_mm, length_mm, width_mm)
    return HeatingPlan(out, rms_before, rms_after, max_before, max_after, after, model.element_mm, notes)


def in_plane_strain_needed(
    points_mm: np.ndarray, shape_mm: np.ndarray, length_mm: float, width_mm: float
) -> float:
    """The in-plane strain (magnitude) a flat plate needs to take ``shape_mm`` (n,) at ``points_mm``:
    from the Gaussian curvature K of its best-fit quadratic, a developable shape (K = 0) needs none,
    a dome or saddle needs |K| r^2 / 6 at the half-diagonal r (a spherical cap's circumferential
    strain, Gauss's theorem). Straight lines give it only through their shrinkage."""
    x, y = points_mm[:, 0] - points_mm[:, 0].mean(), points_mm[:, 1] - points_mm[:, 1].mean()
    a = np.column_stack([np.ones_like(x), x, y, x * x, x * y, y * y])
    c, *_ = np.linalg.lstsq(a, shape_mm, rcond=None)
    gauss = abs(4.0 * c[3] * c[5] - c[4] ** 2)
    return float(gauss * (length_mm**2 + width_mm**2) / 4.0 / 6.0)


def in_plane_strain_given(lines: list[PlannedLine], length_mm: float, width_mm: float) -> float:
    """The larger of the mean shrinkage strains the lines give across and along the plate (a
    diagonal line's shrinkage across it counted in x and y by its normal's squared components)."""
    across = along = 0.0
    for line in lines:
        dx, dy = np.subtract(line.end_plate_mm, line.start_plate_mm)
        nx2 = dy * dy / (dx * dx + dy * dy)  # the squared x component of the line's unit normal
        across += line.shrink_mm * nx2 / length_mm
        along += line.shrink_mm * (1.0 - nx2) / width_mm
    return max(across, along)


def _words(
    lines: list[PlannedLine],
    rms_before: float,
    rms_after: float,
    rules: HeatingRules,
    points_mm: np.ndarray,
    deviation_mm: np.ndarray,
    length_mm: float,
    width_mm: float,
) -> list[str]:
    notes: list[str] = []
    bottom = [f"H{line.order}" for line in lines if line.face == "bottom"]
    if bottom and len(bottom) == len(lines):
        notes.append("over-bent: every line is on the bottom face; turn the plate over and heat that face")
    elif bottom:
        # a few bottom-face lines beside top-face ones bend back where the plate, or the top-face
        # lines next to them, bend past the design there: the plate as a whole is not over-bent
        notes.append(
            f"{', '.join(bottom)} on the bottom face bend{'s' if len(bottom) == 1 else ''} back where the plate "
            "with the top-face lines goes past its design: turn the plate over for "
            f"{'it' if len(bottom) == 1 else 'them'} once the top-face lines are done"
        )
    if not lines:
        notes.append(
            "heating cannot reduce this deviation: no line of the rules brings the plate nearer its design"
        )
        return notes
    if rms_after > rules.target_fraction * rms_before:
        if rms_after > 0.8 * rms_before:
            notes.append(
                f"heating cannot do it: the predicted RMS only falls from {rms_before:.2f} to {rms_after:.2f} mm"
            )
        else:
            notes.append(
                f"one round is not enough: the predicted RMS falls from {rms_before:.2f} to {rms_after:.2f} mm; "
                "scan after this round and plan again"
            )
    needed = in_plane_strain_needed(points_mm, -deviation_mm, length_mm, width_mm)
    if needed > in_plane_strain_given(lines, length_mm, width_mm):
        notes.append(
            f"doubly curved: the plate needs about {needed * 1e3:.2f} mm/m of in-plane shrinkage and these lines "
            f"give {in_plane_strain_given(lines, length_mm, width_mm) * 1e3:.2f}: edge or triangle heating, or the press"
        )
    return notes
