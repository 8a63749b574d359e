"""IGES and STEP designs: files written by OpenCASCADE in the test, checked against the analytic
surface they came from, and the real hull files of ../shared/testdata/designs/."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from analysis.design.cad import read_cad, read_design
from analysis.design.cad_facts import DesignError
from analysis.design.cad_write import plate_faces, write_design, write_faces
from analysis.design.mesh import TriMesh
from analysis.design.plates import design_corners, design_height_mm, design_mesh, plate_spec
from analysis.templates import DetectionLayout, detection_lines, exact_section

# Every CAD read runs in a forked child (OpenCASCADE can crash on a bad file): a process test.
pytestmark = pytest.mark.process

HULLS = Path(__file__).resolve().parents[2] / ".." / "shared" / "testdata" / "designs"
HULLS = HULLS if HULLS.is_dir() else Path("/work/shared/testdata/designs")
SAIL = plate_spec("sail")
CYLINDER = plate_spec("cylinder")


def _corner_error(design, spec) -> float:
    return float(np.abs(design.corners_mm - design_corners(spec)).max())


def _template_error(design, spec, T=np.eye(4)) -> tuple[float, int]:
    """Largest distance of exact template points (23 lines of the 1200 x 800 layout) from the
    analytic surface, measured vertically in the design frame; and the number of points."""
    c = design_corners(spec) @ T[:3, :3].T + T[:3, 3]
    up = T[:3, :3] @ np.array([0.0, 0.0, 1.0])
    worst, n = 0.0, 0
    for line in detection_lines(c, DetectionLayout(), up=up):
        sec = exact_section(design, T, line, 1.0)
        p_m = (
            line.start_mm
            + np.outer(sec.s_mm, line.direction)
            + np.outer(sec.h_mm - line.start_mm @ line.up, line.up)
        )
        p_d = (p_m - T[:3, 3]) @ T[:3, :3]
        ok = np.isfinite(p_d).all(axis=1)
        assert ok.mean() > 0.99, (line.family, line.index, ok.mean())
        dz = p_d[ok, 2] - design_height_mm(spec, p_d[ok, 0], p_d[ok, 1])
        worst, n = max(worst, float(np.abs(dz).max())), n + int(ok.sum())
    return worst, n


@pytest.mark.parametrize("suffix", [".igs", ".step"])
@pytest.mark.parametrize("units", ["mm", "m"])
def test_polynomial_sail_reads_into_millimetres_with_exact_corners_and_templates(
    tmp_path: Path, suffix: str, units: str
) -> None:
    path = write_design(SAIL, tmp_path / f"sail{suffix}", units=units)
    d = read_cad(path)
    assert d.facts.units == units and d.facts.fmt == ("IGES" if suffix == ".igs" else "STEP")
    assert len(d.faces) == 1 and not d.faces[0].rational
    if suffix == ".igs":
        assert d.facts.entities.get("128") == 1
    else:
        assert d.facts.entities.get("B_SPLINE_SURFACE_WITH_KNOTS", 0) >= 1
    assert _corner_error(d, SAIL) < 0.01
    np.testing.assert_allclose(d.size_mm(), (1200.0, 800.0), atol=0.01)
    assert d.chord_error_mm <= 0.02
    worst, n = _template_error(d, SAIL)
    assert n > 15000 and worst < 0.005, worst


def test_rational_cylinder_is_evaluated_exactly(tmp_path: Path) -> None:
    d = read_cad(write_design(CYLINDER, tmp_path / "cyl.igs"))
    assert d.faces[0].rational
    assert _corner_error(d, CYLINDER) < 0.01
    # a registration-like pose: templates cut in a tilted, turned measured frame
    a, b = np.radians(25.0), np.radians(2.0)
    T = np.eye(4)
    T[:3, :3] = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]) @ np.array(
        [[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]]
    )
    T[:3, 3] = [2500.0, 900.0, 300.0]
    worst, _ = _template_error(d, CYLINDER, T)
    assert worst < 0.005, worst
    assert d.smallest_radius_mm() == pytest.approx(2500.0, rel=1e-3)


def test_trimmed_iges_face_keeps_its_trimmed_outline(tmp_path: Path) -> None:
    path = write_design(SAIL, tmp_path / "trimmed.igs", trimmed=True)
    d = read_cad(path)
    assert {"144"} <= set(d.facts.entities) or {"143"} <= set(d.facts.entities)
    # the surface extends 80 mm past the trim; the outline and size are the trim's
    assert _corner_error(d, SAIL) < 0.01
    np.testing.assert_allclose(d.size_mm(), (1200.0, 800.0), atol=0.01)
    assert np.abs(d.boundary_mm[:, :2]).max(axis=0) == pytest.approx([600.0, 400.0], abs=0.01)
    worst, _ = _template_error(d, SAIL)
    assert worst < 0.005


def test_several_faces_of_one_plate_are_sewn_and_cornered_at_the_plate(tmp_path: Path) -> None:
    d = read_cad(write_design(SAIL, tmp_path / "split.step", split=(3, 2)))
    assert len(d.faces) == 6
    assert _corner_error(d, SAIL) < 0.01  # not the vertices where the faces meet on an edge
    worst, _ = _template_error(d, SAIL)
    assert worst < 0.005
    # one connected surface: the seams are welded
    edges = np.sort(np.concatenate([d.mesh.triangles[:, [0, 1]], d.mesh.triangles[:, [1, 2]],
                                    d.mesh.triangles[:, [2, 0]]]), axis=1)  # fmt: skip
    _, counts = np.unique(edges, axis=0, return_counts=True)
    border = np.count_nonzero(counts == 1)
    assert border < 1.2 * 4000 / 1.0  # outline only (about 4 m of edge), no internal seams


def test_a_plate_in_ship_coordinates_gets_its_own_frame(tmp_path: Path) -> None:
    # a side-shell plate: stood up 80 degrees, turned, 13 m above the keel, written in metres
    a, b = np.radians(80.0), np.radians(30.0)
    Rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    Rz = np.array([[np.cos(b), -np.sin(b), 0], [np.sin(b), np.cos(b), 0], [0, 0, 1]])
    T = np.eye(4)
    T[:3, :3] = Rz @ Rx
    T[:3, 3] = [95000.0, 11000.0, 13000.0]
    d = read_cad(write_design(SAIL, tmp_path / "side.igs", units="m", T_file_design=T))
    np.testing.assert_allclose(d.size_mm(), (1200.0, 800.0), atol=0.01)
    # the design frame is the plate's: corners as in the design frame, up to a shift along z
    c = design_corners(SAIL)
    got = d.corners_mm
    if got[0, 0] * c[0, 0] < 0:  # the half-turn symmetry of a rectangle: either long edge first
        got = np.roll(got, 2, axis=0) * [-1, -1, 1]
    np.testing.assert_allclose(got[:, :2], c[:, :2], atol=0.01)
    np.testing.assert_allclose(got[:, 2] - got[0, 2], c[:, 2] - c[0, 2], atol=0.01)
    # T_design_file maps the file's corners onto the design frame's
    file_c = design_corners(SAIL) @ T[:3, :3].T + T[:3, 3]
    back = file_c @ d.T_design_file[:3, :3].T + d.T_design_file[:3, 3]
    assert np.abs(np.sort(back[:, 2]) - np.sort(got[:, 2])).max() < 0.01


# ------------------------------------------------------------------------------- unusable files


def _one_line(exc: pytest.ExceptionInfo, *words: str) -> str:
    msg = str(exc.value)
    assert "\n" not in msg and "Traceback" not in msg
    for w in words:
        assert w in msg, msg
    return msg


def test_truncated_iges_and_step_are_refused_by_name(tmp_path: Path) -> None:
    for suffix in (".igs", ".step"):
        src = write_design(SAIL, tmp_path / f"whole{suffix}")
        data = src.read_bytes()
        cut = tmp_path / f"cut{suffix}"
        cut.write_bytes(data[: len(data) * 2 // 3])
        with pytest.raises(DesignError) as exc:
            read_cad(cut)
        _one_line(exc, str(cut), "truncated")


def test_corrupted_iges_and_step_are_refused_by_name(tmp_path: Path) -> None:
    igs = write_design(SAIL, tmp_path / "a.igs").read_text(encoding="latin-1").splitlines()
    p_at = next(k for k, line in enumerate(igs) if line[72:73] == "P")
    igs[p_at + 1] = "#@!garbage" + igs[p_at + 1][10:]  # parameter data no longer numbers
    bad = tmp_path / "bad.igs"
    bad.write_text("\n".join(igs) + "\n", encoding="latin-1")
    with pytest.raises(DesignError) as exc:
        read_cad(bad)
    _one_line(exc, str(bad))
    noise = tmp_path / "noise.igs"
    noise.write_bytes(np.random.default_rng(1).integers(0, 256, 20000, dtype=np.uint8).tobytes())
    with pytest.raises(DesignError) as exc:
        read_cad(noise)
    _one_line(exc, str(noise), "corrupted")
    step = write_design(SAIL, tmp_path / "a.step").read_text(encoding="latin-1")
    k = step.index("B_SPLINE_SURFACE_WITH_KNOTS")
    bad_step = tmp_path / "bad.step"
    bad_step.write_text(step[:k] + "B_SPLINE_SURFACE_WITH_KNOTS('',2,2,((#1,#2" + step[k + 200 :])
    with pytest.raises(DesignError) as exc:
        read_cad(bad_step)
    _one_line(exc, str(bad_step))


def test_a_surface_entity_no_face_can_be_made_from_is_refused_as_unsupported(tmp_path: Path) -> None:
    """Files in good order whose one surface OpenCASCADE cannot make a face from: an IGES 128 whose
    degree its poles cannot carry, a STEP B-spline surface with knot multiplicities that do not add up."""
    igs = write_design(SAIL, tmp_path / "a.igs").read_text(encoding="latin-1")
    assert "128,2,2,2,2," in igs  # upper indices 2, 2; degrees 2, 2
    bad_igs = tmp_path / "degree.igs"
    bad_igs.write_text(igs.replace("128,2,2,2,2,", "128,2,2,5,2,", 1), encoding="latin-1")
    step = write_design(SAIL, tmp_path / "a.step").read_text(encoding="latin-1")
    assert "(3,3),(3,3),(0.,1.),(0.,1.)" in step
    bad_step = tmp_path / "knots.step"
    bad_step.write_text(step.replace("(3,3),(3,3),(0.,1.),(0.,1.)", "(3,3),(2,3),(0.,1.),(0.,1.)", 1))
    for path, entity in ((bad_igs, "128 x1"), (bad_step, "B_SPLINE")):
        with pytest.raises(DesignError) as exc:
            read_cad(path)
        _one_line(exc, str(path), "unsupported entity")
        assert entity in str(exc.value), str(exc.value)


def test_missing_units_are_refused(tmp_path: Path) -> None:
    lines = write_design(SAIL, tmp_path / "u.igs").read_text(encoding="latin-1").splitlines()
    g = "".join(line[:72] for line in lines if line[72:73] == "G")
    fields = g.split(",")
    # the units flag is parameter 14 (no Hollerith commas before it in OCC's global section)
    assert fields[13].strip() == "2"
    fields[13] = ""
    g2 = ",".join(fields)
    g_lines = [
        g2[i : i + 72].ljust(72) + "G" + str(k + 1).rjust(7) for k, i in enumerate(range(0, len(g2), 72))
    ]
    rest = [line for line in lines if line[72:73] != "G"]
    s_lines = [line for line in rest if line[72:73] == "S"]
    others = [line for line in rest if line[72:73] in "DP"]
    counts = {c: sum(1 for line in lines if line[72:73] == c) for c in "SDP"}
    t_line = (f"S{counts['S']:7d}G{len(g_lines):7d}D{counts['D']:7d}P{counts['P']:7d}").ljust(72) + "T      1"
    path = tmp_path / "nounits.igs"
    path.write_text("\n".join([*s_lines, *g_lines, *others, t_line]) + "\n", encoding="latin-1")
    with pytest.raises(DesignError) as exc:
        read_cad(path)
    _one_line(exc, str(path), "units missing")
    step = write_design(SAIL, tmp_path / "u.step").read_text(encoding="latin-1")
    step_path = tmp_path / "nounits.step"
    step_path.write_text(step.replace("LENGTH_UNIT", "MASS_UNIT"))
    with pytest.raises(DesignError) as exc:
        read_cad(step_path)
    _one_line(exc, str(step_path), "units missing")


def test_a_file_without_surfaces_and_one_with_two_plates_are_refused(tmp_path: Path) -> None:
    from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeEdge, BRepBuilderAPI_Transform
    from OCP.gp import gp_Pnt, gp_Trsf, gp_Vec

    edge = BRepBuilderAPI_MakeEdge(gp_Pnt(0, 0, 0), gp_Pnt(1000, 0, 0)).Edge()
    curves = write_faces([edge], tmp_path / "curve.igs")
    with pytest.raises(DesignError) as exc:
        read_cad(curves)
    _one_line(exc, str(curves), "no surface")
    face = plate_faces(SAIL)[0]
    trsf = gp_Trsf()
    trsf.SetTranslation(gp_Vec(3000.0, 0.0, 0.0))
    other = BRepBuilderAPI_Transform(face, trsf, True).Shape()
    two = write_faces([face, other], tmp_path / "two.step")
    with pytest.raises(DesignError) as exc:
        read_cad(two)
    _one_line(exc, str(two), "several disjoint plates")


def test_read_design_dispatches_by_suffix_and_keeps_meshes(tmp_path: Path) -> None:
    from analysis.design.mesh import save_mesh

    ply = save_mesh(
        design_mesh(plate_spec("sail", length_mm=300, width_mm=200), pitch_mm=20), tmp_path / "d.ply"
    )
    assert isinstance(read_design(ply), TriMesh)
    (tmp_path / "d.dxf").write_text("0\nSECTION\n")
    with pytest.raises(DesignError) as exc:
        read_design(tmp_path / "d.dxf")
    _one_line(exc, "unsupported design format")
    with pytest.raises(DesignError) as exc:
        read_design(tmp_path / "missing.igs")
    _one_line(exc, "no such file")


# ------------------------------------------------------------------------------ real hull files


@pytest.mark.slow
def test_kcs_hull_every_patch_read_in_millimetres() -> None:
    d = read_cad(HULLS / "KCS_half_hull_SVA.igs", deflection_mm=50.0, one_plate=False)
    assert d.facts.units == "m" and d.facts.entities == {"128": 55}
    assert len(d.faces) == 55 and not any(p.rational for p in d.faces)
    lo, hi = _file_bounds(d)
    np.testing.assert_allclose(lo, [-6000.0, 0.0, 0.0], atol=30.0)
    np.testing.assert_allclose(hi, [237844.0, 16150.0, 23500.0], atol=60.0)
    with pytest.raises(DesignError) as exc:
        read_cad(HULLS / "KCS_half_hull_SVA.igs", deflection_mm=50.0)
    _one_line(exc, "several disjoint plates")


def _file_bounds(d) -> tuple[np.ndarray, np.ndarray]:
    Ti = np.linalg.inv(d.T_design_file)
    v = d.mesh.vertices_mm @ Ti[:3, :3].T + Ti[:3, 3]
    return v.min(axis=0), v.max(axis=0)


@pytest.mark.slow
def test_dtmb_5415_overlapping_patches_are_read_but_not_taken_for_one_plate() -> None:
    with pytest.raises(DesignError) as exc:
        read_cad(HULLS / "ship_5415.igs")
    _one_line(exc, "several disjoint plates")
    d = read_cad(HULLS / "ship_5415.igs", deflection_mm=5.0, one_plate=False)
    assert d.facts.units == "m" and len(d.faces) == 3
    lo, hi = _file_bounds(d)
    assert -400 < lo[0] < -380 and 5770 < hi[0] < 5790 and 640 < hi[2] < 660


@pytest.mark.slow
def test_step_hull_every_face_read_in_millimetres() -> None:
    d = read_cad(HULLS / "optiwise_test_step.step", deflection_mm=100.0)
    assert d.facts.units == "m" and d.facts.entities["B_SPLINE_SURFACE_WITH_KNOTS"] == 8
    assert len(d.faces) == 12
    lo, hi = _file_bounds(d)
    # the faces are trimmed at z = 8.2485 m (their B-spline surfaces reach 34 m above it)
    assert 299000 < hi[0] < 300500 and hi[2] == pytest.approx(8248.5, abs=1.0)
    assert lo[2] == pytest.approx(-1615.0, abs=5.0)


@pytest.mark.slow
def test_a_plate_sized_region_of_the_kcs_hull_is_usable_as_a_design(tmp_path: Path) -> None:
    """A 1.2 x 0.8 m piece of a midship side patch, written as IGES in metres, read as a design."""
    from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeFace
    from OCP.GeomAPI import GeomAPI_ProjectPointOnSurf
    from OCP.gp import gp_Pnt, gp_Vec

    from analysis.design.cad_facts import iges_facts
    from analysis.design.occ_read import read_shape, shape_faces

    src = HULLS / "KCS_half_hull_SVA.igs"
    faces = shape_faces(read_shape(src, iges_facts(src, src.read_bytes())))
    from OCP.BRep import BRep_Tool

    # the patch whose middle is highest on the side (a side-shell patch near midship)
    best = None
    for f in faces:
        s = BRep_Tool.Surface_s(f)
        u0, u1, v0, v1 = s.Bounds()
        p = s.Value((u0 + u1) / 2, (v0 + v1) / 2)
        if 80000 < p.X() < 160000 and (best is None or p.Z() > best[1]):
            best = (s, p.Z(), (u0, u1, v0, v1))
    assert best is not None
    surf, _, (u0, u1, v0, v1) = best
    um, vm = (u0 + u1) / 2, (v0 + v1) / 2
    p, du, dv = gp_Pnt(), gp_Vec(), gp_Vec()
    surf.D1(um, vm, p, du, dv)
    hu, hv = 600.0 / du.Magnitude(), 400.0 / dv.Magnitude()
    piece = surf.Copy()
    piece.Segment(um - hu, um + hu, vm - hv, vm + hv)
    path = write_faces([BRepBuilderAPI_MakeFace(piece, 1e-7).Face()], tmp_path / "kcs-plate.igs", units="m")
    d = read_cad(path)
    length, width = d.size_mm()
    assert 1150 < length < 1250 and 750 < width < 850, (length, width)
    assert not np.allclose(d.T_design_file, np.eye(4))  # it stood in ship coordinates
    # the base plane is the design frame's xy: the corners lie close to z = const
    assert np.ptp(d.corners_mm[:, 2]) < 50.0
    lines = detection_lines(d.corners_mm, DetectionLayout())
    pts = []
    for line in lines:
        sec = exact_section(d, np.eye(4), line, 5.0)
        ok = np.isfinite(sec.h_mm)
        assert ok.mean() > 0.95
        h = sec.h_mm[ok] - line.start_mm @ line.up
        pts.append(line.start_mm + np.outer(sec.s_mm[ok], line.direction) + np.outer(h, line.up))
    P = np.concatenate(pts)
    Ti = np.linalg.inv(d.T_design_file)
    P_file = P @ Ti[:3, :3].T + Ti[:3, 3]
    dist = []
    for q in P_file[:: max(1, len(P_file) // 200)]:
        proj = GeomAPI_ProjectPointOnSurf(gp_Pnt(*map(float, q)), surf)
        dist.append(proj.LowerDistance())
    assert max(dist) < 0.005, max(dist)
