"""Shared fixtures for the whole suite."""

from __future__ import annotations

import ast
import inspect
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
PARALLEL_DIRS = ("analysis", "inspect", "motion", "planning", "report")
REAL_TIME = re.compile(
    r"drivers\.abb_egm\.sim|drivers\.laser\.sim|cellctl\.simcell|controller_process"
    r"|tests\.support\.(?:simcell|e2e_cell|faultcell|fleet_cells)"
)
# Every test that starts a real-time simulator, anywhere in the suite, is marked `realtime` and runs
# in the second part (the Makefile's rule), found from the code: its module imports a simulator (the
# EGM / RWS controller simulator, the HD8 simulator, the simulated cell) or a harness that starts one
# (e2e, fault and fleet cells, the in-process simcell), or a fixture it uses names one in its own
# code (a conftest's controller process). A helper module that imports a simulator for a constant
# does not make its importers real-time; a test that imports the simulator itself is taken to run it.
REAL_TIME_MODULES = (
    "drivers.abb_egm.sim",
    "drivers.laser.sim",
    "cellctl.simcell",
    "tests.support.simcell",
    "tests.support.e2e_cell",
    "tests.support.faultcell",
    "tests.support.cellfaults",
    "tests.support.fleet_cells",
    "tests.laser.laser_helpers",
)
_starts_simulator: dict[Path, bool] = {}
_fixture_starts: dict[object, bool] = {}


def _imported_modules(path: Path) -> set[str]:
    """Every module ``path`` imports (module level, in functions, relative imports resolved), and for
    ``from package import name`` also ``package.name`` (it may be a module)."""
    try:
        tree = ast.parse(path.read_text(encoding="utf-8"))
    except (OSError, SyntaxError, UnicodeDecodeError):
        return set()
    try:
        package = ".".join(path.relative_to(REPO_ROOT).with_suffix("").parts[:-1])
    except ValueError:  # a test file outside the repository (the suite rules' own throw-away one)
        package = ""
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1] + ([base] if base else []))
            out.add(base)
            out.update(f"{base}.{a.name}" for a in node.names)
    return out


def starts_simulator(path: Path) -> bool:
    """True when the module at ``path`` imports a real-time simulator or a harness that starts one."""
    path = path.resolve()
    if path not in _starts_simulator:
        _starts_simulator[path] = any(
            name == m or name.startswith(m + ".")
            for name in _imported_modules(path)
            for m in REAL_TIME_MODULES
        )
    return _starts_simulator[path]


def _fixture_names_a_simulator(func: object) -> bool:
    if func not in _fixture_starts:
        try:
            source = inspect.getsource(func)  # type: ignore[arg-type]
        except (OSError, TypeError):
            source = ""
        _fixture_starts[func] = REAL_TIME.search(source) is not None or any(
            m in source for m in REAL_TIME_MODULES
        )
    return _fixture_starts[func]


def _uses_simulator(item: pytest.Item) -> bool:
    if starts_simulator(Path(str(item.path))):
        return True
    info = getattr(item, "_fixtureinfo", None)
    for defs in info.name2fixturedefs.values() if info is not None else ():
        for fd in defs:
            module = sys.modules.get(getattr(fd.func, "__module__", ""))
            file = getattr(module, "__file__", None)
            if (
                file
                and Path(file).resolve().is_relative_to(REPO_ROOT / "tests")
                and _fixture_names_a_simulator(fd.func)
            ):
                return True
    return False


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    tests_dir = REPO_ROOT / "tests"
    real_time: dict[Path, bool] = {}
    for item in items:
        if _uses_simulator(item):
            item.add_marker(pytest.mark.realtime)
        path = Path(str(item.path)).resolve()
        try:
            top = path.relative_to(tests_dir).parts[0]
        except ValueError:
            continue
        if top not in PARALLEL_DIRS or item.get_closest_marker("realtime"):
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
