"""The soak's code (benchmarks/soak.py) for two jobs: the worker link cut mid-scan, and 1 % EGM loss
through the simulator's fault channel (the worker kill -9 has its own case in test_worker_faults.py).

Expected outcome (the soak's target, not its timings): both jobs complete (``done``) with their raw
data intact (every profile the daemon counted is on disk, none twice): a cut of a few seconds costs
the worker a reconnect, 1 % EGM loss is within what the executor bridges. The one fallback: a job
during which the machine starved a simulator (its overrun counters grew) may end in a stated,
recoverable state instead; the case then skips as a fallback, counted by .ci/run. No EGM packet is
lost in a job without an injected EGM fault; every process exits 0 at the end.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from soak import FAULTS, run_soak, slope_per_job


def test_slope_per_job_is_the_least_squares_trend():
    assert slope_per_job([]) == 0.0 and slope_per_job([5.0]) == 0.0
    assert slope_per_job([1.0, 2.0, 3.0, 4.0]) == pytest.approx(1.0)
    assert slope_per_job([3.0, 1.0, 3.0, 1.0]) == pytest.approx(-0.4)


def test_unknown_fault_names_are_refused_naming_them(tmp_path):
    with pytest.raises(ValueError, match="bogus"):
        run_soak(tmp_path, jobs=1, faults=["bogus"])


@pytest.mark.slow
@pytest.mark.e2e
@pytest.mark.long  # a minute and a half of jobs under mixed faults, each of which tests/faults checks alone in CI
@pytest.mark.timeout(900)
def test_short_soak_every_job_completes_or_is_recoverable_with_no_data_lost(tmp_path):
    faults = ["link_cut", "egm_loss_1pct"]
    result = run_soak(tmp_path, jobs=2, seed=1, faults=faults)
    jobs = result["per_job"]
    assert result["jobs"] == result["faults_injected"] == 2
    assert sorted(j["fault"] for j in jobs) == sorted(faults), "each fault drawn once"
    assert result["completed"] + result["recoverable"] == 2, jobs
    unfinished = [j for j in jobs if j["outcome"] != "completed"]
    # a job that did not complete on a machine that kept real time is a failure, not a fallback
    assert all(_starved(j) for j in unfinished), unfinished
    assert all(j["data_ok"] for j in jobs), [j["data_problem"] for j in jobs]
    assert all(j["job_id"] and j["profiles"] > 1000 for j in jobs), jobs
    assert result["missed_egm_cycles"] == 0, jobs
    assert all(FAULTS[j["fault"]][0] == "egm" or j["egm"].get("lost", 0) == 0 for j in jobs)
    # the daemon's <prefix>/stats answered with its whole-run EGM counters
    assert result["daemon_egm"]["received"] >= sum(j["egm"].get("received", 0) for j in jobs) > 0
    assert all(code == 0 for code in result["exit_codes"].values()), result["exit_codes"]
    if unfinished:
        pytest.skip(
            "fallback: simulators starved: "
            + "; ".join(
                f"{j['fault']} job {j['state']} ({j['message']}), overruns {j['sim_overruns']}"
                for j in unfinished
            )
        )


def _starved(job: dict) -> bool:
    o = job["sim_overruns"]
    return o["laser_overrun_frames"] > 0 or o["egm_overruns"] > 0.01 * max(o["egm_cycles"], 1)
