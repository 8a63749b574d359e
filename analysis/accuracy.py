"""Accuracy of an inspection against the truth of a synthetic scan (benchmarks and tests).

A synthetic plate whose forming error only dents it (every bump of its :class:`FormingError`
points down, no springback, no bend) has an exact resting pose for a template: the design where
the generator put it, ``SynthScan.T_bed_design`` -- it touches the plate everywhere outside the
dents, so no other pose that penetrates nowhere has a lower sum of squared gaps. Against that pose:

* :func:`template_lift` -- how far the fitted design stands above the true undented surface
  (the bias a noisy resting surface gives every figure);
* :func:`true_line_zmax` -- each judged line's Zmax on the exact surfaces, cut where the
  inspection cut it (so the comparison isolates the metrology, not the line placement).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from analysis.design.plates import (
    FormingError,
    PlateSpec,
    design_height_mm,
    edge_inward_distances,
    footprint_bounds,
    footprint_contains,
    forming_dz_mm,
    is_rectangle,
)
from analysis.register.height_field import HeightField
from analysis.register.onesided import deflection_gaps
from analysis.register.transforms import apply_transform, invert_transform


class AccuracyError(ValueError):
    """A truth that cannot serve: the forming error is not dents only."""


def check_dents_only(error: FormingError) -> None:
    """Raise :class:`AccuracyError` unless ``error`` only dents the plate (its resting pose is exact)."""
    if error.springback is not None or error.bend_fraction != 0.0:
        raise AccuracyError("the truth pose is exact only for dents: no springback, no bend")
    up = [b for b in error.bumps if b.amplitude_mm > 0]
    if up:
        raise AccuracyError(f"the truth pose is exact only for dents: {len(up)} bump(s) point up")


@dataclass(frozen=True)
class Lift:
    """The fitted design's height above the true undented surface over the footprint, mm.

    mean_mm: the mean (the template's lift); max_abs_mm: the largest |height| (lift plus tilt);
    min_mm: the lowest (negative: the fitted design dips below the true surface there).
    """

    mean_mm: float
    max_abs_mm: float
    min_mm: float


def template_lift(
    surface: HeightField,
    spec: PlateSpec,
    T_true: np.ndarray,
    T_fit: np.ndarray,
    *,
    inset_mm: float = 10.0,
    step_mm: float = 5.0,
) -> Lift:
    """Heights of the design at ``T_fit`` above the design at ``T_true`` (both design -> measured).

    surface: the design's height field; spec: its plate (the footprint); the grid of design points
    every ``step_mm`` stays ``inset_mm`` inside the footprint's edges.
    """
    if is_rectangle(spec):
        x = np.arange(-spec.length_mm / 2 + inset_mm, spec.length_mm / 2 - inset_mm + 1e-9, step_mm)
        y = np.arange(-spec.width_mm / 2 + inset_mm, spec.width_mm / 2 - inset_mm + 1e-9, step_mm)
        X, Y = np.meshgrid(x, y)
        x, y = X.ravel(), Y.ravel()
    else:  # any outline: the grid over its bounds, kept inset_mm inside every edge
        x0, x1, y0, y1 = footprint_bounds(spec)
        X, Y = np.meshgrid(np.arange(x0, x1 + 1e-9, step_mm), np.arange(y0, y1 + 1e-9, step_mm))
        x, y = X.ravel(), Y.ravel()
        keep = np.all([d >= inset_mm for d, _, _ in edge_inward_distances(spec, x, y)], axis=0)
        x, y = x[keep], y[keep]
    true_pts = apply_transform(T_true, np.column_stack([x, y, design_height_mm(spec, x, y)]))
    gap, _, _, valid = deflection_gaps(surface, true_pts, T_fit, geometry=False)
    g = gap[valid]
    return Lift(float(g.mean()), float(np.abs(g).max()), float(g.min()))


def true_line_zmax(
    spec: PlateSpec,
    error: FormingError,
    T_true: np.ndarray,
    start_mm: np.ndarray,
    direction: np.ndarray,
    s_mm: np.ndarray,
) -> float:
    """Zmax of one line on the exact surfaces: max over the samples of the depth of the dents.

    start_mm, direction: (3,) the line's start and horizontal unit direction, measured frame;
    s_mm: (n,) the sample positions along it. The sample points are taken into the design frame
    (their height does not matter to a dent's depth beyond the placement's tilt squared).
    """
    check_dents_only(error)
    p = np.asarray(start_mm)[None, :] + np.outer(s_mm, direction)
    q = apply_transform(invert_transform(T_true), p)
    inside = footprint_contains(spec, q[:, 0], q[:, 1])
    if not inside.any():
        return float("nan")
    return float(np.abs(forming_dz_mm(spec, error, q[inside, 0], q[inside, 1])).max())
