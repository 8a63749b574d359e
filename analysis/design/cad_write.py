"""Writing designs as a hull design system would: the analytic plates as exact NURBS in IGES or STEP.

The project's plate shapes (:mod:`analysis.design.plates`) are exactly NURBS: the sail, saddle and flat
plates are polynomials of degree 2 in x and y (a biquadratic Bezier patch), the twisted plate
``z = k x y`` is bilinear, the cylinder is a circular arc in x (a rational quadratic) swept along y.
:func:`plate_surface` builds that surface through OpenCASCADE; :func:`write_design` writes it, whole,
trimmed to the footprint, or split into several faces, in millimetres or metres, moved into ship
coordinates by a 4x4 transform if asked. ``cellctl synth`` and the tests make their IGES and
STEP designs with it, so the files come from the same writer a CAD system's translator uses.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from analysis.design.plates import PlateSpec, design_height_mm, footprint_bounds, is_rectangle, outline_edges

UNIT_MM = {"mm": 1.0, "m": 1000.0}


def _bezier_poles(spec: PlateSpec, margin_mm: float) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Poles (nu, nv, 3) mm, weights (nu, nv) and degrees of the plate's exact surface."""
    hl, hw = spec.length_mm / 2 + margin_mm, spec.width_mm / 2 + margin_mm
    if spec.kind == "cylinder":
        r = spec.radius_x_mm
        a = np.arcsin(hl / r)  # half angle of the arc
        # rational quadratic arc z = r - sqrt(r^2 - x^2), |x| <= hl: middle pole at the tangents' meet
        xs = np.array([-hl, 0.0, hl])
        z_end = r - r * np.cos(a)
        zs = np.array([z_end, z_end - hl * np.tan(a), z_end])
        wx = np.array([1.0, np.cos(a), 1.0])
        ys = np.array([-hw, hw])
        P = np.array([[[x, y, z] for y in ys] for x, z in zip(xs, zs, strict=True)])
        W = np.repeat(wx[:, None], 2, axis=1)
        return P, W, 2, 1
    if spec.kind == "twisted":
        xs, ys = np.array([-hl, hl]), np.array([-hw, hw])
        X, Y = np.meshgrid(xs, ys, indexing="ij")
        return np.stack([X, Y, design_height_mm(spec, X, Y)], axis=2), np.ones((2, 2)), 1, 1
    # z = f(x) + g(y) with f, g quadratics: Bezier poles are the sums of the 1-D poles
    xs, ys = np.array([-hl, 0.0, hl]), np.array([-hw, 0.0, hw])
    fx = design_height_mm(spec, xs, np.zeros(3))
    gy = design_height_mm(spec, np.zeros(3), ys)
    bx = np.array([fx[0], 2 * fx[1] - (fx[0] + fx[2]) / 2, fx[2]])
    by = np.array([gy[0], 2 * gy[1] - (gy[0] + gy[2]) / 2, gy[2]])
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    Z = bx[:, None] + by[None, :]
    return np.stack([X, Y, Z], axis=2), np.ones((3, 3)), 2, 2


def plate_surface(spec: PlateSpec, margin_mm: float = 0.0):
    """The plate's exact top surface as an OpenCASCADE ``Geom_BSplineSurface`` (design frame, mm),
    covering the footprint plus ``margin_mm`` all round; u runs along x, v along y (normal up)."""
    from OCP.Geom import Geom_BSplineSurface
    from OCP.gp import gp_Pnt
    from OCP.OCP.collections import Array1_double, Array1_int, Array2_double, Array2_gp_Pnt

    P, W, du, dv = _bezier_poles(spec, margin_mm)
    nu, nv = W.shape
    poles = Array2_gp_Pnt(1, nu, 1, nv)
    weights = Array2_double(1, nu, 1, nv)
    for i in range(nu):
        for j in range(nv):
            poles.SetValue(i + 1, j + 1, gp_Pnt(*map(float, P[i, j])))
            weights.SetValue(i + 1, j + 1, float(W[i, j]))

    def knots(deg: int) -> tuple:
        k = Array1_double(1, 2)
        k.SetValue(1, 0.0)
        k.SetValue(2, 1.0)
        m = Array1_int(1, 2)
        m.SetValue(1, deg + 1)
        m.SetValue(2, deg + 1)
        return k, m

    ku, mu = knots(du)
    kv, mv = knots(dv)
    return Geom_BSplineSurface(poles, weights, ku, kv, mu, mv, du, dv)


