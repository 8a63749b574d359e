"""The analysis child's heap policy (cellctl.worker.heap), in a process of its own (it lasts for a process's life)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from cellctl.worker.heap import RESERVE_BYTES_PER_POINT, HeapReserve

REPO = Path(__file__).resolve().parents[2]

_PROBE = """
import json, numpy as np
from cellctl.worker.heap import HeapReserve, free_heap_bytes, single_arena

def rss():
    return int(open("/proc/self/statm").read().split()[1]) * 4096

out = {"one_arena": single_arena()}
r0 = rss(); a = np.ones(8 << 20); out["plain_growth"] = rss() - r0; del a
out["reserve_before_start"] = HeapReserve(256 << 20).top_up(640_000)
reserve = HeapReserve(256 << 20)
out["started"] = reserve.start()
out["touched"] = reserve.top_up(640_000)
out["free"] = free_heap_bytes()
out["again"] = reserve.top_up(640_000)
r0 = rss(); a = np.ones(8 << 20); out["reserved_growth"] = rss() - r0; del a
out["rss_kept"] = rss(); reserve.stop(); out["rss_released"] = rss()
r0 = rss(); a = np.ones(8 << 20); out["growth_after_stop"] = rss() - r0; del a
big = HeapReserve(256 << 20)
big.start()
out["too_big"] = big.top_up(10**7)  # 10 M points x 400 B: past the cap
out["gave_up"] = [big.gave_up, big.active]
print(json.dumps(out))
"""


@pytest.mark.process
def test_a_kept_heap_serves_new_arrays_from_pages_touched_beforehand_and_gives_them_back():
    got = subprocess.run(
        [sys.executable, "-c", _PROBE], cwd=REPO, capture_output=True, text=True, timeout=120, check=True
    )
    out = json.loads(got.stdout.strip().splitlines()[-1])
    mb = 1 << 20
    # the default policy: a new 64 MB array comes from fresh pages (its first touch faults them in)
    assert out["plain_growth"] >= 60 * mb, out
    assert out["reserve_before_start"] == 0, "a reserve freed to the system would be no reserve"
    assert out["one_arena"] is True and out["started"] is True  # glibc (Debian)
    assert out["touched"] >= 200 * mb and out["free"] >= 640_000 * 400, out  # 400 B a point
    assert out["again"] == 0, "a reserve already there is not touched again"
    # kept: the same array is served from the touched free heap, the process does not grow
    assert out["reserved_growth"] < 8 * mb, out
    # the job's end gives the free heap back, and glibc's usual policy returns
    assert out["rss_kept"] - out["rss_released"] >= 200 * mb, out
    assert out["growth_after_stop"] >= 60 * mb, out
    # a stream whose reserve would pass the cap stops keeping (a 6 m plate's analysis peaks at 12.75 GB)
    assert out["too_big"] == 0 and out["gave_up"] == [True, False], out


def test_the_reserve_grows_with_the_points_received_up_to_its_cap():
    r = HeapReserve(1 << 30)
    assert r.target(0) == 0
    assert r.target(1000) == 1000 * RESERVE_BYTES_PER_POINT
    assert r.target(10**9) == 1 << 30
    assert HeapReserve(-5).target(10**6) == 0
