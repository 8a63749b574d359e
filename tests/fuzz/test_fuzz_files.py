"""Fuzz the file boundaries: clouds (analysis.cloud_io), meshes (analysis.design.mesh), `cellctl inspect`, and
the binary cloud decoder (cellctl/cloud_codec.py).

Valid files of every supported format are mutated byte-wise (and their headers made to lie about
counts). Reading one gives the data or one clear error of the module's own type (``CloudError``,
``MeshError``, ``CloudFormatError``), never another exception and never a hang (bounded by SIGALRM).
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
from fuzzlib import fuzz_settings, mutated, no_hang
from hypothesis import example, given
from hypothesis import strategies as st

from analysis.cloud_io import CloudError, ScanCloud, read_cloud, write_cloud_npz, write_cloud_ply
from analysis.contracts.placement import Placement
from analysis.design.mesh import MeshError, TriMesh, load_mesh, save_mesh
from cellctl.api.cloud_codec import Cloud, CloudFormatError, CloudMeta, decode_cloud, encode_cloud
from cellctl.cli import main as cli_main

_RNG = np.random.default_rng(11)
_PTS = np.round(_RNG.normal(0, 50, (12, 3)), 3)
_ORG = ScanCloud(_PTS, np.zeros(12, int), np.arange(12) // 4, np.arange(12) % 4)


def _cloud_seeds(tmp: Path) -> dict[str, tuple[bytes, ...]]:
    write_cloud_ply(_ORG, tmp / "org.ply")
    write_cloud_npz(_ORG, tmp / "org.npz")
    rows = "\n".join(" ".join(f"{v:.3f}" for v in p) for p in _PTS)
    ascii_ply = (
        f"ply\nformat ascii 1.0\nelement vertex {len(_PTS)}\nproperty double x\nproperty double y\n"
        f"property double z\nend_header\n{rows}\n"
    ).encode()
    pcd_head = "VERSION .7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\nPOINTS {n}\nDATA {kind}\n"
    pcd_ascii = (pcd_head.format(n=len(_PTS), kind="ascii") + rows + "\n").encode()
    pcd_bin = pcd_head.format(n=len(_PTS), kind="binary").encode() + _PTS.astype("<f4").tobytes()
    return {
        ".ply": ((tmp / "org.ply").read_bytes(), ascii_ply),
        ".pcd": (pcd_ascii, pcd_bin),
        ".xyz": (rows.encode(), ("x,y,z\n" + rows.replace(" ", ",")).encode()),
        ".npz": ((tmp / "org.npz").read_bytes(),),
    }


def _mesh_seeds(tmp: Path) -> dict[str, tuple[bytes, ...]]:
    mesh = TriMesh(
        np.array([[0, 0, 0], [100, 0, 0], [0, 100, 0], [100, 100, 5.0]]), np.array([[0, 1, 2], [1, 3, 2]])
    )
    out = {}
    for suffix in (".stl", ".ply", ".obj"):
        out[suffix] = (save_mesh(mesh, tmp / f"m{suffix}").read_bytes(),)
    out[".obj"] += (b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",)
    out[".stl"] += (
        b"solid a\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nvertex 0 1 0\nendloop\nendfacet\nendsolid a\n",
    )
    return out


@pytest.fixture(scope="module")
def seeds(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("seeds")
    return {"cloud": _cloud_seeds(tmp), "mesh": _mesh_seeds(tmp)}


def _lying_counts(data: bytes) -> st.SearchStrategy[bytes]:
    """The header's count replaced by a lie: huge, negative, zero."""
    return st.sampled_from([b"99999999", b"4000000000", b"-1", b"0", b"18446744073709551617"]).map(
        lambda n: data.replace(b"vertex 12", b"vertex " + n, 1).replace(b"POINTS 12", b"POINTS " + n, 1)
    )


def _file(kind: str):
    @st.composite
    def draw_file(draw: st.DrawFn, seeds) -> tuple[str, bytes]:
        suffix = draw(st.sampled_from(sorted(seeds[kind])))
        pool = seeds[kind][suffix]
        seed = draw(st.sampled_from(pool))
        data = draw(mutated(seed, pool) | _lying_counts(seed))
        return suffix, data

    return draw_file


@fuzz_settings(80)
@given(data=st.data())
def test_any_mutated_cloud_file_reads_or_raises_one_cloud_error(data, seeds, tmp_path):
    suffix, raw = data.draw(_file("cloud")(seeds))
    path = tmp_path / f"c{suffix}"
    path.write_bytes(raw)
    with no_hang(30):
        try:
            cloud = read_cloud(path)
        except CloudError as err:
            assert str(err).startswith(str(path)) and "\n" not in str(err)
            return
    assert cloud.xyz_mm.shape[1] == 3 and np.isfinite(cloud.xyz_mm).all()


@fuzz_settings(40)
@given(data=st.data())
# found by fuzzing: a 187-byte PLY claiming 10^8 vertices kept open3d busy for 10 to 36 s
@example(data=None)
def test_any_mutated_mesh_file_loads_or_raises_one_mesh_error(data, seeds, tmp_path):
    if data is None:
        suffix = ".ply"
        raw = (
            b"ply\nformat ascii 1.0\nelement vertex 99999999\nproperty float x\nproperty float y\n"
            b"property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
            b"0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n"
        )
    else:
        suffix, raw = data.draw(_file("mesh")(seeds))
    path = tmp_path / f"m{suffix}"
    path.write_bytes(raw)
    with no_hang(30):
        try:
            mesh = load_mesh(path)
        except MeshError as err:
            assert str(err).startswith(str(path)) and "\n" not in str(err)
            return
    assert mesh.triangles.max() < len(mesh.vertices_mm) and np.isfinite(mesh.vertices_mm).all()


