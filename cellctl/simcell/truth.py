"""The simulated cell's ground truth: a formed plate laid on the bed with a known pose.

The plate is a design surface plus a known forming error (:mod:`analysis.design.plates`), placed by
``T_base_plate``; its scene (plate solid, bed, supports) is what the HD8 simulator ray-casts, and its
surface is what the acquired cloud is judged against (``cellctl sim`` writes it to
``sim-truth.json``; the acquisition tests and benchmarks measure accuracy with it).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from analysis.contracts.placement import Placement, placement_transform
from analysis.design.plates import (
    FormingError,
    PlateSpec,
    default_forming_error,
    design_mesh,
    plate_spec,
    surface_gradient,
)
from drivers.laser.sim.scene import Scene, cell_scene

__all__ = ["PlateTruth", "plate_truth"]


@dataclass(frozen=True)
class PlateTruth:
    """A formed plate laid on the bed: its spec, forming error and pose ``T_base_plate`` (mm)."""

    spec: PlateSpec
    error: FormingError | None
    T_base_plate: np.ndarray

    def scene(self, pitch_mm: float = 4.0) -> Scene:
        """The sensor's scene: plate solid (formed top surface), supports, bed; base frame."""
        mesh = design_mesh(self.spec, pitch_mm=pitch_mm, error=self.error).transformed(self.T_base_plate)
        return cell_scene(mesh.vertices_mm, mesh.triangles, thickness_mm=self.spec.thickness_mm)

    def height_mm(self, x_mm: np.ndarray, y_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Top-surface height and gradient at plate-frame (x, y)."""
        if self.error is None:
            err = FormingError()
        else:
            err = self.error
        return surface_gradient(self.spec, err, x_mm, y_mm)

    def distance_mm(
        self, xyz_base_mm: np.ndarray, edge_margin_mm: float = 10.0
    ) -> tuple[np.ndarray, np.ndarray]:
        """Signed distance of base-frame points to the true top surface, along its normal.

        Returns ``(d_mm (k,), inside (k,) bool)``: ``inside`` marks points over the plate at least
        ``edge_margin_mm`` from its edges (the accuracy target is stated away from edges).
        """
        T_inv = np.linalg.inv(self.T_base_plate)
        p = np.asarray(xyz_base_mm, dtype=np.float64) @ T_inv[:3, :3].T + T_inv[:3, 3]
        h, gx, gy = self.height_mm(p[:, 0], p[:, 1])
        d = (p[:, 2] - h) / np.sqrt(1.0 + gx**2 + gy**2)
        inside = (np.abs(p[:, 0]) <= self.spec.length_mm / 2 - edge_margin_mm) & (
            np.abs(p[:, 1]) <= self.spec.width_mm / 2 - edge_margin_mm
        )
        return d, inside

    def to_base(self, xyz_plate_mm: np.ndarray) -> np.ndarray:
        """Plate-frame points (k, 3) into the base frame."""
        return np.asarray(xyz_plate_mm) @ self.T_base_plate[:3, :3].T + self.T_base_plate[:3, 3]


def plate_truth(
    kind: str = "sail",
    *,
    pos_mm: Sequence[float] = (1500.0, 0.0, 300.0),
    angle_deg: float = 3.0,
    forming_error: bool = True,
    **spec_overrides: float,
) -> PlateTruth:
    """The cell.toml ``[sim.plate]`` / ``[sim.placement]`` plate (defaults: the 1200 x 800 sail)."""
    spec = plate_spec(kind, **spec_overrides)
    return PlateTruth(
        spec=spec,
        error=default_forming_error(spec) if forming_error else None,
        T_base_plate=placement_transform(Placement.on_bed(pos_mm[0], pos_mm[1], angle_deg, z_mm=pos_mm[2])),
    )
