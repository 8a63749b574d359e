"""The streamed analysis (a cloud arriving pass by pass) against the whole-cloud analysis."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from analysis.cloud_io import ScanCloud
from analysis.contracts.job import AnalysisJob, Report
from analysis.contracts.settings import InspectionSettings
from analysis.design.mesh import save_mesh
from analysis.design.plates import FormingError, GaussianBump, design_mesh, plate_spec
from analysis.pipeline import CloudStream, GrowingCloud, InspectionError, analyse_job, concat_clouds
from analysis.segment import pass_cells, segment_plate
from analysis.synth import ScanSettings, synthesize_scan
from analysis.templates import DetectionLayout

SETTINGS = InspectionSettings(layout=DetectionLayout(5, 100.0, 3, 100.0, True))
FIGURES = ("sz_mm2", "sz_avg_mm", "zmax_mm", "zmax_at_mm", "ci", "sc_avg_per_mm", "cmax_per_mm", "length_mm")


def _pass_chunks(cloud: ScanCloud) -> list[ScanCloud]:
    """The cloud cut where its pass changes, in time order (as the daemon streams it)."""
    order = np.argsort(cloud.t_s, kind="stable") if cloud.t_s is not None else np.arange(len(cloud))
    pid = cloud.pass_id[order]
    cuts = np.nonzero(pid[1:] != pid[:-1])[0] + 1
    parts = np.split(order, cuts)
    return [
        ScanCloud(cloud.xyz_mm[i], cloud.pass_id[i], cloud.profile_index[i], cloud.point_index[i],
                  t_s=None if cloud.t_s is None else cloud.t_s[i])
        for i in parts
    ]  # fmt: skip


@pytest.fixture(scope="module")
def plate(tmp_path_factory):
    spec = plate_spec("sail", length_mm=600, width_mm=400)
    error = FormingError(bumps=(GaussianBump(x_mm=50.0, y_mm=-40.0, amplitude_mm=1.5, sigma_mm=60.0),))
    scan = synthesize_scan(spec, error, settings=ScanSettings.coarse(), seed=7)
    path = save_mesh(design_mesh(spec, pitch_mm=2.0), tmp_path_factory.mktemp("design") / "design.ply")
    return scan.cloud, AnalysisJob(job_id="J1", plate_id="P1", design=str(path), settings=SETTINGS)


@pytest.mark.slow
def test_the_streamed_analysis_gives_every_line_the_whole_cloud_figures(plate) -> None:
    cloud, job = plate
    chunks = _pass_chunks(cloud)
    assert len(chunks) >= 3
    stream = CloudStream(job)
    for c in chunks:
        stream.add(c)
    made = sorted(k for k, c in stream._cells.items() if c is not None)
    assert made == sorted({int(c.pass_id[0]) for c in chunks} - {0}), made  # every pass but 0, before the end
    streamed = stream.finish()
    whole = analyse_job(concat_clouds(chunks), job)
    assert streamed.verdict == whole.verdict
    assert [ln.name for ln in streamed.lines] == [ln.name for ln in whole.lines]
    assert len(whole.lines) >= 8
    for a, b in zip(streamed.lines, whole.lines, strict=True):
        for f in FIGURES:
            assert abs(getattr(a, f) - getattr(b, f)) <= 0.005, (a.name, f, getattr(a, f), getattr(b, f))
    np.testing.assert_allclose(streamed.corners_mm, whole.corners_mm, atol=0.005)
    assert streamed.inputs.points == whole.inputs.points == len(cloud)
    # the design's part ran at the stream's start: the final stage did not rasterise it again
    assert streamed.timings_s["design"] < 0.05


def _empty_like(chunk: ScanCloud) -> ScanCloud:
    """A chunk of no rows with the fields of ``chunk`` (the retract's rows, none of which saw the plate)."""
    none = np.zeros(0, dtype=np.int64)
    return ScanCloud(np.zeros((0, 3)), none, none, none, t_s=None if chunk.t_s is None else np.zeros(0))


def _figures(report: Report) -> list[tuple]:
    return [(ln.name, *(getattr(ln, f) for f in FIGURES)) for ln in report.lines]


@pytest.mark.slow
def test_the_analysis_made_ahead_stands_when_the_tail_adds_no_point_and_is_made_again_when_it_does(
    plate,
) -> None:
    cloud, job = plate
    chunks = _pass_chunks(cloud)
    whole = analyse_job(concat_clouds(chunks), job)
    # every pass in, then the retract's rows without a point: the report made ahead is the report
    stream = CloudStream(job)
    for c in chunks:
        stream.add(c)
    stream.ahead()
    made = stream._ahead[1]
    stream.add(_empty_like(chunks[-1]))
    kept = stream.finish()
    assert kept is made and stream.timings_s["ahead_kept"] == 1.0
    assert _figures(kept) == _figures(whole)
    assert kept.inputs.points == whole.inputs.points
    # made ahead of the last pass: the pass's points change the cloud, the analysis runs again
    stream = CloudStream(job)
    for c in chunks[:-1]:
        stream.add(c)
    stream.ahead()
    early = stream._ahead[1]
    stream.add(chunks[-1])
    again = stream.finish()
    assert again is not early and stream.timings_s["ahead_dropped"] == 1.0
    assert _figures(again) == _figures(whole)
    assert early.inputs.points < again.inputs.points == whole.inputs.points
    # a tail without times drops them from the whole cloud: that too is another cloud
    stream = CloudStream(job)
    for c in chunks:
        stream.add(c)
    stream.ahead()
    if chunks[-1].t_s is not None:
        none = np.zeros(0, dtype=np.int64)
        stream.add(ScanCloud(np.zeros((0, 3)), none, none, none))
        assert stream._ahead is None
    stream.close()


def test_an_analysis_that_fails_ahead_fails_at_the_end_with_its_error(plate) -> None:
    _, job = plate
    stream = CloudStream(job)
    stream.ahead()  # nothing arrived yet: nothing is kept
    assert stream._ahead is None
    with pytest.raises(InspectionError, match="no chunk arrived"):
        stream.finish()


def test_the_chunks_concatenated_are_the_cloud_point_for_point(plate) -> None:
    cloud, _ = plate
    chunks = _pass_chunks(cloud)
    cat = concat_clouds(chunks)
    order = np.argsort(cloud.t_s, kind="stable") if cloud.t_s is not None else np.arange(len(cloud))
    np.testing.assert_array_equal(cat.xyz_mm, cloud.xyz_mm[order])
    np.testing.assert_array_equal(cat.pass_id, cloud.pass_id[order])
    np.testing.assert_array_equal(cat.profile_index, cloud.profile_index[order])
    assert concat_clouds(chunks[:1]) is chunks[0]


def test_an_empty_stream_is_a_clear_error(plate, tmp_path) -> None:
    _, job = plate
    stream = CloudStream(job)
    with pytest.raises(InspectionError, match="no chunk arrived"):
        stream.finish()


def test_a_design_that_cannot_be_read_fails_when_the_stream_opens(tmp_path) -> None:
    bad = tmp_path / "design.ply"
    bad.write_text("not a mesh")
    with pytest.raises(InspectionError):
        CloudStream(AnalysisJob(job_id="J2", design=str(bad)))


def test_passes_segmented_one_by_one_select_the_whole_cloud_segmentation(plate) -> None:
    cloud, _ = plate
    chunks = _pass_chunks(cloud)
    cat = concat_clouds(chunks)
    cells, offset = {}, 0
    for c in chunks:
        k = int(c.pass_id[0])
        cells[k] = pass_cells(c.xyz_mm, c.profile_index, c.point_index, np.arange(len(c)) + offset)
        offset += len(c)
    whole = segment_plate(cat)
    streamed = segment_plate(cat, passes=cells)
    np.testing.assert_array_equal(streamed.mask, whole.mask)
    assert streamed.noise_sigma_mm == whole.noise_sigma_mm
    assert streamed.plate_area_mm2 == pytest.approx(whole.plate_area_mm2, rel=1e-9)


@settings(max_examples=60, deadline=None)
@given(
    sizes=st.lists(st.integers(0, 3000), min_size=1, max_size=12),
    organised=st.lists(st.booleans(), min_size=12, max_size=12),
    timed=st.lists(st.booleans(), min_size=12, max_size=12),
    seed=st.integers(0, 2**16),
)
def test_the_stream_grows_the_cloud_chunk_by_chunk_into_the_arrays_concat_clouds_makes(
    sizes, organised, timed, seed
):
    rng = np.random.default_rng(seed)
    chunks = []
    for k, m in enumerate(sizes):
        org = (
            (rng.integers(0, 30, m), rng.integers(0, 10**6, m), rng.integers(0, 500, m))
            if organised[k]
            else ()
        )
        chunks.append(
            ScanCloud(rng.normal(size=(m, 3)) * 100.0, *org, t_s=rng.random(m) if timed[k] else None)
        )
    grown = GrowingCloud()
    for c in chunks:
        grown.append(c)
    got, want = grown.cloud(), concat_clouds(chunks)
    assert got.organised == want.organised and (got.t_s is None) == (want.t_s is None)
    for name in ("xyz_mm", "pass_id", "profile_index", "point_index", "t_s"):
        a, b = getattr(got, name), getattr(want, name)
        assert (a is None and b is None) or (a.dtype == b.dtype and np.array_equal(a, b)), name


def test_a_stream_with_no_chunk_says_the_cloud_is_empty():
    with pytest.raises(InspectionError, match="no chunk arrived"):
        GrowingCloud().cloud()
