"""End to end through Zenoh on loopback, real processes: sim, daemon, worker.

One module-scoped cell serves the trigger tests and the scan; the slow scan is marked ``slow``.
"""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import numpy as np
import pytest

from analysis.contracts.job import Report
from analysis.contracts.placement import Placement, placement_transform
from analysis.design.mesh import load_mesh
from analysis.pipeline import design_corners_from_mesh
from cellctl.api import MAX_TRIGGER_BYTES, ApiCallError, Keys, TriggerAccepted, call
from cellctl.api.session import close_session
from cellctl.commands.demo_cmd import DEMO_DESIGN
from cellctl.commands.scan_cmd import StatusFollower, wait_for_job
from tests.support.e2e_cell import Cell, open_client, tiny_cell_config, wait_status

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def cell(tmp_path_factory):
    out = tmp_path_factory.mktemp("cell")
    # A plate without forming error, the same after a half turn, laid at -87 deg: the bed convention
    # (corner 0 starts the long edge pointing within 90 deg of +x) then agrees with this lay, and the
    # lay turned by 180 deg (93 deg) names the opposite corner. (The planner refuses 183 deg, a wrist
    # wrap on joint 6, so the usual 3 deg lay cannot be turned.)
    c = Cell(out, tiny_cell_config(out, forming_error="none", angle_deg=-87.0))
    c.procs.env["CELL_DAEMON__QUEUE_MAX"] = "0"  # the refuse-while-busy mode (the queue: test_queue_e2e)
    c.start()
    try:
        yield c
    finally:
        codes = c.stop()
        # every process ended by itself on SIGTERM
        assert all(code == 0 for code in codes.values()), (codes, (out / "logs").as_posix())


def _trigger(cell: Cell, **changes) -> dict:
    pl = cell.cfg.sim.placement
    req = {"plate_id": "e2e-plate", "design": DEMO_DESIGN,
           "placement": {"pos_mm": list(pl.pos_mm), "rpy_deg": [0.0, 0.0, pl.angle_deg]}}  # fmt: skip
    req.update(changes)
    return req


def _run(coro):
    return asyncio.run(coro)


def test_malformed_oversized_and_unknown_field_triggers_each_get_an_error_and_change_nothing(cell: Cell):
    async def go():
        session = await open_client(cell.cfg)
        keys = Keys(cell.cfg.key_prefix)
        follower = StatusFollower(session, keys)
        try:
            await wait_status(follower, lambda s: s.state.value == "idle")
            bad = {
                "malformed": b"{not json",
                "too_large": json.dumps(_trigger(cell, note="x" * MAX_TRIGGER_BYTES)).encode(),
                "unknown": json.dumps({**_trigger(cell), "speed": 5}).encode(),
                "outside": json.dumps(_trigger(cell, design="../cell.toml")).encode(),
                "missing": json.dumps(_trigger(cell, design="nope.ply")).encode(),
            }
            codes = {}
            for name, payload in bad.items():
                with pytest.raises(ApiCallError) as exc:
                    await call(session, keys.trigger, payload, TriggerAccepted, timeout_s=10.0)
                codes[name] = (exc.value.error.code, exc.value.error.field)
            st = await wait_status(follower, lambda s: True)
            return codes, st
        finally:
            follower.close()
            await asyncio.to_thread(close_session, session)

    codes, st = _run(go())
    assert codes["malformed"] == ("malformed", "payload")
    assert codes["too_large"] == ("too_large", "payload")
    assert codes["unknown"] == ("invalid", "speed")
    assert codes["outside"][0] == "invalid" and codes["outside"][1] == "design"
    assert codes["missing"] == ("design_not_found", "design")
    assert st.state.value == "idle" and st.job is None
    assert not cell.jobs_dir.exists() or not any(cell.jobs_dir.iterdir())


