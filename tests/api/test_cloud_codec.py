"""The published cloud's binary layout: round trips and strict refusal of corrupt messages; a streamed
job's chunks concatenated in memory and straight to a file, byte for byte the same."""

from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cellctl.api.cloud_codec import (
    FIELD_ENTRY,
    HEADER_SIZE,
    Cloud,
    CloudFormatError,
    concat_encoded,
    decode_cloud,
    encode_cloud,
    peek_meta,
    write_concatenated,
)


def _cloud(
    n: int, seed: int = 0, optional: tuple[str, ...] = ("pass_id", "profile_index", "point_index", "t_s")
):
    rng = np.random.default_rng(seed)
    kw = {}
    if "pass_id" in optional:
        kw["pass_id"] = rng.integers(0, 60, n).astype(np.uint16)
    if "profile_index" in optional:
        kw["profile_index"] = rng.integers(0, 2**31, n).astype(np.uint32)
    if "point_index" in optional:
        kw["point_index"] = rng.integers(0, 500, n).astype(np.uint16)
    if "t_s" in optional:
        kw["t_s"] = np.sort(rng.uniform(0, 300, n))
    xyz = rng.normal(0, 500, (n, 3)).astype(np.float32)
    return Cloud(xyz_mm=xyz, job_id="job-1", plate_id="P-7", meta={"frame": "base"}, **kw)


def _recrc(buf: bytearray) -> bytearray:
    """Recompute the header CRC so a test reaches the check behind it."""
    n_fields = struct.unpack_from("<H", buf, 16)[0]
    meta_len = struct.unpack_from("<I", buf, 20)[0]
    end = HEADER_SIZE + FIELD_ENTRY.size * n_fields + meta_len
    struct.pack_into("<I", buf, 40, zlib.crc32(bytes(buf[:40]) + bytes(buf[HEADER_SIZE:end])))
    return buf


@settings(max_examples=40, deadline=None)
@given(
    n=st.integers(0, 3000),
    seed=st.integers(0, 2**32 - 1),
    optional=st.sets(st.sampled_from(["pass_id", "profile_index", "point_index", "t_s"])),
)
def test_cloud_round_trip_preserves_every_array_and_metadata(n, seed, optional):
    cloud = _cloud(n, seed, tuple(optional))
    back = decode_cloud(bytes(encode_cloud(cloud)))
    assert back.job_id == "job-1" and back.plate_id == "P-7" and back.meta == {"frame": "base"}
    assert back.n_points == n
    assert set(back.arrays()) == set(cloud.arrays())
    for name, arr in cloud.arrays().items():
        np.testing.assert_array_equal(back.arrays()[name], arr)
        assert back.arrays()[name].dtype == np.asarray(arr).dtype or name == "t_s"


def test_encode_casts_float64_coordinates_to_float32_mm():
    xyz = np.array([[1.25, 2.5, -3.0]], dtype=np.float64)
    back = decode_cloud(encode_cloud(Cloud(xyz_mm=xyz, job_id="j", plate_id="p")))
    assert back.xyz_mm.dtype == np.float32
    np.testing.assert_array_equal(back.xyz_mm, xyz.astype(np.float32))


def test_arrays_are_aligned_views_without_copy():
    buf = bytes(encode_cloud(_cloud(1001)))
    back = decode_cloud(buf)
    for arr in back.arrays().values():
        assert not arr.flags.owndata
        assert arr.ctypes.data % 8 == np.frombuffer(buf, np.uint8).ctypes.data % 8


def test_peek_meta_reads_job_and_point_count_only():
    meta = peek_meta(encode_cloud(_cloud(17)))
    assert meta["job_id"] == "job-1" and meta["n_points"] == 17


@pytest.mark.parametrize(
    ("mutate", "field"),
    [
        (lambda b: b.__setitem__(slice(0, 4), b"XXXX"), "magic"),
        (lambda b: struct.pack_into("<H", b, 4, 2), "version"),
        (lambda b: struct.pack_into("<H", b, 6, 40), "header_size"),
        (lambda b: struct.pack_into("<Q", b, 32, len(b) + 8), "total_size"),
        (lambda b: struct.pack_into("<H", b, 16, 0), "n_fields"),
        (lambda b: struct.pack_into("<I", b, 20, 10**6), "meta_len"),
        (lambda b: struct.pack_into("<Q", b, 24, 3), "data_offset"),
        (lambda b: b.__setitem__(HEADER_SIZE + FIELD_ENTRY.size * 5 + 2, 0), "header_crc"),
    ],
)
def test_corrupt_header_is_refused_naming_the_field(mutate, field):
    buf = encode_cloud(_cloud(50))
    mutate(buf)
    with pytest.raises(CloudFormatError) as err:
        decode_cloud(buf)
    assert err.value.field == field
    assert field in str(err.value)


