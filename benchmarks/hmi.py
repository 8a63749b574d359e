"""The HMI's benchmark: page load, status-to-screen time, live-view rate, and whether it disturbs EGM.

A simulated cell (the tests' tiny plate, coarse profiles) scans one plate with no HMI running, then
`cellctl hmi` starts, Chromium (Playwright, Debian's /usr/bin/chromium, headless) logs in and stays
on the Scan page while the same plate is scanned again. Prints one JSON object:

* ``page_load_s``: navigation to the Cell page showing the cell's state (logged in);
* ``status_to_screen_ms_p50/p95``: a state publication's ``t_utc`` to the page having rendered it
  (one machine, one clock), over the second scan;
* ``live_updates_per_s``: live-cloud chunks the page drew per second of scanning, and
  ``live_points``: the points the view holds at the end of the scan;
* ``egm_p99_us_without_hmi`` / ``egm_p99_us_with_hmi``: the daemon's EGM reply latency p99 over
  each scan (``<prefix>/stats`` histogram difference; the bin's upper edge), with
  ``egm_replies_*`` the replies counted.

    python benchmarks/hmi.py [--out DIR]
"""

from __future__ import annotations

import argparse
import asyncio
import concurrent.futures
import json
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cellctl.api import Keys
from cellctl.api.session import async_get, close_session
from cellctl.hmi.auth import add_user
from tests.support.e2e_cell import Cell, open_client, tiny_cell_config
from tests.support.ports import free_port

CHROMIUM_ARGS = [
    "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
    "--disable-sync",
]  # fmt: skip


async def egm_snapshot(cfg: Any) -> dict[str, Any]:
    session = await open_client(cfg)
    try:
        replies = await async_get(session, Keys(cfg.key_prefix).stats, timeout_s=10.0)
    finally:
        await asyncio.to_thread(close_session, session)
    for r in replies:
        if r.ok is not None:
            return json.loads(r.ok.payload.to_bytes())["egm"]
    raise RuntimeError("the daemon's stats did not answer")


def egm_now(cfg: Any) -> dict[str, Any]:
    """:func:`egm_snapshot` from any thread (Playwright's sync API runs an event loop in this one)."""
    with concurrent.futures.ThreadPoolExecutor(1) as ex:
        return ex.submit(lambda: asyncio.run(egm_snapshot(cfg))).result()


def p99_us(before: dict[str, Any], after: dict[str, Any]) -> tuple[float, int]:
    """The p99 of the replies between two snapshots: the upper edge of the bin reaching 99 %."""
    counts = np.asarray(after["latency_counts"]) - np.asarray(before["latency_counts"])
    edges = [*after["latency_bins_us"], after["latency_max_us"]]
    n = int(counts.sum())
    if n == 0:
        return float("nan"), 0
    k = int(np.searchsorted(np.cumsum(counts), 0.99 * n))
    return float(edges[k + 1]), n


def trigger(cell: Cell, plate: str) -> str:
    pl = cell.cfg.sim.placement.to_placement()
    out = subprocess.run(
        [sys.executable, "-m", "cellctl", "scan", "--config", str(cell.config_path), "--plate", plate,
         "--design", "demo-plate.ply", "--placement", ",".join(str(v) for v in [pl.pos_mm[0], pl.pos_mm[1], pl.rpy_deg[2]]),
         "--wait"],
        capture_output=True, text=True, env=cell.procs.env, timeout=600,
    )  # fmt: skip
    if out.returncode not in (0, 1):
        raise RuntimeError(f"cellctl scan failed: {out.stderr[-800:]}")
    return out.stdout


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", help="work directory (default: a temporary one)")
    args = ap.parse_args()
    out = Path(args.out or tempfile.mkdtemp(prefix="bench-hmi-"))
    out.mkdir(parents=True, exist_ok=True)
    cell = Cell(out, tiny_cell_config(out, profile_spacing_mm=3.0))
    result: dict[str, Any] = {"benchmark": "hmi"}
    hmi = None
    try:
        cell.start()
        # 1. a scan without the HMI
        e0 = egm_now(cell.cfg)
        trigger(cell, "BENCH-1")
        e1 = egm_now(cell.cfg)
        result["egm_p99_us_without_hmi"], result["egm_replies_without_hmi"] = p99_us(e0, e1)
        # 2. the HMI, a browser on the Scan page, the same scan
        users = out / "hmi-users"
        add_user(users, "bench", "operator", "bench-password")
        port = free_port()
        log = open(out / "logs" / "hmi.log", "wb")  # noqa: SIM115
        hmi = subprocess.Popen(
            [sys.executable, "-m", "cellctl", "--log-format", "json", "hmi", "--config", str(cell.config_path),
             "--users", str(users), "--listen", f"127.0.0.1:{port}"],
            stdout=subprocess.PIPE, stderr=log, env=cell.procs.env,
        )  # fmt: skip
        log.close()
        json.loads(hmi.stdout.readline())
        url = f"http://127.0.0.1:{port}"
        from playwright.sync_api import sync_playwright

        with sync_playwright() as pw:
            ctx = pw.chromium.launch_persistent_context(
                str(out / "chromium-profile"), executable_path="/usr/bin/chromium", headless=True,
                args=CHROMIUM_ARGS, viewport={"width": 1280, "height": 800}, bypass_csp=True,
            )  # fmt: skip
            try:
                page = ctx.new_page()
                assert ctx.request.post(
                    url + "/api/login", data={"user": "bench", "password": "bench-password"}
                ).ok
                t0 = time.perf_counter()
                page.goto(url + "/#cell")
                page.wait_for_function("document.getElementById('cell-state').textContent !== '-'")
                result["page_load_s"] = round(time.perf_counter() - t0, 3)
                page.goto(url + "/#scan")
                page.evaluate("S.statusLatencyMs = []; S.liveUpdates = 0")
                e2 = egm_now(cell.cfg)
                t_scan = [None, None]

                def watch() -> None:
                    page.wait_for_function("document.body.dataset.cellState === 'scanning'", timeout=120_000)
                    t_scan[0] = time.perf_counter()
                    page.evaluate("S.liveUpdates = 0")
                    page.wait_for_function("document.body.dataset.cellState !== 'scanning'", timeout=600_000)
                    t_scan[1] = time.perf_counter()

                scan = threading.Thread(target=trigger, args=(cell, "BENCH-1"), daemon=True)
                scan.start()
                watch()
                updates = page.evaluate("S.liveUpdates || 0")
                result["live_points"] = page.evaluate("S.livePoints || 0")
                lat = np.asarray(page.evaluate("S.statusLatencyMs"), float)
                scan.join(600)
                e3 = egm_now(cell.cfg)
                result["egm_p99_us_with_hmi"], result["egm_replies_with_hmi"] = p99_us(e2, e3)
                dt = t_scan[1] - t_scan[0]
                result["live_updates_per_s"] = round(updates / dt, 2) if dt > 0 else None
                result["scan_s"] = round(dt, 1)
                result["status_to_screen_ms_p50"] = round(float(np.percentile(lat, 50)), 1)
                result["status_to_screen_ms_p95"] = round(float(np.percentile(lat, 95)), 1)
                result["status_samples"] = int(lat.size)
            finally:
                ctx.close()
    finally:
        if hmi is not None:
            hmi.terminate()
            hmi.wait(15)
        cell.stop()
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
