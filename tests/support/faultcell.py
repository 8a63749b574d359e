"""The fault-injection harness: a simulated cell in real processes, faults through ``<prefix>/sim/faults``.

Builds on :mod:`tests.support.e2e_cell` (``Cell``, ``open_client``, ``wait_status``). Every fault goes to
the running ``cellctl sim`` over its fault-control channel (Zenoh on loopback), never in-process.
Used by the fault tests, the e-stop e2e test and ``benchmarks/soak.py``.

Typical use::

    cell = FaultCell.create(tmp_path)          # sim + daemon + worker, fault channel on a free port
    async with cell.client() as c:             # Zenoh client session, status follower
        job_id = await c.trigger()
        await c.wait_scanning(min_fraction=0.2)
        await cell.fault(egm={"loss_fraction": 0.05})
        state, message = await c.wait_job_end(job_id)
    check = check_job_data(cell, job_id)       # nothing acquired lost, no duplicate profile
    cell.stop()
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from cellctl.api import ApiCallError, CellStatus, Keys, TriggerAccepted, call
from cellctl.commands.demo_cmd import DEMO_DESIGN, to_toml, wait_ready_line
from cellctl.config import load_config
from cellctl.simcell.faults import FaultState, open_fault_session, send_faults
from tests.support.e2e_cell import REPO, Cell, open_client, tiny_cell_config, wait_status
from tests.support.ports import free_port

__all__ = [
    "ANALYSIS_REFUSED_WHEN_SENSOR_STARVED",
    "PARTIAL_CLOUD_REFUSED",
    "REPO",
    "SENSOR_STARVED_SHARE",
    "STALL_WHEN_CONTROLLER_STARVED",
    "ApiCallError",
    "CellClient",
    "Fallback",
    "FaultCell",
    "JobDataCheck",
    "JobRun",
    "check_job_data",
    "expect_done",
    "fault_cell_config",
    "module_cell",
    "open_client",
    "run_job",
    "sensor_starved",
    "wait_record",
    "wait_status",
]

#: states a job ends in
FINAL_JOB_STATES = ("done", "failed", "aborted", "interrupted")
#: the job.json history a job that starts must begin with
STARTED_PREFIX = ["queued", "planning"]


def module_cell(name: str, **config: Any):
    """A module-scoped pytest fixture ``cell``: a started :class:`FaultCell` (``config`` as for
    :func:`fault_cell_config`), stopped at the end; every process must end by itself on SIGTERM."""

    @pytest.fixture(scope="module")
    def cell(tmp_path_factory):
        out = tmp_path_factory.mktemp(name)
        c = FaultCell.create(out, **config)
        try:
            yield c
        finally:
            codes = c.stop()
            assert all(code == 0 for code in codes.values()), (codes, str(out / "logs"))

    return cell


def fault_cell_config(out: Path, *, sim_faults: dict[str, Any] | None = None, **changes: Any) -> Path:
    """The e2e tiny cell's cell.toml with the fault channel on a free loopback port.

    ``sim_faults``: start-time ``[sim.faults]`` knobs. ``changes``: ``{"section.key": value}`` written
    as ``section_key=value`` keywords, e.g. ``robot__egm_comm_timeout_s=0.5`` (double underscore
    separates the section), plus the plate keywords of ``tiny_cell_config`` (``length_mm``, ...).
    """
    plate = {k: changes.pop(k) for k in ("length_mm", "width_mm", "profile_spacing_mm") if k in changes}
    path = tiny_cell_config(out, **plate)
    data = load_config(path).model_dump(mode="json")
    data["sim"]["fault_control"] = True
    data["sim"]["fault_listen"] = f"tcp/127.0.0.1:{free_port()}"
    if sim_faults:
        data["sim"]["faults"].update(sim_faults)
    for key, value in changes.items():
        *sections, name = key.split("__")
        node = data
        for s in sections:
            node = node[s]
        if name not in node:
            raise KeyError(f"no config key {key.replace('__', '.')}")
        node[name] = value
    path.write_text(to_toml(data), encoding="utf-8")
    load_config(path)  # fail here, not in three processes
    return path


class FaultCell(Cell):
    """A simulated cell whose faults are driven over the simulator's fault-control channel."""

    def __init__(self, out: Path, config: Path) -> None:
        super().__init__(out, config)
        self.ready: dict[str, Any] = {}
        self._fault_session: Any = None

    @classmethod
    def create(cls, out: Path, *, start: bool = True, worker: bool = True, **config: Any) -> FaultCell:
        """Write the config (see :func:`fault_cell_config`) and start sim, daemon (and worker)."""
        cell = cls(out, fault_cell_config(out, **config))
        if start:
            cell.start(worker=worker)
        return cell

    def start(self, *, sim: bool = True, run: bool = True, worker: bool = True) -> None:
        if sim:
            p = self.procs.start("sim", "sim")
            self.ready = wait_ready_line(self.out / "logs" / "sim.out", p, 300.0)
            if not self.ready.get("fault_control"):
                raise RuntimeError(
                    f"the simulator serves no fault channel; see {self.out / 'logs' / 'sim.log'}"
                )
        if run:
            self.procs.start("run", "run")
        if worker:
            self.procs.start("worker", "worker")

    def start_process(self, name: str) -> None:
        """(Re)start one of ``run`` / ``worker`` (``sim`` too, waiting for its ready line)."""
        self.start(sim=name == "sim", run=name == "run", worker=name == "worker")

    def stop(self) -> dict[str, Any]:
        if self._fault_session is not None:
            from cellctl.api.session import close_session

            close_session(self._fault_session)
            self._fault_session = None
        return super().stop()

    async def fault(self, request: dict[str, Any] | None = None, **sections: Any) -> FaultState:
        """Send one fault request (``cell.fault(egm={"loss_fraction": 0.05})``); returns the state."""
        if self._fault_session is None:
            self._fault_session = await asyncio.to_thread(open_fault_session, self.cfg, role="connect")
        body = {**(request or {}), **sections}
        return await send_faults(self._fault_session, self.cfg.key_prefix, body, timeout_s=30.0)

    def fault_sync(self, request: dict[str, Any] | None = None, **sections: Any) -> FaultState:
        """:meth:`fault` from synchronous code."""
        return asyncio.run(self.fault(request, **sections))

    def trigger_request(self, **changes: Any) -> dict[str, Any]:
        """A trigger for the simulated plate where it lies."""
        pl = self.cfg.sim.placement
        req = {"plate_id": "fault-plate", "design": DEMO_DESIGN,
               "placement": {"pos_mm": list(pl.pos_mm), "rpy_deg": [0.0, 0.0, pl.angle_deg]}}  # fmt: skip
        req.update(changes)
        return req

    def log_text(self, name: str) -> str:
        """The JSON log lines of one process so far (``sim``, ``run``, ``worker``)."""
        with contextlib.suppress(OSError):
            return (self.out / "logs" / f"{name}.log").read_text(errors="replace")
        return ""

    def log_events(self, name: str, event: str) -> list[dict[str, Any]]:
        """The structured log records of ``event`` from process ``name``."""
        out = []
        for line in self.log_text(name).splitlines():
            if f'"{event}"' not in line:
                continue
            with contextlib.suppress(ValueError):
                rec = json.loads(line)
                if rec.get("event") == event:
                    out.append(rec)
        return out

    @contextlib.asynccontextmanager
    async def client(self):
        """A Zenoh client session with a status follower (``CellClient``), closed on exit."""
        from cellctl.api.session import close_session
        from cellctl.commands.scan_cmd import StatusFollower

        session = await open_client(self.cfg)
        keys = Keys(self.cfg.key_prefix)
        follower = StatusFollower(session, keys)
        try:
            yield CellClient(self, session, keys, follower)
        finally:
            follower.close()
            await asyncio.to_thread(close_session, session)