def test_point_count_larger_than_the_payload_is_refused():
    buf = encode_cloud(_cloud(50))
    struct.pack_into("<Q", buf, 8, 10**9)
    with pytest.raises(CloudFormatError, match="runs past"):
        decode_cloud(_recrc(buf))


def test_unknown_field_name_and_wrong_dtype_are_refused():
    buf = encode_cloud(_cloud(10, optional=("pass_id",)))
    entry = HEADER_SIZE + FIELD_ENTRY.size  # second entry: pass_id
    bad = bytearray(buf)
    bad[entry : entry + 16] = b"colour".ljust(16, b"\0")
    with pytest.raises(CloudFormatError, match="unknown field name 'colour'"):
        decode_cloud(_recrc(bad))
    bad = bytearray(buf)
    bad[entry + 16] = 1  # float32 instead of uint16
    with pytest.raises(CloudFormatError) as err:
        decode_cloud(_recrc(bad))
    assert err.value.field == "pass_id"


def test_truncated_message_is_refused():
    buf = bytes(encode_cloud(_cloud(20)))
    for cut in (0, 10, HEADER_SIZE - 1, len(buf) - 8):
        with pytest.raises(CloudFormatError):
            decode_cloud(buf[:cut])


@settings(max_examples=150, deadline=None)
@given(
    data=st.binary(max_size=400),
    flips=st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255)), max_size=6),
)
def test_random_bytes_never_raise_anything_but_cloud_format_error(data, flips):
    buf = bytearray(encode_cloud(_cloud(8))) if len(data) % 2 else bytearray(data)
    for pos, val in flips:
        if buf:
            buf[pos % len(buf)] = val
    try:
        cloud = decode_cloud(bytes(buf))
    except CloudFormatError:
        return
    assert cloud.xyz_mm.shape == (cloud.n_points, 3)


def test_non_finite_coordinates_are_refused_on_both_sides():
    xyz = np.zeros((3, 3), np.float32)
    xyz[1, 2] = np.nan
    with pytest.raises(CloudFormatError, match="non-finite"):
        encode_cloud(Cloud(xyz_mm=xyz, job_id="j", plate_id="p"))
    buf = encode_cloud(Cloud(xyz_mm=np.zeros((3, 3), np.float32), job_id="j", plate_id="p"))
    data_offset = struct.unpack_from("<Q", buf, 24)[0]
    struct.pack_into("<f", buf, data_offset, float("inf"))
    with pytest.raises(CloudFormatError, match="non-finite"):
        decode_cloud(buf)


def test_wrong_shapes_and_out_of_range_integers_are_refused_on_encode():
    with pytest.raises(CloudFormatError, match="shape"):
        encode_cloud(Cloud(xyz_mm=np.zeros((4, 2)), job_id="j", plate_id="p"))
    with pytest.raises(CloudFormatError) as err:
        encode_cloud(Cloud(xyz_mm=np.zeros((4, 3)), job_id="j", plate_id="p", pass_id=np.zeros(5)))
    assert err.value.field == "pass_id"
    with pytest.raises(CloudFormatError, match="range"):
        encode_cloud(
            Cloud(xyz_mm=np.zeros((2, 3)), job_id="j", plate_id="p", point_index=np.array([1, 70000]))
        )


@settings(max_examples=40, deadline=None)
@given(
    sizes=st.lists(st.integers(0, 300), min_size=1, max_size=6),
    seed=st.integers(0, 2**16),
    dropped=st.sampled_from(["", "t_s", "pass_id"]),
)
def test_a_streamed_jobs_chunks_written_to_a_file_are_the_concatenated_message(
    tmp_path_factory, sizes, seed, dropped
):
    """cloud.bin of a streamed job is written from its chunks (write_concatenated, no copy in
    memory): the same bytes as concat_encoded, including a field one chunk lacks (left out) and
    empty chunks (a pass that saw nothing)."""
    full = ("pass_id", "profile_index", "point_index", "t_s")
    chunks = [
        bytes(encode_cloud(_cloud(n, seed + k, tuple(f for f in full if not (k == 1 and f == dropped)))))
        for k, n in enumerate(sizes)
    ]
    path = tmp_path_factory.mktemp("cat") / "cloud.bin"
    written = write_concatenated(path, chunks)
    expected = bytes(concat_encoded(chunks))
    assert path.read_bytes() == expected and written == len(expected)
    back = decode_cloud(path.read_bytes())
    assert back.n_points == sum(sizes)


def test_writing_no_chunks_is_refused(tmp_path):
    with pytest.raises(CloudFormatError):
        write_concatenated(tmp_path / "cloud.bin", [])
