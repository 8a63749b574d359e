"""The simulated cell's ground truth: a formed plate laid on the bed with a known pose.

The plate is a design surface plus a known forming error (:mod:`analysis.design.plates`), placed by
``T_base_plate`` (:class:`PlateTruth`), or a formed top surface read from a mesh file
(:class:`MeshPlateTruth`, ``[sim.plate] kind = "mesh"``: the truth is that mesh itself); its scene (plate solid, bed, supports) is what the HD8 simulator ray-casts, and its
surface is what the acquired cloud is judged against (``cellctl sim`` writes it to
``sim-truth.json``; the acquisition tests and benchmarks measure accuracy with it).
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from analysis.contracts.placement import Placement, placement_transform
from analysis.design.cad import CAD_SUFFIXES, read_cad
from analysis.design.mesh import MeshError, TriMesh, load_mesh, surface_mismatch
from analysis.design.outline import frame_design_mesh
from analysis.design.plates import (
    FormingError,
    PlateSpec,
    default_forming_error,
    design_mesh,
    plate_spec,
    surface_gradient,
)
from drivers.laser.sim.scene import Scene, SceneRaycaster, cell_scene

__all__ = ["MeshPlateTruth", "PlateTruth", "mesh_plate_truth", "plate_truth"]


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


@dataclass(frozen=True)
class MeshPlateTruth:
    """A formed plate given by its top surface's mesh (``[sim.plate] kind = "mesh"``), laid on the bed.

    ``surface``: the formed top surface in the design frame (the frame the product puts the design
    file in: :attr:`analysis.design.cad_surface.CadDesign.T_design_file`, the identity for a design
    already in its own frame), mm; ``T_base_plate``: that frame -> base, as for :class:`PlateTruth`;
    ``T_design_file``: the design file's (and the mesh file's) coordinates -> the design frame.
    Every figure here (the scene, heights, distances) comes from the mesh alone.
    """

    surface: TriMesh
    thickness_mm: float
    T_base_plate: np.ndarray
    T_design_file: np.ndarray
    mesh_file: Path | None = None
    design_file: Path | None = None
    spec: None = None  # no analytic design: the surface is the truth
    error: None = None

    def scene(self, pitch_mm: float = 4.0) -> Scene:
        """The sensor's scene from the mesh as it is (``pitch_mm``, the analytic plates' tessellation,
        does not apply): plate solid, supports, bed; base frame."""
        mesh = self.surface.transformed(self.T_base_plate)
        return cell_scene(mesh.vertices_mm, mesh.triangles, thickness_mm=self.thickness_mm)

    def height_mm(self, x_mm: np.ndarray, y_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Top-surface height and gradient at design-frame (x, y): the first hit of a ray cast down
        onto the mesh, the gradient of the triangle hit; NaN off the plate."""
        x, y = np.broadcast_arrays(np.asarray(x_mm, dtype=np.float64), np.asarray(y_mm, dtype=np.float64))
        top = float(self.surface.vertices_mm[:, 2].max()) + 10.0
        k = x.size
        hits = self._raycaster().cast(
            np.column_stack([x.ravel(), y.ravel(), np.full(k, top)]), np.tile([0.0, 0.0, -1.0], (k, 1))
        )
        t = np.asarray(hits.t_mm, dtype=np.float64)
        n = np.asarray(hits.normal, dtype=np.float64)
        ok = np.isfinite(t) & (np.abs(n[:, 2]) > 1e-9)
        nz = np.where(ok, n[:, 2], 1.0)
        h = np.where(ok, top - t, np.nan)
        gx, gy = np.where(ok, -n[:, 0] / nz, np.nan), np.where(ok, -n[:, 1] / nz, np.nan)
        return h.reshape(x.shape), gx.reshape(x.shape), gy.reshape(x.shape)

    def _raycaster(self) -> SceneRaycaster:
        rc = self.__dict__.get("_rc")
        if rc is None:
            rc = SceneRaycaster(Scene(self.surface.vertices_mm, self.surface.triangles))
            object.__setattr__(self, "_rc", rc)
        return rc

    def distance_mm(
        self, xyz_base_mm: np.ndarray, edge_margin_mm: float = 10.0
    ) -> tuple[np.ndarray, np.ndarray]:
        """Signed distance of base-frame points to the mesh's top surface along its normal, and
        ``inside``: over the plate at least ``edge_margin_mm`` (in x and y) from its edges
        (as :meth:`PlateTruth.distance_mm`)."""
        T_inv = np.linalg.inv(self.T_base_plate)
        p = np.asarray(xyz_base_mm, dtype=np.float64) @ T_inv[:3, :3].T + T_inv[:3, 3]
        h, gx, gy = self.height_mm(p[:, 0], p[:, 1])
        d = (p[:, 2] - h) / np.sqrt(1.0 + gx**2 + gy**2)
        inside = np.isfinite(h)
        m = edge_margin_mm
        for dx, dy in ((m, 0.0), (-m, 0.0), (0.0, m), (0.0, -m)):
            inside &= np.isfinite(self.height_mm(p[:, 0] + dx, p[:, 1] + dy)[0])
        return d, inside

    def to_base(self, xyz_plate_mm: np.ndarray) -> np.ndarray:
        """Design-frame points (k, 3) into the base frame."""
        return np.asarray(xyz_plate_mm) @ self.T_base_plate[:3, :3].T + self.T_base_plate[:3, 3]

    def record(self) -> dict:
        """What ``sim-truth.json`` holds of the plate: the files (and the mesh's SHA-256, so that a
        reader knows it reads the surface the simulator scanned), the thickness, ``T_design_file``."""
        return {
            "kind": "mesh",
            "mesh_file": None if self.mesh_file is None else str(self.mesh_file),
            "mesh_sha256": None if self.mesh_file is None else file_sha256(self.mesh_file),
            "design_file": None if self.design_file is None else str(self.design_file),
            "thickness_mm": self.thickness_mm,
            "T_design_file": self.T_design_file.tolist(),
            "triangles": len(self.surface.triangles),
        }