def _uv_of_xy(spec: PlateSpec, margin_mm: float, x: float, y: float) -> tuple[float, float]:
    """Surface parameters over design (x, y): linear in x and y except along the cylinder's arc."""
    hl, hw = spec.length_mm / 2 + margin_mm, spec.width_mm / 2 + margin_mm
    v = (y + hw) / (2 * hw)
    if spec.kind != "cylinder":
        return (x + hl) / (2 * hl), v
    # invert x(u) of the rational arc numerically (monotone)
    from OCP.gp import gp_Pnt

    surf = plate_surface(spec, margin_mm)
    lo, hi = 0.0, 1.0
    for _ in range(60):
        mid = (lo + hi) / 2
        p = gp_Pnt()
        surf.D0(mid, v, p)
        lo, hi = (mid, hi) if p.X() < x else (lo, mid)
    return (lo + hi) / 2, v


def plate_faces(spec: PlateSpec, *, trimmed: bool = False, split: tuple[int, int] = (1, 1)) -> list:
    """TopoDS faces of the plate's top surface: one face, or ``split`` (nx, ny) faces sharing edges,
    or (``trimmed``) a larger surface trimmed to the footprint by a boundary in its parameters. A
    plate whose outline is not a rectangle (:mod:`analysis.design.plates`) is always one trimmed face."""
    from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeEdge, BRepBuilderAPI_MakeFace, BRepBuilderAPI_MakeWire
    from OCP.BRepLib import BRepLib
    from OCP.Geom2d import Geom2d_BezierCurve, Geom2d_Line
    from OCP.gp import gp_Dir2d, gp_Pnt2d
    from OCP.OCP.collections import Array1_gp_Pnt2d

    rectangle = is_rectangle(spec)
    if not rectangle and (spec.kind == "cylinder" or split != (1, 1)):
        raise ValueError(
            "a non-rectangular outline is written as one trimmed face of a sail, saddle, twisted or flat plate"
        )
    if trimmed or not rectangle:
        # the surface must reach beyond the whole outline (a sheared or bowed one too)
        x_min, x_max, y_min, y_max = footprint_bounds(spec)
        beyond = max(x_max - spec.length_mm / 2, -spec.length_mm / 2 - x_min,
                     y_max - spec.width_mm / 2, -spec.width_mm / 2 - y_min, 0.0)  # fmt: skip
        margin = 0.1 * spec.width_mm + beyond
        surf = plate_surface(spec, margin)
        wire = BRepBuilderAPI_MakeWire()
        for ed in outline_edges(spec):
            # u, v are linear in x, y off the cylinder: a straight edge is a line in (u, v), a
            # parabolic bow the quadratic Bezier through its chord ends and twice its sagitta
            a = np.array(_uv_of_xy(spec, margin, *ed.a))
            b = np.array(_uv_of_xy(spec, margin, *(ed.a + ed.chord_mm * ed.e)))
            if ed.k_per_mm == 0.0:
                d = b - a
                line = Geom2d_Line(gp_Pnt2d(*a), gp_Dir2d(*d))
                wire.Add(BRepBuilderAPI_MakeEdge(line, surf, 0.0, float(np.linalg.norm(d))).Edge())
                continue
            sag = ed.k_per_mm * ed.chord_mm**2 / 4.0
            mid = ed.a + 0.5 * ed.chord_mm * ed.e + 2.0 * sag * ed.n
            m = np.array(_uv_of_xy(spec, margin, *mid))
            poles = Array1_gp_Pnt2d(1, 3)
            for i, pt in enumerate((a, m, b)):
                poles.SetValue(i + 1, gp_Pnt2d(*pt))
            curve = Geom2d_BezierCurve(poles)
            wire.Add(BRepBuilderAPI_MakeEdge(curve, surf, 0.0, 1.0).Edge())
        face = BRepBuilderAPI_MakeFace(surf, wire.Wire(), True).Face()
        BRepLib.BuildCurves3d_s(face)
        return [face]
    surf = plate_surface(spec)
    nx, ny = split
    us = [
        _uv_of_xy(spec, 0.0, x, 0.0)[0] for x in np.linspace(-spec.length_mm / 2, spec.length_mm / 2, nx + 1)
    ]
    vs = np.linspace(0.0, 1.0, ny + 1)
    faces = []
    for i in range(nx):
        for j in range(ny):
            faces.append(
                BRepBuilderAPI_MakeFace(
                    surf, float(us[i]), float(us[i + 1]), float(vs[j]), float(vs[j + 1]), 1e-7
                ).Face()
            )
    return faces


