"""A design file's shape through OpenCASCADE, turned into numpy: the faces read and sewn into one
plate, each as a :class:`~analysis.design.nurbs.NurbsPatch`, tessellated (a whole parameter rectangle
gridded in numpy, a trimmed face by OpenCASCADE's mesher), and the free boundary sampled into closed
loops. OCP is imported inside the functions: a mesh design never loads it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from analysis.design.cad_facts import DesignError, FileFacts
from analysis.design.nurbs import NurbsPatch


def quiet_occ() -> None:
    """OpenCASCADE prints progress to stdout; a command's stdout is for its own output."""
    from OCP.Message import Message, Message_Gravity

    printers = Message.DefaultMessenger_s().Printers()
    for k in range(1, printers.Length() + 1):
        printers.Value(k).SetTraceLevel(Message_Gravity.Message_Fail)


def read_shape(path: Path, facts: FileFacts):
    """The file's shape through OpenCASCADE's IGES or STEP reader, in millimetres."""
    from OCP.IFSelect import IFSelect_RetDone
    from OCP.IGESControl import IGESControl_Reader
    from OCP.Interface import Interface_Static
    from OCP.STEPControl import STEPControl_Reader

    quiet_occ()
    Interface_Static.SetCVal_s("xstep.cascade.unit", "MM")
    reader = IGESControl_Reader() if facts.fmt == "IGES" else STEPControl_Reader()
    status = reader.ReadFile(str(path))
    if status != IFSelect_RetDone:
        raise DesignError(f"{path}: corrupted {facts.fmt} file (OpenCASCADE cannot parse it)")
    if facts.fmt == "IGES":
        reader.SetReadVisible(True)
    reader.TransferRoots()
    if reader.NbShapes() == 0:
        raise DesignError(f"{path}: no surface ({entity_list(facts)})")
    return reader.OneShape()


def entity_list(facts: FileFacts) -> str:
    items = sorted(facts.entities.items(), key=lambda kv: -kv[1])[:6]
    prefix = "entities " if facts.fmt == "IGES" else ""
    return prefix + ", ".join(f"{k} x{n}" for k, n in items)


def shape_faces(shape) -> list:
    from OCP.TopAbs import TopAbs_FACE
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopoDS import TopoDS

    out = []
    ex = TopExp_Explorer(shape, TopAbs_FACE)
    while ex.More():
        out.append(TopoDS.Face(ex.Current()))
        ex.Next()
    return out


def sew_faces(faces: list, tol_mm: float):
    """Sew the faces into shells; returns (sewn shape, number of connected plates)."""
    from OCP.BRepBuilderAPI import BRepBuilderAPI_Sewing
    from OCP.TopAbs import TopAbs_SHELL
    from OCP.TopExp import TopExp_Explorer

    sew = BRepBuilderAPI_Sewing(tol_mm)
    for f in faces:
        sew.Add(f)
    sew.Perform()
    shape = sew.SewedShape()
    shells = 0
    ex = TopExp_Explorer(shape, TopAbs_SHELL)
    while ex.More():
        shells += 1
        ex.Next()
    free_faces = len(shape_faces(shape)) - sum(len(shape_faces(s)) for s in _shells(shape))
    return shape, max(shells, 1 if len(faces) == 1 else 0) + free_faces


def _shells(shape) -> list:
    from OCP.TopAbs import TopAbs_SHELL
    from OCP.TopExp import TopExp_Explorer

    out = []
    ex = TopExp_Explorer(shape, TopAbs_SHELL)
    while ex.More():
        out.append(ex.Current())
        ex.Next()
    return out


def as_nurbs(shape, faces: list) -> tuple:
    """Faces on planes, cylinders, offsets... converted to NURBS faces (their pcurves follow), so
    that the tessellation's parameters are the NURBS patch's. A shape of B-spline faces is kept."""
    from OCP.BRep import BRep_Tool
    from OCP.BRepBuilderAPI import BRepBuilderAPI_NurbsConvert
    from OCP.Geom import Geom_BSplineSurface

    if all(isinstance(BRep_Tool.Surface_s(f), Geom_BSplineSurface) for f in faces):
        return shape, faces
    converted = BRepBuilderAPI_NurbsConvert(shape, True).Shape()
    return converted, shape_faces(converted)


