"""The published cloud's binary layout: round trips and strict refusal of corrupt messages; a streamed
job's chunks concatenated in memory and straight to a file, byte for byte the same."""

from __future__ import annotations

import json
import struct
import zlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from analysis.contracts.placement import Placement
from cellctl.api.cloud_codec import (
    FIELD_ENTRY,
    HEADER_SIZE,
    Cloud,
    CloudFormatError,
    CloudMeta,
    CloudMetaBlock,
    concat_encoded,
    decode_cloud,
    encode_cloud,
    peek_meta,
    write_concatenated,
)

_META = CloudMeta(cell_id="cell-A", placement=Placement.on_bed(1200.0, -40.0, 90.0))


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
    return Cloud(xyz_mm=xyz, job_id="job-1", plate_id="P-7", meta=_META, **kw)


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
    assert back.job_id == "job-1" and back.plate_id == "P-7" and back.meta == _META
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
    block, n_points = peek_meta(encode_cloud(_cloud(17)))
    assert (block.job_id, block.plate_id, block.meta, n_points) == ("job-1", "P-7", _META, 17)


def _with_meta_json(meta_json: bytes, n: int = 5) -> bytearray:
    """An encoded cloud of ``n`` points whose metadata block is ``meta_json`` (header, offsets and
    checksum made consistent), as an older or a foreign writer would have sent it."""
    buf = encode_cloud(Cloud(xyz_mm=np.ones((n, 3), np.float32), job_id="j", plate_id="p"))
    table_end = HEADER_SIZE + FIELD_ENTRY.size
    data_offset = (table_end + len(meta_json) + 7) // 8 * 8
    xyz = bytes(buf[struct.unpack_from("<Q", buf, 24)[0] :][: n * 12])
    out = bytearray(buf[:table_end]) + meta_json
    out += bytes(data_offset - len(out)) + xyz
    out += bytes((len(out) + 7) // 8 * 8 - len(out))
    struct.pack_into("<I", out, 20, len(meta_json))
    struct.pack_into("<Q", out, 24, data_offset)
    struct.pack_into("<Q", out, 32, len(out))
    struct.pack_into("<Q", out, HEADER_SIZE + 24, data_offset)
    return _recrc(out)


def test_metadata_as_every_daemon_so_far_wrote_it_decodes_to_its_model():
    """The daemon's block since its first version (2026-11-22): five keys, placement maybe null."""
    written = {"frame": "robot base", "cell_id": "sim-cell",
               "placement": {"pos_mm": [1500.0, 0.0, 0.0], "rpy_deg": [0.0, 0.0, 90.0]},
               "job_id": "J-old", "plate_id": "P-old"}  # fmt: skip
    cloud = decode_cloud(_with_meta_json(json.dumps(written).encode()))
    assert (cloud.job_id, cloud.plate_id, cloud.meta.cell_id) == ("J-old", "P-old", "sim-cell")
    assert cloud.meta.placement == Placement(pos_mm=[1500.0, 0.0, 0.0], rpy_deg=[0.0, 0.0, 90.0])
    unplaced = decode_cloud(_with_meta_json(json.dumps({**written, "placement": None}).encode()))
    assert unplaced.meta.placement is None and unplaced.meta.frame == "robot base"


def test_metadata_of_only_the_ids_decodes_with_the_optional_fields_unset():
    cloud = decode_cloud(_with_meta_json(b'{"job_id":"j2","plate_id":"p2"}'))
    assert (cloud.job_id, cloud.plate_id) == ("j2", "p2")
    assert cloud.meta == CloudMeta() and cloud.meta.cell_id is None and cloud.meta.placement is None


@pytest.mark.parametrize(
    ("meta_json", "problem"),
    [
        (b'{"job_id":"j","plate_id":"p","note":"x"}', "note"),
        (b'{"job_id":"j","plate_id":"p","frame":"flange"}', "frame"),
        (b'{"job_id":"j","plate_id":"p","placement":{"pos_mm":[0,0]}}', "placement"),
        (b'{"job_id":"j","plate_id":"p","placement":{"pos_mm":[0,0,0],"scale":2}}', "placement"),
        (b'{"job_id":7,"plate_id":"p"}', "job_id"),
        (b'{"plate_id":"p"}', "job_id"),
        (b'["j","p"]', "metadata"),
        (b'{"job_id":"j",', "metadata"),
        (b"\xff\xfe", "metadata"),
    ],
)
def test_metadata_with_an_unknown_key_or_a_wrong_value_is_refused(meta_json, problem):
    buf = _with_meta_json(meta_json)
    for read in (decode_cloud, peek_meta):
        with pytest.raises(CloudFormatError) as err:
            read(buf)
        assert err.value.field == "meta" and problem in str(err.value)


def test_encode_refuses_metadata_that_is_not_the_model():
    with pytest.raises(CloudFormatError, match="CloudMeta") as err:
        encode_cloud(Cloud(xyz_mm=np.zeros((1, 3)), job_id="j", plate_id="p", meta={"frame": "base"}))
    assert err.value.field == "meta"
    assert CloudMetaBlock.model_fields.keys() == {"frame", "cell_id", "placement", "job_id", "plate_id"}


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
