"""Deviation figures per detection line and the tolerance judgement (paper 2.3.2).

For one line, the design and measured sections are heights ``f(x)`` along the deflection direction
over positions ``x`` along the line. Both are turned into cubic smoothing splines -- the measured one
smoothed by its noise level (Dierckx's criterion: sum of squared residuals = n sigma^2), because a
second derivative of raw samples is noise, not curvature -- and compared on their common domain
[a, b] with ``d(x) = f_design(x) - f_measure(x)``:

* SZ = integral of |d| dx (mm^2), SZ-average = SZ / (b - a) (mm), Zmax = max |d| (mm);
* kappa = f'' / (1 + f'^2)^(3/2) of each curve; CI = integral of |kappa_d - kappa_m| ds over the
  design curve's arc length s, SC-average = CI / L (1/mm), Cmax = max |kappa_d - kappa_m| (1/mm);
  L = integral of sqrt(1 + f_design'^2) dx is the line's length.

The judgement compares Zmax with the configured tolerances (CSQS 2016 defaults for a doubly curved
plate: standard 2 mm, limit 3 mm) and, if configured, Cmax with a curvature limit.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.interpolate import UnivariateSpline


class MetricsError(ValueError):
    """Section data that cannot be evaluated: wrong shapes, too few samples, no common domain."""


@dataclass(frozen=True)
class Tolerances:
    """Tolerances a plate is judged against (plain dataclass; the application fills it from config).

    standard: the name printed in the report. deviation_standard_mm / deviation_limit_mm: the
    template-to-plate deviation's standard range and allowable limit (CSQS 2016, doubly curved
    plate: 2 mm / 3 mm). judge_at: "limit" (a line passes within the allowable limit) or
    "standard" (only within the standard range). cmax_limit_per_mm: optional limit on Cmax.
    """

    standard: str = "CSQS 2016, doubly curved plate"
    deviation_standard_mm: float = 2.0
    deviation_limit_mm: float = 3.0
    judge_at: str = "limit"
    cmax_limit_per_mm: float | None = None

    def __post_init__(self) -> None:
        if self.judge_at not in ("limit", "standard"):
            raise MetricsError(f"judge_at must be 'limit' or 'standard', got {self.judge_at!r}")
        if not 0 < self.deviation_standard_mm <= self.deviation_limit_mm:
            raise MetricsError(
                "need 0 < deviation_standard_mm <= deviation_limit_mm, got "
                f"{self.deviation_standard_mm} and {self.deviation_limit_mm}"
            )

    def as_dict(self) -> dict:
        """Plain dict for the report."""
        return {
            "standard": self.standard,
            "deviation_standard_mm": self.deviation_standard_mm,
            "deviation_limit_mm": self.deviation_limit_mm,
            "judge_at": self.judge_at,
            "cmax_limit_per_mm": self.cmax_limit_per_mm,
        }


@dataclass(frozen=True)
class LineMetrics:
    """The six figures of one detection line (report field names) and where the line lies.

    a_mm, b_mm: the common domain along the line (mm from its start); zmax_at_mm: where |d| peaks.
    noise_mm: the measured noise level the smoothing used. position_mm: the line's distance from
    the reference corner along its edge (see ``templates.DetectionLine``).
    grade: "standard" (Zmax within the standard range), "limit" (within the allowable limit) or
    "out"; passed: the verdict of this line under the tolerances.
    """

    family: str
    index: int
    sz_mm2: float
    sz_avg_mm: float
    zmax_mm: float
    zmax_at_mm: float
    ci: float
    sc_avg_per_mm: float
    cmax_per_mm: float
    length_mm: float
    a_mm: float
    b_mm: float
    noise_mm: float
    position_mm: float = 0.0
    grade: str = ""
    passed: bool = True

    def as_dict(self) -> dict:
        """The report's line record (``pass`` is a keyword in Python, hence ``passed`` here)."""
        return {
            "family": self.family,
            "index": self.index,
            "position_mm": self.position_mm,
            "sz_mm2": self.sz_mm2,
            "sz_avg_mm": self.sz_avg_mm,
            "zmax_mm": self.zmax_mm,
            "zmax_at_mm": self.zmax_at_mm,
            "ci": self.ci,
            "sc_avg_per_mm": self.sc_avg_per_mm,
            "cmax_per_mm": self.cmax_per_mm,
            "length_mm": self.length_mm,
            "grade": self.grade,
            "pass": self.passed,
        }


def estimate_noise_mm(h_mm: np.ndarray) -> float:
    """Noise level (mm) of evenly spaced samples from their second differences, robustly.

    For white noise sigma, the second difference has standard deviation sigma * sqrt(6); a smooth
    plate curve contributes only f'' * step^2 (about 5e-4 mm at 1 mm steps on a 2 m radius). The
    median absolute deviation keeps dents and edges from inflating the estimate.
    """
    h = np.asarray(h_mm, dtype=np.float64)
    h = h[np.isfinite(h)]
    if len(h) < 5:
        return 0.0
    d2 = np.diff(h, 2)
    return float(1.4826 * np.median(np.abs(d2 - np.median(d2))) / np.sqrt(6.0))