def face_patch(face, path: Path) -> NurbsPatch:
    """The face's surface as a NURBS patch with the face's parameter bounds (file frame, mm)."""
    from OCP.BRep import BRep_Tool
    from OCP.BRepTools import BRepTools
    from OCP.Geom import Geom_BSplineSurface
    from OCP.GeomConvert import GeomConvert

    u0, u1, v0, v1 = BRepTools.UVBounds_s(face)
    surf = BRep_Tool.Surface_s(face)  # in the face's own coordinates: its location moves it
    bs = surf if isinstance(surf, Geom_BSplineSurface) else None
    if bs is None:
        try:
            from OCP.Geom import Geom_RectangularTrimmedSurface

            bs = GeomConvert.SurfaceToBSplineSurface_s(Geom_RectangularTrimmedSurface(surf, u0, u1, v0, v1))
        except Exception as exc:  # OCC's Standard_Failure: a surface kind it cannot convert
            raise DesignError(
                f"{path}: unsupported surface {type(surf).__name__} ({str(exc)[:80]})"
            ) from None
    bs = bs.Copy()  # OCP hands back the concrete type; the copy may be made non-periodic
    if bs.IsUPeriodic():
        bs.SetUNotPeriodic()
    if bs.IsVPeriodic():
        bs.SetVNotPeriodic()
    nu, nv = bs.NbUPoles(), bs.NbVPoles()
    poles = np.array([[(p.X(), p.Y(), p.Z()) for p in (bs.Pole(i, j) for j in range(1, nv + 1))]
                      for i in range(1, nu + 1)])  # fmt: skip
    weights = np.array([[bs.Weight(i, j) for j in range(1, nv + 1)] for i in range(1, nu + 1)])
    ku = np.array([bs.UKnotSequence().Value(i) for i in range(1, bs.UKnotSequence().Length() + 1)])
    kv = np.array([bs.VKnotSequence().Value(i) for i in range(1, bs.VKnotSequence().Length() + 1)])
    trsf = face.Location().Transformation()
    T = np.eye(4)
    T[:3, :] = [[trsf.Value(i, j) for j in range(1, 5)] for i in range(1, 4)]
    patch = NurbsPatch(poles, weights, ku, kv, bs.UDegree(), bs.VDegree(), (u0, u1), (v0, v1))
    return patch if np.allclose(T, np.eye(4)) else patch.transformed(T)


def _untrimmed(face, patch: NurbsPatch) -> bool:
    """True when the face is its patch's whole parameter rectangle: one wire, every edge's curve on
    the surface lying on one side of the rectangle (no trimming curve inside it)."""
    from OCP.BRepAdaptor import BRepAdaptor_Curve2d
    from OCP.TopAbs import TopAbs_EDGE, TopAbs_WIRE
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopoDS import TopoDS

    wires = TopExp_Explorer(face, TopAbs_WIRE)
    n_wires = 0
    while wires.More():
        n_wires += 1
        wires.Next()
    if n_wires != 1:
        return False
    (u0, u1), (v0, v1) = patch.u_range, patch.v_range
    tol_u, tol_v = 1e-9 * max(u1 - u0, 1e-9), 1e-9 * max(v1 - v0, 1e-9)
    ex = TopExp_Explorer(face, TopAbs_EDGE)
    while ex.More():
        c = BRepAdaptor_Curve2d(TopoDS.Edge(ex.Current()), face)
        pts = [c.Value(t) for t in np.linspace(c.FirstParameter(), c.LastParameter(), 5)]
        u = np.array([p.X() for p in pts])
        v = np.array([p.Y() for p in pts])
        on_side = (
            np.all(np.abs(u - u0) < tol_u) or np.all(np.abs(u - u1) < tol_u)
            or np.all(np.abs(v - v0) < tol_v) or np.all(np.abs(v - v1) < tol_v)
        )  # fmt: skip
        if not on_side:
            return False
        ex.Next()
    return True


