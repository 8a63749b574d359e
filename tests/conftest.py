"""Shared fixtures for the whole suite."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parent.parent
SHARED = REPO_ROOT.parent / "shared"


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
