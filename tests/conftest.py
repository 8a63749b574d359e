"""Shared fixtures for the whole suite."""

from __future__ import annotations

import multiprocessing.process
import os
import re
import shutil
import sys
from pathlib import Path

import pytest

from tests.support.skiplog import SKIP_LOG_ENV, log_entry

REPO_ROOT = Path(__file__).resolve().parent.parent
SHARED = REPO_ROOT.parent / "shared"

# A test that starts another process (a CLI run, a simulator process, a worker, protoc, pdftotext)
# carries one of the markers `make test-fast` deselects (`process` says it; `e2e` and `slow` imply
# it), so that test-fast starts none: an unmarked test that tries is refused at the spawn.
SPAWN_MARKERS = ("process", "e2e", "slow")
SPAWN_EVENTS = (
    "subprocess.Popen",
    "os.fork",
    "os.forkpty",
    "os.posix_spawn",
    "os.exec",
    "os.spawn",
    "os.system",
)
# Every skip is written to the file SKIP_LOG_ENV names (tests/support/skiplog.py); .ci/run checks it
# against tests/skip_allowlist.txt and counts the fallbacks.

_current: dict[str, object] = {"item": None}


def _refuse_unmarked_spawn(what: str) -> None:
    item = _current["item"]
    if item is None or any(item.get_closest_marker(m) for m in SPAWN_MARKERS):
        return
    raise RuntimeError(
        f"{item.nodeid} starts a process ({what}) but is not marked "
        f"{' or '.join('@pytest.mark.' + m for m in SPAWN_MARKERS)}: make test-fast must start none"
    )


def _audit(event: str, args: tuple) -> None:
    if event in SPAWN_EVENTS:
        _refuse_unmarked_spawn(event if event != "subprocess.Popen" else f"{event} {args[0]!s}")


sys.addaudithook(_audit)  # audit hooks cannot be removed; the check only acts while a test runs
_process_start = multiprocessing.process.BaseProcess.start


def _checked_start(self: multiprocessing.process.BaseProcess) -> None:
    # multiprocessing's spawn start method forks through _posixsubprocess, which raises no audit event
    _refuse_unmarked_spawn(f"multiprocessing {self.name}")
    _process_start(self)


multiprocessing.process.BaseProcess.start = _checked_start  # type: ignore[method-assign]


@pytest.hookimpl(wrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None):
    _current["item"] = item
    try:
        return (yield)
    finally:
        _current["item"] = None


# make test's first part runs on both cores (pytest-xdist): the unit tests, and these directories'
# slow and process tests, which compute (planning, analysis, reports, CLI runs of them). A module
# that names a simulator or a simulated cell runs one in real time (the executor's tests against
# the controller simulator): it stays in the second part, one test at a time.
PARALLEL_DIRS = ("analysis", "inspect", "motion", "report")
REAL_TIME = re.compile(
    r"drivers\.abb_egm\.sim|drivers\.laser\.sim|cellctl\.simcell|controller_process"
    r"|tests\.support\.(?:simcell|e2e_cell|faultcell|fleet_cells)"
)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    tests_dir = REPO_ROOT / "tests"
    real_time: dict[Path, bool] = {}
    for item in items:
        path = Path(str(item.path)).resolve()
        try:
            top = path.relative_to(tests_dir).parts[0]
        except ValueError:
            continue
        if top not in PARALLEL_DIRS:
            continue
        if path not in real_time:
            real_time[path] = REAL_TIME.search(path.read_text(encoding="utf-8")) is not None
        if not real_time[path]:
            item.add_marker(pytest.mark.compute)


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    path = os.environ.get(SKIP_LOG_ENV)
    # under pytest-xdist (make test's unit tests) the controller sees every worker's reports: it
    # alone writes them, once
    if not path or not report.skipped or os.environ.get("PYTEST_XDIST_WORKER"):
        return
    if hasattr(report, "wasxfail"):  # an expected failure is a skip too: it proves nothing
        reason = f"xfail: {report.wasxfail}"
    else:
        reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else str(report.longrepr)
        reason = reason.removeprefix("Skipped: ")
    log_entry(report.nodeid, report.when, reason)


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO_ROOT


@pytest.fixture(scope="session")
def cellctl_exe() -> list[str]:
    """The installed console script (falls back to `python -m cellctl` when not on PATH)."""
    exe = Path(sys.executable).parent / "cellctl"
    if exe.exists():
        return [str(exe)]
    found = shutil.which("cellctl")
    return [found] if found else [sys.executable, "-m", "cellctl"]


@pytest.fixture(autouse=True)
def _fresh_logging():
    """Each test starts and ends with default logging: a test that configured structlog onto a
    stream pytest has since closed must not break the next one."""
    import logging

    import structlog

    yield
    structlog.reset_defaults()
    structlog.contextvars.clear_contextvars()
    logging.getLogger().handlers[:] = []
