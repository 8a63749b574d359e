"""Soak: N consecutive jobs on the simulated cell, each with one random fault; prints one JSON object.

    python benchmarks/soak.py [--jobs 10] [--seed 0] [--faults a,b,...] [--out DIR] [--keep]

The cell runs as real processes (`cellctl sim`, `cellctl run`, `cellctl worker`) on loopback, the
tiny plate of the e2e tests (a scan of ~30 s). The worker reaches the daemon through a loopback TCP
forwarder (tests/support/tcp_forwarder.py), so the link between them can be cut. Each job draws one
fault (seeded; every fault once before any twice) from :data:`FAULTS`: EGM loss, bursts,
duplicates/reordering and silence, sensor corrupt frames, stall, disconnect and clock jump, RWS slow
or answering 503, motors off and the emergency stop (then the operator's reset), all through the
simulator's fault channel (``<prefix>/sim/faults``); the worker ``kill -9``'d mid-analysis (then
restarted); the worker link cut for a few seconds mid-scan.

Keys: ``jobs``, ``completed`` (done), ``recoverable`` (ended failed / aborted / interrupted with a
message, raw data intact, the cell taking triggers again), ``faults_injected``,
``missed_egm_cycles`` (EGM packets lost, from the daemon's per-job endpoint counters, over the jobs
without an injected EGM fault), ``daemon_egm`` (its whole-run counters from ``<prefix>/stats``,
injected faults included), ``rss_growth_mb_per_job`` (least-squares slope of the daemon's RSS
after each job), ``wall_s``, ``load_avg_1m`` (start, end), and ``per_job`` detail. Target: every job
completed or recoverable, zero missed EGM cycles outside injected faults, no RSS growth trend.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import random
import shutil
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from cellctl.commands.demo_cmd import Processes  # noqa: E402
from cellctl.logging import configure_logging  # noqa: E402
from tests.support.cellfaults import kill9_tree, stop_cell, wait_until, worker_config_via  # noqa: E402
from tests.support.faultcell import FaultCell, check_job_data, fault_cell_config  # noqa: E402
from tests.support.tcp_forwarder import TcpForwarder  # noqa: E402

#: name -> (kind, scan fraction at which it is injected, fault-channel request or None). Kinds:
#: egm / sensor / rws / controller / estop go through the simulator's fault channel mid-scan;
#: rws_down is in force when the trigger arrives (the job fails before motion); worker and link act
#: on the worker process and its forwarder.
FAULTS: dict[str, tuple[str, float, dict[str, Any] | None]] = {
    "egm_loss_1pct": ("egm", 0.2, {"egm": {"loss_fraction": 0.01}}),
    "egm_loss_5pct_bursts": ("egm", 0.2, {"egm": {"loss_fraction": 0.05, "burst_ms": 50.0}}),
    "egm_duplicates_reorder": ("egm", 0.2, {"egm": {"duplicate_fraction": 0.02, "reorder_fraction": 0.02}}),
    "egm_silent": ("egm", 0.3, {"egm": {"stop_sending": True}}),
    "sensor_corrupt_frames": ("sensor", 0.3, {"laser": {"corrupt": {"groups": 3, "mode": "payload"}}}),
    "sensor_stall": ("sensor", 0.3, {"laser": {"stall_s": 1.0}}),
    "sensor_disconnect": ("sensor", 0.3, {"laser": {"disconnect_after_frames": 30}}),
    "sensor_clock_jump": ("sensor", 0.4, {"laser": {"clock_jump_ms": 250.0}}),
    "rws_slow": ("rws", 0.2, {"rws": {"delay_s": 1.0, "delay_path": "/"}}),
    "rws_503": ("rws_down", 0.0, {"rws": {"error_status": 503}}),
    "motors_off": ("controller", 0.3, {"controller": {"action": "motors_off"}}),
    "emergency_stop": ("estop", 0.3, {"controller": {"action": "emergency_stop"}}),
    "worker_kill9": ("worker", 0.0, None),
    "link_cut": ("link", 0.3, None),
}
#: the fault kinds that go through the simulator's fault channel (cleared after the job)
_SIM_KINDS = ("egm", "sensor", "rws", "rws_down", "controller", "estop")
#: the kinds whose injected fault stops or drops the EGM stream (their lost packets are not "missed")
_EGM_KINDS = ("egm", "controller", "estop")
FINAL = ("done", "failed", "aborted", "interrupted")


@dataclass
class JobResult:
    """One soak job: the fault drawn, how the job ended and what the daemon counted."""

    index: int
    fault: str
    job_id: str = ""
    state: str = ""
    message: str = ""
    outcome: str = ""  # completed | recoverable | lost
    data_ok: bool = False
    data_problem: str = ""
    profiles: int = 0
    egm: dict[str, int] = field(default_factory=dict)
    cell_state_after: str = ""
    rss_mb: float = 0.0
    heap_mb: float | None = None  # the daemon's traced Python heap (PYTHONTRACEMALLOC set), MB
    # how far the simulators fell behind real time during the job (their overrun counters' growth):
    # laser frames rendered late, EGM cycles run late, of all cycles
    sim_overruns: dict[str, int] = field(default_factory=dict)
    wall_s: float = 0.0


def rss_mb(pid: int) -> float:
    """Resident set size of ``pid``, MB (0 when it is gone)."""
    with contextlib.suppress(OSError):
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return 0.0


def slope_per_job(values: list[float]) -> float:
    """Least-squares slope of ``values`` against their index (0 for fewer than 2 values)."""
    n = len(values)
    if n < 2:
        return 0.0
    mx = (n - 1) / 2.0
    my = sum(values) / n
    sxx = sum((i - mx) ** 2 for i in range(n))
    return sum((i - mx) * (v - my) for i, v in enumerate(values)) / sxx


class SoakCell:
    """The soak's cell: FaultCell (sim + daemon, fault channel) and a worker behind a forwarder."""

    def __init__(self, out: Path) -> None:
        self.out = out
        (out / "logs").mkdir(parents=True, exist_ok=True)
        self.cell = FaultCell(out, fault_cell_config(out))
        self.fwd = TcpForwarder(("127.0.0.1", int(self.cell.cfg.zenoh.listen[0].rsplit(":", 1)[1])))
        self.workers: Processes | None = None
        self.worker_starts = 0

    def start(self) -> None:
        self.cell.start(worker=False)
        self.fwd.start()
        self.workers = Processes(
            self.out / "logs", worker_config_via(self.cell, self.fwd.endpoint), self.cell.procs.env
        )
        self.start_worker()

    def start_worker(self) -> Any:
        assert self.workers is not None
        self.worker_starts += 1
        return self.workers.start(f"worker{self.worker_starts}", "worker")

    @property
    def worker(self) -> Any:
        assert self.workers is not None
        return self.workers.procs[-1][1]

    @property
    def worker_log(self) -> str:
        return f"worker{self.worker_starts}"

    def stop(self) -> dict[str, Any]:
        codes: dict[str, Any] = {}
        if self.workers is not None:
            self.workers.procs = [(n, p) for n, p in self.workers.procs if p.poll() is None]
            codes.update(self.workers.stop_all(grace_s=60.0))
        self.fwd.close()
        codes.update(stop_cell(self.cell))
        return codes


