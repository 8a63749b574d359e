"""A plate laid moulded side down: the design is the moulded face, the sensor sees the other one.

The synthetic scan is of the plate's visible face A (the formed sail, with a dent). The design
handed over is the moulded face: A offset by the thickness against its normals (analytic normals
of the sail), turned over so that it faces up in its own frame, as a yard's file gives it. Judged
with ``design_side = "moulded_down"`` and the thickness, the figures are those of A itself; without
the offset they are large.
"""

from __future__ import annotations

import dataclasses
from functools import cache

import numpy as np
import pytest

from analysis.contracts.job import Report
from analysis.contracts.settings import InspectionSettings
from analysis.design.mesh import TriMesh
from analysis.design.moulded import MouldedError, design_as_laid
from analysis.design.plates import FormingError, GaussianBump, design_mesh, plate_spec, surface_gradient
from analysis.pipeline import InspectionError, inspect_cloud
from analysis.synth import ScanSettings, synthesize_scan
from analysis.templates import DetectionLayout

THICKNESS_MM = 15.0
SETTINGS = InspectionSettings(layout=DetectionLayout(5, 100.0, 3, 100.0))


@cache
def _plate():
    spec = plate_spec("sail", length_mm=600, width_mm=400, thickness_mm=THICKNESS_MM)
    error = FormingError(bumps=(GaussianBump(x_mm=50.0, y_mm=0.0, amplitude_mm=-1.5, sigma_mm=40.0),))
    scan = synthesize_scan(spec, error, settings=ScanSettings.coarse(), seed=11)
    visible = design_mesh(spec, pitch_mm=2.0)  # face A: the design of the side the sensor sees
    x, y = visible.vertices_mm[:, 0], visible.vertices_mm[:, 1]
    z, gx, gy = surface_gradient(spec, FormingError(), x, y)
    n = np.column_stack([-gx, -gy, np.ones_like(x)])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    moulded = np.column_stack([x, y, z]) - THICKNESS_MM * n  # the other face, exactly
    turned = moulded * [1.0, -1.0, -1.0]  # turned over: the moulded face up, as the yard draws it
    design = TriMesh(turned, visible.triangles[:, ::-1].copy())
    return scan, visible, design


def _figures(report: Report) -> dict[str, tuple[float, float]]:
    return {ln.name: (ln.zmax_mm, ln.sz_avg_mm) for ln in report.lines}


@pytest.mark.slow
def test_a_moulded_side_down_plate_is_judged_with_the_thickness_offset() -> None:
    scan, visible, design = _plate()
    truth = _figures(inspect_cloud(scan.cloud, visible, SETTINGS).report)
    down = dataclasses.replace(SETTINGS, design_side="moulded_down", thickness_mm=THICKNESS_MM)
    report = inspect_cloud(scan.cloud, design, down).report
    assert report.design.side == "moulded_down" and report.design.thickness_mm == THICKNESS_MM
    got = _figures(report)
    assert got.keys() == truth.keys()
    # within 0.03 mm: the turned design's tessellation and corner order differ from face A's, and
    # the non-penetrating fit of this half-turn-symmetric plate settles 0.01-0.025 mm apart
    for name, (zmax, sz_avg) in truth.items():
        assert got[name][0] == pytest.approx(zmax, abs=0.03), name
        assert got[name][1] == pytest.approx(sz_avg, abs=0.03), name
    assert max(z for z, _ in truth.values()) > 1.0  # the dent is there to be found, and is found

    # the same moulded face judged as if it faced up: the plate reads as badly formed (or is refused)
    try:
        wrong = _figures(inspect_cloud(scan.cloud, design, SETTINGS).report)
    except InspectionError:
        return
    assert max(abs(z) for z, _ in wrong.values()) > 5.0


