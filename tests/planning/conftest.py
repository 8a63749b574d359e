"""The shared plans for the planning tests (tests/support/plans.py, with the motion tests)."""

from tests.support.plans import sail_plan, small_plan  # noqa: F401 (the session fixtures)
