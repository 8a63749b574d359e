"""Per-line templates: the paper's 2D case (its Table 2, "2D point cloud") -- a template per line.

A worker who places a single template on one detection line rests it on that line's section
alone: it turns in the section plane and slides, until it lies on the plate, as close as possible,
penetrating nowhere. The rigid 3D fit (``analysis.register``) rests one template on the whole
plate, so a line far from any defect reads the lift of the largest bump elsewhere; the per-line fit
does not. Here, for one line:

* :func:`line_rest_samples` -- what the template rests on: the plate's points within
  ``band_mm / 2`` of the section plane, binned along the line; each bin stands for its points by
  their mean position and the mean of their gaps to the rigidly fitted design (the noise-aware
  estimate of ``analysis.register.rest_surface`` in one dimension: bins sized so the highest bin error stays
  below ``target_sigmas`` sigma with the stated confidence).
* :func:`fit_line_template` -- the motion in the section plane (a rotation ``angle_rad`` about the
  samples' centroid, a shift ``shift_s_mm`` along the line and ``shift_h_mm`` along up) that
  minimises the sum of squared gaps subject to every gap >= 0: linearised motion with the exact
  Jacobian of the moved polyline's height, the exact one-sided QP of ``register``, repeated until
  the step vanishes, then a pure lift to contact (zero penetration, like the 3D fit's).

Coordinates: ``s`` mm along the line from its start (horizontal), ``h`` mm along up (the deflection
direction); the design section is the registered design's cut, so the per-line motion is small.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from analysis.contracts.settings import TEMPLATE_FITS
from analysis.register.onesided import DAMPING, solve_onesided_qp
from analysis.register.rest_surface import max_normal_quantile
from analysis.templates import DetectionLine


class TemplateFitError(ValueError):
    """A section that cannot carry a template: too few samples, bad shapes, an unknown mode."""


def check_mode(mode: str) -> str:
    """``mode`` if it is one of :data:`TEMPLATE_FITS`, else TemplateFitError naming it."""
    if mode not in TEMPLATE_FITS:
        raise TemplateFitError(f"template_fit must be one of {', '.join(TEMPLATE_FITS)}, got {mode!r}")
    return mode


@dataclass(frozen=True)
class LineRest:
    """Rest samples of one line: s_mm (m,), h_mm (m,) heights along up, counts (m,) points per bin.

    bin_mm: the bin length; bound_mm: the highest bin error stays below it with ``confidence``.
    """

    s_mm: np.ndarray
    h_mm: np.ndarray
    counts: np.ndarray
    bin_mm: float
    bound_mm: float
    confidence: float


def line_rest_samples(
    points_mm: np.ndarray,
    gaps_mm: np.ndarray,
    line: DetectionLine,
    design_s_mm: np.ndarray,
    design_h_mm: np.ndarray,
    noise_mm: float,
    *,
    band_mm: float = 10.0,
    target_sigmas: float = 0.25,
    confidence: float = 0.99,
    max_bin_mm: float = 20.0,
) -> LineRest:
    """The bins of plate points along ``line`` the per-line template rests on.

    points_mm: (n, 3) plate points, measured frame; gaps_mm: (n,) their gaps to the rigidly fitted
    design (NaN off it); design_s_mm, design_h_mm: that design's section on the line (NaN-free
    where defined). A bin's height is the design's at the bin's mean position minus the bin's mean
    gap, so the design's own curvature across a bin costs no bias.
    """
    P = np.asarray(points_mm, dtype=np.float64)
    g = np.asarray(gaps_mm, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3 or g.shape != (len(P),):
        raise TemplateFitError(f"points_mm (n, 3) and gaps_mm (n,) needed, got {P.shape}, {g.shape}")
    d = (P - line.start_mm) @ line.normal
    near = (np.abs(d) <= band_mm / 2) & np.isfinite(g)
    s = (P[near] - line.start_mm) @ line.direction
    g = g[near]
    ok = np.isfinite(design_h_mm)
    sd, hd = np.asarray(design_s_mm)[ok], np.asarray(design_h_mm)[ok]
    if len(sd) < 2:
        raise TemplateFitError(f"{line.family} line {line.index}: no design section")
    inside = (s >= sd[0]) & (s <= sd[-1])
    s, g = s[inside], g[inside]
    if len(s) < 6:
        raise TemplateFitError(f"{line.family} line {line.index}: only {len(s)} points near the line")
    length = float(s.max() - s.min()) or 1.0
    per_mm = len(s) / length
    bins = max(length / 5.0, 1.0)
    for _ in range(4):
        q = max_normal_quantile(math.ceil(bins), confidence)
        n_min = max(math.ceil((q / target_sigmas) ** 2), 1)
        bin_mm = float(np.clip(1.5 * n_min / per_mm, 1.0, max_bin_mm))
        bins = max(2.0 * length / bin_mm, 1.0)
    n_min = min(n_min, max(int(0.66 * per_mm * bin_mm), 1))
    # a whole number of bins from one end of the section to the other: the end bins then sit the
    # same way on the plate in every scan (a partial end bin, kept or dropped as the density and the
    # placement change, moved the line's support by up to a bin and its Zmax by 0.1 mm)
    s0 = float(s.min())
    n_bins = max(round(length / bin_mm), 1)
    bin_mm = length / n_bins
    k = np.minimum(np.floor((s - s0) / bin_mm).astype(np.int64), n_bins - 1)
    count = np.bincount(k, minlength=n_bins)
    keep = count >= n_min
    if keep.sum() < 3:
        raise TemplateFitError(f"{line.family} line {line.index}: fewer than 3 bins of {n_min} points")
    safe = np.maximum(count, 1)
    s_mean = (np.bincount(k, weights=s, minlength=n_bins) / safe)[keep]
    g_mean = (np.bincount(k, weights=g, minlength=n_bins) / safe)[keep]
    counts = count[keep].astype(np.float64)
    # the ends: a template on a raised edge touches the section's end, not its end bin's centroid
    ends = [_end_sample(s, g, k, n_bins, end, n_min, noise_mm) for end in (0, n_bins - 1)]
    ends = [e for e in ends if e is not None]
    if ends:
        s_mean = np.concatenate([s_mean, [e[0] for e in ends]])
        g_mean = np.concatenate([g_mean, [e[1] for e in ends]])
        counts = np.concatenate([counts, [e[2] for e in ends]])
    order = np.argsort(s_mean)
    s_mean, g_mean, counts = s_mean[order], g_mean[order], counts[order]
    h = np.interp(s_mean, sd, hd) - g_mean
    bound = max_normal_quantile(len(counts), confidence) * noise_mm / math.sqrt(float(counts.min()))
    return LineRest(s_mean, h, counts, bin_mm, bound, confidence)


# trimmed like the 3D patches (analysis.register.rest_surface.TRIM_SIGMAS): the thickness face's points
END_TRIM_SIGMAS = 3.0


def _end_sample(
    s: np.ndarray, g: np.ndarray, k: np.ndarray, n_bins: int, end: int, n_min: int, noise_mm: float
) -> tuple[float, float, float] | None:
    """The section's end held by a line of the gaps: (s at the end, gap there, n_eff) or None.

    The line is fitted on the end bin and its neighbours (one, then two), points more than
    END_TRIM_SIGMAS off a first fit left out, and evaluated at the outermost point; its variance
    there is ``sigma^2 / n_eff``, ``1 / n_eff = 1 / n + (s_end - mean s)^2 / S_ss``. The first
    block where ``n_eff >= n_min`` (the bins' variance bound) serves; None if none does.
    """
    step = 1 if end == 0 else -1
    for r in (1, 2):
        if r >= n_bins:
            return None
        lo, hi = sorted((end, end + step * r))
        sel = (k >= lo) & (k <= hi)
        ss, gg = s[sel], g[sel]
        if len(ss) < 3:
            continue
        at = float(ss.min() if end == 0 else ss.max())
        use = np.ones(len(ss), dtype=bool)
        for trim in (True, False):
            m_s, m_g = float(ss[use].mean()), float(gg[use].mean())
            sss = float(((ss[use] - m_s) ** 2).sum())
            if sss <= 0.0 or use.sum() < 3:
                break
            slope = float(((ss[use] - m_s) * (gg[use] - m_g)).sum()) / sss
            if trim:
                use = np.abs(gg - m_g - slope * (ss - m_s)) <= END_TRIM_SIGMAS * noise_mm
        else:
            n_eff = 1.0 / (1.0 / int(use.sum()) + (at - m_s) ** 2 / sss)
            if n_eff >= n_min:
                return at, m_g + slope * (at - m_s), n_eff
    return None


@dataclass(frozen=True)
class LineFitResult:
    """The per-line template's motion in the section plane and the moved design section.

    angle_rad: rotation about (pivot_s_mm, pivot_h_mm), counter-clockwise in (s, h); shift_s_mm,
    shift_h_mm: translation after it. objective_mm2: sum of squared gaps over the rest samples;
    min_gap_mm >= 0; penetrating_after: samples below the template (0); points: rest samples.
    """

    angle_rad: float
    shift_s_mm: float
    shift_h_mm: float
    pivot_s_mm: float
    pivot_h_mm: float
    objective_mm2: float
    rms_mm: float
    min_gap_mm: float
    points: int
    penetrating_after: int
    iterations: int
    converged: bool

    def move(self, s_mm: np.ndarray, h_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Points (s, h) of the section plane moved by the fit's motion."""
        c, sn = math.cos(self.angle_rad), math.sin(self.angle_rad)
        ds, dh = np.asarray(s_mm) - self.pivot_s_mm, np.asarray(h_mm) - self.pivot_h_mm
        return (
            self.pivot_s_mm + c * ds - sn * dh + self.shift_s_mm,
            self.pivot_h_mm + sn * ds + c * dh + self.shift_h_mm,
        )

    def moved_heights(
        self, design_s_mm: np.ndarray, design_h_mm: np.ndarray, at_s_mm: np.ndarray
    ) -> np.ndarray:
        """The moved design section's heights at ``at_s_mm`` (NaN beyond its ends)."""
        ok = np.isfinite(design_h_mm)
        s2, h2 = self.move(np.asarray(design_s_mm)[ok], np.asarray(design_h_mm)[ok])
        return np.interp(at_s_mm, s2, h2, left=np.nan, right=np.nan)

    def as_dict(self) -> dict:
        """The report's record of the fit."""
        return {
            "angle_deg": math.degrees(self.angle_rad),
            "shift_s_mm": self.shift_s_mm,
            "shift_h_mm": self.shift_h_mm,
            "rms_mm": self.rms_mm,
            "rest_points": self.points,
            "penetration_points": self.penetrating_after,
            "converged": self.converged,
        }


def fit_line_template(
    design_s_mm: np.ndarray,
    design_h_mm: np.ndarray,
    rest_s_mm: np.ndarray,
    rest_h_mm: np.ndarray,
    *,
    max_iterations: int = 30,
    tolerance_mm: float = 1e-6,
    rel_tolerance: float = 1e-9,
    slide_weight: float = 1e-3,
) -> LineFitResult:
    """Rest the design section on the samples: least squares, no sample above the template.

    design_s_mm, design_h_mm: (k,) the design's section polyline, s increasing (NaN = none);
    rest_s_mm, rest_h_mm: (m,) the samples it rests on. Unknowns: rotation (about the samples'
    centroid) and translation in the section plane. Each step linearises the moved polyline's height
    at the samples, ``dh = (s - c_s) dtheta + dt_h - h'(s) (dt_s - (h - c_h) dtheta)``, and solves the
    one-sided QP exactly. The slide along the line is held near the rigid fit's placement by a
    penalty ``slide_weight`` x samples x shift_s^2 (the sliding of a straight or circular section
    along itself costs nothing else, and noise would drive it). Steps are halved until they lower the objective of the pose lifted into
    contact; the fit stops when a step is below ``tolerance_mm`` or gains less than
    ``rel_tolerance`` of the objective. Ends with that lift (lowest gap 0).
    """
    sd = np.asarray(design_s_mm, dtype=np.float64)
    hd = np.asarray(design_h_mm, dtype=np.float64)
    ok = np.isfinite(hd) & np.isfinite(sd)
    sd, hd = sd[ok], hd[ok]
    sm = np.asarray(rest_s_mm, dtype=np.float64)
    hm = np.asarray(rest_h_mm, dtype=np.float64)
    if len(sd) < 2 or np.any(np.diff(sd) <= 0):
        raise TemplateFitError("the design section needs at least 2 samples with s increasing")
    if sm.shape != hm.shape or sm.ndim != 1 or len(sm) < 3 or not np.isfinite(sm).all():
        raise TemplateFitError(f"need at least 3 finite rest samples, got shapes {sm.shape}, {hm.shape}")
    inside = (sm >= sd[0]) & (sm <= sd[-1]) & np.isfinite(hm)
    sm, hm = sm[inside], hm[inside]
    if len(sm) < 3:
        raise TemplateFitError("fewer than 3 rest samples lie over the design section")
    cs, ch = float(sm.mean()), float(hm.mean())
    scale = float(np.sqrt(np.mean((sm - cs) ** 2))) or 1.0
    theta, t = 0.0, np.zeros(2)
    fit = LineFitResult(0.0, 0.0, 0.0, cs, ch, 0.0, 0.0, 0.0, len(sm), 0, 0, False)
    lift = np.array([0.0, 0.0, 1.0])

    # the slide along the line is held by the rigid fit's placement (the plate's corners), as a
    # worker lines a template up with the line's marks: weight slide_weight per sample, as the 3D
    # fit's corner anchoring
    anchor = slide_weight * len(sm)

    def heights(f: LineFitResult) -> np.ndarray:
        # the moved section at the samples, its end segments extended: a sample the motion moves
        # just past an end keeps its cost (else the fit could gain by sliding samples off)
        s2, h2 = f.move(sd, hd)
        out = np.interp(sm, s2, h2)
        lo, hi = sm < s2[0], sm > s2[-1]
        out[lo] = h2[0] + (sm[lo] - s2[0]) * (h2[1] - h2[0]) / (s2[1] - s2[0])
        out[hi] = h2[-1] + (sm[hi] - s2[-1]) * (h2[-1] - h2[-2]) / (s2[-1] - s2[-2])
        return out

    def merit(f: LineFitResult) -> float:
        # the objective once the pose is lifted (or lowered) into contact: every pose has a
        # feasible twin along h, so this ranks poses without a feasibility test
        g = heights(f) - hm
        g = g - g.min()
        return float(g @ g) + anchor * f.shift_s_mm**2

    best = merit(fit)
    converged, it = False, 0
    for it in range(1, max_iterations + 1):
        s2, h2 = fit.move(sd, hd)
        h_at = heights(fit)
        gap = h_at - hm
        k = np.interp(sm, s2, np.gradient(h2, s2))
        J = np.column_stack([((sm - cs) + k * (h_at - ch)) / scale, -k, np.ones(len(sm))])
        damping = DAMPING * float(np.einsum("ij,ij->", J, J)) / 3.0
        K = math.sqrt(anchor) * np.array([[0.0, 1.0, 0.0]])
        x, _, _ = solve_onesided_qp(J, gap, lift, damping, K, math.sqrt(anchor) * np.array([t[0]]))
        # the linear model overreaches along a nearly free slide (an arc along itself): halve the
        # step until the merit falls
        for _ in range(10):
            dtheta = x[0] / scale
            c, sn = math.cos(dtheta), math.sin(dtheta)
            t_new = np.array([c * t[0] - sn * t[1], sn * t[0] + c * t[1]]) + x[1:]
            trial = LineFitResult(theta + dtheta, float(t_new[0]), float(t_new[1]), cs, ch,
                                  0.0, 0.0, 0.0, len(sm), 0, it, False)  # fmt: skip
            m = merit(trial)
            if m < best:
                break
            x = 0.5 * x
        else:
            converged = True  # no step lowers the merit: at the optimum to round-off
            break
        gain = (best - m) / max(best, 1e-300)
        fit, best, theta, t = trial, m, theta + dtheta, t_new
        if abs(x[0]) + abs(x[1]) + abs(x[2]) < tolerance_mm or gain < rel_tolerance:
            converged = True
            break
    theta, t = fit.angle_rad, np.array([fit.shift_s_mm, fit.shift_h_mm])
    # exact gaps at the final motion, then the lift to contact (a shift along h adds to every gap)
    gap = heights(fit) - hm
    t[1] -= float(gap.min())
    g = gap - float(gap.min())
    obj = float(g @ g)
    return LineFitResult(
        theta, float(t[0]), float(t[1]), cs, ch, obj, math.sqrt(obj / len(g)), float(g.min()),
        len(g), int((g < 0).sum()), it, converged,
    )  # fmt: skip