async def _one_job(sc: SoakCell, res: JobResult, timeout_s: float) -> None:
    kind, fraction, request = FAULTS[res.fault]
    cell = sc.cell
    async with cell.client() as c:
        await c.wait_idle_or_faulted(timeout_s=180.0)
        before = await cell.fault()
        if kind == "rws_down":
            await cell.fault(request)
        try:
            job_id = res.job_id = await c.trigger(plate_id=f"soak-{res.index}")
            if kind in ("egm", "sensor", "rws", "controller", "estop", "link"):
                st = await c.wait(
                    lambda s: s.job is not None and s.job.job_id == job_id and (
                        s.job.state.value in FINAL
                        or (s.job.state.value == "scanning" and s.job.fraction >= fraction and s.job.profiles > 0)
                    ),
                    timeout_s,
                )  # fmt: skip
                if st.job.state.value not in FINAL:
                    if kind == "link":
                        sc.fwd.cut()
                        await asyncio.sleep(5.0)
                        sc.fwd.restore()
                    else:
                        await cell.fault(request)
            elif kind == "worker":

                def started() -> bool:
                    ev = cell.log_events(sc.worker_log, "job_started")
                    return (
                        any(e.get("job_id") == job_id for e in ev)
                        or cell.job_record(job_id)["state"] in FINAL
                    )

                await wait_until(started, timeout_s, what="the worker started the job")
                if cell.job_record(job_id)["state"] not in FINAL:
                    kill9_tree(sc.worker.pid)
                    sc.worker.wait(10)
                    sc.start_worker()
            final = await c.wait_job_end(job_id, timeout_s)
        finally:
            after = await cell.fault(clear=True) if kind in _SIM_KINDS else await cell.fault()
            sc.fwd.restore()
            res.sim_overruns = {
                "laser_overrun_frames": after.stats["laser"]["overrun_frames"]
                - before.stats["laser"]["overrun_frames"],
                "egm_overruns": after.stats["egm"]["overruns"] - before.stats["egm"]["overruns"],
                "egm_cycles": after.stats["egm"]["cycles"] - before.stats["egm"]["cycles"],
            }
        res.state = final.job.state.value
        res.message = final.job.message[:300]
        if kind == "estop":
            # the operator's procedure (docs/operations.md): release and reset the controller's
            # e-stop, then reset the cell
            await c.wait(lambda s: s.state.value == "emergency_stopped", 60.0)
            await cell.fault(controller={"action": "reset_emergency_stop"})
            await c.control("reset")
        # the cell takes triggers again (idle, or faulted: a stated state a trigger leaves)
        st = await c.wait(lambda s: s.state.value in ("idle", "faulted") and bool(s.workers), 120.0)
        res.cell_state_after = st.state.value


