"""A scan cut short (issue 43): re-analysing a job interrupted at pass 9 of 15 failed with IndexError in
the segmentation, and a cloud of part of the plate was refused as "the design does not match the
plate". Now the segmentation takes a last pass of a few profiles, and with the placement the scan was
planned from the analysis reports what was scanned: the lines it covered judged (the same figures as
the whole scan's), the others listed as not scanned, and a verdict that is never ``pass``."""

from __future__ import annotations

import numpy as np
import pytest

from analysis.cloud_io import ScanCloud
from analysis.contracts.job import Report
from analysis.design.plates import plate_spec
from analysis.pipeline import PARTIAL_LINE_COVERAGE, InspectionError, inspect_cloud
from analysis.segment import segment_plate
from analysis.synth import ScanSettings, synthesize_scan


@pytest.fixture(scope="module")
def sail():
    return synthesize_scan(plate_spec("sail"), settings=ScanSettings.coarse(), seed=6)


@pytest.fixture(scope="module")
def whole(sail):
    return inspect_cloud(sail.cloud, sail.design_mesh(), nominal_placement=sail.placement).report


def _cut(scan, before_pass: int, profiles: int | None = None) -> ScanCloud:
    """The scan's passes before ``before_pass``, and the first ``profiles`` profiles of that pass
    (None: none of it; a string "half": half of it), as an interrupted scan leaves them."""
    c = scan.cloud
    keep = c.pass_id < before_pass
    if profiles is not None:
        sel = c.pass_id == before_pass
        prof = c.profile_index[sel]
        keep |= sel & (c.profile_index < prof.min() + profiles)
    return c.subset(keep)


def _cell_cloud(scan, cloud: ScanCloud) -> ScanCloud:
    """``cloud`` as the daemon publishes a scan: profiles numbered by frame over the whole scan."""
    pid = cloud.pass_id.astype(np.int64)
    frames = np.zeros(int(scan.cloud.pass_id.max()) + 1, np.int64)
    np.maximum.at(frames, scan.cloud.pass_id.astype(np.int64), scan.cloud.profile_index.astype(np.int64) + 1)
    start = np.concatenate([[0], np.cumsum(frames + 20)[:-1]])  # 20 transit frames between passes
    return ScanCloud(cloud.xyz_mm, cloud.pass_id, cloud.profile_index + start[pid], cloud.point_index)


@pytest.mark.parametrize("profiles", [3, 4])
def test_a_last_pass_of_a_few_profiles_does_not_break_the_segmentation(sail, profiles):
    # its cells have no smooth region; as the last pass its label offset was the label count
    cloud = _cell_cloud(sail, _cut(sail, 9, profiles))
    res = segment_plate(cloud)  # IndexError before
    assert res.method == "grid" and res.plate_area_mm2 > 1e5


@pytest.mark.slow
@pytest.mark.parametrize(("before_pass", "profiles"), [(9, None), (9, 150), (5, 100), (2, None)])
def test_a_partial_scan_is_reported_for_what_was_scanned(sail, whole, before_pass, profiles):
    cloud = _cell_cloud(sail, _cut(sail, before_pass, profiles))
    ins = inspect_cloud(cloud, sail.design_mesh(), nominal_placement=sail.placement)
    rep = ins.report
    assert Report.model_validate_json(rep.model_dump_json()) == rep  # its file reads back as itself
    cov = rep.coverage
    assert cov.partial is True and cov.fraction < 0.6
    assert rep.verdict in ("incomplete", "fail")  # a part of a plate never passes
    assert rep.verdict == ("fail" if any(not ln.passed for ln in rep.lines) else "incomplete")
    judged = {ln.name: ln for ln in rep.lines}
    missing = {x.name: x.scanned_fraction for x in cov.lines_not_scanned}
    # every line of the plate is either judged or listed as not scanned, never both
    assert set(judged) | set(missing) == {ln.name for ln in whole.lines}
    assert not set(judged) & set(missing) and missing
    assert all(f < PARTIAL_LINE_COVERAGE for f in missing.values())
    # the transverse lines cross the whole width: a scan cut short covers none of them whole
    assert not any(name.startswith("T") for name in judged)
    # the judged lines are the whole scan's lines, seen whole; their figures are the whole scan's
    # but for the registration (the design rests on the part seen, not on the whole plate: observed
    # up to 0.6 mm of Zmax on this forming error)
    full = {ln.name: ln for ln in whole.lines}
    for name, ln in judged.items():
        assert abs(ln.zmax_mm - full[name].zmax_mm) < 1.0, (name, ln.zmax_mm, full[name].zmax_mm)
        assert ln.length_mm > 0.95 * full[name].length_mm
    # registered where the plate lies: in plane from the planned placement (the scan saw no whole
    # edge); the height of corners far from the part seen is an extrapolation, and no line there is judged
    corners = np.asarray(rep.corners_mm)[:, :2]
    true_corners = sail.corners_bed_mm()[:, :2]
    assert min(np.abs(np.roll(corners, k, axis=0) - true_corners).max() for k in range(4)) < 3.0


@pytest.mark.slow
def test_a_whole_scans_report_keeps_its_shape(whole):
    assert whole.verdict in ("pass", "fail")
    assert set(whole.coverage.model_dump()) == {"fraction", "holes_mm2"}  # what every daemon version reads


@pytest.mark.slow
def test_a_partial_scan_without_its_placement_is_refused_with_the_way_to_analyse_it(sail):
    with pytest.raises(InspectionError, match=r"does not match the plate.*placement"):
        inspect_cloud(_cut(sail, 9, None), sail.design_mesh())


@pytest.mark.slow
def test_a_partial_scans_report_renders_what_was_not_scanned(sail, tmp_path):
    from analysis.pipeline import write_results
    from analysis.report.write import write_report

    ins = inspect_cloud(_cut(sail, 5, None), sail.design_mesh(), nominal_placement=sail.placement)
    write_results(ins, tmp_path)
    files = {p.name: p for p in write_report(tmp_path)}
    html = files["report.html"].read_text()
    assert f"{ins.report.verdict.upper()} — plate" in html
    assert "lines not scanned (not judged)" in html and "T1 (" in html
    from cellctl.commands.tables import line_table

    text = line_table(ins.report)  # what `cellctl scan --wait` and `cellctl inspect` print
    assert f"verdict: {ins.report.verdict.upper()}" in text and "partial scan, not judged: T1 (" in text
