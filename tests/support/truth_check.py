"""The simulated plate's known forming error, seen the way the analysis reports it.

``cellctl sim`` writes its ground truth to ``<data_dir>/sim-truth.json`` (cellctl/simcell/truth.py):
the true plate (design spec plus forming error) and its pose ``T_base_plate``. The analysis reports,
for the design registered onto the cloud (``registration.transform``, design frame -> base frame),
the deviation ``design height - measured height`` along its detection lines and over the plate.
:class:`TruthDeviation` computes the same quantity from the truth alone: the true top surface,
carried into the design frame by the reported registration, against the design surface. A test can
then compare the figures the cell measured with the ones the simulator put in.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from analysis.pipeline import design_corners_from_mesh, plate_frame
from analysis.plates import FormingError, PlateSpec, design_height_mm, formed_height_mm, load_design


class TruthDeviation:
    """``design height - true height`` in the design frame, for one job's registration."""

    def __init__(self, truth_json: Path, report: dict, design_path: Path) -> None:
        truth = json.loads(Path(truth_json).read_text())
        self.spec = PlateSpec(**truth["plate"])
        self.error = FormingError.from_dict(truth["forming_error"] or {})
        T_base_plate = np.asarray(truth["T_base_plate"], dtype=np.float64)
        T_base_design = np.asarray(report["registration"]["transform"], dtype=np.float64)
        # true plate frame -> registered design frame
        self.M = np.linalg.inv(T_base_design) @ T_base_plate
        self.T_plate_design = plate_frame(design_corners_from_mesh(load_design(design_path)))

    def true_height_mm(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        """Height of the true top surface over design-frame (x, y): the point of the formed surface
        whose image in the design frame lies at (x, y), found by fixed-point iteration (M is a
        small rigid motion)."""
        x, y = np.asarray(x_mm, dtype=np.float64), np.asarray(y_mm, dtype=np.float64)
        R, t = self.M[:3, :3], self.M[:3, 3]
        uv = np.linalg.solve(R[:2, :2], np.stack([x - t[0], y - t[1]]))  # first guess: flat plate
        for _ in range(8):
            p = np.stack([uv[0], uv[1], formed_height_mm(self.spec, self.error, uv[0], uv[1])])
            q = R @ p + t[:, None]
            uv = uv + np.linalg.solve(R[:2, :2], np.stack([x - q[0], y - q[1]]))
        p = np.stack([uv[0], uv[1], formed_height_mm(self.spec, self.error, uv[0], uv[1])])
        return (R @ p + t[:, None])[2]

    def deviation_mm(self, x_mm: np.ndarray, y_mm: np.ndarray) -> np.ndarray:
        """``design height - true height`` at design-frame (x, y), the analysis' sign."""
        return design_height_mm(self.spec, x_mm, y_mm) - self.true_height_mm(x_mm, y_mm)

    def line_deviation_mm(self, line: dict, s_mm: np.ndarray) -> np.ndarray:
        """The true deviation along a reported detection line at distances ``s_mm`` from its start."""
        a, b = (np.asarray(line[k], dtype=np.float64) for k in ("start_plate_mm", "end_plate_mm"))
        ab = (b - a) / np.linalg.norm(b - a)
        xy_plate = a[None, :] + np.asarray(s_mm, dtype=np.float64)[:, None] * ab[None, :]
        T_design_plate = np.linalg.inv(self.T_plate_design)
        xy = xy_plate @ T_design_plate[:2, :2].T + T_design_plate[:2, 3]
        return self.deviation_mm(xy[:, 0], xy[:, 1])
