"""The loopback hub for the API's Zenoh tests (tests/support/hub.py, with tests/zenoh)."""

from tests.support.hub import _plain_structlog, hub  # noqa: F401 (the fixtures)
