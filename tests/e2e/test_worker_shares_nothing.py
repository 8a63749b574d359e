"""A worker that can see none of the daemon's files completes a job: the design comes by hash over
Zenoh, the results go back over Zenoh, and the daemon renders HTML and PDF from its own copy."""

from __future__ import annotations

import asyncio
import json
import subprocess
from pathlib import Path

import pytest

from cellctl.commands.demo_cmd import DEMO_DESIGN, to_toml, wait_html_report
from cellctl.config import load_config
from tests.support.e2e_cell import Cell, tiny_cell_config, trigger_demo_plate
from tests.support.isolated import hidden_mounts_command, start_hidden

pytestmark = [pytest.mark.slow, pytest.mark.e2e]


def test_a_worker_that_sees_none_of_the_daemons_files_completes_a_job_rendered_at_the_daemon(
    tmp_path_factory,
):
    out = tmp_path_factory.mktemp("cell")
    wdir = tmp_path_factory.mktemp("worker")
    cell = Cell(out, tiny_cell_config(out))
    cell.procs.env["CELL_DAEMON__WRITE_HTML_REPORT"] = "true"
    # the worker's own cell.toml, in its own directory: its data dir is relative to its cwd
    wcfg = load_config(cell.config_path).model_dump(mode="json")
    wcfg["worker"]["data_dir"] = "own-data"
    (wdir / "cell.toml").write_text(to_toml(wcfg), encoding="utf-8")
    design = Path(cell.cfg.cell.designs_dir) / DEMO_DESIGN
    # the premise: in the worker's namespace the design (and all of the daemon's data) is unreachable
    probe = subprocess.run(hidden_mounts_command([out], wdir, ["test", "-e", str(design)]), check=False)
    assert design.exists() and probe.returncode == 1
    worker = None
    cell.start(worker=False)
    try:
        worker = start_hidden(
            "worker", [out], wdir, ["worker", "--config", "cell.toml", "--worker-id", "far"], cell.procs.env,
            wdir / "logs",
        )  # fmt: skip

        acc, (state, message, _report) = asyncio.run(trigger_demo_plate(cell.cfg, "far-plate"))
        assert state == "done", message
        html = wait_html_report(Path(cell.cfg.cell.data_dir), acc.job_id, 300.0)
        results = cell.jobs_dir / acc.job_id / "results"
        rec = cell.job_record(acc.job_id)
        assert rec["info"]["worker_id"] == "far"
        # everything the job keeps came over Zenoh into the daemon's results directory
        for name in ("report.json", "report.csv", "results.npz", "cloud.ply"):
            assert (results / name).stat().st_size > 0, name
        assert json.loads((results / "report.json").read_text())["job_id"] == acc.job_id
        assert rec["info"]["results_bytes"] >= sum(
            (results / n).stat().st_size for n in ("results.npz", "cloud.ply")
        )
        assert html is not None and Path(html).stat().st_size > 0
        assert (results / "report.pdf").stat().st_size > 0
        # the worker cached the design by its hash in its own directory, and kept no results
        cached = list((wdir / "own-data" / "designs").glob(f"*/{DEMO_DESIGN}"))
        assert len(cached) == 1 and cached[0].read_bytes() == design.read_bytes()
        assert not any((wdir / "own-data" / "jobs").iterdir())
    finally:
        if worker is not None:
            worker.terminate()
            try:
                worker.wait(30)
            except subprocess.TimeoutExpired:
                worker.kill()
                worker.wait()
        codes = cell.stop()
        assert all(code == 0 for code in codes.values()), (codes, (out / "logs").as_posix())
