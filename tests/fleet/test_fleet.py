"""The fleet shares nothing: a router, two simulated cells and a server of two workers, each in its
own network namespace (and every process in its own mount namespace, /dev/shm included), the
server's link slowed to 20 ms and 1 % loss: by netem where the kernel has it, else by a relay in
user space (tests/support/slow_link.py; this CI kernel has no sch_netem). One fleet serves every
case (started once); namespaces are removed whatever happens (the fixture's finalizer, and
leftovers of a killed run by name at the start). Waits are on job states, never fixed sleeps; the
only timed pauses are the faults' own durations (router down 3 s, link cut 10 s)."""

from __future__ import annotations

import json
import os
import re
import shutil
import time
from collections import Counter
from datetime import datetime

import pytest

from tests.support import fleet_cells
from tests.support.netns_fleet import Fleet, remove_leftovers

pytestmark = [
    pytest.mark.slow,
    pytest.mark.e2e,
    pytest.mark.skipif(
        os.geteuid() != 0 or shutil.which("ip") is None or shutil.which("tc") is None,
        reason="network namespaces need root, ip and tc",
    ),
]


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    remove_leftovers()
    f = Fleet(tmp_path_factory.mktemp("fleet"), cells=2, workers=2)
    try:
        f.create()
        _, server_connect = fleet_cells.slow_server_link(f, 20.0, 1.0)
        fleet_cells.configure(f, server_connect)
        fleet_cells.start(f)
        yield f
    finally:
        f.close()
        assert not [n for n in remove_leftovers(f.ns_prefix)], "namespaces left behind"


def _stored(fleet, cell, job_id) -> bool:
    d = fleet_cells.results_dir(fleet, cell, job_id)
    return all(
        (d / n).is_file() and (d / n).stat().st_size > 0 for n in ("report.json", "results.npz", "cloud.ply")
    )


def _analysing(recs, job_id):
    """The worker analysing the job now ("analysing on w0 (attempt 1)", or for a streamed scan
    "cloud streamed in 28 chunks, analysing on w0"), else None."""
    r = recs[job_id]
    found = re.search(r"analysing on (\S+)", r["history"][-1]["message"])
    if r["state"] != "analysing" or found is None:
        return None
    return found.group(1)


def _reported_once(fleet, ids):
    """Each job's results stored exactly once at its daemon, and done exactly once."""
    for job_id, cell in ids.items():
        rec = fleet_cells.jobs(fleet, cell)[job_id]
        assert [h["state"] for h in rec["history"]].count("done") == 1, rec["history"]
        assert _stored(fleet, cell, job_id), job_id
        assert (
            json.loads((fleet_cells.results_dir(fleet, cell, job_id) / "report.json").read_text())["job_id"]
            == job_id
        )
    log = "".join(fleet.proc(f"run{c}").log.read_text() for c in range(fleet.cells))
    stored = Counter(json.loads(line)["job_id"] for line in log.splitlines() if '"results_stored"' in line)
    assert all(stored[j] == 1 for j in ids), stored


def test_four_jobs_over_both_cells_each_analysed_once_with_results_stored_at_its_daemon(fleet):
    ids = fleet_cells.trigger_all(fleet, [(i % 2, f"P{i}") for i in range(4)])  # two scans per cell
    fleet_cells.wait_jobs(
        fleet, ids, lambda recs: all(r["state"] in fleet_cells.FINAL for r in recs.values()), 900
    )
    recs = {**fleet_cells.jobs(fleet, 0), **fleet_cells.jobs(fleet, 1)}
    assert all(recs[j]["state"] == "done" for j in ids), {
        j: (recs[j]["state"], recs[j]["history"][-1]) for j in ids
    }
    _reported_once(fleet, ids)
    workers_log = "".join(fleet.proc(f"worker{w}").log.read_text() for w in range(2))
    reported = Counter(
        json.loads(line)["job_id"] for line in workers_log.splitlines() if '"job_reported"' in line
    )
    assert all(reported[j] == 1 for j in ids), reported  # analysed exactly once
    assert {recs[j]["info"]["worker_id"] for j in ids} == {"w0", "w1"}  # both workers took jobs


