"""The daemon <-> worker contract: typed both ways, unknown fields refused, the placement carried through."""

from __future__ import annotations

import json
from functools import cache
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from analysis.contracts.job import AnalysisJob, Report
from analysis.contracts.placement import Placement, placement_transform
from analysis.contracts.settings import InspectionSettings
from analysis.design.mesh import MeshError, save_mesh
from analysis.design.plates import FormingError, design_mesh, plate_spec
from analysis.pipeline import analyse_job, design_corners_from_mesh
from analysis.synth import ScanSettings, synthesize_scan
from analysis.templates import DetectionLayout
from cellctl.analysis_job import analysis_job
from cellctl.api import JobSpec, ReportEnvelope
from cellctl.config import CellConfig

TURNED = Placement.on_bed(40.0, -30.0, 93.0, z_mm=60.0)


def _job(**changes) -> AnalysisJob:
    base = dict(
        job_id="j1", plate_id="P-1", cell_id="c1", design="/designs/sail.ply", placement=TURNED,
        settings=InspectionSettings(layout=DetectionLayout(2, 100.0, 1, 100.0, False), sample_step_mm=2.0),
        out_dir="/data/jobs/j1/results",
    )  # fmt: skip
    return AnalysisJob(**{**base, **changes})


def test_job_spec_goes_through_json_unchanged_with_placement_and_settings():
    spec = JobSpec(attempt=2, job=_job())
    back = JobSpec.model_validate_json(spec.to_json())
    assert back == spec
    assert (back.job_id, back.plate_id) == ("j1", "P-1")
    assert back.job.placement == TURNED and back.job.settings.layout.transverse_count == 2
    assert json.loads(spec.to_json())["job"]["placement"] == {
        "pos_mm": [40.0, -30.0, 60.0],
        "rpy_deg": [0.0, 0.0, 93.0],
    }


@pytest.mark.parametrize(
    "path",
    [
        (),
        ("job",),
        ("job", "placement"),
        ("job", "settings"),
        ("job", "settings", "layout"),
        ("job", "settings", "tolerances"),
    ],
    ids=lambda p: ".".join(p) or "spec",
)
def test_an_unknown_field_anywhere_in_the_job_spec_is_refused_naming_it(path):
    doc = json.loads(JobSpec(attempt=1, job=_job()).to_json())
    node = doc
    for key in path:
        node = node[key]
    node["speed_mm_s"] = 5
    with pytest.raises(ValidationError) as err:
        JobSpec.model_validate(doc)
    assert err.value.errors()[0]["loc"][-1] == "speed_mm_s"


def test_a_placement_out_of_range_or_not_three_numbers_is_refused():
    with pytest.raises(ValidationError, match="pos_mm"):
        Placement(pos_mm=[1.0, 2.0])
    with pytest.raises(ValidationError, match="rpy_deg"):
        Placement(pos_mm=[0.0, 0.0, 0.0], rpy_deg=[0.0, 0.0, 400.0])


