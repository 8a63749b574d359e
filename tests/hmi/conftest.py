"""The HMI tests' shared browser: one Chromium context per module (a page per test, its console
errors failing the test). Modules that drive a whole cell define their own (tests/hmi/test_hmi_browser.py,
test_hmi_screens.py)."""

from __future__ import annotations

import pytest

from tests.support.chromium import chromium_context, watched_page


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    # bypass_csp: Playwright's wait_for_function evaluates strings
    with chromium_context(
        tmp_path_factory.mktemp("chromium-profile"), viewport={"width": 1400, "height": 1000}, bypass_csp=True
    ) as ctx:
        yield ctx


@pytest.fixture
def page(browser):
    with watched_page(browser) as (p, errors):
        yield p
    assert not errors, errors