async def daemon_stats(cell: FaultCell) -> dict[str, Any]:
    """The daemon's ``<prefix>/stats`` reply (docs/api.md), or {} when it does not answer."""
    from cellctl.api.session import async_get

    async with cell.client() as c:
        replies = await async_get(c.session, c.keys.stats, timeout_s=10.0)
    for r in replies:
        if r.ok is not None:
            return json.loads(r.ok.payload.to_bytes())
    return {}


def run_soak(
    out: Path, *, jobs: int = 10, seed: int = 0, faults: list[str] | None = None, timeout_s: float = 300.0
) -> dict[str, Any]:
    """Run the soak in ``out`` (created); returns the result object (see the module docstring)."""
    menu = sorted(faults or FAULTS)
    unknown = [f for f in menu if f not in FAULTS]
    if unknown:
        raise ValueError(f"unknown fault(s) {unknown}; known: {sorted(FAULTS)}")
    rng = random.Random(seed)
    # seeded shuffles of the menu, one after the other: random order, yet every fault is drawn
    # once before any is drawn twice (14 jobs cover the 14 faults)
    drawn: list[str] = []
    while len(drawn) < jobs:
        drawn += rng.sample(menu, len(menu))
    drawn = drawn[:jobs]
    out.mkdir(parents=True, exist_ok=True)
    sc = SoakCell(out)
    results: list[JobResult] = []
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    codes: dict[str, Any] = {}
    stats: dict[str, Any] = {}
    try:
        sc.start()
        for i, fault in enumerate(drawn):
            res = JobResult(index=i, fault=fault)
            t_job = time.perf_counter()
            try:
                asyncio.run(_one_job(sc, res, timeout_s))
            except Exception as exc:  # a soak records a failure and goes on to the next job
                res.message = res.message or f"{type(exc).__name__}: {exc}"[:300]
            res.wall_s = round(time.perf_counter() - t_job, 1)
            if res.job_id:
                try:
                    check = check_job_data(sc.cell, res.job_id)
                    res.data_ok = True
                    res.profiles = check.raw_profiles
                    res.egm = dict(check.record.get("info", {}).get("egm", {}))
                except (AssertionError, OSError, ValueError) as exc:
                    res.data_problem = str(exc)[:300]
            if res.state == "done" and res.data_ok:
                res.outcome = "completed"
            elif res.state in FINAL and res.message and res.data_ok and res.cell_state_after:
                res.outcome = "recoverable"
            else:
                res.outcome = "lost"
            res.rss_mb = round(rss_mb(sc.cell.proc("run").pid), 1)
            if os.environ.get("PYTHONTRACEMALLOC"):
                with contextlib.suppress(Exception):
                    res.heap_mb = asyncio.run(daemon_stats(sc.cell))["python_heap"]["traced_mb"]
            results.append(res)
        with contextlib.suppress(Exception):
            stats = asyncio.run(daemon_stats(sc.cell))
    finally:
        codes = sc.stop()
    egm = (stats.get("egm") or {}) if stats else {}
    rss = [r.rss_mb for r in results if r.rss_mb > 0]
    missed = sum(int(r.egm.get("lost", 0)) for r in results if FAULTS[r.fault][0] not in _EGM_KINDS)
    return {
        "jobs": jobs,
        "completed": sum(r.outcome == "completed" for r in results),
        "recoverable": sum(r.outcome == "recoverable" for r in results),
        "faults_injected": len(results),
        "missed_egm_cycles": missed,
        "rss_growth_mb_per_job": round(slope_per_job(rss), 3),
        "rss_mb_first_last": [rss[0], rss[-1]] if rss else [],
        # the daemon's whole-run EGM counters (<prefix>/stats), injected faults included
        "daemon_egm": {
            k: egm.get(k) for k in ("received", "lost", "watchdog_events", "sessions", "malformed")
        },
        # with PYTHONTRACEMALLOC set for the cell: where the daemon's Python heap is after the run
        **({"daemon_python_heap": stats["python_heap"]} if stats.get("python_heap") else {}),
        "seed": seed,
        "wall_s": round(time.perf_counter() - t0, 1),
        "load_avg_1m": [round(load0, 2), round(os.getloadavg()[0], 2)],
        "exit_codes": codes,
        "per_job": [asdict(r) for r in results],
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    ap.add_argument("--jobs", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--faults", default="", help=f"comma-separated subset of {','.join(sorted(FAULTS))}")
    ap.add_argument("--out", type=Path, default=None, help="working directory (default: a temporary one)")
    ap.add_argument("--keep", action="store_true", help="keep the working directory (logs, jobs)")
    args = ap.parse_args(argv)
    out = args.out or Path(tempfile.mkdtemp(prefix="cellctl-soak-"))
    faults = [f for f in args.faults.split(",") if f] or None
    # stdout carries the one JSON object; anything else (logs) goes to stderr
    configure_logging("json", "WARNING", stream=sys.stderr)
    real_stdout, sys.stdout = sys.stdout, sys.stderr
    try:
        result = run_soak(out, jobs=args.jobs, seed=args.seed, faults=faults)
    finally:
        sys.stdout = real_stdout
        if args.out is None and not args.keep:
            shutil.rmtree(out, ignore_errors=True)
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