def _spline(x: np.ndarray, y: np.ndarray, sigma: float) -> UnivariateSpline:
    ok = np.isfinite(y)
    if ok.sum() < 6:
        raise MetricsError(f"a section needs at least 6 finite samples, got {int(ok.sum())}")
    return UnivariateSpline(x[ok], y[ok], k=3, s=float(ok.sum()) * sigma**2)


def _curvature(f: UnivariateSpline, x: np.ndarray) -> np.ndarray:
    d1 = f.derivative(1)(x)
    d2 = f.derivative(2)(x)
    return d2 / (1.0 + d1**2) ** 1.5


def line_metrics(
    s_mm: np.ndarray,
    design_h_mm: np.ndarray,
    measured_h_mm: np.ndarray,
    *,
    noise_mm: float | None = None,
    design_sigma_mm: float = 0.005,
    smoothing_factor: float = 1.0,
    resolution_mm: float = 0.1,
    family: str = "",
    index: int = 0,
    position_mm: float = 0.0,
) -> LineMetrics:
    """SZ, SZ-average, Zmax, CI, SC-average, Cmax of one line (not yet judged).

    s_mm: (n,) increasing positions along the line, mm. design_h_mm, measured_h_mm: (n,) heights
    along the deflection direction, mm (NaN = no data). noise_mm: the measurement noise (1 sigma);
    None estimates it from the measured samples (:func:`estimate_noise_mm`). design_sigma_mm: the
    design mesh's chordal error, so its facet kinks do not read as curvature.
    smoothing_factor scales the smoothing (s = factor * n * sigma^2). Integrals use the trapezoid
    rule on a ``resolution_mm`` grid over the common domain [a, b] of finite samples.
    """
    x = np.asarray(s_mm, dtype=np.float64)
    hd = np.asarray(design_h_mm, dtype=np.float64)
    hm = np.asarray(measured_h_mm, dtype=np.float64)
    if x.ndim != 1 or hd.shape != x.shape or hm.shape != x.shape:
        raise MetricsError(
            f"s_mm, design_h_mm, measured_h_mm must be equal (n,) arrays, got {x.shape}, {hd.shape}, {hm.shape}"
        )
    if len(x) < 2 or np.any(np.diff(x) <= 0):
        raise MetricsError("s_mm must be strictly increasing with at least 2 samples")
    both = np.isfinite(hd) & np.isfinite(hm)
    if both.sum() < 6:
        raise MetricsError(f"design and measurement overlap in only {int(both.sum())} samples")
    a, b = float(x[both][0]), float(x[both][-1])
    sigma = estimate_noise_mm(hm) if noise_mm is None else float(noise_mm)
    if sigma < 0:
        raise MetricsError(f"noise_mm must be >= 0, got {sigma}")
    fd = _spline(x, hd, design_sigma_mm * np.sqrt(smoothing_factor))
    fm = _spline(x, hm, max(sigma, design_sigma_mm) * np.sqrt(smoothing_factor))
    n = max(int(np.ceil((b - a) / resolution_mm)), 1) + 1
    xs = np.linspace(a, b, n)
    d = fd(xs) - fm(xs)
    ad = np.abs(d)
    sz = float(np.trapezoid(ad, xs))
    k = int(np.argmax(ad))
    ds_dx = np.sqrt(1.0 + fd.derivative(1)(xs) ** 2)
    length = float(np.trapezoid(ds_dx, xs))
    dk = np.abs(_curvature(fd, xs) - _curvature(fm, xs))
    ci = float(np.trapezoid(dk * ds_dx, xs))
    return LineMetrics(
        family=family,
        index=index,
        sz_mm2=sz,
        sz_avg_mm=sz / (b - a) if b > a else 0.0,
        zmax_mm=float(ad[k]),
        zmax_at_mm=float(xs[k]),
        ci=ci,
        sc_avg_per_mm=ci / length if length > 0 else 0.0,
        cmax_per_mm=float(dk.max()),
        length_mm=length,
        a_mm=a,
        b_mm=b,
        noise_mm=sigma,
        position_mm=float(position_mm),
    )


def judge_line(m: LineMetrics, tol: Tolerances) -> LineMetrics:
    """``m`` with its grade and pass flag under ``tol``."""
    if m.zmax_mm <= tol.deviation_standard_mm:
        grade = "standard"
    elif m.zmax_mm <= tol.deviation_limit_mm:
        grade = "limit"
    else:
        grade = "out"
    ok = grade == "standard" or (grade == "limit" and tol.judge_at == "limit")
    if tol.cmax_limit_per_mm is not None and m.cmax_per_mm > tol.cmax_limit_per_mm:
        ok = False
    return LineMetrics(**{**m.__dict__, "grade": grade, "passed": ok})


@dataclass(frozen=True)
class Verdict:
    """The plate's judgement: every line judged, the overall verdict, the worst line."""

    verdict: str
    lines: list[LineMetrics]
    tolerances: Tolerances
    worst_zmax_mm: float
    failed: list[tuple[str, int]] = field(default_factory=list)


def judge(lines: list[LineMetrics], tol: Tolerances = Tolerances()) -> Verdict:
    """Judge every line; the plate passes when every line does (and there is at least one line)."""
    judged = [judge_line(m, tol) for m in lines]
    failed = [(m.family, m.index) for m in judged if not m.passed]
    verdict = "pass" if judged and not failed else "fail"
    worst = max((m.zmax_mm for m in judged), default=float("nan"))
    return Verdict(verdict, judged, tol, worst, failed)
