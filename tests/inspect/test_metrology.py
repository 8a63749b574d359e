"""Metrology at real sensor noise (issue 21): the template rests on the plate, not on its noise."""

from __future__ import annotations

import numpy as np
import pytest

from analysis.accuracy import template_lift, true_line_zmax
from analysis.contracts.placement import Placement
from analysis.design.plates import FormingError, GaussianBump, design_mesh, plate_spec
from analysis.pipeline import InspectionSettings, inspect_cloud
from analysis.register.height_field import height_field_from_mesh
from analysis.report.html_page import _compare_html
from analysis.synth import ScanSettings, synthesize_scan
from analysis.templates import DetectionLayout

DENTS = FormingError(bumps=(GaussianBump(0.0, 0.0, -1.5, 40.0), GaussianBump(-180.0, 100.0, -0.8, 30.0)))


def _inspect(noise_mm: float, seed: int, **settings):
    spec = plate_spec("sail", length_mm=600, width_mm=400)
    st = ScanSettings.coarse(
        point_pitch_mm=0.5, points_per_profile=100, profile_step_mm=1.0, noise_mm=noise_mm
    )
    scan = synthesize_scan(spec, DENTS, settings=st, seed=seed)
    T = scan.T_bed_design
    nominal = Placement.on_bed(T[0, 3], T[1, 3], float(np.degrees(np.arctan2(T[1, 0], T[0, 0]))))
    design = design_mesh(spec, pitch_mm=2.0)
    s = InspectionSettings(layout=DetectionLayout(5, 100.0, 3, 100.0, True), **settings)
    return spec, scan, design, inspect_cloud(scan.cloud, design, s, nominal_placement=nominal)


def test_at_0_05_mm_noise_the_template_lifts_under_0_3_sigma_and_every_zmax_is_within_0_1_mm():
    noise = 0.05
    spec, scan, design, ins = _inspect(noise, seed=3, template_fit_compare=True)
    lift = template_lift(height_field_from_mesh(design, 1.0), spec, scan.T_bed_design, ins.T_measured_design)
    assert lift.max_abs_mm < 0.3 * noise, lift
    reg = ins.report.registration
    assert reg.penetration_points == 0
    assert reg.rest_surface.noise_mm == pytest.approx(noise, rel=0.1)
    for cut, line in zip(ins.cuts, ins.report.lines, strict=True):
        truth = true_line_zmax(
            spec, DENTS, scan.T_bed_design, cut.line.start_mm, cut.line.direction, cut.s_mm
        )
        assert abs(line.zmax_mm - truth) < 0.1, (line.name, line.zmax_mm, truth)
    # the report says which fit judged, and carries the other when asked
    assert ins.report.template_fit == "rigid"
    other = ins.report.template_fit_compare
    assert other.template_fit == "per_line" and len(other.lines) == len(ins.report.lines)
    html = _compare_html(ins.report)
    assert (
        'data-compare="per_line"' in html
        and "Zmax rigid" in html
        and html.count("<tr data-line=") == len(other.lines)
    )


def test_per_line_mode_judges_each_line_on_its_own_template_without_penetration():
    _, _, _, ins = _inspect(0.05, seed=4, template_fit="per_line")
    assert ins.report.template_fit == "per_line" and ins.report.template_fit_compare is None
    by_name = {line.name: line for line in ins.report.lines}
    assert all(line.line_fit.penetration_points == 0 for line in ins.report.lines)
    for name in ("T3", "L2"):  # through the 1.5 mm dent
        assert abs(by_name[name].zmax_mm - 1.5) < 0.1, by_name[name]
    assert _compare_html(ins.report) == ""


def test_an_unknown_template_fit_is_refused():
    with pytest.raises(ValueError, match="template_fit"):
        InspectionSettings(template_fit="floating")
