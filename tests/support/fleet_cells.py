"""Configuration and driving of a netns fleet (tests/support/netns_fleet.py) of simulated cells."""

from __future__ import annotations

import contextlib
import json
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from cellctl.commands.demo_cmd import DEMO_DESIGN, to_toml
from cellctl.config import load_config
from tests.support.e2e_cell import tiny_cell_config
from tests.support.netns_fleet import ROUTER_PORT, Fleet

FINAL = ("done", "failed", "aborted", "interrupted", "cancelled")


def configure(fleet: Fleet, server_connect: str | None = None) -> None:
    """cell.toml of every host: the router's, each cell's (peer, connecting to the router), the
    server's (client, [worker] cells = cell/*; connecting to ``server_connect``, a slow-link relay,
    when given, else to the router)."""
    hub = f"tcp/{fleet.router_ip}:{ROUTER_PORT}"
    (fleet.host_dir("r") / "cell.toml").write_text(
        f'[cell]\nid = "hub"\n\n[router]\nlisten = ["tcp/0.0.0.0:{ROUTER_PORT}"]\n', encoding="utf-8"
    )
    for i in range(fleet.cells):
        out = fleet.host_dir(f"c{i}")
        path = tiny_cell_config(out)
        cfg = load_config(path).model_dump(mode="json")
        cfg["cell"]["id"] = f"c{i}"
        cfg["zenoh"]["connect"] = [hub]
        cfg["analysis"].update(ack_timeout_s=10.0, heartbeat_timeout_s=8.0, max_attempts=5)
        path.write_text(to_toml(cfg), encoding="utf-8")
    (fleet.host_dir("s") / "cell.toml").write_text(
        f'[cell]\nid = "srv"\n\n[zenoh]\nmode = "client"\nconnect = ["{server_connect or hub}"]\nlisten = []\n'
        'multicast_scouting = false\n\n[worker]\ncells = ["cell/*"]\n', encoding="utf-8"
    )  # fmt: skip


def slow_server_link(fleet: Fleet, delay_ms: float = 20.0, loss_pct: float = 1.0) -> tuple[str, str | None]:
    """Delay and loss on the server's link: kernel netem where the kernel has it, else the user-space
    relay (``Fleet.slow_link``). Returns (which, the endpoint the server connects to or None)."""
    if fleet.netem("s", delay_ms, loss_pct):
        return "netem", None
    return "user-space relay", fleet.slow_link("s", delay_ms, loss_pct)


def start(fleet: Fleet) -> None:
    """Router, then each cell's sim and daemon, then the workers."""
    fleet.start("router", "r", ["router", "--config", "cell.toml"])
    fleet.wait_ready("router", 120)
    for i in range(fleet.cells):
        fleet.start(f"sim{i}", f"c{i}", ["sim", "--config", "cell.toml"])
    for i in range(fleet.cells):
        fleet.wait_ready(f"sim{i}", 180)
        fleet.start(f"run{i}", f"c{i}", ["run", "--config", "cell.toml"])
    for w in range(fleet.workers):
        fleet.start(
            f"worker{w}",
            "s",
            ["worker", "--config", "cell.toml", "--worker-id", f"w{w}", "--data-dir", f"w{w}"],
        )


def trigger(fleet: Fleet, cell: int, plate_id: str) -> str:
    """Trigger one scan at a cell (`cellctl scan` inside its namespace); returns the job id."""
    cfg = load_config(fleet.host_dir(f"c{cell}") / "cell.toml")
    pl = cfg.sim.placement
    placement = f"{pl.pos_mm[0]},{pl.pos_mm[1]},{pl.pos_mm[2]},{pl.angle_deg}"
    deadline = time.monotonic() + 120
    while True:
        r = fleet.run_in(f"c{cell}", ["scan", "--plate", plate_id, "--design", DEMO_DESIGN, "--placement", placement,
                                      "--config", "cell.toml"])  # fmt: skip
        if r.returncode == 0:
            return next(line.split()[1] for line in r.stdout.splitlines() if line.startswith("job "))
        if time.monotonic() > deadline:
            raise RuntimeError(f"trigger at c{cell} failed: {r.stdout} {r.stderr}")
        time.sleep(1.0)


def trigger_all(fleet: Fleet, plates: list[tuple[int, str]]) -> dict[str, int]:
    """Trigger several scans: each cell's one after the other, the cells in parallel (one
    `cellctl scan` at a time per daemon: six at once on a loaded machine kept a daemon from
    answering one for two minutes); job id -> cell, in trigger order per cell."""
    by_cell: dict[int, list[str]] = {}
    for cell, plate in plates:
        by_cell.setdefault(cell, []).append(plate)
    with ThreadPoolExecutor(max_workers=len(by_cell)) as pool:
        done = pool.map(
            lambda item: [(trigger(fleet, item[0], p), item[0]) for p in item[1]], by_cell.items()
        )
        return {job: cell for per_cell in done for job, cell in per_cell}


def jobs(fleet: Fleet, cell: int) -> dict[str, dict[str, Any]]:
    """Every job record of a cell (from its data dir), by job id."""
    out = {}
    for p in (fleet.host_dir(f"c{cell}") / "data" / "jobs").glob("*/job.json"):
        with contextlib.suppress(OSError, ValueError):
            out[p.parent.name] = json.loads(p.read_text())
    return out


def wait_jobs(
    fleet: Fleet, ids: dict[str, int], pred, timeout_s: float, poll_s: float = 0.5
) -> dict[str, dict[str, Any]]:
    """Wait until ``pred(records)`` holds for the records of ``ids`` (job id -> cell)."""
    deadline = time.monotonic() + timeout_s
    while True:
        recs = {}
        for cell in set(ids.values()):
            recs.update({k: v for k, v in jobs(fleet, cell).items() if k in ids})
        if len(recs) == len(ids) and pred(recs):
            return recs
        if time.monotonic() > deadline:
            raise TimeoutError({k: v.get("state") for k, v in recs.items()})
        time.sleep(poll_s)


def results_dir(fleet: Fleet, cell: int, job_id: str) -> Path:
    return fleet.host_dir(f"c{cell}") / "data" / "jobs" / job_id / "results"
