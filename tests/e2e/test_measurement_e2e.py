"""The measurement end to end: full-process jobs (sim, daemon, worker through Zenoh on loopback) on
simulated plates with known forming errors, judged against the simulator's truth alone
(tests/support/truth_check.py: the truth's own resting pose of the design on the exact formed
surface, its own figures and verdict); the worker that did the first shares none of the daemon's
files; and that job leaks no secret.

Four plates, one cell each (the shared cell of test_cell_e2e.py runs a plate without forming error,
against which a measurement proves nothing): the 300 x 200 sail with the trigger's placement 20 mm
and 1 degree off the truth, a saddle turned -25 degrees found by the locate run (no placement), a
340 x 220 cylinder turned 12 degrees, the placement 18 mm and 0.6 degree off, under tolerances
that fail its dent, and the sail designed in ship coordinates, given as IGES and scanned from its
formed mesh (``[sim.plate] kind = "mesh"``). Each cell scans once (about a minute and a half of CI each) and is stopped
before its cases read the results, so no case depends on another's order. The sail's job serves
every case here:

* its only worker runs in a mount namespace of its own with the daemon's directory hidden (the
  design comes by hash over Zenoh, the results go back over Zenoh), and the daemon renders HTML and
  PDF from its own copy; the cases on the figures read the results the daemon stored, which is what
  any worker's results become;
* the cell runs with known, unique secret values (the RWS password from the environment, the Zenoh
  password from a secrets file and the dictionary, access control on); after the job the cell is
  stopped and every log line, every file under the data directories (the daemon's and the
  worker's: job.json, report.json, results, raw files, the renders), every error reply and every
  state, event and report publication is searched for them.
"""

from __future__ import annotations

import asyncio
import json
import subprocess
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pytest

from analysis.contracts.placement import Placement
from cellctl.analysis_job import inspection_settings
from cellctl.api import ApiCallError, Keys, TriggerAccepted, call
from cellctl.api.session import close_session, subscribe
from cellctl.commands.demo_cmd import DEMO_DESIGN, to_toml, wait_html_report
from cellctl.commands.scan_cmd import StatusFollower
from cellctl.config import load_config
from tests.support.e2e_cell import (
    IGES_DESIGN,
    Cell,
    iges_ship_plate,
    open_client,
    tiny_cell_config,
    trigger_demo_plate,
    wait_status,
)
from tests.support.isolated import hidden_mounts_command, start_hidden
from tests.support.truth_check import CheckLimits, MeasurementCheck, check_measurement, load_truth

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
        codes = c.stop()  # nothing left to stop once the module's job ran (`scanned` stops the cell)
        assert all(code == 0 for code in codes.values()), (codes, (out / "logs").as_posix())


class Scanned(NamedTuple):
    """The module's one job: id, final state and message, the HTML report the daemon rendered after
    it, what its client saw (every publication and every reply) and each process's exit code when
    the cell was stopped after it."""

    job_id: str
    state: str
    message: str
    html: str | None
    published: list[bytes]
    replies: list[str]
    stop_codes: dict


@pytest.fixture(scope="module")
def scanned(cell: Cell) -> Scanned:
    """A trigger the daemon refuses (a design path reaching for the secrets file), then one job on
    the plate (the trigger's placement 20 mm and 1 degree off the truth), followed to its end and on
    to its HTML report (None if none within 300 s; waited for here, so that the cell never stops in
    the middle of the render). Then the cell is stopped (every process must end by itself on
    SIGTERM), so that every log is complete for the secrets case whatever order the cases run in."""
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
            acc, (state, message, _report) = await trigger_demo_plate(
                cell.cfg, "measured", placement=_off(cell.cfg, PLATES[0])
            )
            replies.extend([acc.model_dump_json(), message])
            html = None
            if state == "done":
                html = await asyncio.to_thread(
                    wait_html_report, Path(cell.cfg.cell.data_dir), acc.job_id, 300.0
                )
            return Scanned(acc.job_id, state, message, html, published, replies, {})
        finally:
            for s in subs:
                s.undeclare()
            follower.close()
            await asyncio.to_thread(close_session, session)

    done = asyncio.run(go())
    return done._replace(stop_codes=cell.stop())


# The plates measured (one cell each; the first is the cell above): kinds, sizes, forming errors and
# poses, and how the trigger gives the placement. "off" places the trigger off the truth by a
# realistic error (the operator's placement; the scan is planned from it and the registration starts
# from nothing of it); None gives no placement: the cell locates the plate first.
@dataclass(frozen=True)
class Plate:
    name: str
    kind: str
    length_mm: float
    width_mm: float
    radii_mm: tuple[float, float]
    pos_xy_mm: tuple[float, float] | None  # None: cell.toml's [sim.placement]
    yaw_deg: float | None
    placement_off: tuple[float, float, float] | None  # (dx mm, dy mm, dyaw deg) from the truth; None: none
    tolerances: dict[str, float]
    iges_ship: bool = False  # designed in ship coordinates, given as IGES; the simulator scans its mesh


