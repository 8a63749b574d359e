"""The measurement end to end: a full-process job (sim, daemon, worker through Zenoh on loopback) on
the simulated plate with its known forming error, its figures compared with ``sim-truth.json``; the
worker that did it shares none of the daemon's files; and the job leaks no secret.

Its own cell: the shared one of test_cell_e2e.py runs a plate without forming error (its half-turn
case needs one that a half turn maps onto itself), against which a measurement proves nothing. One
scan (about a minute of CI) serves every case here:

* its only worker runs in a mount namespace of its own with the daemon's directory hidden (the
  design comes by hash over Zenoh, the results go back over Zenoh), and the daemon renders HTML and
  PDF from its own copy; the cases on the figures read the results the daemon stored, which is what
  any worker's results become;
* the cell runs with known, unique secret values (the RWS password from the environment, the Zenoh
  password from a secrets file and the dictionary, access control on); afterwards every log line,
  every file under the data directories (the daemon's and the worker's: job.json, report.json,
  results, raw files, the renders), every error reply and every state, event and report
  publication is searched for them. That case runs last: it stops the cell, so that every log is
  complete.
"""

from __future__ import annotations

import asyncio
import json
import subprocess
import uuid
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pytest

from cellctl.api import ApiCallError, Keys, TriggerAccepted, call
from cellctl.api.session import close_session, subscribe
from cellctl.commands.demo_cmd import DEMO_DESIGN, to_toml, wait_html_report
from cellctl.commands.scan_cmd import StatusFollower
from cellctl.config import load_config
from tests.support.e2e_cell import Cell, open_client, tiny_cell_config, trigger_demo_plate, wait_status
from tests.support.isolated import hidden_mounts_command, start_hidden
from tests.support.truth_check import TruthDeviation

pytestmark = [pytest.mark.slow, pytest.mark.e2e]

RWS_SECRET = f"rws-{uuid.uuid4().hex}"
ZENOH_SECRET = f"zen-{uuid.uuid4().hex}"


@pytest.fixture(scope="module")
def worker_dir(tmp_path_factory) -> Path:
    """The worker's own directory: its cell.toml and data directory, nothing of the daemon's."""
    return tmp_path_factory.mktemp("worker")


@pytest.fixture(scope="module")
def secrets_env(tmp_path_factory) -> dict[str, str]:
    """The cell's secrets: the RWS password in the environment, the Zenoh password and the
    dictionary of user passwords in secrets files (mode 600 in a directory of mode 700)."""
    secrets = tmp_path_factory.mktemp("secrets")
    secrets.chmod(0o700)
    pw_file = secrets / "zenoh.secret"
    pw_file.write_text(ZENOH_SECRET + "\n")
    pw_file.chmod(0o600)
    dictionary = secrets / "zenoh-users.txt"
    dictionary.write_text(f"cellctl:{ZENOH_SECRET}\n")
    dictionary.chmod(0o600)
    return {
        "CELL_RWS_PASSWORD": RWS_SECRET,
        "CELL_ZENOH__ACCESS__ENABLED": "true",
        "CELL_ZENOH__ACCESS__PASSWORD_FILE": str(pw_file),
        "CELL_ZENOH__ACCESS__DICTIONARY_FILE": str(dictionary),
    }


@pytest.fixture(scope="module")
def cell(tmp_path_factory, worker_dir: Path, secrets_env: dict[str, str]):
    """The cell (sim, daemon rendering HTML and PDF, access control on) and its only worker, "far",
    which sees none of the daemon's files."""
    out = tmp_path_factory.mktemp("measured")
    # the default forming error (a dent, a bump, spring-back); the arm starts at cell.toml's home,
    # 1.6 m up: of the tiny cells, this one's first job makes the long approach to the plan's start
    c = Cell(out, tiny_cell_config(out, parked=False))
    c.procs.env.update(secrets_env)
    c.procs.env["CELL_DAEMON__WRITE_HTML_REPORT"] = "true"
    # the worker's own cell.toml, in its own directory: its data dir is relative to its cwd
    wcfg = load_config(c.config_path).model_dump(mode="json")
    wcfg["worker"]["data_dir"] = "own-data"
    (worker_dir / "cell.toml").write_text(to_toml(wcfg), encoding="utf-8")
    with pytest.MonkeyPatch.context() as mp:  # our own client's config, with the access settings
        for k, v in secrets_env.items():
            mp.setenv(k, v)
        c.cfg = load_config(c.config_path)
    assert c.cfg.zenoh.access.enabled
    c.start(worker=False)
    try:
        far = start_hidden(
            "worker", [out], worker_dir, ["worker", "--config", "cell.toml", "--worker-id", "far"],
            c.procs.env, worker_dir / "logs",
        )  # fmt: skip
        c.procs.procs.append(("far", far))  # stopped first, like a cell's own worker
        yield c
    finally:
        codes = c.stop()  # nothing left to stop when the secrets case ran (it stops the cell)
        assert all(code == 0 for code in codes.values()), (codes, (out / "logs").as_posix())


