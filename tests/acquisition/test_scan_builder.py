"""The whole scan's rows kept once (ScanBuilder): the same scan as concatenated batches, no copy at the end."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cellctl.acquisition.assembly import AssembledBatch, AssembledScan, AssemblyError, ScanBuilder


def _batch(rng: np.random.Generator, first: int, n: int, w: int) -> AssembledBatch:
    valid = rng.random((n, w)) > 0.3
    xyz = rng.normal(0, 100, (n, w, 3)).astype(np.float32)
    xyz[~valid] = np.nan
    return AssembledBatch(
        profile_index=np.arange(first, first + n, dtype=np.int64),
        frame_index=np.arange(first, first + n, dtype=np.uint64) + 7,
        pass_id=rng.integers(-1, 5, n).astype(np.int32),
        t_ns=np.arange(first, first + n, dtype=np.int64) * 5_000_000,
        xyz_mm=xyz,
        valid=valid,
        sensor_pos_mm=rng.normal(0, 1, (n, 3)).astype(np.float32),
    )


@settings(max_examples=40, deadline=None)
@given(
    sizes=st.lists(st.integers(1, 40), min_size=0, max_size=25),
    reserve=st.integers(0, 300),
    w=st.integers(1, 9),
)
def test_builder_scan_is_the_concatenation(sizes: list[int], reserve: int, w: int) -> None:
    rng = np.random.default_rng(len(sizes) * 31 + reserve)
    batches, first = [], 0
    b = ScanBuilder(reserve)
    for n in sizes:
        batches.append(_batch(rng, first, n, w))
        b.append(batches[-1])
        first += n
    assert b.scan(w).digest() == AssembledScan.concat(batches, w).digest()
    assert len(b.scan(w)) == sum(sizes)


def test_scan_is_a_view_and_stays_valid_while_rows_grow() -> None:
    rng = np.random.default_rng(1)
    b = ScanBuilder(4)
    b.append(_batch(rng, 0, 3, 5))
    early = b.scan()
    digest = early.digest()
    assert early.xyz_mm.base is not None  # a view of the builder's arrays, not a copy
    for k in range(10):  # grows past the reserve several times
        b.append(_batch(rng, 3 + 50 * k, 50, 5))
    assert early.digest() == digest  # the rows taken before are unchanged
    assert len(b.scan()) == 503


def test_reserved_rows_are_not_copied_when_the_estimate_holds() -> None:
    rng = np.random.default_rng(2)
    b = ScanBuilder(1000)
    b.append(_batch(rng, 0, 10, 4))
    buf = b.scan().xyz_mm.base
    for k in range(20):
        b.append(_batch(rng, 10 + 40 * k, 40, 4))
    assert b.scan().xyz_mm.base is buf  # one allocation for the whole scan


def test_width_change_is_refused() -> None:
    rng = np.random.default_rng(3)
    b = ScanBuilder()
    b.append(_batch(rng, 0, 2, 4))
    with pytest.raises(AssemblyError, match="points per profile"):
        b.append(_batch(rng, 2, 2, 5))


def test_empty_builder_gives_an_empty_scan_of_the_width() -> None:
    s = ScanBuilder(10).scan(7)
    assert len(s) == 0 and s.xyz_mm.shape == (0, 7, 3) and s.valid.shape == (0, 7)


@pytest.mark.parametrize("step", [1, 3, "rows"])
def test_cloud_arrays_in_blocks_are_the_points(monkeypatch: pytest.MonkeyPatch, step) -> None:
    """Filled block by block (blocks of 7 rows here) at any dtypes: the same points as :meth:`points`."""
    import cellctl.acquisition.assembly as asm

    rng = np.random.default_rng(4)
    b = ScanBuilder()
    for k in range(6):
        b.append(_batch(rng, 10 * k, 10, 11))
    scan = b.scan()
    col_step = rng.integers(1, 4, len(scan)) if step == "rows" else step
    ref = scan.points(col_step)
    monkeypatch.setattr(asm, "_BLOCK_ROWS", 7)
    got = scan.cloud_arrays(col_step, dtypes={"pass_id": np.uint16, "profile_index": np.uint32})
    assert got["pass_id"].dtype == np.uint16 and got["profile_index"].dtype == np.uint32
    assert np.array_equal(got["xyz_mm"], ref["xyz_mm"], equal_nan=False)
    assert np.array_equal(got["pass_id"], np.maximum(ref["pass_id"], 0))
    assert np.array_equal(got["profile_index"], ref["profile_index"])
    assert np.array_equal(got["point_index"], ref["point_index"])
    assert np.allclose(got["t_s"], (ref["t_ns"] - scan.t_ns.min()) * 1e-9)


def test_cloud_arrays_refuse_a_dtype_too_small() -> None:
    rng = np.random.default_rng(5)
    b = ScanBuilder()
    b.append(_batch(rng, 70_000, 3, 4))
    with pytest.raises(AssemblyError, match="profile_index 70002 does not fit"):
        b.scan().cloud_arrays(dtypes={"profile_index": np.uint16})


@pytest.mark.parametrize("expected", [0, 50, 100_000])
def test_acquisition_cloud_is_the_same_whatever_the_reserve(expected: int) -> None:
    """Reserved short (grows), long (pages never touched) or not at all: bit for bit the same scan."""
    from cellctl.acquisition.pipeline import Acquisition, AcquisitionSettings
    from tests.support.synthetic_scan import feed, make_run

    run = make_run(2.0)
    ref = Acquisition(AcquisitionSettings(epoch_ns=run.epoch_ns))
    feed(ref, run)
    acq = Acquisition(AcquisitionSettings(epoch_ns=run.epoch_ns), expected_profiles=expected)
    feed(acq, run)
    assert len(acq.cloud()) > 100
    assert acq.cloud().digest() == ref.cloud().digest()


def test_batches_since_are_the_appended_batches() -> None:
    rng = np.random.default_rng(6)
    b = ScanBuilder(5)
    batches = [_batch(rng, 4 * k, 4, 3) for k in range(6)]
    for x in batches[:3]:
        b.append(x)
    first = b.batches_since(1)
    for x in batches[3:]:
        b.append(x)  # grows past the reserve: the views taken before stay as they were
    got = b.batches_since(2)
    assert len(first) == 2 and len(got) == 4
    assert AssembledScan.concat(first).digest() == AssembledScan.concat(batches[1:3]).digest()
    assert AssembledScan.concat(got).digest() == AssembledScan.concat(batches[2:]).digest()
    assert b.batches_since(6) == []
