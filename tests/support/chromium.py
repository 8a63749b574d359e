"""Debian's Chromium under Playwright, as the browser tests and benchmarks drive it.

Playwright's own browser download cannot work on the cell network: every test and benchmark launches
``/usr/bin/chromium`` (scripts/setup.sh installs it) headless with :data:`CHROMIUM_ARGS`.
:func:`chromium_context` opens a persistent context; :func:`watched_page` a page whose script errors
and console errors are collected, for the caller to assert on.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from playwright import sync_api as playwright_sync

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
    "--disable-sync",
]  # fmt: skip


@contextmanager
def chromium_context(profile_dir: Path, **options: Any) -> Iterator[Any]:
    """A persistent headless Chromium context (``options``: Playwright's, e.g. ``viewport``), closed
    on exit."""
    with playwright_sync.sync_playwright() as pw:
        ctx = pw.chromium.launch_persistent_context(
            str(profile_dir), executable_path=CHROMIUM, headless=True, args=CHROMIUM_ARGS, **options
        )
        try:
            yield ctx
        finally:
            ctx.close()


@contextmanager
def watched_page(context: Any) -> Iterator[tuple[Any, list[str]]]:
    """A new page of ``context`` and the list its script errors and console errors are added to;
    the page is closed on exit."""
    page = context.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    try:
        yield page, errors
    finally:
        page.close()