def _assigned_worker(fleet, cell: int, job_id: str, timeout_s: float) -> str:
    """The worker the daemon of ``cell`` gave the job to (its ``job_assigned`` log line: a streamed
    scan goes out as the plate is scanned), waited for."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        got = [
            e["worker_id"]
            for e in _log_events(fleet, f"run{cell}", "job_assigned")
            if e.get("job_id") == job_id
        ]
        if got:
            return got[-1]
        time.sleep(0.05)
    raise TimeoutError(f"{job_id} was not assigned within {timeout_s} s")


def test_a_worker_killed_mid_job_loses_nothing_the_other_completes_it(fleet):
    job = fleet_cells.trigger(fleet, 0, "PK")
    # killed while it holds the job mid-stream, the plate still being scanned: waiting for
    # "analysing" (the scan's end) left too short a window once the analysis started at the last
    # pass (the job was done on the worker before it was killed)
    holder = _assigned_worker(fleet, 0, job, 300)
    recs = fleet_cells.wait_jobs(fleet, {job: 0}, lambda r: True, 60)
    assert recs[job]["state"] not in fleet_cells.FINAL, recs[job]["history"][-3:]
    fleet.kill(f"worker{holder[1:]}")
    try:
        recs = fleet_cells.wait_jobs(fleet, {job: 0}, lambda r: r[job]["state"] in fleet_cells.FINAL, 300)
        assert recs[job]["state"] == "done" and recs[job]["info"]["worker_id"] != holder
        _reported_once(fleet, {job: 0})
    finally:
        fleet.restart(f"worker{holder[1:]}")


def test_the_router_killed_mid_analysis_and_restarted_the_job_completes(fleet):
    job = fleet_cells.trigger(fleet, 1, "PR")
    fleet_cells.wait_jobs(fleet, {job: 1}, lambda r: _analysing(r, job), 300, poll_s=0.05)
    fleet.kill("router")
    time.sleep(3.0)  # stays: the fault, the router down for 3 s
    fleet.restart("router")
    fleet.wait_ready("router", 60)
    recs = fleet_cells.wait_jobs(fleet, {job: 1}, lambda r: r[job]["state"] in fleet_cells.FINAL, 300)
    assert recs[job]["state"] == "done", recs[job]["history"][-3:]
    _reported_once(fleet, {job: 1})


def _log_events(fleet, name: str, event: str, since_utc_s: float = 0.0) -> list[dict]:
    out = []
    for line in fleet.proc(name).log.read_text(errors="replace").splitlines():
        if f'"{event}"' in line:
            ev = json.loads(line)
            if datetime.fromisoformat(ev["timestamp"].replace("Z", "+00:00")).timestamp() >= since_utc_s:
                out.append(ev)
    return out


def test_the_server_link_cut_for_10_s_mid_transfer_loses_nothing_and_doubles_nothing(fleet):
    # A job of each cell; the cut comes as the first is handed to a worker (its cloud on the slow link).
    ids = fleet_cells.trigger_all(fleet, [(0, "PL0"), (1, "PL1")])
    fleet_cells.wait_jobs(fleet, ids, lambda r: any(_analysing(r, j) for j in ids), 300, poll_s=0.05)
    t_cut = time.time()
    fleet.link("s", up=False)
    try:
        time.sleep(10.0)  # the fault: 10 s without the server (its workers' lease is 10 s)
    finally:
        fleet.link("s", up=True)
    recs = fleet_cells.wait_jobs(
        fleet, ids, lambda r: all(x["state"] in fleet_cells.FINAL for x in r.values()), 400
    )
    assert all(recs[j]["state"] == "done" for j in ids), {j: recs[j]["history"][-4:] for j in ids}
    _reported_once(fleet, ids)
    # the workers found the router again on their own (same processes, no restart), and each cell's
    # dispatcher saw both come back
    assert all(fleet.proc(f"worker{w}").popen.poll() is None for w in range(fleet.workers))
    for c in range(fleet.cells):
        gone = {e["worker_id"] for e in _log_events(fleet, f"run{c}", "worker_gone", t_cut)}
        back = {e["worker_id"] for e in _log_events(fleet, f"run{c}", "worker_appeared", t_cut)}
        assert gone <= back, (c, gone, back)