class Scanned(NamedTuple):
    """The module's one job: id, final state and message, the HTML report the daemon rendered after
    it, and what its client saw: every publication and every reply."""

    job_id: str
    state: str
    message: str
    html: str | None
    published: list[bytes]
    replies: list[str]


@pytest.fixture(scope="module")
def scanned(cell: Cell) -> Scanned:
    """A trigger the daemon refuses (a design path reaching for the secrets file), then one job on
    the plate, followed to its end and on to its HTML report (None if none within 300 s; waited for
    here, so that the cell never stops in the middle of the render)."""
    published: list[bytes] = []
    replies: list[str] = []

    async def go() -> Scanned:
        session = await open_client(cell.cfg)
        keys = Keys(cell.cfg.key_prefix)
        follower = StatusFollower(session, keys)
        subs = [
            subscribe(session, key, lambda s: published.append(s.payload.to_bytes()))
            for key in (keys.state, keys.report("*"), keys.job_event("*"))
        ]
        try:
            await wait_status(follower, lambda s: s.state.value == "idle" and s.workers, 180.0)
            pl = cell.cfg.sim.placement
            bad = {"plate_id": "measured", "design": "../zenoh.secret",
                   "placement": {"pos_mm": list(pl.pos_mm), "rpy_deg": [0.0, 0.0, pl.angle_deg]}}  # fmt: skip
            with pytest.raises(ApiCallError) as refused:
                await call(session, keys.trigger, json.dumps(bad), TriggerAccepted)
            replies.append(str(refused.value))
            acc, (state, message, _report) = await trigger_demo_plate(cell.cfg, "measured")
            replies.extend([acc.model_dump_json(), message])
            html = None
            if state == "done":
                html = await asyncio.to_thread(
                    wait_html_report, Path(cell.cfg.cell.data_dir), acc.job_id, 300.0
                )
            return Scanned(acc.job_id, state, message, html, published, replies)
        finally:
            for s in subs:
                s.undeclare()
            follower.close()
            await asyncio.to_thread(close_session, session)

    return asyncio.run(go())


def _truth(cell: Cell, job_dir: Path, report: dict) -> TruthDeviation:
    return TruthDeviation(
        Path(cell.cfg.cell.data_dir) / "sim-truth.json", report, cell.out / "designs" / DEMO_DESIGN
    )


# Tolerances of the measurement against the simulator's truth. The sensor's noise is 0.02 mm (1
# sigma) and the analysis reconstructs the surface in cells of a few points; the simulator renders
# the formed plate from a 4 mm mesh (chord error under 0.02 mm on the dent).
ZMAX_TOL_MM = 0.15  # per line: reported Zmax vs the forming error's Zmax on the same line
PROFILE_MEDIAN_TOL_MM = 0.05  # per line: median |measured - true| deviation along it
FIELD_MEDIAN_TOL_MM = 0.05  # the deviation field over the plate: median |measured - true|
FIELD_P99_TOL_MM = 0.3  # ... and its 99th percentile (edges, where cells hold few points)
REGISTRATION_INPLANE_TOL_MM = 1.5  # the registered design vs the true plate at its corners, in plane
REGISTRATION_HEIGHT_TOL_MM = 3.0  # ... and in height (the dent is 2.5 mm deep)


def test_the_reported_deviations_are_the_forming_error_the_simulator_put_in(cell: Cell, scanned):
    """The measurement end to end: per-line Zmax, the deviation along each line and the deviation
    field of the job's results equal what the simulated plate's known forming error gives
    (``sim-truth.json``) on the same lines, for the registration the analysis reported."""
    job_id, state, message = scanned.job_id, scanned.state, scanned.message
    assert state == "done", message
    job_dir = cell.jobs_dir / job_id
    report = json.loads((job_dir / "report.json").read_text())
    results = np.load(job_dir / "results" / "results.npz")
    truth = _truth(cell, job_dir, report)
    assert not truth.error.is_zero, "the simulated plate carries a forming error"

    lines = report["lines"]
    assert len(lines) == len(
        [k for k in results.files if k.endswith("_deviation_mm") and k.startswith("line")]
    )
    figures = []
    for k, line in enumerate(lines):
        s = results[f"line{k}_s_mm"]
        measured = results[f"line{k}_deviation_mm"]
        ok = np.isfinite(measured)
        expected = truth.line_deviation_mm(line, s[ok])
        zmax_true = float(np.max(np.abs(expected)))
        figures.append(
            (line["name"], line["zmax_mm"], zmax_true, float(np.median(np.abs(measured[ok] - expected))))
        )
    assert all(abs(z - zt) <= ZMAX_TOL_MM for _, z, zt, _ in figures), figures
    assert all(m <= PROFILE_MEDIAN_TOL_MM for *_, m in figures), figures
    assert max(zt for _, _, zt, _ in figures) > 0.5, figures  # the lines cross the dent or the bump

    xy_plate = results["plate_xy_mm"].astype(np.float64)
    T_design_plate = np.linalg.inv(truth.T_plate_design)
    xy = xy_plate @ T_design_plate[:2, :2].T + T_design_plate[:2, 3]
    diff = np.abs(results["plate_deviation_mm"] - truth.deviation_mm(xy[:, 0], xy[:, 1]))
    assert diff.size > 1000
    assert np.median(diff) <= FIELD_MEDIAN_TOL_MM and np.percentile(diff, 99) <= FIELD_P99_TOL_MM, (
        np.median(diff),
        np.percentile(diff, 99),
        diff.max(),
    )


