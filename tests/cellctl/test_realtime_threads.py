"""drivers.runtime's real-time helpers: the simulated controller raises its helper threads with its
loop (a helper at normal priority holding the GIL would hold the real-time loop back), and a
priority of 0 leaves the loop at normal scheduling. Each case runs in a child process so the test
run itself never becomes real-time."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import pytest

pytestmark = pytest.mark.process

CHILD = textwrap.dedent(
    """
    import asyncio, json, os, threading
    from drivers.runtime import realtime_other_threads, use_realtime_loop

    stop = threading.Event()
    helpers = [threading.Thread(target=stop.wait) for _ in range(3)]
    for t in helpers:
        t.start()

    async def main():
        off = use_realtime_loop(0)
        policy_off = os.sched_getscheduler(0)
        raised, refused = realtime_other_threads(7)
        return off, policy_off, raised, refused

    off, policy_off, raised, refused = asyncio.run(main())
    policies = [os.sched_getscheduler(t.native_id) for t in helpers]
    stop.set()
    print(json.dumps({"off": off, "policy_off": policy_off, "raised": raised, "refused": refused,
                      "helpers": policies, "me": os.sched_getscheduler(0),
                      "fifo": os.SCHED_FIFO, "other": os.SCHED_OTHER}))
    """
)


def test_other_threads_are_raised_and_priority_zero_stays_normal():
    out = subprocess.run(
        [sys.executable, "-c", CHILD], capture_output=True, text=True, timeout=60, check=True
    )
    r = json.loads(out.stdout.strip().splitlines()[-1])
    assert r["off"] is False and r["policy_off"] == r["other"]
    assert r["me"] == r["other"]  # the caller's own thread is left as it was
    if r["refused"]:  # no CAP_SYS_NICE here: every helper's refusal is said, none is raised silently
        assert r["raised"] == 0 and len(r["refused"]) >= 3
        assert all("SCHED_FIFO 7" in line for line in r["refused"])
        assert all(p == r["other"] for p in r["helpers"])
    else:
        assert r["raised"] >= 3
        assert all(p == r["fifo"] for p in r["helpers"])
