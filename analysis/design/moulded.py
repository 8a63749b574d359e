"""Moulded side and thickness: the surface the sensor sees when the plate lies the other way up.

A yard's design surface is the plate's *moulded* surface, one of its two faces. In the design
frame that surface faces +z (its normals point up, away from the plate's material, which lies
below it: :mod:`analysis.design.cad` turns the frame to the faces' normals, a mesh is given z up).

* ``moulded_up``: the plate lies on the bed with the moulded side up. The sensor sees the design
  surface itself.
* ``moulded_down``: the plate was turned over; the moulded side lies on the bed. The sensor sees
  the other face: the design offset by the thickness against its normals, turned over (a half
  turn about the design frame's x axis). :func:`design_as_laid` makes that surface: for a mesh
  every vertex moves along its normal; for a CAD design the faces are turned and the templates
  are cut from the exact offset surface (``CadDesign.offset_mm``), the tessellation and the
  corners moved with it.

The figure ``docs/moulded-side.png`` (``scripts/moulded_side_figure.py``) shows both cases.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import numpy as np

from analysis.design.cad_surface import CadDesign
from analysis.design.mesh import TriMesh
from analysis.design.outline import canonical_corner_order_in_plane

__all__ = ["DESIGN_SIDES", "DesignSide", "MouldedError", "design_as_laid", "vertex_normals"]

DesignSide = Literal["moulded_up", "moulded_down"]
DESIGN_SIDES: tuple[str, ...] = ("moulded_up", "moulded_down")
# a half turn about the design frame's x axis: the plate turned over
T_TURN = np.diag([1.0, -1.0, -1.0, 1.0])


class MouldedError(ValueError):
    """A design side or thickness that cannot be used."""


def vertex_normals(mesh: TriMesh) -> np.ndarray:
    """(n, 3) unit normals at the vertices: the area-weighted mean of the triangles' normals."""
    tv = mesh.triangle_vertices_mm
    face_n = np.cross(tv[:, 1] - tv[:, 0], tv[:, 2] - tv[:, 0])  # length: twice the area
    n = np.zeros_like(mesh.vertices_mm)
    for k in range(3):
        np.add.at(n, mesh.triangles[:, k], face_n)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return n / np.where(length > 0, length, 1.0)


def _turn(points_mm: np.ndarray) -> np.ndarray:
    return points_mm @ T_TURN[:3, :3].T


def design_as_laid(design: TriMesh | CadDesign, side: str, thickness_mm: float) -> TriMesh | CadDesign:
    """The design surface as the sensor sees it on the bed (design frame z up).

    ``moulded_up`` returns ``design`` unchanged (whatever the thickness). ``moulded_down`` needs a
    positive, finite ``thickness_mm``: the other face, offset against the normals by it and turned
    over (triangles rewound so their normals point up again).
    """
    if side not in DESIGN_SIDES:
        raise MouldedError(f"design side must be one of {', '.join(DESIGN_SIDES)}, got {side!r}")
    if side == "moulded_up":
        return design
    if not (np.isfinite(thickness_mm) and 0.0 < thickness_mm < 1000.0):
        raise MouldedError(
            f"a plate laid moulded side down needs its thickness (0 to 1000 mm), got {thickness_mm!r}"
        )
    if isinstance(design, CadDesign):
        return _cad_as_laid(design, thickness_mm)
    V = design.vertices_mm - thickness_mm * vertex_normals(design)
    return TriMesh(_turn(V), design.triangles[:, ::-1].copy())


def _cad_as_laid(design: CadDesign, thickness_mm: float) -> CadDesign:
    """The CAD design turned over, cut on its exact offset: the turned faces' normals (oriented up
    like the new tessellation) point away from the plate, the sensor's side is ``+thickness`` along them."""
    if design.offset_mm:
        raise MouldedError("the design is already offset (laid moulded side down once)")

    def offset(points_mm: np.ndarray) -> np.ndarray:
        face, uv = design.nearest_parameters(points_mm)
        return points_mm - thickness_mm * design.normals(face, uv)

    mesh = TriMesh(_turn(offset(design.mesh.vertices_mm)), design.mesh.triangles[:, ::-1].copy())
    corners = canonical_corner_order_in_plane(_turn(offset(design.corners_mm)), np.array([0.0, 0.0, 1.0]))
    return dataclasses.replace(
        design,
        faces=[f.transformed(T_TURN) for f in design.faces],
        mesh=mesh,
        triangle_uv=design.triangle_uv[:, ::-1].copy(),
        corners_mm=corners,
        boundary_mm=_turn(offset(design.boundary_mm))[::-1].copy(),
        T_design_file=T_TURN @ design.T_design_file,
        offset_mm=thickness_mm,
        timings_s=dict(design.timings_s),
    )
