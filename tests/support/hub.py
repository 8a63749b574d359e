"""A loopback-only Zenoh hub for one test cell (its [zenoh] section, key prefix and a cell.toml for
workers), and plain structlog around each test: fixtures for the Zenoh tests of tests/zenoh and
tests/api, imported into their conftests."""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
import structlog

from cellctl.config import ZenohSection
from tests.support.ports import free_port


@pytest.fixture(autouse=True)
def _plain_structlog() -> Iterator[None]:
    """Tests that run `cellctl.cli.main` in-process bind structlog to a captured stream that pytest
    closes afterwards; in-process dispatchers and queryables here must not log into it."""
    structlog.reset_defaults()
    yield
    structlog.reset_defaults()


@dataclass
class Hub:
    """One test cell: its [zenoh] section (the daemon's), key prefix and a cell.toml for workers."""

    section: ZenohSection
    prefix: str
    toml: Path
    tmp: Path


@pytest.fixture
def hub(tmp_path: Path) -> Hub:
    port = free_port()
    cell_id = "t" + uuid.uuid4().hex[:8]
    toml = tmp_path / "cell.toml"
    toml.write_text(
        f'[cell]\nid = "{cell_id}"\n\n[zenoh]\nmode = "peer"\nlisten = ["tcp/127.0.0.1:{port}"]\n'
        "multicast_scouting = false\n"
    )
    section = ZenohSection(listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    return Hub(section=section, prefix=f"cell/{cell_id}", toml=toml, tmp=tmp_path)
