"""Designs as shipyards hand them over: IGES and STEP B-spline surfaces, read through OpenCASCADE.

A hull design system exports a shell plate as one or more NURBS faces (IGES entity 128, bounded
or trimmed as 143 / 144; STEP ``B_SPLINE_SURFACE_WITH_KNOTS`` in an ``ADVANCED_FACE``), in ship
coordinates, in the file's units. :func:`read_cad` turns such a file into a
:class:`~analysis.design.cad_surface.CadDesign`:

* units from the file (IGES global section's units flag, STEP ``SI_UNIT`` with its prefix or a
  ``CONVERSION_BASED_UNIT``) converted into millimetres (:mod:`analysis.design.cad_facts`),
* the faces sewn into one plate (a file holding several plates that do not touch is refused),
  tessellated, their free boundary sampled (:mod:`analysis.design.occ_read`),
* the plate's own frame (its base plane and long edge; see :func:`plate_frame_from_surface`),
* every face as an exact NURBS patch evaluated with numpy (:mod:`analysis.design.nurbs`: points,
  first derivatives, normals), so that templates are cut from the surface itself
  (:meth:`CadDesign.vertical_heights`) and points can be projected onto it (:meth:`CadDesign.project`),
* a tessellation (:attr:`CadDesign.mesh`) for registration, with its chord error measured against
  the exact surface (:func:`measured_chord_error_mm`),
* the outline sampled from the faces' own free boundary and the four corners at its vertices.

An unusable file raises :class:`~analysis.design.cad_facts.DesignError` with one line naming the
file and what is wrong; OpenCASCADE reads in a forked child (:func:`read_cad`), so a file that
crashes it is refused the same way. :func:`read_design` is the one entry point for every design
format (PLY, STL and OBJ meshes too; :data:`DESIGN_SUFFIXES`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import structlog

from analysis.design.cad_facts import DesignError, iges_facts, step_facts
from analysis.design.cad_surface import CadDesign
from analysis.design.mesh import TriMesh, load_mesh
from analysis.design.occ_read import (
    as_nurbs,
    entity_list,
    face_patch,
    read_shape,
    sew_faces,
    shape_boundary_loops,
    shape_diagonal_mm,
    shape_faces,
    tessellate,
    weld,
)
from analysis.design.outline import OutlineError, frame_design_mesh, outline_corners, plate_frame_from_surface
from analysis.design.plates import canonical_corner_order

log = structlog.get_logger(__name__)

CAD_SUFFIXES = (".igs", ".iges", ".stp", ".step")
MESH_SUFFIXES = (".ply", ".stl", ".obj")
DESIGN_SUFFIXES = MESH_SUFFIXES + CAD_SUFFIXES


def read_cad(
    path: str | Path,
    deflection_mm: float | None = None,
    sew_tol_mm: float | None = None,
    *,
    one_plate: bool = True,
    isolated: bool = True,
    timeout_s: float = 300.0,
) -> CadDesign:
    """Read an IGES or STEP design (see :func:`read_cad_in_process` for the parameters).

    isolated: read in a forked child process. OpenCASCADE's translators trust the file: a
    corrupted STEP entity crashed the whole process (segmentation fault), as open3d did on a bad
    PLY. A :class:`CadDesign` is plain arrays, so the child pickles it back through a pipe; a
    child that dies or runs past ``timeout_s`` refuses the file with one line.
    """
    if not isolated:
        return read_cad_in_process(path, deflection_mm, sew_tol_mm, one_plate=one_plate)
    import OCP.BRepMesh
    import OCP.IGESControl
    import OCP.STEPControl  # noqa: F401 - loaded once here, inherited by every forked reader

    design = _in_child(
        lambda: read_cad_in_process(path, deflection_mm, sew_tol_mm, one_plate=one_plate, quiet=True),
        path,
        timeout_s,
    )
    log.info("design_read", file=str(path), fmt=design.facts.fmt, units=design.facts.units,
             faces=len(design.faces), triangles=len(design.mesh.triangles),
             chord_error_mm=round(design.chord_error_mm, 5))  # fmt: skip
    return design


def _in_child(work, path: str | Path, timeout_s: float):
    """Run ``work()`` in a forked child; its result or exception comes back pickled."""
    import os
    import pickle
    import select
    import signal
    import time

    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: never returns into the caller's code
        import faulthandler

        faulthandler.disable()  # a crash is reported by the parent in one line, not as a dump
        os.close(r)
        code = 0
        try:
            try:
                payload = pickle.dumps(("ok", work()))
            except DesignError as exc:
                payload = pickle.dumps(("error", str(exc)))
            except Exception as exc:  # a reader bug still ends in one line, with its type
                payload = pickle.dumps(
                    ("error", f"{path}: the CAD reader failed ({type(exc).__name__}: {exc})")
                )
            with os.fdopen(w, "wb") as f:
                f.write(payload)
        except BaseException:  # the child must exit, whatever happened
            code = 1
        os._exit(code)
    os.close(w)
    chunks: list[bytes] = []
    deadline = time.monotonic() + timeout_s
    try:
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                os.kill(pid, signal.SIGKILL)
                raise DesignError(f"{path}: the CAD reader did not finish within {timeout_s:.0f} s")
            ready, _, _ = select.select([r], [], [], min(left, 1.0))
            if ready:
                chunk = os.read(r, 1 << 20)
                if not chunk:
                    break
                chunks.append(chunk)
    finally:
        os.close(r)
        _, status = os.waitpid(pid, 0)
    if os.WIFSIGNALED(status) or not chunks:
        kind = Path(path).suffix.lstrip(".").upper()
        why = f"signal {os.WTERMSIG(status)}" if os.WIFSIGNALED(status) else f"exit {os.WEXITSTATUS(status)}"
        raise DesignError(f"{path}: corrupted {kind} file (the CAD reader crashed on it: {why})")
    kind, value = pickle.loads(b"".join(chunks))
    if kind == "error":
        raise DesignError(value)
    return value


def read_cad_in_process(
    path: str | Path,
    deflection_mm: float | None = None,
    sew_tol_mm: float | None = None,
    *,
    one_plate: bool = True,
    quiet: bool = False,
) -> CadDesign:
    """Read an IGES or STEP design into a :class:`CadDesign` (design frame, mm), in this process.

    deflection_mm: the tessellation's chord tolerance; default 0.01 mm (half the sensor noise) for a plate up to 5 m
    across, 1e-5 of the diagonal beyond (a whole hull). sew_tol_mm: gap up to which faces sharing an
    edge are sewn into one plate (default 0.05 mm, 1e-5 of the diagonal for a whole hull).
    one_plate: refuse a file whose faces form several separate pieces (a whole hull's patches may
    overlap and be read with False). Raises :class:`DesignError` (one line) for an unusable file.
    """
    import time

    path = Path(path)
    timings: dict[str, float] = {}
    t0, c0 = time.perf_counter(), time.process_time()
    if not path.is_file():
        raise DesignError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if suffix not in CAD_SUFFIXES:
        raise DesignError(f"{path}: not an IGES or STEP file (suffix {path.suffix!r})")
    data = path.read_bytes()
    if not data.strip():
        raise DesignError(f"{path}: empty file")
    facts = iges_facts(path, data) if suffix in (".igs", ".iges") else step_facts(path, data)
    shape = read_shape(path, facts)
    faces = shape_faces(shape)
    if not faces:
        kinds = entity_list(facts)
        if facts.surfaces:
            raise DesignError(f"{path}: unsupported entity: no face could be made from {kinds}")
        raise DesignError(f"{path}: no surface in the file ({kinds})")
    if facts.surfaces and len(faces) < facts.surfaces:
        raise DesignError(
            f"{path}: {facts.surfaces - len(faces)} of {facts.surfaces} surfaces could not be read "
            f"(corrupted or unsupported entity; {entity_list(facts)})"
        )
    timings["read"] = time.perf_counter() - t0
    t = time.perf_counter()
    diag = shape_diagonal_mm(shape)
    if sew_tol_mm is None:
        sew_tol_mm = max(0.05, 1e-5 * diag)
    if len(faces) > 1:
        shape, plates = sew_faces(faces, sew_tol_mm)
        faces = shape_faces(shape)
        if plates > 1 and one_plate:
            raise DesignError(
                f"{path}: several disjoint plates ({plates} separate pieces among {len(faces)} faces); "
                "give one plate per file"
            )
    shape, faces = as_nurbs(shape, faces)
    patches = [face_patch(f, path) for f in faces]
    timings["sew"] = time.perf_counter() - t
    t = time.perf_counter()
    if deflection_mm is None:
        deflection_mm = 0.01 if diag <= 5000.0 else 1e-5 * diag
    try:
        V, Tr, tface, tuv = tessellate(faces, patches, deflection_mm)
    except DesignError as exc:
        raise DesignError(f"{path}: {exc}") from None
    V, Tr = weld(V, Tr, min(1e-3, sew_tol_mm))
    timings["tessellate"] = time.perf_counter() - t
    t = time.perf_counter()
    wires = shape_boundary_loops(shape, path)
    samples, vflag = max(wires, key=lambda w: np.ptp(w[0], axis=0).sum())
    mesh_file = TriMesh(V, Tr)
    up = mesh_file.triangle_normals().T @ mesh_file.triangle_areas_mm2()
    up /= max(np.linalg.norm(up), 1e-300)
    try:
        corners_file = samples[outline_corners(samples, up, candidates=vflag)]
    except OutlineError as exc:
        raise DesignError(f"{path}: {exc}") from None
    T = plate_frame_from_surface(V, Tr, corners_file)

    def framed(T: np.ndarray) -> CadDesign:
        mesh = mesh_file.transformed(T)
        R, shift_mm = T[:3, :3], T[:3, 3]
        return CadDesign(
            path=path, facts=facts, faces=[p.transformed(T) for p in patches], mesh=mesh,
            triangle_face=tface, triangle_uv=tuv, corners_mm=canonical_corner_order(corners_file @ R.T + shift_mm),
            boundary_mm=samples @ R.T + shift_mm, T_design_file=T, deflection_mm=float(deflection_mm),
            chord_error_mm=0.0, area_mm2=float(mesh.triangle_areas_mm2().sum()), timings_s=timings,
        )  # fmt: skip

    design = framed(T)
    if not np.array_equal(T, np.eye(4)):
        # the origin on the surface itself, over the corners' centre (as a mesh's design frame has it)
        foot = design.vertical_heights(np.zeros((1, 3)), np.array([0.0, 0.0, 1.0]))[0]
        if np.isfinite(foot).all():
            shift = np.eye(4)
            shift[2, 3] = -foot[2]
            design = framed(shift @ T)
    design.chord_error_mm = measured_chord_error_mm(design)
    timings["boundary"] = time.perf_counter() - t
    timings["cpu"] = time.process_time() - c0  # the reader's own CPU time (a forked child's too)
    if not quiet:  # a forked child does not log: another thread may have held the log's lock
        log.info("design_read", file=str(path), fmt=facts.fmt, units=facts.units, faces=len(patches),
                 triangles=len(design.mesh.triangles), chord_error_mm=round(design.chord_error_mm, 5))  # fmt: skip
    return design


def measured_chord_error_mm(design: CadDesign, max_triangles: int = 5000) -> float:
    """The largest distance between the tessellation and the exact surface (mm), measured where a
    triangle departs most from its surface: its centroid and its edge midpoints (a subsample of at
    most ``max_triangles`` triangles)."""
    m = len(design.mesh.triangles)
    idx = np.arange(m) if m <= max_triangles else np.random.default_rng(0).choice(m, max_triangles, False)
    tv = design.mesh.triangle_vertices_mm[idx]
    tuv = design.triangle_uv[idx]
    face = design.triangle_face[idx]
    worst = 0.0
    for wts in ((1 / 3, 1 / 3, 1 / 3), (0.5, 0.5, 0.0), (0.0, 0.5, 0.5), (0.5, 0.0, 0.5)):
        w = np.asarray(wts)
        p = np.einsum("k,nkc->nc", w, tv)
        _, dist = design.project(p, iterations=6, seeds=(face, np.einsum("k,nkc->nc", w, tuv)))
        worst = max(worst, float(dist.max()))
    return worst


def read_design(path: str | Path) -> TriMesh | CadDesign:
    """Any design file: IGES / STEP -> :class:`CadDesign`; PLY / STL / OBJ -> :class:`TriMesh` (mm)."""
    suffix = Path(path).suffix.lower()
    if suffix in CAD_SUFFIXES:
        return read_cad(path)
    if suffix in MESH_SUFFIXES:
        # a mesh in ship coordinates is moved into its own plate frame, as a CAD design is
        try:
            return frame_design_mesh(load_mesh(path)).mesh
        except OutlineError as exc:
            raise DesignError(f"{path}: {exc}") from None
    raise DesignError(
        f"{path}: unsupported design format {Path(path).suffix!r} (use {', '.join(DESIGN_SUFFIXES)})"
    )


def design_mesh_of(design: TriMesh | CadDesign) -> TriMesh:
    """The triangle mesh of a design (a CAD design's tessellation)."""
    return design.mesh if isinstance(design, CadDesign) else design


def design_mesh_from_file(path: str | Path) -> TriMesh:
    """The design's triangle mesh from any design file, in the design frame (the planner's input)."""
    return design_mesh_of(read_design(path))
