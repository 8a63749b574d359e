"""Where a plate lies on the bed: the product's one placement type and its one transform.

A :class:`Placement` maps the design frame (the design mesh's own: x along the plate's length, y
along its width, z up) into the robot base frame (the bed's): ``pos_mm`` is where the design origin
lies, ``rpy_deg`` the rotation as roll, pitch, yaw about the fixed x, y, z axes (``R = Rz(yaw) @
Ry(pitch) @ Rx(roll)``, the convention of ``cell.toml`` poses). It is what an operator says in a
trigger, what the planner plans around, what the analysis uses to pick the reference corner of a
design that looks the same after a half turn, and what ``report.json`` records under ``inputs``.
:func:`placement_transform` is the one way to turn it into a matrix.

It is a pydantic model (unknown fields refused) because it crosses process boundaries inside the
cell's messages; the analysis package owns it so that the analysis, which never imports ``cellctl``,
speaks the same type as the daemon.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Annotated

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

__all__ = ["MAX_PLACEMENT_DEG", "MAX_PLACEMENT_MM", "Placement", "T_from_pos_rpy", "placement_transform"]

#: A placement beyond these is no plate on a bed but a typo or an attack: refused at the door.
MAX_PLACEMENT_MM = 100_000.0
MAX_PLACEMENT_DEG = 360.0
PosMm = Annotated[float, Field(ge=-MAX_PLACEMENT_MM, le=MAX_PLACEMENT_MM, allow_inf_nan=False)]
AngleDeg = Annotated[float, Field(ge=-MAX_PLACEMENT_DEG, le=MAX_PLACEMENT_DEG, allow_inf_nan=False)]


class Placement(BaseModel):
    """Nominal placement of the plate: design frame -> robot base frame (``T_base_design``).

    ``pos_mm`` (3,) within +-100 m, ``rpy_deg`` (3,) within +-360 deg.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    pos_mm: Annotated[list[PosMm], Field(min_length=3, max_length=3)]
    rpy_deg: Annotated[list[AngleDeg], Field(min_length=3, max_length=3)] = [0.0, 0.0, 0.0]

    @classmethod
    def on_bed(
        cls,
        x_mm: float,
        y_mm: float,
        yaw_deg: float,
        *,
        z_mm: float = 0.0,
        tilt_deg: float = 0.0,
        tilt_axis_deg: float = 0.0,
    ) -> Placement:
        """A plate laid at (x, y, z) mm, turned ``yaw_deg`` about z; optionally then tilted by
        ``tilt_deg`` about the horizontal axis at ``tilt_axis_deg`` from x (a plate not lying flat)."""
        rpy = [0.0, 0.0, float(yaw_deg)]
        if tilt_deg:
            ta = np.deg2rad(tilt_axis_deg)
            R = _rotation_about(np.array([np.cos(ta), np.sin(ta), 0.0]), tilt_deg) @ _rpy_rotation(rpy)
            rpy = _rpy_of(R)
        return cls(pos_mm=[float(x_mm), float(y_mm), float(z_mm)], rpy_deg=rpy)

    @property
    def x_mm(self) -> float:
        return self.pos_mm[0]

    @property
    def y_mm(self) -> float:
        return self.pos_mm[1]

    @property
    def z_mm(self) -> float:
        return self.pos_mm[2]

    @property
    def yaw_deg(self) -> float:
        """Rotation about the bed's z axis (the only one for a plate lying flat)."""
        return self.rpy_deg[2]

    @property
    def flat(self) -> bool:
        """Roll and pitch zero: the plate lies flat on the bed."""
        return all(abs(v) <= 1e-9 for v in self.rpy_deg[:2])


def T_from_pos_rpy(pos_mm: Sequence[float], rpy_deg: Sequence[float]) -> np.ndarray:
    """(4, 4) transform from a translation (3,) mm and roll-pitch-yaw (3,) deg about fixed x, y, z.

    The convention of ``cell.toml`` poses and of placements: ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)``.
    """
    T = np.eye(4)
    T[:3, :3] = _rpy_rotation(rpy_deg)
    T[:3, 3] = np.asarray(pos_mm, dtype=np.float64)
    return T


def placement_transform(placement: Placement) -> np.ndarray:
    """(4, 4) ``T_base_design`` of a placement: maps design-frame mm into base-frame mm."""
    return T_from_pos_rpy(placement.pos_mm, placement.rpy_deg)


def _rpy_rotation(rpy_deg: Sequence[float]) -> np.ndarray:
    r, p, y = np.deg2rad(np.asarray(rpy_deg, dtype=np.float64))
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    Ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    Rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    return Rz @ Ry @ Rx


def _rpy_of(R: np.ndarray) -> list[float]:
    """Roll, pitch, yaw (deg) of a rotation, the inverse of :func:`_rpy_rotation` (|pitch| < 90)."""
    pitch = -np.arcsin(np.clip(R[2, 0], -1.0, 1.0))
    roll = np.arctan2(R[2, 1], R[2, 2])
    yaw = np.arctan2(R[1, 0], R[0, 0])
    return [float(v) for v in np.rad2deg([roll, pitch, yaw])]


def _rotation_about(axis: np.ndarray, angle_deg: float) -> np.ndarray:
    """Rodrigues: rotation by ``angle_deg`` about the unit ``axis``."""
    axis = axis / np.linalg.norm(axis)
    K = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    a = np.deg2rad(angle_deg)
    return np.eye(3) + np.sin(a) * K + (1.0 - np.cos(a)) * (K @ K)