def _grid_tessellation(patch: NurbsPatch, chord_mm: float, max_nodes: int = 400_000):
    """A patch's whole parameter rectangle as a grid mesh with chord error about ``chord_mm``.

    The grid is refined once from a 17 x 17 trial: the midpoints' departure from the chords falls
    with the square of the spacing. Returns (vertices, triangles, uv (n, 2)); triangles are
    counter-clockwise in (u, v) (du x dv side).
    """
    (u0, u1), (v0, v1) = patch.u_range, patch.v_range

    def departure(nu: int, nv: int) -> tuple[float, float, float, float]:
        u = np.linspace(u0, u1, nu)
        v = np.linspace(v0, v1, nv)
        U, V = np.meshgrid(u, v, indexing="ij")
        S = patch.evaluate(U.ravel(), V.ravel())[0].reshape(nu, nv, 3)
        Um, Vm = np.meshgrid((u[:-1] + u[1:]) / 2, v, indexing="ij")
        Su = patch.evaluate(Um.ravel(), Vm.ravel())[0].reshape(nu - 1, nv, 3)
        Um, Vm = np.meshgrid(u, (v[:-1] + v[1:]) / 2, indexing="ij")
        Sv = patch.evaluate(Um.ravel(), Vm.ravel())[0].reshape(nu, nv - 1, 3)
        Um, Vm = np.meshgrid((u[:-1] + u[1:]) / 2, (v[:-1] + v[1:]) / 2, indexing="ij")
        Sc = patch.evaluate(Um.ravel(), Vm.ravel())[0].reshape(nu - 1, nv - 1, 3)
        dc = np.linalg.norm(Sc - (S[:-1, :-1] + S[1:, 1:]) / 2, axis=2).max()  # the cell's diagonal
        du = max(np.linalg.norm(Su - (S[:-1] + S[1:]) / 2, axis=2).max(), dc)
        dv = max(np.linalg.norm(Sv - (S[:, :-1] + S[:, 1:]) / 2, axis=2).max(), dc)
        len_u = np.linalg.norm(np.diff(S, axis=0), axis=2).sum(axis=0).max()
        len_v = np.linalg.norm(np.diff(S, axis=1), axis=2).sum(axis=1).max()
        return float(du), float(dv), float(len_u), float(len_v)

    n0 = 17
    du, dv, len_u, len_v = departure(n0, n0)
    # fine enough for the chord error, and no cell longer than 20 mm on a plate (a hull's patch:
    # 1 % of its length), so seeds and section extents stay local
    cell = max(20.0, 0.01 * max(len_u, len_v))
    nu = int(np.clip(max(np.ceil((n0 - 1) * np.sqrt(du / chord_mm)), np.ceil(len_u / cell)) + 1, 2, 4000))
    nv = int(np.clip(max(np.ceil((n0 - 1) * np.sqrt(dv / chord_mm)), np.ceil(len_v / cell)) + 1, 2, 4000))
    if nu * nv > max_nodes:
        scale = np.sqrt(max_nodes / (nu * nv))
        nu, nv = max(2, int(nu * scale)), max(2, int(nv * scale))
    u = np.linspace(u0, u1, nu)
    v = np.linspace(v0, v1, nv)
    U, V = np.meshgrid(u, v, indexing="ij")
    uv = np.column_stack([U.ravel(), V.ravel()])
    S = patch.evaluate(uv[:, 0], uv[:, 1])[0]
    idx = np.arange(nu * nv).reshape(nu, nv)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    tri = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    return S, tri, uv


def tessellate(faces: list, patches: list[NurbsPatch], deflection_mm: float):
    """(vertices (n, 3), triangles (m, 3), triangle face (m,), triangle uv (m, 3, 2)), file frame.

    A face that is its patch's whole parameter rectangle is gridded in numpy at a fifth of the
    deflection (exact nodes, fast); a trimmed face is meshed by OpenCASCADE within the deflection.
    """
    from OCP.BRep import BRep_Tool
    from OCP.BRepMesh import BRepMesh_IncrementalMesh
    from OCP.TopAbs import TopAbs_REVERSED
    from OCP.TopLoc import TopLoc_Location

    verts, tris, tface, tuv = [], [], [], []
    offset = 0
    for k, (face, patch) in enumerate(zip(faces, patches, strict=True)):
        if _untrimmed(face, patch):
            pts, t, uv = _grid_tessellation(patch, deflection_mm / 5.0)
        else:
            BRepMesh_IncrementalMesh(face, deflection_mm, False, 0.1, False)
            loc = TopLoc_Location()
            tri = BRep_Tool.Triangulation_s(face, loc)
            if tri is None or tri.NbTriangles() == 0:
                continue
            trsf = loc.Transformation()
            n = tri.NbNodes()
            pts = []
            for i in range(1, n + 1):
                p = tri.Node(i).Transformed(trsf)
                pts.append((p.X(), p.Y(), p.Z()))
            pts = np.asarray(pts)
            uv = np.array([(tri.UVNode(i).X(), tri.UVNode(i).Y()) for i in range(1, n + 1)])
            t = np.array([tri.Triangle(i).Get() for i in range(1, tri.NbTriangles() + 1)], dtype=np.int64) - 1
        if face.Orientation() == TopAbs_REVERSED:
            t = t[:, [0, 2, 1]]
        verts.append(pts)
        tris.append(t + offset)
        tface.append(np.full(len(t), k))
        tuv.append(uv[t])
        offset += len(pts)
    if not tris:
        raise DesignError("the surface could not be tessellated")
    return np.concatenate(verts), np.concatenate(tris), np.concatenate(tface), np.concatenate(tuv)