PLATES = (
    # the secrets cell's plate: 300 x 200 sail, the default forming error (a 2.5 mm dent, a 1.5 mm
    # bump, 1 mm spring-back), the trigger 20 mm and 1 degree off
    Plate("sail-off-20mm-1deg", "sail", 300.0, 200.0, (4000.0, 3000.0), None, None, (14.14, -14.14, 1.0), {}),
    # a saddle turned -25 degrees, no placement: the locate run finds it
    Plate("saddle-located", "saddle", 300.0, 200.0, (3000.0, 2500.0), (1470.0, 40.0), -25.0, None, {}),
    # a 340 x 220 cylinder (its forming error scaled to it) turned 12 degrees, the trigger 18 mm and
    # 0.6 degree off, judged against tolerances that fail the dent's lines
    Plate("cylinder-off-fails", "cylinder", 340.0, 220.0, (2000.0, 3000.0), (1530.0, -30.0), 12.0,
          (-10.0, 15.0, -0.6), {"deviation_standard_mm": 1.0, "deviation_limit_mm": 2.0}),
    # the first plate designed in ship coordinates (turned 90 degrees, 40 m aft, 3 m up) and given as
    # IGES; the simulator scans its formed surface from a mesh file in the same coordinates
    # ([sim.plate] kind = "mesh", 1 mm grid), the truth is that mesh; its pose and the trigger's error
    # the first plate's (at -8 degrees and (1480, 20) the product rests this sail 0.122 mm low: a
    # sparse stripe between passes over its bump's top; docs/testing.md)
    Plate("sail-iges-ship", "sail", 300.0, 200.0, (4000.0, 3000.0), None, None, (14.14, -14.14, 1.0), {},
          iges_ship=True),
)  # fmt: skip
LOCATE = {"check_given": True, "bed_min_xy_mm": [1250.0, -250.0], "bed_max_xy_mm": [1750.0, 250.0],
          "pass_spacing_mm": 120.0, "across_within_deg": 45.0}  # fmt: skip


def _off(cfg, plate: Plate) -> Placement | None:
    """The trigger's placement: the simulated plate's, moved by the plate's placement error."""
    if plate.placement_off is None:
        return None
    pl = cfg.sim.placement
    dx, dy, dyaw = plate.placement_off
    return Placement(
        pos_mm=(pl.pos_mm[0] + dx, pl.pos_mm[1] + dy, pl.pos_mm[2]), rpy_deg=(0.0, 0.0, pl.angle_deg + dyaw)
    )


class Measured(NamedTuple):
    """One plate's job: its record, report and results, and the check against the truth alone."""

    plate: Plate
    state: str
    message: str
    record: dict
    report: dict | None
    check: MeasurementCheck | None
    truth_yaw_deg: float


def _measure(plate: Plate, cfg, data_dir: Path, job_id: str, state: str, message: str) -> Measured:
    job_dir = data_dir / "jobs" / job_id
    record = json.loads((job_dir / "job.json").read_text())
    yaw = cfg.sim.placement.angle_deg
    if state != "done":
        return Measured(plate, state, message, record, None, None, yaw)
    report = json.loads((job_dir / "report.json").read_text())
    results = dict(np.load(job_dir / "results" / "results.npz"))
    truth = load_truth(data_dir / "sim-truth.json")
    check = check_measurement(truth, report, results, inspection_settings(cfg.analysis).layout)
    return Measured(plate, state, message, record, report, check, yaw)