@pytest.mark.slow  # each example runs the analysis pipeline in-process
@fuzz_settings(4)
@given(data=st.data())
def test_inspect_refuses_mutated_inputs_with_exit_2_and_one_line(data, seeds, tmp_path, capsys):
    suffix, raw = data.draw(_file("cloud")(seeds))
    msuffix, mraw = data.draw(_file("mesh")(seeds))
    cloud, design = tmp_path / f"c{suffix}", tmp_path / f"d{msuffix}"
    cloud.write_bytes(raw)
    design.write_bytes(mraw)
    with no_hang(120):
        rc = cli_main(
            ["inspect", str(cloud), "--design", str(design), "--out", str(tmp_path / "out"), "--quiet"]
        )
    err = capsys.readouterr().err
    assert rc in (0, 1, 2), rc
    if rc == 2:
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("cellctl inspect: "), err
    assert "Traceback" not in err


_CODEC_SEED = bytes(
    encode_cloud(
        Cloud(
            xyz_mm=_PTS.astype(np.float32),
            job_id="j1",
            plate_id="P1",
            pass_id=np.arange(12, dtype=np.uint16) % 3,
            profile_index=np.arange(12, dtype=np.uint32),
            point_index=np.arange(12, dtype=np.uint16),
            t_s=np.linspace(0, 1, 12),
            meta=CloudMeta(cell_id="seed", placement=Placement.on_bed(100.0, 50.0, 90.0)),
        )
    )
)
_CODEC_SEEDS = (
    _CODEC_SEED,
    bytes(encode_cloud(Cloud(xyz_mm=np.zeros((1, 3), np.float32), job_id="a", plate_id="b"))),
)


@fuzz_settings(200)
@given(
    buf=st.sampled_from(_CODEC_SEEDS).flatmap(lambda s: mutated(s, _CODEC_SEEDS)) | st.binary(max_size=200)
)
def test_cloud_decoder_returns_a_cloud_or_a_cloud_format_error(buf):
    with no_hang(10):
        try:
            cloud = decode_cloud(buf)
        except CloudFormatError as err:
            assert err.field or str(err)
            return
    assert cloud.xyz_mm.ndim == 2 and cloud.xyz_mm.shape[1] == 3
    assert isinstance(cloud.job_id, str) and isinstance(cloud.plate_id, str)
    io.BytesIO(encode_cloud(cloud))  # what was decoded encodes again


# found by fuzzing: the container types' own checks raised errors that did not name the file
_BAD_INDEX_PLY = (
    b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
    b"element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n"
)
_NEGATIVE_PROFILE_PLY = (
    b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
    b"property int pass\nproperty int profile\nproperty int point\nend_header\n0 0 0 0 -1 0\n1 0 0 0 0 1\n"
)


def test_a_mesh_whose_triangle_points_past_its_vertices_is_refused_naming_the_file(tmp_path):
    path = tmp_path / "bad.ply"
    path.write_bytes(_BAD_INDEX_PLY)
    with pytest.raises(MeshError, match=r"bad\.ply: triangle index out of range"):
        load_mesh(path)


def test_a_cloud_with_a_negative_profile_index_is_refused_naming_the_file(tmp_path):
    path = tmp_path / "neg.ply"
    path.write_bytes(_NEGATIVE_PROFILE_PLY)
    with pytest.raises(CloudError, match=r"neg\.ply: profile_index has negative indices"):
        read_cloud(path)


# found by fuzzing: open3d's PLY reader crashed the whole process (SIGSEGV) on this 335-byte binary
# PLY, whose face lists disagree with its bytes; PLY meshes are now read with plyfile
_SEGFAULT_PLY = bytes.fromhex(
    "706c790a666f726d61742062696e6172795f6c6974746c655f656e6469616e20312e300a636f6d6d656e742043726561"
    "746564206279204f70656e33440a656c656d656e742076657274657820340a70726f706572747920646f75626c652078"
    "0a70726f706572747920646f75626c6520790a70726f706572747920646f75626c65207a0a656c656d656e7420666163"
    "6520320a70726f7065727479206c6973742075636861722075696e74207665727465785f696e64696365730a656e645f"
    "6865616465720a0000000000000000000000000000000000000000000000000000000000005940000000000000000000"
    "000000594000000000000000000000000000000000000000000000000000000000000059400000000000000000000000"
    "0000005940000000000000594000000000000014400300000000010000000200000003010000000300000002000000"
)


def test_a_binary_ply_mesh_whose_faces_disagree_with_its_bytes_is_an_error_not_a_crash(tmp_path):
    path = tmp_path / "crash.ply"
    path.write_bytes(_SEGFAULT_PLY)
    with pytest.raises(MeshError, match=r"crash\.ply: "):
        load_mesh(path)


def test_a_binary_stl_whose_size_disagrees_with_its_triangle_count_is_refused(tmp_path, seeds):
    path = tmp_path / "short.stl"
    path.write_bytes(seeds["mesh"][".stl"][0][:-7])
    with pytest.raises(MeshError, match="declares 2 triangles"):
        load_mesh(path)