@pytest.fixture(scope="module")
def scanned(cell: Cell):
    """One scan of the simulated plate, with a second trigger sent while it runs."""

    async def go():
        session = await open_client(cell.cfg)
        keys = Keys(cell.cfg.key_prefix)
        follower = StatusFollower(session, keys)
        try:
            await wait_status(follower, lambda s: s.state.value == "idle" and s.workers)
            acc = await call(session, keys.trigger, json.dumps(_trigger(cell)), TriggerAccepted)
            with pytest.raises(ApiCallError) as busy:
                await call(
                    session, keys.trigger, json.dumps(_trigger(cell, plate_id="second")), TriggerAccepted
                )
            state, message, report = await wait_for_job(follower, acc.job_id, 240.0)
            return acc, busy.value, state, message, report
        finally:
            follower.close()
            await asyncio.to_thread(close_session, session)

    return _run(go())


def test_scan_is_analysed_by_the_worker_and_a_trigger_while_busy_is_refused(cell: Cell, scanned):
    acc, busy, state, message, report = scanned
    assert busy.error.code == "busy" and acc.job_id in busy.error.message
    assert state == "done", message
    rec = cell.job_record(acc.job_id)
    assert rec["state"] == "done"
    states = [h["state"] for h in rec["history"]]
    assert (
        states.index("planning") < states.index("scanning") < states.index("analysing") < states.index("done")
    )
    job_dir = cell.jobs_dir / acc.job_id
    assert (job_dir / "raw" / "profiles.craw").stat().st_size > 0
    stored = json.loads((job_dir / "report.json").read_text())
    # the plate is its design (no forming error): it passes, every line within the measurement's scale
    # (sensor noise 0.02 mm, the resting bias a tenth of a millimetre: tests/support/truth_check.py)
    assert stored["job_id"] == acc.job_id and stored["verdict"] == "pass", stored["verdict"]
    assert max(line["zmax_mm"] for line in stored["lines"]) < 0.3, [
        line["zmax_mm"] for line in stored["lines"]
    ]
    assert report is not None and report.verdict == stored["verdict"]
    assert [line["family"] for line in stored["lines"]].count("transverse") == 2
    assert rec["info"]["profiles"] > 1000 and Path(message).exists()
    # only one job was created: the refused trigger left nothing behind
    assert [p.name for p in cell.jobs_dir.iterdir()] == [acc.job_id]


def test_a_half_turned_placement_puts_the_reference_corner_where_the_trigger_says(cell: Cell):
    """The sail without forming error fits the design equally well both ways round: only the operator's
    placement, carried in the job parameters to the analysis, says which corner is the reference."""
    pl = cell.cfg.sim.placement
    turned = Placement.on_bed(pl.pos_mm[0], pl.pos_mm[1], pl.angle_deg + 180.0, z_mm=pl.pos_mm[2])

    async def go():
        session = await open_client(cell.cfg)
        keys = Keys(cell.cfg.key_prefix)
        follower = StatusFollower(session, keys)
        try:
            await wait_status(follower, lambda s: s.state.value == "idle" and s.workers)
            req = _trigger(cell, plate_id="turned", placement=turned.model_dump())
            acc = await call(session, keys.trigger, json.dumps(req), TriggerAccepted)
            state, message, _ = await wait_for_job(follower, acc.job_id, 240.0)
            return acc, state, message
        finally:
            follower.close()
            await asyncio.to_thread(close_session, session)

    acc, state, message = _run(go())
    assert state == "done", message
    job_dir = cell.jobs_dir / acc.job_id
    stored = Report.model_validate_json((job_dir / "report.json").read_text())
    results = Report.model_validate_json((job_dir / "results" / "report.json").read_text())
    assert stored.inputs.placement == turned and results.inputs.placement == turned
    design_c = design_corners_from_mesh(load_mesh(cell.cfg.cell.designs_dir / DEMO_DESIGN))
    T_turned = placement_transform(turned)
    where_said = T_turned[:3, :3] @ design_c[0] + T_turned[:3, 3]
    T_lay = placement_transform(pl.to_placement())
    other_end = T_lay[:3, :3] @ design_c[0] + T_lay[:3, 3]  # the bed convention's choice for this lay
    corner0 = np.asarray(stored.corners_mm[0])
    assert np.linalg.norm((corner0 - where_said)[:2]) < 15.0, (corner0, where_said)
    assert np.linalg.norm((corner0 - other_end)[:2]) > 300.0
