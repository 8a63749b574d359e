"""The simulated plate from a file (``[sim.plate] kind = "mesh"``): the cell.toml refusals, the scene
built from the mesh file against the scene of the same surface by kind, and the formed-mesh writer
read back."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from analysis.contracts.placement import placement_transform
from analysis.design.mesh import load_mesh, save_mesh
from analysis.design.plates import default_forming_error, design_mesh, plate_spec
from analysis.synth import SynthError, formed_plate_mesh, write_formed_mesh
from cellctl.config import ConfigError, load_config
from cellctl.simcell.service import SimCellError, sim_plate_truth, truth_dict
from cellctl.simcell.truth import file_sha256, mesh_plate_truth, plate_truth
from drivers.laser.sim.scene import SceneRaycaster

SPEC = plate_spec("sail", length_mm=300.0, width_mm=200.0, thickness_mm=12.0)
ERROR = default_forming_error(SPEC)


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> Path:
    """A folder with the formed sail's top surface (formed.ply) and its design (design.ply)."""
    d = tmp_path_factory.mktemp("plate")
    write_formed_mesh(SPEC, ERROR, d / "formed.ply", pitch_mm=4.0)
    save_mesh(design_mesh(SPEC, pitch_mm=10.0), d / "design.ply")
    return d


def _cell_toml(folder: Path, repo_root: Path, **plate: object) -> Path:
    """The shipped cell.toml with ``[sim.plate]`` replaced, written into ``folder``."""
    lines = [f"{k} = {v!r}".replace("'", '"') for k, v in plate.items()]
    text = (repo_root / "cell.toml").read_text()
    start, end = text.index("[sim.plate]"), text.index("[sim.placement]")
    path = folder / "cell.toml"
    path.write_text(text[:start] + "[sim.plate]\n" + "\n".join(lines) + "\n\n" + text[end:])
    return path


def _problems(folder: Path, repo_root: Path, **plate: object) -> str:
    with pytest.raises(ConfigError) as info:
        load_config(_cell_toml(folder, repo_root, **plate))
    return "; ".join(info.value.problems)


def test_a_mesh_plate_loads_with_paths_against_the_cell_toml_folder(files: Path, repo_root: Path) -> None:
    cfg = load_config(
        _cell_toml(
            files, repo_root, kind="mesh", mesh_file="formed.ply", design_file="design.ply", thickness_mm=12.0
        )
    )
    assert cfg.sim.plate.mesh_file == files / "formed.ply"
    assert cfg.sim.plate.design_file == files / "design.ply"