@dataclass
class CellClient:
    """What a test does over the cell's Zenoh API: trigger, follow the status, wait for a job."""

    cell: FaultCell
    session: Any
    keys: Keys
    follower: Any
    seen: list[CellStatus] = field(default_factory=list)

    async def wait(self, pred, timeout_s: float = 120.0) -> CellStatus:
        """Wait until ``pred(status)``; every status seen is kept in ``seen``."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            st = self.follower.latest
            if st is not None and (not self.seen or self.seen[-1] is not st):
                self.seen.append(st)
            if st is not None and pred(st):
                return st
            await self.follower.next(0.5)
        raise TimeoutError(f"status condition not met within {timeout_s} s; last {self.follower.latest}")

    async def wait_idle(self, *, workers: bool = True, timeout_s: float = 300.0) -> CellStatus:
        return await self.wait(
            lambda s: s.state.value == "idle" and (bool(s.workers) or not workers), timeout_s
        )

    async def wait_idle_or_faulted(self, timeout_s: float = 300.0) -> CellStatus:
        """Wait until the cell takes a trigger (idle, or faulted after an earlier case) with a worker."""
        return await self.wait(lambda s: s.state.value in ("idle", "faulted") and bool(s.workers), timeout_s)

    async def trigger(self, **changes: Any) -> str:
        """Trigger a scan of the simulated plate; returns the job id."""
        acc = await call(
            self.session, self.keys.trigger, json.dumps(self.cell.trigger_request(**changes)), TriggerAccepted,
            timeout_s=30.0,
        )  # fmt: skip
        return acc.job_id

    async def wait_scanning(
        self, job_id: str, min_fraction: float = 0.0, timeout_s: float = 300.0
    ) -> CellStatus:
        """Wait until the job scans and its progress reached ``min_fraction`` (0..1)."""
        return await self.wait(
            lambda s: s.job is not None and s.job.job_id == job_id and s.job.state.value == "scanning"
            and s.job.fraction >= min_fraction and s.job.profiles > 0,
            timeout_s,
        )  # fmt: skip

    async def wait_job_end(self, job_id: str, timeout_s: float = 480.0) -> CellStatus:
        """Wait until the published status shows the job in a final state; returns that status."""
        return await self.wait(
            lambda s: s.job is not None and s.job.job_id == job_id and s.job.state.value in FINAL_JOB_STATES,
            timeout_s,
        )

    async def control(self, action: str, job_id: str | None = None) -> Any:
        """A control request (pause, resume, abort, reset, reanalyse); returns the ControlReply."""
        from cellctl.api import ControlReply

        payload = json.dumps({"job_id": job_id} if job_id else {})
        return await call(self.session, self.keys.control(action), payload, ControlReply, timeout_s=30.0)


async def wait_record(cell: Cell, job_id: str, pred, timeout_s: float = 120.0) -> dict[str, Any]:
    """Wait until ``pred(job.json record)`` holds (the record is read from disk, as an operator would)."""
    deadline = time.monotonic() + timeout_s
    rec: dict[str, Any] = {}
    while time.monotonic() < deadline:
        with contextlib.suppress(OSError, ValueError):
            rec = cell.job_record(job_id)
            if pred(rec):
                return rec
        await asyncio.sleep(0.5)
    raise TimeoutError(
        f"job {job_id} record condition not met within {timeout_s} s; last {rec.get('history')}"
    )


# ------------------------------------------------------------------------------------------- checks


@dataclass
class JobDataCheck:
    """What a job left on disk, and how it agrees with what the daemon said it received."""

    record: dict[str, Any]
    states: list[str]
    raw_profiles: int
    raw_unique_frames: int
    raw_frame_index: np.ndarray
    raw_problems: list[str]
    cloud_points: int = 0
    cloud_duplicate_points: int = 0
    cloud_profiles: int = 0

    @property
    def received_profiles(self) -> int:
        return int(self.record.get("info", {}).get("profiles", -1))


def check_job_data(cell: Cell, job_id: str) -> JobDataCheck:
    """Read a job's record, raw profiles and (if written) published cloud, and check nothing was lost.

    Asserts: the raw files read cleanly; every profile the daemon counted as received is on disk;
    no sensor frame is stored twice; no profile appears twice in the cloud; the state history starts
    with queued, planning and holds no state after a final one.
    """
    from cellctl.acquisition.pipeline import KIND_PROFILES
    from cellctl.jobstore.rawstore import RawReader

    rec = cell.job_record(job_id)
    states = [h["state"] for h in rec["history"]]
    assert states[:2] == STARTED_PREFIX, states
    finals = [i for i, s in enumerate(states) if s in FINAL_JOB_STATES]
    assert finals and finals[0] == len(states) - 1, f"state after a final one, or none final: {states}"
    assert rec["state"] == states[-1]
    raw_dir = cell.jobs_dir / job_id / "raw"
    frames: list[np.ndarray] = []
    problems: list[str] = []
    if (raw_dir / "profiles.craw").exists():
        reader = RawReader(raw_dir)
        for r in reader.records():
            if r.kind == KIND_PROFILES:
                frames.append(np.asarray(r.arrays["frame_index"], dtype=np.int64))
        problems = list(reader.report.problems)
    fi = np.concatenate(frames) if frames else np.zeros(0, dtype=np.int64)
    check = JobDataCheck(rec, states, int(fi.size), int(np.unique(fi).size), fi, problems)
    # a job whose raw files were closed reads to the end: no torn or corrupt chunk
    assert not [p for p in problems if "missing" not in p], problems
    info = rec.get("info", {})
    if "profiles" in info:
        assert check.raw_profiles == check.received_profiles, (
            f"{check.received_profiles} profiles received, {check.raw_profiles} on disk"
        )
    assert check.raw_unique_frames == check.raw_profiles, (
        f"{check.raw_profiles - check.raw_unique_frames} sensor frames stored twice"
    )
    cloud_bin = cell.jobs_dir / job_id / "cloud.bin"
    if cloud_bin.exists():
        from cellctl.api.cloud_codec import decode_cloud

        cloud = decode_cloud(cloud_bin.read_bytes())
        t = np.asarray(cloud.t_s, dtype=np.float64)
        key = np.stack([t.view(np.int64), cloud.point_index.astype(np.int64)], axis=1)
        check.cloud_points = len(t)
        check.cloud_duplicate_points = int(len(t) - len(np.unique(key, axis=0)))
        check.cloud_profiles = int(np.unique(t).size)
        assert check.cloud_duplicate_points == 0, f"{check.cloud_duplicate_points} cloud points duplicated"
        assert check.cloud_profiles <= check.raw_unique_frames
    return check


# ------------------------------------------------------------------------------------------- one job


@dataclass
class JobRun:
    """One job run under faults: its id, the final published status, what each injection replied,
    the cell states seen meanwhile, and the on-disk check."""

    job_id: str
    final: CellStatus
    replies: list[FaultState]
    cell_states: list[str]
    check: JobDataCheck
    before: FaultState | None = None
    after: FaultState | None = None

    def sim_delta(self, sim: str, counter: str) -> int:
        """How much a simulator counter (``stats[sim][counter]``) grew during the job."""
        if self.before is None or self.after is None:
            return 0
        return int(self.after.stats[sim][counter]) - int(self.before.stats[sim][counter])

    @property
    def sensor_starved(self) -> bool:
        """The simulated HD8 could not render in real time: more than SENSOR_STARVED_SHARE of the
        frames it acquired during the job overran (one late frame is not starvation; a machine that
        starves the simulator costs it a percent and more). The machine was then too loaded for the
        acquisition to be judged, though nothing received may be lost all the same."""
        return sensor_starved(
            self.sim_delta("laser", "overrun_frames"), self.sim_delta("laser", "frames_acquired")
        )

    @property
    def controller_starved(self) -> bool:
        """The simulated controller ran late on more than 1 % of its cycles (a loaded machine): a
        controller that stalls for real then is a stall the daemon must stop on."""
        return self.sim_delta("egm", "overruns") > 0.01 * max(self.sim_delta("egm", "cycles"), 1)

    @property
    def starved(self) -> bool:
        return self.sensor_starved or self.controller_starved

    @property
    def info(self) -> dict[str, Any]:
        return self.check.record.get("info", {})

    @property
    def state(self) -> str:
        return self.final.job.state.value if self.final.job is not None else ""

    @property
    def message(self) -> str:
        return self.final.job.message if self.final.job is not None else ""


async def run_job(
    cell: FaultCell,
    faults: list[tuple[float, dict[str, Any]]],
    *,
    timeout_s: float = 480.0,
    clear_after: bool = True,
) -> JobRun:
    """Trigger a scan and inject ``faults``: ``(fraction, request)`` sent once the scan's progress
    reached ``fraction`` (0..1); a fault that ends the scan early skips the later ones. Waits until
    the job ends (done / failed / aborted / interrupted), then clears every fault knob.
    """
    async with cell.client() as c:
        await c.wait_idle_or_faulted()
        before = await cell.fault()
        job_id = await c.trigger()
        replies = []
        after = None
        try:
            for fraction, request in sorted(faults, key=lambda f: f[0]):
                st = await c.wait(
                    lambda s, fr=fraction: s.job is not None and s.job.job_id == job_id and (
                        s.job.state.value in FINAL_JOB_STATES
                        or (s.job.state.value == "scanning" and s.job.fraction >= fr and s.job.profiles > 0)
                    ),
                    timeout_s,
                )  # fmt: skip
                if st.job.state.value in FINAL_JOB_STATES:
                    break
                replies.append(await cell.fault(request))
            final = await c.wait_job_end(job_id, timeout_s)
        finally:
            after = await cell.fault(clear=True) if clear_after else await cell.fault()
        states = [s.state.value for s in c.seen]
    return JobRun(job_id, final, replies, states, check_job_data(cell, job_id), before, after)


#: the share of the simulated sensor's frames that must overrun before a case may call it starved
SENSOR_STARVED_SHARE = 0.01
# The analysis' plain refusal of a cloud that covers only part of the plate (what a scan a starved
# sensor thinned out leaves): the worker reports the pipeline's InspectionError.
PARTIAL_CLOUD_REFUSED = "analysis error: InspectionError: the design does not match the plate"


def sensor_starved(overrun_frames: int, frames_acquired: int) -> bool:
    """Whether ``overrun_frames`` of ``frames_acquired`` prove a starved sensor simulator."""
    return overrun_frames > SENSOR_STARVED_SHARE * max(frames_acquired, 1)


@dataclass(frozen=True)
class Fallback:
    """An outcome other than ``done`` that a fault case accepts only when the machine starved the
    named simulator (its overrun counters grew during the job): the job ends ``state`` with a message
    containing ``message``, the executor's ``execution`` as given (None: any)."""

    name: str
    starved: str  # "controller" or "sensor"
    state: str
    message: str
    execution: str | None = None

    def matches(self, run: JobRun) -> bool:
        starved = run.controller_starved if self.starved == "controller" else run.sensor_starved
        return (
            starved
            and run.state == self.state
            and run.message.startswith(self.message)
            and (self.execution is None or run.info.get("execution") == self.execution)
        )


