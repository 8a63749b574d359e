"""A heating plan applied to a formed plate's mesh by the simulated (mismatched) forming model of
:mod:`analysis.forming.simulate`: ``cellctl sim heat`` and benchmarks/forming_loop.py.

Frames: heating-plan.json's positions are in the plate frame of report.json's lines (mm from the
reference corner, x along edge 0 -> 1, y along 0 -> 3, z up), the frame the inspection makes from
the design's corners. The mesh is in its design frame or in file coordinates (ship coordinates); it
is framed as the inspection frames a design mesh (:func:`analysis.design.outline.frame_design_mesh`,
then :func:`analysis.design.outline.plate_frame` of its corners), its vertices moved in that frame by
the simulated deflection (along z) and in-plane shrinkage, and moved back to the file's coordinates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from analysis.design.mesh import TriMesh
from analysis.design.outline import OutlineError, design_corners_from_mesh, frame_design_mesh, plate_frame
from analysis.forming.plan_file import HeatingPlanFile
from analysis.forming.simulate import (
    COEFFICIENT_SPREAD,
    POSITION_SPREAD_MM,
    HeatError,
    SimulatedRound,
    heat_points,
)

__all__ = ["HeatedPlate", "heat_mesh", "mesh_plate_frame"]


@dataclass(frozen=True)
class HeatedPlate:
    """The heated mesh (the input's coordinates), the plate's size as measured on the mesh, and the
    simulated round (its draw and model)."""

    mesh: TriMesh
    plate_size_mm: tuple[float, float]
    round: SimulatedRound

    @property
    def max_deflection_mm(self) -> float:
        return float(np.abs(self.round.displacement_mm[:, 2]).max())

    def sidecar(self) -> dict:
        """The output's sidecar JSON."""
        return {"plate_size_mm": [round(v, 2) for v in self.plate_size_mm], **self.round.sidecar()}


def mesh_plate_frame(mesh: TriMesh) -> tuple[np.ndarray, float, float]:
    """4x4 transform mesh coordinates -> plate frame (origin the reference corner, x along edge
    0 -> 1, z up), and the plate's length and width (mm, edges 0 -> 1 and 0 -> 3). HeatError for a
    mesh without a four-cornered outline."""
    try:
        framed = frame_design_mesh(mesh)
        corners = design_corners_from_mesh(framed.mesh)
    except OutlineError as exc:
        raise HeatError(f"the mesh's plate outline: {exc}") from None
    T = plate_frame(corners) @ framed.T_design_file
    length = float(np.linalg.norm(corners[1, :2] - corners[0, :2]))
    width = float(np.linalg.norm(corners[3, :2] - corners[0, :2]))
    return T, length, width


def heat_mesh(
    plan: HeatingPlanFile,
    mesh: TriMesh,
    seed: int = 0,
    *,
    coefficient_spread: float = COEFFICIENT_SPREAD,
    position_spread_mm: float = POSITION_SPREAD_MM,
) -> HeatedPlate:
    """``mesh`` (a formed plate's top surface) after the plan's lines, by the mismatched model.

    HeatError when the plan has no lines, was made for another plate size, or the mesh has no
    four-cornered outline.
    """
    if plan.status == "plan" and plan.model is not None and plan.lines:
        T, length_mm, width_mm = mesh_plate_frame(mesh)
        v = mesh.vertices_mm @ T[:3, :3].T + T[:3, 3]
    else:  # heat_points says what is wrong with the plan
        v, length_mm, width_mm = np.zeros((0, 3)), 0.0, 0.0
        T = np.eye(4)
    sim = heat_points(
        plan, v, (length_mm, width_mm), seed,
        coefficient_spread=coefficient_spread, position_spread_mm=position_spread_mm,
    )  # fmt: skip
    Ti = np.linalg.inv(T)
    moved = v + sim.displacement_mm
    out = TriMesh(moved @ Ti[:3, :3].T + Ti[:3, 3], mesh.triangles)
    return HeatedPlate(out, (length_mm, width_mm), sim)