def test_the_registered_design_lies_where_the_true_plate_lies(cell: Cell, scanned):
    """The registration against the truth: the design, registered onto the cloud, sits where the
    simulator put the plate (``T_base_plate`` in sim-truth.json)."""
    job_id, state, message = scanned.job_id, scanned.state, scanned.message
    assert state == "done", message
    job_dir = cell.jobs_dir / job_id
    report = json.loads((job_dir / "report.json").read_text())
    truth = _truth(cell, job_dir, report)
    # In its plane within a millimetre or so at the corners (the boundary anchors it); in height
    # where the non-penetrating rest on the formed plate puts it (at most the forming error's depth).
    corners = np.array([[x, y, 0.0, 1.0] for x in (-150.0, 150.0) for y in (-100.0, 100.0)])
    moved = (truth.M @ corners.T)[:3] - corners.T[:3]
    assert np.hypot(moved[0], moved[1]).max() < REGISTRATION_INPLANE_TOL_MM, moved
    assert np.abs(moved[2]).max() < REGISTRATION_HEIGHT_TOL_MM, moved


def test_a_worker_that_sees_none_of_the_daemons_files_completes_a_job_rendered_at_the_daemon(
    cell: Cell, worker_dir: Path, scanned
):
    """The worker's namespace hides the daemon's directory: the design came by hash over Zenoh, the
    results went back over Zenoh into the daemon's results directory, and the daemon rendered HTML
    and PDF from its own copy."""
    wdir = worker_dir
    design = Path(cell.cfg.cell.designs_dir) / DEMO_DESIGN
    # the premise: in the worker's namespace the design (and all of the daemon's data) is unreachable
    probe = subprocess.run(hidden_mounts_command([cell.out], wdir, ["test", "-e", str(design)]), check=False)
    assert design.exists() and probe.returncode == 1
    job_id, state, message, html = scanned.job_id, scanned.state, scanned.message, scanned.html
    assert state == "done", message
    results = cell.jobs_dir / job_id / "results"
    rec = cell.job_record(job_id)
    assert rec["info"]["worker_id"] == "far"
    # everything the job keeps came over Zenoh into the daemon's results directory
    for name in ("report.json", "report.csv", "results.npz", "cloud.ply"):
        assert (results / name).stat().st_size > 0, name
    assert json.loads((results / "report.json").read_text())["job_id"] == job_id
    assert rec["info"]["results_bytes"] >= sum(
        (results / n).stat().st_size for n in ("results.npz", "cloud.ply")
    )
    assert html is not None and Path(html).stat().st_size > 0
    assert (results / "report.pdf").stat().st_size > 0
    # the worker cached the design by its hash in its own directory, and kept no results
    cached = list((wdir / "own-data" / "designs").glob(f"*/{DEMO_DESIGN}"))
    assert len(cached) == 1 and cached[0].read_bytes() == design.read_bytes()
    assert not any((wdir / "own-data" / "jobs").iterdir())


def _files_under(root: Path) -> list[Path]:
    return [p for p in root.rglob("*") if p.is_file()]


def test_the_job_leaks_neither_password_to_logs_files_replies_or_publications(
    cell: Cell, worker_dir: Path, scanned: Scanned
):
    """Runs last: stops the cell (every process must end by itself on SIGTERM), then searches."""
    codes = cell.stop()
    assert codes and all(code == 0 for code in codes.values()), codes
    assert scanned.state == "done", scanned.message
    job_dir = cell.jobs_dir / scanned.job_id
    assert (job_dir / "job.json").is_file() and (job_dir / "report.json").is_file()
    searched = {
        "logs": _files_under(cell.out / "logs"),
        "data": _files_under(Path(cell.cfg.cell.data_dir)),
        "worker": _files_under(worker_dir),
    }
    assert searched["logs"] and len(searched["data"]) >= 3 and searched["worker"]
    assert scanned.published and scanned.replies
    for secret in (RWS_SECRET, ZENOH_SECRET):
        needle = secret.encode()
        for where, files in searched.items():
            leaked = [str(p) for p in files if needle in p.read_bytes()]
            assert not leaked, f"{where}: {leaked}"
        assert not [p for p in scanned.published if needle in p]
        assert not [r for r in scanned.replies if secret in r]