# A starved controller runs late; a controller late for longer than the feedback timeout is a
# stall the daemon must stop on (a motion fault, every received profile on disk).
STALL_WHEN_CONTROLLER_STARVED = Fallback("stall", "controller", "failed", "stalled", "faulted")
# A starved sensor leaves a cloud with holes that the analysis refuses as covering only part of the
# plate (that refusal only: any other analysis error is a failure).
ANALYSIS_REFUSED_WHEN_SENSOR_STARVED = Fallback(
    "partial cloud refused", "sensor", "failed", PARTIAL_CLOUD_REFUSED, "finished"
)


def overruns(run: JobRun) -> str:
    return (
        f"sensor overruns {run.sim_delta('laser', 'overrun_frames')} of "
        f"{run.sim_delta('laser', 'frames_acquired')} frames, controller overruns "
        f"{run.sim_delta('egm', 'overruns')} of {run.sim_delta('egm', 'cycles')} cycles"
    )


def expect_done(run: JobRun, *fallbacks: Fallback) -> None:
    """Return when the job is ``done``. When it ended as one of the case's named ``fallbacks`` (only
    possible on a machine that starved a simulator), the case is skipped with reason "fallback:
    simulators starved ..." and the overrun counts: tests/skip_allowlist.txt allows it and .ci/run
    counts it, so a starved run is visible and bounded instead of silently green. Checks the caller
    made before this call ran either way (make there every check that holds on the fallbacks too);
    the ones after it need a job that kept real time. Any other outcome fails the case."""
    if run.state == "done":
        return
    for fb in fallbacks:
        if fb.matches(run):
            if fb is STALL_WHEN_CONTROLLER_STARVED:
                assert run.check.raw_profiles == run.info["profiles"]
            pytest.skip(
                f"fallback: simulators starved ({overruns(run)}): job {run.state} ({fb.name}): {run.message}"
            )
    raise AssertionError(f"job {run.state}: {run.message} ({overruns(run)}; accepted fallbacks: "
                         f"{[fb.name for fb in fallbacks] or 'none'})")  # fmt: skip