# the IGES plate runs with `make test-long` (80-100 s of its own cell: CI stands at 37 of its 40 minutes)
@pytest.fixture(
    scope="module",
    params=[pytest.param(p.name, marks=pytest.mark.long) if p.iges_ship else p.name for p in PLATES],
)
def measured(request, tmp_path_factory) -> Measured:
    """Each plate's job, checked against the truth alone. The first plate's is the module's secrets
    cell's job; the others each start their own cell, scan once and stop it here (so that no case
    depends on another's order)."""
    plate = next(p for p in PLATES if p.name == request.param)
    if plate is PLATES[0]:
        cell, scanned = request.getfixturevalue("cell"), request.getfixturevalue("scanned")
        return _measure(plate, cell.cfg, Path(cell.cfg.cell.data_dir), scanned.job_id, scanned.state,
                        scanned.message)  # fmt: skip
    out = tmp_path_factory.mktemp(plate.name)
    path = tiny_cell_config(
        out, kind=plate.kind, length_mm=plate.length_mm, width_mm=plate.width_mm, radius_x_mm=plate.radii_mm[0],
        radius_y_mm=plate.radii_mm[1], angle_deg=plate.yaw_deg, pos_xy_mm=plate.pos_xy_mm,
        tolerances=plate.tolerances,
    )  # fmt: skip
    if plate.iges_ship:
        iges_ship_plate(path)
    if plate.placement_off is None:
        raw = load_config(path).model_dump(mode="json")
        raw["locate"].update(LOCATE)
        path.write_text(to_toml(raw), encoding="utf-8")
    c = Cell(out, path)
    c.start()
    try:
        acc, (state, message, _) = asyncio.run(
            trigger_demo_plate(c.cfg, plate.name, placement=_off(c.cfg, plate),
                               design=IGES_DESIGN if plate.iges_ship else DEMO_DESIGN)
        )  # fmt: skip
    finally:
        codes = c.stop()
    assert all(code == 0 for code in codes.values()), (codes, (out / "logs").as_posix())
    return _measure(plate, c.cfg, Path(c.cfg.cell.data_dir), acc.job_id, state, message)


@pytest.mark.timeout(900)
def test_the_figures_and_the_verdict_agree_with_the_truth_alone(measured: Measured):
    """The figures of the job against the truth's own resting pose of the design on the exact formed
    plate (tests/support/truth_check.py): Zmax per line within 0.1 mm, the deviation over the field
    (median within 0.05 mm) and along each line (median within 0.1 mm) once the common resting offset
    (-0.08 .. +0.08 mm) is taken out, each line valid over 90 % of its length, every line's grade and
    the verdict the truth's."""
    assert measured.state == "done", measured.message
    check = measured.check
    assert check is not None
    assert not check.figure_failures, check.summary()


# The located saddle's registration lay 0.08-0.22 deg (0.34-1.21 mm at the corners) off the truth's
# in yaw in six runs on a loaded machine, three of them beyond 0.1 deg (its measured corners 0.6-1.8
# mm off the true ones); the sail and the cylinder within 0.09 deg. A finding for the registration
# (docs/testing.md, "Found by the stronger checks"), kept visible: expected to fail there until
# fixed (not strict: it passes on some runs), its figures checked by the case above all the same.
POSE_FINDING = {"saddle-located": "the located saddle's registration turns 0.08-0.22 deg off the truth"}


@pytest.mark.timeout(900)
def test_the_registered_design_lies_where_the_truth_rests_it_in_plane(measured: Measured, request):
    """The registered design's corners within 1 mm of the truth's resting pose in plane, its turn about
    the vertical within 0.1 deg."""
    if measured.plate.name in POSE_FINDING:
        request.applymarker(pytest.mark.xfail(reason=POSE_FINDING[measured.plate.name], strict=False))
    assert measured.state == "done", measured.message
    check = measured.check
    assert check is not None
    assert not check.pose_failures, check.summary()


@pytest.mark.timeout(900)
def test_each_plate_was_triggered_as_its_case_says_and_carries_a_forming_error_to_find(measured: Measured):
    """The premises: the trigger's placement was off by the plate's error (or none was given and the
    locate run found the plate), the lines cross the forming error, and every line's true Zmax lies
    clear of the tolerances' thresholds (so that equal verdicts are not a coin toss)."""
    assert measured.state == "done", measured.message
    plate, rec, check = measured.plate, measured.record, measured.check
    assert check is not None
    found = rec["info"].get("placement_found")
    if plate.placement_off is None:
        assert found is not None and found["source"] == "located" and found["given"] is None, found
    else:
        # the scan was planned from the given placement, off the truth by the plate's error
        given = Placement.model_validate(rec["placement"])
        assert found is None or found["source"] == "given", found
        assert abs(given.yaw_deg - measured.truth_yaw_deg - plate.placement_off[2]) < 1e-6, given
        assert np.hypot(*plate.placement_off[:2]) >= 17.0 and abs(plate.placement_off[2]) >= 0.5
    true_z = [c.zmax_true_mm for c in check.lines]
    assert max(true_z) > 1.0, true_z
    tol = measured.report["tolerances"]
    thresholds = (tol["deviation_standard_mm"], tol["deviation_limit_mm"])
    margin = min(abs(z - t) for z in true_z for t in thresholds)
    assert margin > 2 * CheckLimits().zmax_mm, (true_z, thresholds)
    if plate.tolerances:  # the tight tolerances fail the plate, as the truth does
        assert check.verdict_true == "fail"


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
    """The cell was stopped after its job (`scanned`): every log is complete; searches them all."""
    codes = scanned.stop_codes
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
