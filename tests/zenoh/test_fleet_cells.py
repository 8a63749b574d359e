"""One worker process serves several cells through `cellctl router`: every job analysed exactly once,
each cell's designs and results over Zenoh, and a fair share when both cells wait."""

from __future__ import annotations

import asyncio
import json
import os
import subprocess
import sys
import uuid
from collections import Counter
from pathlib import Path

import pytest

from analysis.contracts.job import AnalysisJob
from cellctl.api import Keys
from cellctl.api.session import build_zenoh_config, close_session, open_session
from cellctl.api.transfer import TransferSpec
from cellctl.commands.demo_cmd import wait_ready_line
from cellctl.config import ZenohSection
from cellctl.daemon.dispatch import Dispatcher
from tests.support.ports import free_port
from tests.zenoh.test_dispatch_workers import GENEROUS, _cloud_bytes, _records, _wait_for

pytestmark = [pytest.mark.e2e, pytest.mark.slow]
HERE = Path(__file__).resolve().parent
REPO = HERE.parent.parent


def _start(tmp: Path, name: str, args: list[str]) -> subprocess.Popen:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), str(HERE), env.get("PYTHONPATH", "")])
    with (tmp / f"{name}.out").open("wb") as out, (tmp / f"{name}.log").open("wb") as err:
        return subprocess.Popen([sys.executable, "-m", "cellctl", "--log-format", "json", *args],
                                stdout=out, stderr=err, env=env, cwd=tmp, stdin=subprocess.DEVNULL)  # fmt: skip


def _stop(procs: list[subprocess.Popen]) -> list[int]:
    codes = []
    for p in reversed(procs):
        p.terminate()
        try:
            codes.append(p.wait(30))
        except subprocess.TimeoutExpired:
            p.kill()
            codes.append(p.wait())
    return codes


def test_one_worker_serves_two_cells_through_the_router_each_job_once_and_in_turn(tmp_path):
    router_ep = f"tcp/127.0.0.1:{free_port()}"
    tag = uuid.uuid4().hex[:6]
    prefixes = [f"fleet{tag}/a", f"fleet{tag}/b"]
    (tmp_path / "router.toml").write_text(f'[cell]\nid = "r"\n\n[router]\nlisten = ["{router_ep}"]\n')
    wdir = tmp_path / "w"
    wdir.mkdir()
    (wdir / "cell.toml").write_text(
        f'[cell]\nid = "w"\n\n[zenoh]\nmode = "client"\nconnect = ["{router_ep}"]\nlisten = []\n'
        f'multicast_scouting = false\n\n[worker]\ndata_dir = "own"\ncells = ["fleet{tag}/*"]\n'
    )
    record = tmp_path / "calls.txt"
    design = tmp_path / "designs" / "todo.json"
    design.parent.mkdir()
    design.write_text(json.dumps({"sleep_s": 0.5, "record_path": str(record)}))
    procs = [_start(tmp_path, "router", ["router", "--config", "router.toml"])]
    try:
        wait_ready_line(tmp_path / "router.out", procs[0], 60)
        procs.append(_start(wdir, "worker", ["worker", "--config", "cell.toml", "--worker-id", "shared",
                                             "--analysis", "tests.support.zworker_fns:centroid_after_sleep", "--heartbeat-s", "0.3"]))  # fmt: skip

        async def main():
            section = ZenohSection(mode="peer", listen=[], connect=[router_ep], multicast_scouting=False)
            sessions = [
                open_session(build_zenoh_config(section, role="serve", key_prefix=p)) for p in prefixes
            ]
            disps = [Dispatcher(s, Keys(p), GENEROUS) for s, p in zip(sessions, prefixes, strict=True)]
            # as `cellctl run` does: the worker finds the cells under its key expression by these
            tokens = [
                s.liveliness().declare_token(Keys(p).daemon_alive)
                for s, p in zip(sessions, prefixes, strict=True)
            ]
            try:
                for d in disps:
                    await d.start()
                await _wait_for(
                    lambda: all(d.workers == ["shared"] for d in disps), 60, "the worker in both cells"
                )
                futs = {}
                for i in range(3):
                    for c, d in zip("ab", disps, strict=True):
                        ref = d.designs.register(design)
                        job = AnalysisJob(job_id=f"{c}{i}", plate_id="P", design=str(design))
                        futs[f"{c}{i}"] = d.submit(
                            job, _cloud_bytes(f"{c}{i}")[0], transfer=TransferSpec(design=ref)
                        )
                envs = {k: await asyncio.wait_for(f, 120) for k, f in futs.items()}
                results = {k: d.take_results(k) for d in disps for k in envs if k[0] == d.keys.prefix[-1]}
                return envs, results
            finally:
                for d in disps:
                    await d.close()
                for t in tokens:
                    t.undeclare()
                for s in sessions:
                    close_session(s)

        envs, results = asyncio.run(main())
    finally:
        codes = _stop(procs)
    assert codes == [0, 0], (tmp_path / "worker.log").read_text()[-3000:]
    assert all(e.ok and e.worker_id == "shared" for e in envs.values())
    assert all("observed.json" in results[k] for k in envs)
    starts = [job for kind, job, _ in _records(record) if kind == "start"]
    assert Counter(starts) == {k: 1 for k in envs}, starts  # each job analysed exactly once
    # fair share: both cells waited all along, so the worker took them in turn (no cell twice running
    # while the other waited, allowing the very first pick)
    cells = [j[0] for j in starts]
    assert all(cells[i] != cells[i + 1] for i in range(1, len(cells) - 1)), cells