def test_placement_transform_maps_the_design_origin_to_pos_and_turns_about_z():
    T = placement_transform(Placement.on_bed(100.0, 50.0, 90.0, z_mm=7.0))
    np.testing.assert_allclose(T @ [0, 0, 0, 1], [100.0, 50.0, 7.0, 1.0])
    np.testing.assert_allclose(T @ [10, 0, 0, 1], [100.0, 60.0, 7.0, 1.0], atol=1e-12)
    tilted = Placement.on_bed(0.0, 0.0, 30.0, tilt_deg=0.5, tilt_axis_deg=10.0)
    R = placement_transform(tilted)[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.degrees(np.arccos(R[2, 2])) == pytest.approx(0.5)  # tilted by 0.5 deg, no more


def test_the_daemon_builds_the_job_from_the_trigger_placement_and_the_cell_settings():
    cfg = CellConfig.model_validate(
        {"cell": {"id": "c7"}, "analysis": {"transverse_count": 3, "diagonals": False}}
    )
    job = analysis_job(
        cfg, job_id="j9", plate_id="P", design="/d/x.ply", placement=TURNED.model_dump(), out_dir=Path("/o")
    )
    assert job.placement == TURNED and job.cell_id == "c7" and job.out_dir == "/o"
    assert job.settings.layout.transverse_count == 3 and not job.settings.layout.diagonals
    assert job.settings.template_fit == "rigid" and not job.settings.template_fit_compare


def test_the_template_fit_of_cell_toml_travels_to_the_analysis_and_a_wrong_one_is_refused():
    cfg = CellConfig.model_validate({"analysis": {"template_fit": "per_line", "template_fit_compare": True}})
    job = analysis_job(
        cfg, job_id="j", plate_id="P", design="/d/x.ply", placement=TURNED.model_dump(), out_dir=Path("/o")
    )
    back = AnalysisJob.model_validate_json(job.model_dump_json())
    assert back.settings.template_fit == "per_line" and back.settings.template_fit_compare
    with pytest.raises(ValidationError, match="template_fit"):
        CellConfig.model_validate({"analysis": {"template_fit": "floating"}})
    with pytest.raises(ValidationError, match="template_fit"):
        AnalysisJob.model_validate({"design": "/d/x.ply", "settings": {"template_fit": "floating"}})


def test_a_report_with_an_unknown_field_is_refused_also_inside_the_envelope():
    with pytest.raises(ValidationError, match="n_points"):
        Report.model_validate({"plate_id": "P", "verdict": "pass", "n_points": 3})
    env = {"job_id": "j", "plate_id": "P", "worker_id": "w", "attempt": 1, "ok": True,
           "report": {"plate_id": "P", "verdict": "maybe"}}  # fmt: skip
    with pytest.raises(ValidationError, match="verdict"):
        ReportEnvelope.model_validate(env)


@cache
def _symmetric_scan():
    """A 600 x 400 sail without forming error (the same after a half turn), laid at -87 deg."""
    spec = plate_spec("sail", length_mm=600, width_mm=400)
    lay = Placement.on_bed(40.0, -30.0, -87.0)
    scan = synthesize_scan(spec, FormingError(), settings=ScanSettings.coarse(), placement=lay, seed=5)
    return spec, scan


def _analyse(tmp_path: Path, placement: Placement | None) -> dict:
    spec, scan = _symmetric_scan()
    tmp_path.mkdir(parents=True, exist_ok=True)
    design = tmp_path / "sail.ply"
    save_mesh(design_mesh(spec, pitch_mm=5.0), design)
    cloud = scan.cloud
    job = _job(design=str(design), placement=placement, out_dir=str(tmp_path / "results"))
    # through JSON, as the worker's child receives it
    return analyse_job(cloud, AnalysisJob.model_validate_json(job.model_dump_json()))


def _where(placement: Placement, design_corner: np.ndarray) -> np.ndarray:
    T = placement_transform(placement)
    return T[:3, :3] @ design_corner + T[:3, 3]


def test_the_job_placement_reaches_the_analysis_and_picks_the_reference_corner(tmp_path):
    spec, scan = _symmetric_scan()
    c0 = design_corners_from_mesh(design_mesh(spec, pitch_mm=5.0))[0]
    lay = scan.placement
    turned = Placement.on_bed(lay.x_mm, lay.y_mm, lay.yaw_deg + 180.0)
    report = _analyse(tmp_path / "turned", turned)
    corner0 = np.asarray(report.corners_mm[0])
    assert np.linalg.norm((corner0 - _where(turned, c0))[:2]) < 10.0
    assert isinstance(report, Report) and report.inputs.placement == turned
    stored = json.loads((tmp_path / "turned" / "results" / "report.json").read_text())
    assert Placement.model_validate(stored["inputs"]["placement"]) == turned
    # without a placement the bed convention decides: the opposite corner, here where the lay puts it
    unplaced = _analyse(tmp_path / "none", None)
    assert np.linalg.norm((np.asarray(unplaced.corners_mm[0]) - _where(lay, c0))[:2]) < 10.0
    assert unplaced.inputs.placement is None


def test_the_field_tables_of_docs_api_md_are_those_of_the_models():
    from tests.api.api_doc import main

    assert main(["--check"]) == 0, "run: python -m tests.api.api_doc"


def test_the_scan_command_sends_the_placement_it_was_given_as_the_one_placement_type():
    from cellctl.api import TriggerRequest
    from cellctl.commands.scan_cmd import placement_payload

    payload = placement_payload("1500,-20,183", 300.0)
    assert Placement.model_validate(payload) == Placement.on_bed(1500.0, -20.0, 183.0, z_mm=300.0)
    req = TriggerRequest.model_validate({"plate_id": "P", "design": "a.ply", "placement": payload})
    assert req.placement.yaw_deg == 183.0


def test_the_daemon_stats_model_takes_the_egm_endpoint_statistics_as_they_are():
    from cellctl.api import DaemonStats
    from drivers.abb_egm.endpoint import EgmStatistics

    stats = DaemonStats(cell_id="c", t_utc="t", rss_mb=1.0, egm=EgmStatistics().snapshot())
    assert DaemonStats.model_validate_json(stats.to_json()) == stats


@pytest.mark.parametrize("design", ["plate.npz", "plate.json", "plate.txt"])
def test_a_trigger_naming_a_design_the_analysis_cannot_read_is_refused_at_the_api(design):
    """One list of design formats: the trigger accepts what analysis.design.cad.read_design reads, no more."""
    from pydantic import ValidationError

    from analysis.design.cad import DESIGN_SUFFIXES, read_design
    from cellctl.api import DESIGN_SUFFIXES as API_SUFFIXES
    from cellctl.api import TriggerRequest

    assert API_SUFFIXES is DESIGN_SUFFIXES
    with pytest.raises(ValidationError, match="design"):
        TriggerRequest.model_validate({"plate_id": "P", "design": design})
    with pytest.raises(MeshError, match="unsupported design format"):
        read_design(design)
    for ok in DESIGN_SUFFIXES:
        assert TriggerRequest.model_validate({"plate_id": "P", "design": f"plate{ok}"}).design == f"plate{ok}"