def test_the_offset_mesh_is_the_other_face_and_bad_settings_are_refused() -> None:
    _, visible, design = _plate()
    laid = design_as_laid(design, "moulded_down", THICKNESS_MM)
    # the turned-over offset of the moulded face is face A again, vertex by vertex
    err = np.linalg.norm(laid.vertices_mm - visible.vertices_mm, axis=1)
    assert err.max() < 0.01  # vertex normals at the 2 mm grid's edges are one-sided
    assert (laid.triangle_normals()[:, 2] > 0).all()
    assert design_as_laid(design, "moulded_up", THICKNESS_MM) is design
    with pytest.raises(MouldedError, match="needs its thickness"):
        design_as_laid(design, "moulded_down", 0.0)
    with pytest.raises(MouldedError, match="design side must be one of"):
        design_as_laid(design, "upside", THICKNESS_MM)


def _moulded_iges(path) -> None:
    """The sail's moulded face as a yard's IGES: OpenCASCADE's offset of the exact surface by the
    thickness against its normal, approximated as a B-spline (1e-6 mm), turned over, its normal up."""
    from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeFace
    from OCP.Geom import Geom_OffsetSurface
    from OCP.GeomAbs import GeomAbs_C2
    from OCP.GeomConvert import GeomConvert_ApproxSurface
    from OCP.gp import gp_Ax1, gp_Dir, gp_Pnt, gp_Trsf

    from analysis.design.cad_write import plate_surface, write_faces

    spec = _plate()[0].spec
    surf = plate_surface(spec)
    u0, u1, v0, v1 = surf.Bounds()
    offset = Geom_OffsetSurface(surf, -THICKNESS_MM)
    assert offset.Value((u0 + u1) / 2, (v0 + v1) / 2).Z() == pytest.approx(-THICKNESS_MM)  # below A
    approx = GeomConvert_ApproxSurface(offset, 1e-6, GeomAbs_C2, GeomAbs_C2, 12, 12, 14, 1)
    assert approx.HasResult() and approx.MaxError() < 1e-5
    bs = approx.Surface()
    turn = gp_Trsf()
    turn.SetRotation(gp_Ax1(gp_Pnt(0, 0, 0), gp_Dir(1, 0, 0)), np.pi)
    bs.Transform(turn)
    bs.UReverse()  # the moulded face's normal points away from the material: up, once turned
    write_faces([BRepBuilderAPI_MakeFace(bs, 1e-7).Face()], path)


@pytest.mark.slow
def test_a_cad_design_is_cut_on_its_exact_offset_surface(tmp_path) -> None:
    from analysis.design.cad import read_design

    scan, visible, _ = _plate()
    _moulded_iges(tmp_path / "moulded.igs")
    design = read_design(tmp_path / "moulded.igs")
    laid = design_as_laid(design, "moulded_down", THICKNESS_MM)
    # corners and template points of the offset: face A's, within 0.01 mm and 0.005 mm
    spec = scan.spec
    np.testing.assert_allclose(
        laid.corners_mm[:, :2], [[-300, -200], [300, -200], [300, 200], [-300, 200]], atol=0.01
    )
    rng = np.random.default_rng(3)
    o = np.column_stack([rng.uniform(-295, 295, 300), rng.uniform(-195, 195, 300), np.full(300, 100.0)])
    pts = laid.vertical_heights(o, np.array([0.0, 0.0, -1.0]))
    z, _, _ = surface_gradient(spec, FormingError(), o[:, 0], o[:, 1])
    dz = pts[:, 2] - z
    assert np.isfinite(dz).all() and np.ptp(dz) < 0.005
    np.testing.assert_allclose(pts[:, :2], o[:, :2], atol=1e-9)

    down = dataclasses.replace(SETTINGS, design_side="moulded_down", thickness_mm=THICKNESS_MM)
    report = inspect_cloud(scan.cloud, design, down).report
    assert report.design.kind == "cad" and report.design.side == "moulded_down"
    truth = _figures(inspect_cloud(scan.cloud, visible, SETTINGS).report)
    got = _figures(report)
    for name, (zmax, sz_avg) in truth.items():
        assert got[name][0] == pytest.approx(zmax, abs=0.03), name
        assert got[name][1] == pytest.approx(sz_avg, abs=0.03), name
