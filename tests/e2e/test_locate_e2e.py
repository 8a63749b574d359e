"""The cell finds the plate: the locate run end to end through Zenoh, real processes (sim, daemon).

One module-scoped cell (no worker: neither test reaches the analysis) with its small sail plate laid
at a random placement on a small bed (the simulated scene's ``[sim.placement]``). A trigger without a
placement is located, planned from the placement found and then aborted (the scan itself is the
other e2e tests' subject); a trigger whose placement is 100 mm off is refused with the reason.
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import time

import numpy as np
import pytest

from analysis.contracts.placement import Placement
from analysis.register.locate import placement_offset
from cellctl.api import ControlReply, Keys, TriggerAccepted, call
from cellctl.api.session import close_session
from cellctl.commands.demo_cmd import DEMO_DESIGN, to_toml
from cellctl.commands.scan_cmd import StatusFollower, wait_for_job
from cellctl.config import load_config
from tests.support.e2e_cell import Cell, open_client, tiny_cell_config, wait_status

pytestmark = [pytest.mark.slow, pytest.mark.e2e]

BED_MIN, BED_MAX = (1250.0, -250.0), (1750.0, 250.0)
LENGTH_MM, WIDTH_MM = 300.0, 200.0


def _random_lay(seed: int) -> tuple[float, float, float]:
    """(x, y, yaw) of a 300 x 200 plate lying wholly on the bed, yaw within 80 deg of the convention."""
    rng = np.random.default_rng(seed)
    while True:
        yaw = float(rng.uniform(-80.0, 80.0))
        a = np.deg2rad(yaw)
        hx = abs(np.cos(a)) * LENGTH_MM / 2 + abs(np.sin(a)) * WIDTH_MM / 2 + 20.0
        hy = abs(np.sin(a)) * LENGTH_MM / 2 + abs(np.cos(a)) * WIDTH_MM / 2 + 20.0
        if 2 * hx < BED_MAX[0] - BED_MIN[0] and 2 * hy < BED_MAX[1] - BED_MIN[1]:
            x = float(rng.uniform(BED_MIN[0] + hx, BED_MAX[0] - hx))
            y = float(rng.uniform(BED_MIN[1] + hy, BED_MAX[1] - hy))
            return x, y, yaw


SEED = int(os.environ.get("CELLCTL_LOCATE_SEED", str(int(time.time()) % 100_000)))


@pytest.fixture(scope="module")
def cell(tmp_path_factory):
    out = tmp_path_factory.mktemp("locate-cell")
    path = tiny_cell_config(out)
    cfg = load_config(path).model_dump(mode="json")
    x, y, yaw = _random_lay(SEED)
    cfg["sim"]["placement"].update(pos_mm=[x, y, cfg["sim"]["placement"]["pos_mm"][2]], angle_deg=yaw)
    # a 300 mm plate's edges are short levers for its yaw (half a millimetre of pose or clock error at
    # its ends is 0.2 deg): the passes across always run
    cfg["locate"].update(
        check_given=True, bed_min_xy_mm=list(BED_MIN), bed_max_xy_mm=list(BED_MAX), pass_spacing_mm=120.0,
        across_within_deg=45.0,
    )  # fmt: skip
    path.write_text(to_toml(cfg), encoding="utf-8")
    c = Cell(out, path)
    c.start(worker=False)
    try:
        yield c
    finally:
        codes = c.stop()
        assert all(code == 0 for code in codes.values()), (codes, (out / "logs").as_posix())


def _truth(cell: Cell) -> Placement:
    pl = cell.cfg.sim.placement
    return Placement.on_bed(pl.pos_mm[0], pl.pos_mm[1], pl.angle_deg, z_mm=pl.pos_mm[2])


async def _job(cell: Cell, trigger: dict, *, abort_when_planned: bool) -> tuple[str, str, str]:
    """Trigger; (job id, final state, final message). With ``abort_when_planned`` the job is aborted
    once its scan has been planned from the placement found."""
    session = await open_client(cell.cfg)
    keys = Keys(cell.cfg.key_prefix)
    follower = StatusFollower(session, keys)
    try:
        await wait_status(follower, lambda s: s.state.value == "idle", 120.0)
        acc = await call(session, keys.trigger, json.dumps(trigger), TriggerAccepted)
        if abort_when_planned:
            deadline = time.monotonic() + 240.0
            while time.monotonic() < deadline:
                rec = cell.job_record(acc.job_id)
                if rec["state"] in ("failed", "aborted", "interrupted", "done"):
                    break
                if any(h["message"] == "planned" for h in rec["history"]):
                    await call(
                        session, keys.control("abort"), json.dumps({"job_id": acc.job_id}), ControlReply
                    )
                    break
                await asyncio.sleep(0.5)
        rec = cell.job_record(acc.job_id)
        if rec["state"] in ("failed", "aborted", "interrupted", "done"):  # ended before we followed it
            return acc.job_id, rec["state"], rec["history"][-1]["message"]
        state, message, _ = await wait_for_job(follower, acc.job_id, 240.0)
        return acc.job_id, state, message
    finally:
        follower.close()
        await asyncio.to_thread(close_session, session)


def test_a_plate_laid_at_random_is_found_within_2_mm_and_a_fifth_of_a_degree_and_planned_from(cell: Cell):
    truth = _truth(cell)
    job_id, state, message = asyncio.run(
        _job(cell, {"plate_id": "locate-1", "design": DEMO_DESIGN}, abort_when_planned=True)
    )
    rec = cell.job_record(job_id)
    found = rec["info"].get("placement_found")
    assert found is not None, (SEED, state, message, rec["history"])
    assert found["source"] == "located" and found["given"] is None
    placed = Placement.model_validate(rec["placement"])
    d_mm, d_deg = placement_offset(placed, truth)
    assert d_mm < 2.0 and d_deg < 0.2, (SEED, truth, placed, rec["info"]["locate"])
    assert abs(placed.z_mm - truth.z_mm) < 2.0
    # at 225 mm/s and 200 Hz the profiles are 1.1 mm apart: an edge is seen within about a profile
    assert found["rms_mm"] < 2.0 and found["coverage"] > 0.1
    # the scan was planned from it (then aborted: the scan is the other e2e tests' subject)
    steps = " | ".join(f"{h['state']}: {h['message']}" for h in rec["history"])
    assert any(h["message"] == "planned" for h in rec["history"]), f"seed {SEED}: {steps}"
    assert state == "aborted", message
    # the locate runs' data reached the disk: raw files and the cloud the fit read
    locate_dir = cell.jobs_dir / job_id / "locate"
    assert any(p.name == "cloud.npz" for p in locate_dir.rglob("cloud.npz"))
    assert all((d / "profiles.craw").stat().st_size > 0 for d in locate_dir.iterdir())


def test_a_placement_given_100_mm_off_is_refused_with_the_reason(cell: Cell):
    truth = _truth(cell)
    a = np.deg2rad(truth.yaw_deg + 90.0)  # across the plate: its outline cannot slide there
    wrong = Placement.on_bed(
        truth.x_mm + 100.0 * np.cos(a), truth.y_mm + 100.0 * np.sin(a), truth.yaw_deg, z_mm=truth.z_mm
    )
    trigger = {"plate_id": "locate-2", "design": DEMO_DESIGN, "placement": wrong.model_dump()}
    job_id, state, message = asyncio.run(_job(cell, trigger, abort_when_planned=False))
    assert state == "failed", (SEED, message)
    assert message.startswith("placement refused: the given placement"), message
    said = re.search(r"is (\d+\.\d) mm and (\d+\.\d+) deg from where the plate was found", message)
    assert said is not None and 97.0 < float(said.group(1)) < 103.0, message
    assert "allows 20 mm / 1 deg" in message
    rec = cell.job_record(job_id)
    assert rec["info"]["placement_found"]["source"] == "checked"
    assert 98.0 < rec["info"]["placement_found"]["offset_mm"] < 102.0
    # nothing was scanned: only the locate run's raw data exists
    assert not (cell.jobs_dir / job_id / "raw").exists()
