"""A small plate beyond a fixed robot's reach, scanned from the linear track: end to end through
real processes (sim, daemon, worker) on loopback. The track moves during the scan, the plan and the
executed motion carry seven axes, and the worker analyses the cloud assembled in the world frame.

It shares the e2e cell harness (tests/support/e2e_cell.py) and its tiny plate; only the cell.toml
differs: a track along +y and the plate 2.5 m along it.
"""

from __future__ import annotations

import asyncio
import json

import numpy as np
import pytest

from analysis.contracts.placement import Placement
from analysis.design.mesh import load_mesh
from cellctl.acquisition.pipeline import KIND_ROBOT
from cellctl.commands.demo_cmd import DEMO_DESIGN, to_toml
from cellctl.config import load_config
from cellctl.jobstore.rawstore import RawReader
from cellctl.planning import PlannerSettings, PlanRefused
from cellctl.planning.coverage import build_segments, design_surface
from cellctl.planning.joint_path import check_reach
from tests.support.e2e_cell import Cell, tiny_cell_config, trigger_demo_plate

pytestmark = [pytest.mark.slow, pytest.mark.e2e, pytest.mark.process]

PLATE_POS_MM = [1500.0, 2500.0, 300.0]
TRACK_START_MM = 2300.0


def _track_config(out) -> object:
    path = tiny_cell_config(out, forming_error="none")
    cfg = load_config(path).model_dump(mode="json")
    cfg["robot"]["track"] = {
        "travel_min_mm": 0.0,
        "travel_max_mm": 4000.0,
        "margin_mm": 10.0,
        "speed_max_mm_s": 500.0,
        "accel_max_mm_s2": 1000.0,
        "jerk_max_mm_s3": 10000.0,
        "origin_mm": [0.0, 0.0, 0.0],
        "direction": [0.0, 1.0, 0.0],
        # the carriage follows the passes though one position would reach them (hold = false)
        "hold": False,
    }
    cfg["robot"]["egm_max_pos_deviation_deg"] = 5000.0  # covers the track's travel, in mm
    cfg["sim"]["egm_track_start_mm"] = TRACK_START_MM
    cfg["sim"]["placement"]["pos_mm"] = PLATE_POS_MM
    # cell.toml's choice of axis (the tiny cells pin "longer"): here the faster passes run along the
    # track, and the carriage follows them
    cfg["scan"]["pass_axis"] = "fastest"
    path.write_text(to_toml(cfg), encoding="utf-8")
    return path


def test_a_plate_beyond_reach_is_scanned_from_the_moving_track_and_analysed(tmp_path):
    out = tmp_path / "cell"
    out.mkdir()
    config = _track_config(out)
    cfg = load_config(config)
    # without the track, this placement is out of the arm's reach: the track is what makes it work
    fixed = PlannerSettings.from_config(cfg).with_(track=None)
    surface = design_surface(load_mesh(out / "designs" / DEMO_DESIGN))
    segments, _ = build_segments(surface, Placement.on_bed(*PLATE_POS_MM[:2], cfg.sim.placement.angle_deg,
                                                           z_mm=PLATE_POS_MM[2]), fixed)  # fmt: skip
    with pytest.raises(PlanRefused, match="reach"):
        check_reach(segments, fixed)

    cell = Cell(out, config)
    cell.start()
    try:
        acc, (state, message, report) = asyncio.run(trigger_demo_plate(cell.cfg, "track-plate"))
    finally:
        codes = cell.stop()
    assert state == "done", (message, (out / "logs").as_posix())
    assert all(code == 0 for code in codes.values()), codes
    job_dir = cell.jobs_dir / acc.job_id
    # the controller's feedback, as recorded: seven axes, the track first, moving during the scan
    robot = [r.arrays["q_deg"] for r in RawReader(job_dir / "raw").records() if r.kind == KIND_ROBOT]
    q = np.concatenate(robot)
    assert q.shape[1] == 7
    assert q[:, 0].min() >= 10.0 - 1e-6 and q[:, 0].max() <= 3990.0 + 1e-6
    assert q[:, 0].max() - q[:, 0].min() > 100.0, "the track did not move during the scan"
    # not only on the way to the start: the carriage follows the passes over the scan's last 3/4
    assert np.ptp(q[len(q) // 4 :, 0]) > 100.0, "the track did not move while scanning"
    # the worker measured the plate where it lies in the world: the report passes its inspection
    stored = json.loads((job_dir / "report.json").read_text())
    assert stored["job_id"] == acc.job_id and report is not None
    assert stored["verdict"] == "pass"
    # a plate without forming error, measured from poses that carry the track: a pose off by the
    # track's travel would show as millimetres; the world-frame cloud fits its design to microns
    zmax = {line["name"]: round(line["zmax_mm"], 4) for line in stored["lines"]}
    info = json.loads((job_dir / "job.json").read_text())["info"]
    said = {k: info.get(k) for k in ("acquisition", "egm", "sensor", "max_tracking_error_mm")}
    assert max(zmax.values()) < 0.05, (zmax, stored["registration"]["rest_surface"], said)