def file_sha256(path: str | Path) -> str:
    """The SHA-256 of a file's bytes (hex)."""
    h = hashlib.sha256()
    with Path(path).open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def mesh_plate_truth(
    mesh_file: str | Path,
    design_file: str | Path,
    *,
    thickness_mm: float,
    pos_mm: Sequence[float] = (1500.0, 0.0, 300.0),
    angle_deg: float = 3.0,
) -> MeshPlateTruth:
    """The formed plate of ``mesh_file`` (its top surface, mm, in ``design_file``'s coordinates) with
    the design frame the product finds for ``design_file`` laid at the placement, as
    :func:`plate_truth` lays the analytic plates. Raises :class:`~analysis.design.mesh.MeshError`
    (:class:`~analysis.design.cad_facts.DesignError` is one) naming the file: unreadable, empty, or
    not the design's plate (:func:`~analysis.design.mesh.surface_mismatch`)."""
    surface_file = load_mesh(mesh_file)
    if Path(design_file).suffix.lower() in CAD_SUFFIXES:
        cad = read_cad(design_file)
        design, T_design_file = cad.mesh, cad.T_design_file
    else:
        framed = frame_design_mesh(load_mesh(design_file))
        design, T_design_file = framed.mesh, framed.T_design_file
    surface = surface_file.transformed(T_design_file)
    why = surface_mismatch(surface, design)
    if why:
        raise MeshError(f"{mesh_file} does not match the design {design_file}: {why}")
    return MeshPlateTruth(
        surface=surface,
        thickness_mm=float(thickness_mm),
        T_base_plate=placement_transform(Placement.on_bed(pos_mm[0], pos_mm[1], angle_deg, z_mm=pos_mm[2])),
        T_design_file=np.asarray(T_design_file, dtype=np.float64),
        mesh_file=Path(mesh_file),
        design_file=Path(design_file),
    )
