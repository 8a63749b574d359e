"""The publication's point budget: a scan too big for the analysis' stated bound is thinned by a whole factor."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from cellctl.acquisition.publish import PublishSettings, budget_steps, column_steps
from cellctl.config import CellConfig


def test_within_budget_the_steps_stay() -> None:
    steps = np.array([5, 5, 2, 2])
    assert np.array_equal(budget_steps(steps, np.array([500, 500, 500, 500]), 10_000), steps)
    assert np.array_equal(budget_steps(steps, np.array([500] * 4), 0), steps)  # 0: no bound


def test_a_long_plate_over_budget_is_thinned_keeping_the_edge_ratio() -> None:
    """340 000 profiles of 490 valid points at 0.5 mm keep 33 M points; a 10 M budget makes it 4x coarser."""
    pid = np.r_[np.zeros(330_000, np.int32), np.full(10_000, 60, np.int32)]
    steps = column_steps(pid, 57, PublishSettings(pitch_mm=0.5, edge_pitch_mm=0.2))
    valid = np.full(len(pid), 490)
    got = budget_steps(steps, valid, 10_000_000)
    assert np.all(got == steps * 4)
    assert float(np.sum(valid / got)) <= 10_000_000


@settings(max_examples=80, deadline=None)
@given(
    n=st.integers(1, 200),
    step=st.integers(1, 10),
    per=st.integers(0, 500),
    budget=st.integers(1, 200_000),
)
def test_the_budget_holds(n: int, step: int, per: int, budget: int) -> None:
    steps = np.full(n, step)
    got = budget_steps(steps, np.full(n, per), budget)
    before = per * n / step
    if before <= budget:
        assert np.array_equal(got, steps)
    else:
        assert float(np.sum(per / got)) <= budget * (1 + 1e-9)
    assert np.all(got % steps == 0) and np.all(got >= steps)


def test_a_publication_that_fits_exactly_is_not_thinned_by_rounding() -> None:
    # hypothesis found it: 10 profiles of 13 points at step 10 keep 13 points, summed as 13.000000000000002
    assert np.array_equal(budget_steps(np.full(10, 10), np.full(10, 13), 13), np.full(10, 10))


def test_config_default_and_no_way_off() -> None:
    assert CellConfig.model_validate({"cell": {"id": "c"}}).scan.publish_max_points == 40_000_000
    # 0 turned the bound off; an unbounded publication can exhaust a worker's memory (issue 43)
    with pytest.raises(ValidationError, match="0 no longer turns the bound off"):
        CellConfig.model_validate({"cell": {"id": "c"}, "scan": {"publish_max_points": 0}})
