"""The suite's own rules, run on a throw-away test file in a fresh pytest: a test that starts a
process without a marker `make test-fast` deselects is refused at the spawn; every skip is logged
for .ci/run, which fails on a skip not on the allow-list and on too many fallbacks."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from tests.conftest import REPO_ROOT, SKIP_LOG_ENV

pytestmark = pytest.mark.process  # a fresh pytest

CASES = textwrap.dedent(
    """
    import multiprocessing, subprocess, sys
    import pytest

    def test_unmarked_spawn():
        subprocess.run([sys.executable, "-c", "pass"], check=True)

    def test_unmarked_multiprocessing():
        p = multiprocessing.get_context("spawn").Process(target=print)
        p.start()
        p.join()

    @pytest.mark.process
    def test_marked_spawn():
        subprocess.run([sys.executable, "-c", "pass"], check=True)

    def test_plain_skip():
        pytest.skip("no reason anyone allowed")

    def test_fallback():
        pytest.skip("fallback: simulators starved (laser overruns 3)")

    def test_retried():
        from tests.support.skiplog import record_fallback
        record_fallback("fallback: simulators starved (controller overruns 9 of 90 cycles): scanned again")
    """
)


def _check(log: Path, allow: Path, max_fallbacks: int, per_module: int = 2) -> subprocess.CompletedProcess:
    cmd = [sys.executable, str(REPO_ROOT / ".ci/check_skips.py"), str(log), "--allowlist", str(allow),
           "--max-fallbacks", str(max_fallbacks), "--max-fallbacks-per-module", str(per_module)]  # fmt: skip
    return subprocess.run(cmd, capture_output=True, text=True, timeout=60)


def test_unmarked_spawns_are_refused_and_skips_are_checked_against_the_allowlist(tmp_path):
    (tmp_path / "test_cases.py").write_text(CASES)
    log = tmp_path / "skips.jsonl"
    env = {**os.environ, SKIP_LOG_ENV: str(log), "PYTHONPATH": str(REPO_ROOT)}
    r = subprocess.run(
        [sys.executable, "-m", "pytest", "-p", "tests.conftest", "-q", "-rA", "-p", "no:cacheprovider",
         "test_cases.py"],
        capture_output=True, text=True, timeout=240, cwd=tmp_path, env=env,
    )  # fmt: skip
    out = r.stdout
    assert "FAILED test_cases.py::test_unmarked_spawn " in out, out
    assert "FAILED test_cases.py::test_unmarked_multiprocessing " in out, out
    assert "PASSED test_cases.py::test_marked_spawn" in out, out
    assert "is not marked @pytest.mark.process or @pytest.mark.e2e" in out, out
    # a fallback taken without skipping passes, is warned in the summary and logged as a retry
    assert "PASSED test_cases.py::test_retried" in out and "FallbackWarning" in out, out
    skips = [json.loads(line) for line in log.read_text().splitlines()]
    assert [(s["nodeid"], s["reason"], s["kind"]) for s in skips] == [
        ("test_cases.py::test_plain_skip", "no reason anyone allowed", "skip"),
        ("test_cases.py::test_fallback", "fallback: simulators starved (laser overruns 3)", "skip"),
        ("test_cases.py::test_retried",
         "fallback: simulators starved (controller overruns 9 of 90 cycles): scanned again", "retry"),
    ]  # fmt: skip

    allow = tmp_path / "allow.txt"
    allow.write_text(
        "# comment\ntest_cases.py::test_fallback | fallback: simulators starved | the test says so\n"
        "test_cases.py::test_retried | fallback: simulators starved | the test says so\n"
    )
    refused = _check(log, allow, max_fallbacks=2)
    assert refused.returncode == 1 and "skip NOT allowed: test_cases.py::test_plain_skip" in refused.stderr
    assert "2 skipped, 2 fallbacks (1 of them retries that went on)" in refused.stdout, refused.stdout
    assert "retry allowed (fallback: simulators starved): test_cases.py::test_retried" in refused.stdout

    allow.write_text(allow.read_text() + "test_cases.py::test_plain_* | no reason | a test of the check\n")
    assert _check(log, allow, max_fallbacks=2).returncode == 0
    too_many = _check(log, allow, max_fallbacks=1)
    assert too_many.returncode == 1 and "2 fallbacks, more than 1" in too_many.stderr
    # both fell back in one module: bounded per module as well as in total
    crowded = _check(log, allow, max_fallbacks=2, per_module=1)
    assert crowded.returncode == 1, crowded.stdout
    assert "test_cases.py: 2 fallbacks, more than 1 in a module" in crowded.stderr, crowded.stderr


def test_a_test_that_starts_a_real_time_simulator_is_marked_realtime_from_its_imports(tmp_path):
    """make test runs `realtime` tests one at a time: tests/conftest.py marks them from the code."""
    (tmp_path / "test_rt.py").write_text(
        "def test_in_function():\n    from drivers.laser.sim.sensor import LaserSimulator  # noqa: F401\n\n"
        "from tests.support import e2e_cell  # noqa: E402,F401\n\ndef test_harness():\n    pass\n"
    )
    (tmp_path / "test_plain.py").write_text(
        "from drivers.laser.source import ProfileBatch  # noqa: F401\n\ndef test_client_side():\n    pass\n"
    )
    env = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
    r = subprocess.run(
        [sys.executable, "-m", "pytest", "-p", "tests.conftest", "-q", "--collect-only", "-m", "realtime",
         "-p", "no:cacheprovider", "test_rt.py", "test_plain.py"],
        capture_output=True, text=True, timeout=240, cwd=tmp_path, env=env,
    )  # fmt: skip
    collected = [line for line in r.stdout.splitlines() if "::" in line]
    assert collected == ["test_rt.py::test_in_function", "test_rt.py::test_harness"], r.stdout