def test_the_mesh_plate_refusals_name_the_key_and_the_file(
    files: Path, tmp_path: Path, repo_root: Path
) -> None:
    (tmp_path / "design.ply").write_bytes((files / "design.ply").read_bytes())
    msg = _problems(tmp_path, repo_root, kind="mesh", design_file="design.ply")
    assert 'sim.plate: kind = "mesh" needs mesh_file' in msg
    msg = _problems(tmp_path, repo_root, kind="mesh", mesh_file="missing.ply", design_file="design.ply")
    assert "mesh_file" in msg and "missing.ply: no such file" in msg
    (tmp_path / "garbage.ply").write_bytes(b"ply\nformat ascii 1.0\nend_header\nnot a mesh")
    msg = _problems(tmp_path, repo_root, kind="mesh", mesh_file="garbage.ply", design_file="design.ply")
    assert "mesh_file" in msg and "garbage.ply" in msg
    # a mesh without triangles: vertices only
    empty = tmp_path / "empty.ply"
    empty.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                     "property float z\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n"
                     "0 0 0\n1 0 0\n0 1 0\n")  # fmt: skip
    msg = _problems(tmp_path, repo_root, kind="mesh", mesh_file="empty.ply", design_file="design.ply")
    assert "mesh_file" in msg and "empty.ply: no triangles" in msg
    # the same plate in micrometres: far larger than the bed (and than its design)
    big = load_mesh(files / "formed.ply")
    save_mesh(type(big)(big.vertices_mm * 1000.0, big.triangles), tmp_path / "um.ply")
    save_mesh(type(big)(big.vertices_mm * 1000.0, big.triangles), tmp_path / "um-design.ply")
    msg = _problems(tmp_path, repo_root, kind="mesh", mesh_file="um.ply", design_file="um-design.ply")
    assert "sim.plate.mesh_file" in msg and "um.ply" in msg and "twice the bed's diagonal" in msg
    # a formed plate that is not its design's: another size, or another frame
    other = formed_plate_mesh(plate_spec("sail", length_mm=600.0, width_mm=200.0), None)
    save_mesh(other, tmp_path / "long.ply")
    msg = _problems(tmp_path, repo_root, kind="mesh", mesh_file="long.ply", design_file="design.ply")
    assert "long.ply does not match design_file" in msg and "length is 600.0 mm" in msg
    shifted = formed_plate_mesh(SPEC, ERROR, T_file_design=np.array(
        [[1.0, 0, 0, 5000.0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]))  # fmt: skip
    save_mesh(shifted, tmp_path / "shifted.ply")
    msg = _problems(tmp_path, repo_root, kind="mesh", mesh_file="shifted.ply", design_file="design.ply")
    assert "shifted.ply does not match" in msg and "not in the design file's frame" in msg
    msg = _problems(tmp_path, repo_root, kind="mesh", mesh_file="um.ply", design_file="design.dxf")
    assert "design_file" in msg and "design.dxf: unsupported design format" in msg
    msg = _problems(tmp_path, repo_root, kind="mesh", mesh_file="um.ply", design_file="nothere.igs")
    assert "design_file" in msg and "nothere.igs: cannot read" in msg
    msg = _problems(tmp_path, repo_root, kind="sail", mesh_file="um.ply")
    assert 'mesh_file is read only with kind = "mesh"' in msg


def _rays(scene_lo: np.ndarray, scene_hi: np.ndarray, n: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """``n`` rays from above the scene, tilted up to 30 degrees, aimed over the plate's footprint."""
    rng = np.random.default_rng(3)
    target = np.column_stack([rng.uniform(scene_lo[0], scene_hi[0], n), rng.uniform(scene_lo[1], scene_hi[1], n),
                              np.full(n, scene_lo[2])])  # fmt: skip
    tilt = np.radians(rng.uniform(0.0, 30.0, n))
    az = rng.uniform(0.0, 2 * np.pi, n)
    d = np.column_stack([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), -np.cos(tilt)])
    origin = target - d * (scene_hi[2] - scene_lo[2] + 400.0) / np.cos(tilt)[:, None]
    return origin, d


def test_the_scene_from_the_mesh_file_is_the_scene_of_the_kind(files: Path) -> None:
    by_kind = plate_truth("sail", length_mm=300.0, width_mm=200.0, thickness_mm=12.0, pos_mm=(1500.0, 20.0, 300.0),
                          angle_deg=7.0)  # fmt: skip
    by_file = mesh_plate_truth(files / "formed.ply", files / "design.ply", thickness_mm=12.0,
                               pos_mm=(1500.0, 20.0, 300.0), angle_deg=7.0)  # fmt: skip
    np.testing.assert_array_equal(by_file.T_design_file, np.eye(4))
    a, b = by_kind.scene(4.0), by_file.scene()
    plate = by_kind.to_base(design_mesh(SPEC, pitch_mm=50.0).vertices_mm)
    origin, d = _rays(plate.min(axis=0), plate.max(axis=0))
    ha, hb = SceneRaycaster(a).cast(origin, d), SceneRaycaster(b).cast(origin, d)
    assert np.isfinite(ha.t_mm).all()
    np.testing.assert_allclose(hb.t_mm, ha.t_mm, rtol=0.0, atol=1e-6)
    # the truth's heights come from the mesh: the analytic surface's within the 4 mm grid's chord
    x, y = np.meshgrid(np.linspace(-135.0, 135.0, 15), np.linspace(-85.0, 85.0, 11))
    h_file = by_file.height_mm(x, y)[0]
    h_kind = by_kind.height_mm(x, y)[0]
    assert np.abs(h_file - h_kind).max() < 0.05
    assert np.isnan(by_file.height_mm(np.array([200.0]), np.array([0.0]))[0]).all()  # off the plate
    # points 1 mm over the true surface are 1 mm away, and the edge margin holds
    p = by_file.to_base(np.column_stack([x.ravel(), y.ravel(), h_file.ravel() + 1.0]))
    dist, inside = by_file.distance_mm(p, edge_margin_mm=10.0)
    np.testing.assert_allclose(dist, 1.0 / np.sqrt(1.0 + by_file.height_mm(x, y)[1].ravel() ** 2
                                                   + by_file.height_mm(x, y)[2].ravel() ** 2), atol=1e-4)  # fmt: skip
    assert inside.all()
    assert not by_file.distance_mm(by_file.to_base(np.array([[145.0, 0.0, 0.0]])), edge_margin_mm=10.0)[1][0]


def test_the_simulated_cell_reads_the_mesh_plate_and_its_truth_names_the_mesh(
    files: Path, repo_root: Path
) -> None:
    cfg = load_config(
        _cell_toml(
            files, repo_root, kind="mesh", mesh_file="formed.ply", design_file="design.ply", thickness_mm=12.0
        )
    )
    truth = sim_plate_truth(cfg)
    rec = truth_dict(cfg, truth)
    assert rec["plate"]["kind"] == "mesh" and rec["forming_error"] is None
    assert rec["plate"]["mesh_sha256"] == file_sha256(files / "formed.ply")
    assert rec["plate"]["mesh_file"] == str(files / "formed.ply")
    np.testing.assert_allclose(rec["T_base_plate"], placement_transform(cfg.sim.placement.to_placement()))
    # a file that changed under a validated config: refused when the simulator starts, by key and file
    save_mesh(
        formed_plate_mesh(plate_spec("sail", length_mm=600.0, width_mm=200.0), None), files / "other.ply"
    )
    cfg2 = cfg.model_copy(update={"sim": cfg.sim.model_copy(update={"plate": cfg.sim.plate.model_copy(
        update={"mesh_file": files / "other.ply"})})})  # fmt: skip
    with pytest.raises(
        SimCellError, match=r"\[sim.plate\] mesh_file / design_file: .*other.ply does not match"
    ):
        sim_plate_truth(cfg2)


def test_a_formed_mesh_written_in_ship_coordinates_reads_back(tmp_path: Path) -> None:
    # the design frame -> ship coordinates: turned 90 degrees about z, 40 m aft, 3 m up
    T = np.array(
        [[0.0, -1.0, 0.0, 40000.0], [1.0, 0.0, 0.0, -2500.0], [0.0, 0.0, 1.0, 3000.0], [0, 0, 0, 1.0]]
    )
    path = write_formed_mesh(SPEC, ERROR, tmp_path / "formed.ply", pitch_mm=5.0, T_file_design=T)
    back = load_mesh(path)
    want = design_mesh(SPEC, pitch_mm=5.0, error=ERROR).transformed(T)
    np.testing.assert_array_equal(back.triangles, want.triangles)
    np.testing.assert_allclose(back.vertices_mm, want.vertices_mm, rtol=0.0, atol=1e-9)  # doubles in the PLY
    with pytest.raises(SynthError, match=r"formed mesh: write \.ply, \.stl or \.obj"):
        write_formed_mesh(SPEC, ERROR, tmp_path / "formed.xyz")


@pytest.mark.parametrize(
    "suffix",
    [
        ".ply",
        pytest.param(".igs", marks=[pytest.mark.slow, pytest.mark.process]),
    ],  # the CAD reader forks: 3-5 s
)
def test_a_plate_designed_in_ship_coordinates_lies_where_its_design_frame_is_placed(
    suffix: str, tmp_path: Path
) -> None:
    # the design and the formed surface both in ship coordinates (turned, 40 m aft, 3 m up): the
    # simulator puts the mesh in the design frame the product's readers find for the design file
    from analysis.design.cad_write import write_design

    T = np.array(
        [[0.0, -1.0, 0.0, 40000.0], [1.0, 0.0, 0.0, -2500.0], [0.0, 0.0, 1.0, 3000.0], [0, 0, 0, 1.0]]
    )
    design = tmp_path / f"design{suffix}"
    if suffix == ".igs":
        write_design(SPEC, design, T_file_design=T)
    else:
        save_mesh(design_mesh(SPEC, pitch_mm=10.0).transformed(T), design)
    formed = write_formed_mesh(SPEC, ERROR, tmp_path / "formed.ply", T_file_design=T)
    truth = mesh_plate_truth(formed, design, thickness_mm=12.0, pos_mm=(1500.0, 0.0, 300.0), angle_deg=3.0)
    # the file -> design frame undoes the ship placement (up to the plate's own symmetry: a turn by
    # 180 degrees about z is the same rectangle)
    moved = truth.T_design_file @ T
    assert abs(abs(moved[0, 0]) - 1.0) < 1e-6 and abs(moved[2, 2] - 1.0) < 1e-6
    assert np.abs(moved[:2, 3]).max() < 1e-3
    x, y = np.meshgrid(np.linspace(-120.0, 120.0, 9), np.linspace(-80.0, 80.0, 7))
    u, v = moved[0, 0] * x, moved[1, 1] * y  # the design frame's (x, y) in the spec's
    h_spec = plate_truth("sail", length_mm=300.0, width_mm=200.0, thickness_mm=12.0).height_mm(u, v)[0]
    np.testing.assert_allclose(truth.height_mm(x, y)[0], h_spec + moved[2, 3], atol=0.05)
