"""Per-line templates (the paper's 2D case) against fits worked out by hand on analytic sections."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.optimize import minimize

from analysis.template_fit import TemplateFitError, check_mode, fit_line_template, line_rest_samples
from analysis.templates import _make_line


def test_straight_template_rests_on_the_two_bumps_it_must_clear():
    # A straight design over 0..1000 mm; the section is flat at 0 but for two 3 mm bumps, 1 mm high at
    # s = 100 and 2 mm high at s = 900. By hand: the least-squares line above both bumps passes
    # through both tops (lowering either end lowers the objective until it touches); rising, it
    # touches the tops' left edges, s = 99 and 899: h(s) = 1 + (s - 99) / 800 -- a rotation by
    # atan(1/800) in the section plane and a lift.
    s = np.arange(0.0, 1001.0)
    h = np.zeros_like(s)
    h[(s >= 99) & (s <= 101)] = 1.0
    h[(s >= 899) & (s <= 901)] = 2.0
    fit = fit_line_template(s, np.zeros_like(s), s, h)
    assert fit.converged and fit.penetrating_after == 0 and fit.min_gap_mm >= 0.0
    assert fit.angle_rad == pytest.approx(math.atan(1.0 / 800.0), rel=1e-6)
    got = fit.moved_heights(s, np.zeros_like(s), s)
    np.testing.assert_allclose(got[50:950], 1.0 + (s[50:950] - 99.0) / 800.0, atol=1e-6)


def test_curved_template_on_a_dented_arc_matches_an_independent_solver_and_reads_the_dent():
    # The design is an arc; the measured section is that arc turned by 0.2 degrees, moved by
    # (1.5, 0.4) mm and dented 0.8 mm deep. Undoing the motion touches everywhere but the dent, yet
    # is not quite the optimum: a curved template rocks a little into a dent (a quadratic change of
    # the gaps, positive on both sides, negative over the dent, is open to it). So the check is
    # against SLSQP on the same three unknowns, and the dent's depth is read within 0.01 mm.
    R = 3000.0
    s = np.arange(0.0, 801.0)
    hd = -((s - 400.0) ** 2) / (2 * R)
    a, ts, th = math.radians(0.2), 1.5, 0.4
    ms = 400.0 + math.cos(a) * (s - 400.0) - math.sin(a) * hd + ts
    mh = math.sin(a) * (s - 400.0) + math.cos(a) * hd + th
    grid = np.arange(10.0, 791.0)
    meas = np.interp(grid, ms, mh) - 0.8 * np.exp(-((grid - 250.0) ** 2) / (2 * 20.0**2))
    # the paper's problem as posed: no anchoring of the slide along the line
    fit = fit_line_template(s, hd, grid, meas, slide_weight=0.0)
    assert fit.penetrating_after == 0 and fit.converged
    d = fit.moved_heights(s, hd, grid) - meas
    assert np.isfinite(d).all() and d.min() >= -1e-9
    assert d.max() == pytest.approx(0.8, abs=0.01)

    def gaps(x):
        f = dataclasses.replace(fit, angle_rad=x[0], shift_s_mm=x[1], shift_h_mm=x[2])
        return f.moved_heights(s, hd, grid) - meas

    x0 = np.array([a, ts, th + 0.5])  # (about the fit's pivot: a start, not the answer)
    res = minimize(lambda x: float(gaps(x) @ gaps(x)), x0, method="SLSQP",
                   constraints=[{"type": "ineq", "fun": gaps}], options={"ftol": 1e-12, "maxiter": 300})  # fmt: skip
    g = gaps(res.x)
    g = g - min(g.min(), 0.0)  # SLSQP may stop a hair infeasible: lift it to feasibility
    assert fit.objective_mm2 <= float(g @ g) * (1 + 1e-3)  # both stop on a nearly free slide
    hand = np.interp(grid, ms, mh) - meas  # the gaps of the motion undone: the dent alone
    assert fit.objective_mm2 <= float(hand @ hand)


def test_rest_samples_bin_the_points_near_the_line_and_bound_their_error():
    rng = np.random.default_rng(4)
    line = _make_line("transverse", 1, np.array([0.0, 0.0, 0.0]), np.array([0.0, 400.0, 0.0]),
                      np.array([0.0, 0.0, 1.0]), 0.0)  # fmt: skip
    xy = rng.uniform([-30.0, 0.0], [30.0, 400.0], (200_000, 2))
    sigma = 0.05
    P = np.column_stack([xy, rng.normal(0.0, sigma, len(xy))])
    s = np.arange(0.0, 401.0)
    rest = line_rest_samples(P, -P[:, 2], line, s, np.zeros_like(s), sigma)
    assert rest.bound_mm <= 0.25 * sigma * 1.0001
    assert np.abs(rest.h_mm).max() < rest.bound_mm
    assert rest.counts.sum() < 0.2 * len(P)  # only the 10 mm band around the line


def test_unknown_mode_and_too_few_samples_are_refused():
    with pytest.raises(TemplateFitError, match="rigid, per_line"):
        check_mode("floating")
    with pytest.raises(TemplateFitError, match="at least 3"):
        fit_line_template(np.arange(10.0), np.zeros(10), np.array([1.0]), np.array([0.0]))


def test_a_line_template_rests_on_raised_ends_not_below_them():
    # 1 mm of springback decaying over 60 mm at both ends of a straight 400 mm section: the template
    # touches the ends, where the plate stands highest; end-bin centroids alone let it sink by the
    # rise over half a bin (about 0.1 mm here). The ends are held by a line through the end bins.
    rng = np.random.default_rng(5)
    line = _make_line("transverse", 1, np.array([0.0, 0.0, 0.0]), np.array([0.0, 400.0, 0.0]),
                      np.array([0.0, 0.0, 1.0]), 0.0)  # fmt: skip
    sigma, a, d = 0.05, 1.0, 60.0

    def plate(s):
        return a * (np.exp(-s / d) + np.exp(-(400.0 - s) / d))

    xy = rng.uniform([-5.0, 0.0], [5.0, 400.0], (8_000, 2))
    P = np.column_stack([xy, plate(xy[:, 1]) + rng.normal(0.0, sigma, len(xy))])
    s = np.arange(0.0, 401.0)
    rest = line_rest_samples(P, -P[:, 2], line, s, np.zeros_like(s), sigma)
    assert rest.bound_mm <= 0.25 * sigma * 1.0001
    assert rest.s_mm[0] < 1.0 and rest.s_mm[-1] > 399.0  # the ends themselves carry the template
    fit = fit_line_template(s, np.zeros_like(s), rest.s_mm, rest.h_mm)
    assert fit.penetrating_after == 0
    ends = np.array([xy[:, 1].min(), xy[:, 1].max()])
    sink = fit.moved_heights(s, np.zeros_like(s), ends) - plate(ends)
    assert np.abs(sink).max() < 0.05, sink
    # without the end samples (the bins' centroids alone) the template sinks below both ends
    inner = slice(1, -1)
    old = fit_line_template(s, np.zeros_like(s), rest.s_mm[inner], rest.h_mm[inner])
    assert (old.moved_heights(s, np.zeros_like(s), ends) - plate(ends)).max() < -0.05
