"""Fleet throughput: N simulated cells x M workers, K jobs, in network namespaces (root; one machine).

The fleet of tests/fleet (tests/support/netns_fleet.py): a router host, one host per cell (sim and
daemon), a server host with the workers, every process in a mount namespace of its own, the
server's link at 20 ms and 1 % loss (netem where the kernel has it, else a user-space relay,
tests/support/slow_link.py). K jobs are triggered round-robin over the cells at once; the benchmark
waits for all of them to end.

Prints one JSON object: ``jobs``, ``analysed_once`` (jobs whose results were stored exactly once and
that were reported by exactly one worker), ``lost`` (not done), ``duplicated`` (stored or reported
more than once), ``jobs_per_hour`` (done jobs over the time from the first trigger to the last
result stored), ``worker_utilisation`` (the workers' summed job time over workers x that span),
``results_stored_s_p50`` (cloud published -> results stored, median), ``link_mb_per_job`` (bytes
through the server's link, both ways, per job: each process has its own /dev/shm, else Zenoh's
shared memory carried the payloads and the link saw 0.5 MB of a 9 MB job), ``slow_link`` ("netem"
or "user-space relay").

    sudo .venv/bin/python benchmarks/fleet.py --cells 2 --workers 2 --jobs 4
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from collections import Counter
from datetime import datetime
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.support import fleet_cells
from tests.support.netns_fleet import Fleet, remove_leftovers


def _events(fleet: Fleet, name: str, event: str) -> list[dict]:
    out = []
    for line in fleet.proc(name).log.read_text(errors="replace").splitlines():
        if f'"{event}"' in line:
            try:
                out.append(json.loads(line))
            except ValueError:
                continue
    return out


def _t(stamp: str) -> float:
    return datetime.fromisoformat(stamp.replace("Z", "+00:00")).timestamp()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", type=int, default=2)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--jobs", type=int, default=4)
    ap.add_argument("--timeout-s", type=float, default=1800.0)
    args = ap.parse_args(argv)
    remove_leftovers()
    with tempfile.TemporaryDirectory(prefix="fleet-bench-") as tmp:
        fleet = Fleet(Path(tmp), cells=args.cells, workers=args.workers)
        try:
            fleet.create()
            slowed_by, server_connect = fleet_cells.slow_server_link(fleet, 20.0, 1.0)
            fleet_cells.configure(fleet, server_connect)
            fleet_cells.start(fleet)
            link0 = fleet.link_bytes("s")
            t0 = time.time()
            ids = fleet_cells.trigger_all(fleet, [(i % args.cells, f"B{i}") for i in range(args.jobs)])
            recs = fleet_cells.wait_jobs(
                fleet, ids, lambda r: all(x["state"] in fleet_cells.FINAL for x in r.values()), args.timeout_s
            )
            link_bytes = fleet.link_bytes("s") - link0
            stored = Counter()
            stored_at: dict[str, float] = {}
            for c in range(args.cells):
                for ev in _events(fleet, f"run{c}", "results_stored"):
                    stored[ev["job_id"]] += 1
                    stored_at[ev["job_id"]] = _t(ev["timestamp"])
            reported = Counter()
            busy_s = 0.0
            for w in range(args.workers):
                for ev in _events(fleet, f"worker{w}", "job_reported"):
                    reported[ev["job_id"]] += 1
                    busy_s += float(ev.get("seconds", 0.0))
        finally:
            fleet.close()
    done = [j for j in ids if recs[j]["state"] == "done"]
    span = max([stored_at[j] for j in done if j in stored_at], default=time.time()) - t0
    lat = [stored_at[j] - float(recs[j]["info"]["published_utc_s"]) for j in done if j in stored_at]
    out = {
        "cells": args.cells,
        "workers": args.workers,
        "jobs": len(ids),
        "analysed_once": sum(stored[j] == 1 and reported[j] == 1 for j in ids),
        "lost": len(ids) - len(done),
        "duplicated": sum(stored[j] > 1 or reported[j] > 1 for j in ids),
        "jobs_per_hour": round(3600.0 * len(done) / span, 1) if span > 0 else None,
        "worker_utilisation": round(busy_s / (args.workers * span), 3) if span > 0 else None,
        "results_stored_s_p50": round(statistics.median(lat), 2) if lat else None,
        "link_mb_per_job": round(link_bytes / 2**20 / max(len(ids), 1), 2),
        "slow_link": slowed_by,
        # why a job is not done (its final state and last message): a lost job's cause
        "not_done": {
            j: f"{recs[j]['state']}: {recs[j]['history'][-1]['message'][:160]}" for j in ids if j not in done
        },
    }
    print(json.dumps(out))
    return 0 if out["lost"] == 0 and out["duplicated"] == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
