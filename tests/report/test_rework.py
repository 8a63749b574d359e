"""Where to rework: regions beyond the standard range found on the gridded deviation field."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from analysis.rework import ReworkError, find_rework_regions, grid_deviation

SIZE_MM = np.array([200.0, 100.0])


def _plate_grid(step_mm: float = 1.0) -> np.ndarray:
    """(n, 2) points at cell-interior positions of a regular grid over the 200 x 100 mm plate."""
    x, y = np.meshgrid(
        np.arange(step_mm / 2, SIZE_MM[0], step_mm),
        np.arange(step_mm / 2, SIZE_MM[1], step_mm),
        indexing="ij",
    )
    return np.column_stack([x.ravel(), y.ravel()])


def _patch(xy: np.ndarray, box: tuple[float, float, float, float], value: float) -> np.ndarray:
    x0, y0, x1, y1 = box
    inside = (xy[:, 0] >= x0) & (xy[:, 0] < x1) & (xy[:, 1] >= y0) & (xy[:, 1] < y1)
    return np.where(inside, value, 0.0)


def test_a_gap_patch_is_one_region_below_the_template_with_its_exact_extent() -> None:
    xy = _plate_grid()
    d = _patch(xy, (50, 20, 90, 50), 3.2)
    regions = find_rework_regions(grid_deviation(xy, d, SIZE_MM, 5.0), 2.0, 3.0)
    assert len(regions) == 1
    r = regions[0]
    assert r.label == "R1" and r.sign == "below"
    assert r.bbox_mm == (50.0, 20.0, 90.0, 50.0)
    assert r.area_mm2 == pytest.approx(40 * 30)
    assert r.peak_mm == pytest.approx(3.2) and r.mean_mm == pytest.approx(3.2)
    assert r.centre_xy_mm == pytest.approx((70.0, 35.0))
    assert r.beyond_limit


def test_a_raised_patch_is_a_region_above_the_template_within_the_limit() -> None:
    xy = _plate_grid()
    d = _patch(xy, (100, 60, 130, 100), -2.5)
    (r,) = find_rework_regions(grid_deviation(xy, d, SIZE_MM, 5.0), 2.0, 3.0)
    assert r.sign == "above" and r.peak_mm == pytest.approx(-2.5) and not r.beyond_limit
    assert r.bbox_mm == (100.0, 60.0, 130.0, 100.0)


def test_regions_are_ordered_worst_first_and_tiny_blips_are_dropped() -> None:
    xy = _plate_grid()
    d = (
        _patch(xy, (10, 10, 30, 30), 2.5)
        + _patch(xy, (150, 50, 180, 80), 4.0)
        + _patch(xy, (100, 0, 105, 5), 9.0)
    )
    regions = find_rework_regions(grid_deviation(xy, d, SIZE_MM, 5.0), 2.0, 3.0, min_area_mm2=50.0)
    assert [r.label for r in regions] == ["R1", "R2"]
    assert [r.peak_mm for r in regions] == pytest.approx([4.0, 2.5])


def test_empty_cells_are_unseen_not_zero_deviation() -> None:
    xy = _plate_grid()
    keep = xy[:, 0] >= 100
    g = grid_deviation(xy[keep], np.zeros(keep.sum()), SIZE_MM, 5.0)
    assert np.isnan(g.mean_mm[:20]).all() and (g.count[:20] == 0).all()
    assert g.seen[20:].all()


@settings(max_examples=40, deadline=None)
@given(
    i0=st.integers(0, 30),
    j0=st.integers(0, 12),
    w=st.integers(2, 8),
    h=st.integers(2, 7),
    value=st.floats(2.05, 20.0),
    sign=st.sampled_from([1.0, -1.0]),
)
def test_a_cell_aligned_patch_beyond_the_standard_is_found_exactly(
    i0: int, j0: int, w: int, h: int, value: float, sign: float
) -> None:
    xy = _plate_grid()
    box = (5.0 * i0, 5.0 * j0, 5.0 * (i0 + w), 5.0 * (j0 + h))
    d = _patch(xy, box, sign * value)
    (r,) = find_rework_regions(grid_deviation(xy, d, SIZE_MM, 5.0), 2.0, 3.0)
    assert r.bbox_mm == box
    assert r.area_mm2 == pytest.approx(25.0 * w * h)
    assert r.sign == ("below" if sign > 0 else "above")
    assert r.beyond_limit == (value > 3.0)


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(-1.99, 1.99), min_size=1, max_size=50), st.integers(0, 2**31 - 1))
def test_deviations_within_the_standard_range_never_make_a_region(values: list[float], seed: int) -> None:
    rng = np.random.default_rng(seed)
    xy = rng.uniform([0, 0], SIZE_MM, size=(len(values) * 40, 2))
    d = np.resize(np.asarray(values), len(xy))
    assert find_rework_regions(grid_deviation(xy, d, SIZE_MM, 5.0), 2.0, 3.0, min_area_mm2=0.0) == []


@pytest.mark.parametrize(
    ("xy", "d", "size", "cell", "field"),
    [
        (np.zeros((4, 3)), np.zeros(4), SIZE_MM, 5.0, "plate_xy_mm"),
        (np.zeros((4, 2)), np.zeros(5), SIZE_MM, 5.0, "deviation_mm"),
        (np.zeros((4, 2)), np.zeros(4), np.array([200.0, -1.0]), 5.0, "plate_size_mm"),
        (np.zeros((4, 2)), np.zeros(4), SIZE_MM, 0.0, "cell_mm"),
    ],
)
def test_bad_field_data_raises_an_error_naming_the_argument(xy, d, size, cell, field) -> None:
    with pytest.raises(ReworkError, match=field):
        grid_deviation(xy, d, size, cell)