def weld(vertices: np.ndarray, triangles: np.ndarray, tol_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Merge coincident vertices (the faces' shared edges) so the mesh is one connected surface."""
    key = np.round(vertices / tol_mm).astype(np.int64)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    return vertices[first], inverse.reshape(-1)[triangles]


def _free_edges(shape) -> list:
    """Edges of the shape used by one face only: the plate's outline (seams excluded)."""
    from OCP.BRep import BRep_Tool
    from OCP.OCP.collections import (
        IndexedDataMap_TopoDS_Shape_List_TopoDS_Shape_TopTools_ShapeMapHasher as EdgeFaces,
    )
    from OCP.TopAbs import TopAbs_EDGE, TopAbs_FACE
    from OCP.TopExp import TopExp
    from OCP.TopoDS import TopoDS

    emap = EdgeFaces()
    TopExp.MapShapesAndAncestors_s(shape, TopAbs_EDGE, TopAbs_FACE, emap)
    out = []
    for k in range(1, emap.Extent() + 1):
        edge = TopoDS.Edge(emap.FindKey(k))
        faces = emap.FindFromIndex(k)
        if faces.Size() == 1 and not BRep_Tool.Degenerated_s(edge):
            face = TopoDS.Face(faces.First())
            if not BRep_Tool.IsClosed_s(edge, face):  # a periodic face's seam is not outline
                out.append(edge)
    return out


def shape_boundary_loops(shape, path: Path) -> list[tuple[np.ndarray, np.ndarray]]:
    """The free boundary as closed loops: per loop (samples (k, 3), vertex flags (k,) bool), the
    boundary curves sampled every 2 mm or finer, chained end to end."""
    from OCP.BRepAdaptor import BRepAdaptor_Curve
    from OCP.GCPnts import GCPnts_AbscissaPoint

    pieces = []
    for edge in _free_edges(shape):
        c = BRepAdaptor_Curve(edge)
        a, b = c.FirstParameter(), c.LastParameter()
        length = GCPnts_AbscissaPoint.Length_s(c)
        n = int(np.clip(np.ceil(length / 2.0), 8, 4000))
        pts = []
        for tt in np.linspace(a, b, n + 1):
            p = c.Value(float(tt))
            pts.append((p.X(), p.Y(), p.Z()))
        pieces.append(np.asarray(pts))
    if not pieces:
        raise DesignError(f"{path}: the surface has no free boundary (a closed solid, not a plate surface)")
    size = max(float(np.ptp(np.concatenate(pieces), axis=0).max()), 1.0)
    loops = []
    left = list(range(len(pieces)))
    while left:
        loop = [pieces[left.pop(0)]]
        while left:
            end = loop[-1][-1]
            ends = np.array([[np.linalg.norm(pieces[i][0] - end), np.linalg.norm(pieces[i][-1] - end)]
                             for i in left])  # fmt: skip
            k, side = np.unravel_index(int(np.argmin(ends)), ends.shape)
            if ends[k, side] > 1e-3 * size:
                break
            piece = pieces[left.pop(int(k))]
            loop.append(piece if side == 0 else piece[::-1])
        samples = np.concatenate([p[:-1] for p in loop])
        flags = np.concatenate([np.arange(len(p) - 1) == 0 for p in loop])
        loops.append((samples, flags))
    return loops


def shape_diagonal_mm(shape) -> float:
    """The diagonal of the shape's bounding box (mm): the scale the read's tolerances follow."""
    from OCP.Bnd import Bnd_Box
    from OCP.BRepBndLib import BRepBndLib

    box = Bnd_Box()
    BRepBndLib.Add_s(shape, box)
    return box.CornerMin().Distance(box.CornerMax())
