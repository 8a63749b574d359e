"""The HMI's memory under a flood of junk log-ins (issue 44): the probe's 2000 log-ins with 40 kB
user names took the HMI from 418 to 484 MB for good; the limiter's tables are bounded now.

The HMI runs in a child process (tests/support/hmi_server.py's LocalHmi: the real server and
authenticator, a fake cell link, no cell), so its resident set is its own; this process sends the
log-ins over loopback from several 127.0.0.x addresses, 200 at a time, every one a user name never
seen before: first names of 40 kB (a body over 4 kB: refused 413 before anything is stored), then
short ones (checked or answered 429), then short ones again from new addresses. The password checks (scrypt, 16 MB
each) leave the worker threads' malloc arenas at their high-water mark in the first phases; a
server whose tables are bounded then holds still, which the last phase shows. It prints one JSON object: the child's RSS (MB) before, after each phase and its
peak, with the answers counted by status.

    python benchmarks/hmi_login_flood.py [--logins 10000]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import multiprocessing as mp
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import aiohttp

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def _rss_mb(pid: int) -> tuple[float, float]:
    """(VmRSS, VmHWM) of a process in MB, from /proc."""
    fields = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("VmRSS", "VmHWM"):
            fields[key] = int(value.split()[0]) / 1024.0
    return fields["VmRSS"], fields["VmHWM"]


def _serve(root: str, conn) -> None:
    from tests.support.hmi_server import LocalHmi

    with LocalHmi(Path(root)) as hmi:
        conn.send(hmi.url)
        conn.recv()  # the parent says when it is done


async def _flood(url: str, bodies: list[dict], sources: list[str]) -> Counter:
    codes: Counter = Counter()
    sessions = [
        aiohttp.ClientSession(connector=aiohttp.TCPConnector(local_addr=(s, 0), limit=0)) for s in sources
    ]
    try:

        async def one(c: aiohttp.ClientSession, body: dict) -> int:
            async with c.post(url + "/api/login", json=body) as r:
                await r.read()
                return r.status

        for k in range(0, len(bodies), 200):
            batch = bodies[k : k + 200]
            got = await asyncio.gather(
                *(one(sessions[(k + i) % len(sessions)], b) for i, b in enumerate(batch))
            )
            codes.update(got)
    finally:
        for c in sessions:
            await c.close()
    return codes


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--logins", type=int, default=10_000, help="log-ins per phase")
    ap.add_argument("--sources", type=int, default=8, help="loopback client addresses")
    args = ap.parse_args()
    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe()
    with tempfile.TemporaryDirectory() as root:
        proc = ctx.Process(target=_serve, args=(root, child), daemon=True)
        proc.start()
        try:
            url = parent.recv()
            sources = [f"127.0.0.{k + 10}" for k in range(args.sources)]
            # one log-in first, so the server's lazy imports and buffers are in the baseline
            asyncio.run(_flood(url, [{"user": "warmup", "password": "x"}], sources[:1]))
            before, _ = _rss_mb(proc.pid)
            t0 = time.monotonic()
            long_names = [{"user": f"{k}-" + "n" * 40_000, "password": "x"} for k in range(args.logins)]
            codes_long = asyncio.run(_flood(url, long_names, sources))
            after_long, _ = _rss_mb(proc.pid)
            short_names = [{"user": f"junk{k}", "password": "x"} for k in range(args.logins)]
            codes_short = asyncio.run(_flood(url, short_names, sources))
            after_short, _ = _rss_mb(proc.pid)
            # the same again with names never seen, from addresses never seen (their first tries
            # are checked again): a bounded server holds still from here
            fresh = [f"127.0.1.{k + 10}" for k in range(args.sources)]
            again = [{"user": f"more{k}", "password": "x"} for k in range(args.logins)]
            codes_again = asyncio.run(_flood(url, again, fresh))
            wall_s = time.monotonic() - t0
            after_again, peak = _rss_mb(proc.pid)
        finally:
            parent.send("done")
            proc.join(10)
            if proc.is_alive():
                proc.kill()
    print(
        json.dumps(
            {
                "benchmark": "hmi_login_flood",
                "logins_per_phase": args.logins,
                "sources": args.sources,
                "rss_before_mb": round(before, 1),
                "rss_after_long_names_mb": round(after_long, 1),
                "rss_after_short_names_mb": round(after_short, 1),
                "rss_after_short_names_again_mb": round(after_again, 1),
                "rss_peak_mb": round(peak, 1),
                "rss_growth_mb": round(after_again - before, 1),
                "rss_growth_last_phase_mb": round(after_again - after_short, 1),
                "answers_long_names": dict(sorted(codes_long.items())),
                "answers_short_names": dict(sorted(codes_short.items())),
                "answers_short_names_again": dict(sorted(codes_again.items())),
                "wall_s": round(wall_s, 1),
            }
        )
    )


if __name__ == "__main__":
    main()