def write_faces(
    faces: list, path: str | Path, *, units: str = "mm", T_file_design: np.ndarray | None = None
) -> Path:
    """Write faces (design frame, mm) as IGES (by suffix .igs/.iges: entity 128, trimmed faces as
    143/144) or STEP (.stp/.step, AP214), in ``units`` ("mm" or "m"), moved by ``T_file_design``
    (4x4, design -> file frame, mm) first."""
    from OCP.BRep import BRep_Builder
    from OCP.BRepBuilderAPI import BRepBuilderAPI_Transform
    from OCP.gp import gp_Trsf
    from OCP.IFSelect import IFSelect_RetDone
    from OCP.IGESControl import IGESControl_Controller, IGESControl_Writer
    from OCP.Interface import Interface_Static
    from OCP.STEPControl import STEPControl_AsIs, STEPControl_Controller, STEPControl_Writer
    from OCP.TopoDS import TopoDS_Compound

    from analysis.design.occ_read import quiet_occ

    quiet_occ()
    path = Path(path)
    if units not in UNIT_MM:
        raise ValueError(f"units must be one of {sorted(UNIT_MM)}, got {units!r}")
    comp = TopoDS_Compound()
    builder = BRep_Builder()
    builder.MakeCompound(comp)
    for f in faces:
        builder.Add(comp, f)
    shape = comp
    if T_file_design is not None:
        T = np.asarray(T_file_design, dtype=np.float64)
        trsf = gp_Trsf()
        trsf.SetValues(*(float(v) for v in T[:3, :].ravel()))
        shape = BRepBuilderAPI_Transform(comp, trsf, True).Shape()
    suffix = path.suffix.lower()
    if suffix in (".igs", ".iges"):
        IGESControl_Controller.Init_s()
        Interface_Static.SetCVal_s("write.iges.unit", units.upper())
        Interface_Static.SetIVal_s("write.iges.brep.mode", 0)  # faces as 128 / 143 / 144, as yards send
        writer = IGESControl_Writer(units.upper(), 0)
        writer.AddShape(shape)
        writer.ComputeModel()
        if not writer.Write(str(path)):
            raise OSError(f"{path}: the IGES writer failed")
    elif suffix in (".stp", ".step"):
        # the STEP parameters exist once its controller is initialised: before that the unit set
        # here was silently dropped, and the first STEP file a process wrote came out in mm
        STEPControl_Controller.Init_s()
        Interface_Static.SetCVal_s("write.step.unit", units.upper())
        Interface_Static.SetCVal_s("xstep.cascade.unit", "MM")
        writer = STEPControl_Writer()
        writer.Transfer(shape, STEPControl_AsIs)
        if writer.Write(str(path)) != IFSelect_RetDone:
            raise OSError(f"{path}: the STEP writer failed")
    else:
        raise ValueError(f"{path}: write .igs/.iges or .stp/.step")
    return path


def write_design(
    spec: PlateSpec,
    path: str | Path,
    *,
    units: str = "mm",
    trimmed: bool = False,
    split: tuple[int, int] = (1, 1),
    T_file_design: np.ndarray | None = None,
) -> Path:
    """Write the plate's exact design surface as IGES or STEP (see :func:`plate_faces`, :func:`write_faces`)."""
    return write_faces(
        plate_faces(spec, trimmed=trimmed, split=split), path, units=units, T_file_design=T_file_design
    )
