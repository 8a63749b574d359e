"""Where to rework: connected regions of the plate whose deviation lies beyond the standard range.

The deviation field of a results directory is a scattered set of plate-frame positions (mm from the
reference corner, x along the length, y along the width) with the signed deviation
``d = z_design - z_measured`` (mm) at each. A line-heating worker needs areas, not points: the field
is averaged on a square grid of ``cell_mm`` cells (averaging also takes the sensor noise out of the
threshold test), cells beyond the threshold are grouped into 8-connected regions per sign, and each
region is described by where it lies, how large it is and how far out it goes.

Sign: ``d > 0`` means the plate lies below the template (a gap under the template); ``d < 0`` means
the plate stands above it (after the non-penetrating fit this only happens within the noise, but
a plate judged against a best fit, or a bad fit, shows it).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy import ndimage

__all__ = [
    "GriddedField",
    "ReworkError",
    "ReworkRegion",
    "bounded_cell_mm",
    "find_rework_regions",
    "grid_deviation",
]

BELOW = "below"  # plate below the template: d > 0
ABOVE = "above"  # plate above the template: d < 0


class ReworkError(ValueError):
    """Deviation data that cannot be gridded: wrong shapes, non-finite sizes, bad cell size."""


@dataclass(frozen=True)
class GriddedField:
    """A deviation field averaged on a regular grid in the plate frame.

    mean_mm: (nx, ny) float64 mean deviation per cell, NaN where no point fell.
    count: (nx, ny) int64 points per cell.
    cell_mm: cell edge length (mm); cell (i, j) covers x in [i, i+1) * cell_mm, y likewise.
    size_mm: (length, width) of the plate (mm); the last row and column of cells may be partial.
    """

    mean_mm: np.ndarray
    count: np.ndarray
    cell_mm: float
    size_mm: tuple[float, float]

    @property
    def seen(self) -> np.ndarray:
        """(nx, ny) bool: cells holding at least one point."""
        return self.count > 0


@dataclass(frozen=True)
class ReworkRegion:
    """One connected region beyond the threshold.

    sign: "below" (plate below the template, d > 0) or "above" (plate above it, d < 0).
    peak_mm: the signed cell-mean deviation of largest magnitude in the region (mm).
    peak_xy_mm: (x, y) of that cell's centre, mm from the reference corner.
    centre_xy_mm: (x, y) deviation-weighted centroid of the region, mm from the reference corner.
    bbox_mm: (x_min, y_min, x_max, y_max) of the region's cells, mm from the reference corner.
    area_mm2: area of the region's cells (mm^2). mean_mm: mean signed deviation over the region.
    beyond_limit: True when the peak also exceeds the allowable limit.
    """

    label: str
    sign: str
    peak_mm: float
    peak_xy_mm: tuple[float, float]
    centre_xy_mm: tuple[float, float]
    bbox_mm: tuple[float, float, float, float]
    area_mm2: float
    mean_mm: float
    beyond_limit: bool

    def as_dict(self) -> dict:
        """Plain JSON-ready dict."""
        d = asdict(self)
        for key in ("peak_xy_mm", "centre_xy_mm", "bbox_mm"):
            d[key] = list(d[key])
        return d


def bounded_cell_mm(plate_size_mm: np.ndarray | tuple[float, float], max_cells: int, cell_mm: float) -> float:
    """``cell_mm``, or the smallest larger cell whose grid over the plate has at most ``max_cells``
    cells: a view of the field (the report's top view, the HMI's map) stays within its budget
    whatever the plate's size. plate_size_mm: (length, width), mm."""
    L, W = (float(v) for v in np.asarray(plate_size_mm, dtype=np.float64).reshape(-1))
    if max_cells < 1:
        raise ReworkError(f"max_cells must be at least 1, got {max_cells}")
    c = max(float(cell_mm), float(np.sqrt(L * W / max_cells)))
    while np.ceil(L / c) * np.ceil(W / c) > max_cells:  # the partial last row and column
        c *= 1.01
    return c


def grid_deviation(
    plate_xy_mm: np.ndarray, deviation_mm: np.ndarray, plate_size_mm: np.ndarray, cell_mm: float = 5.0
) -> GriddedField:
    """Average a scattered deviation field on a ``cell_mm`` grid covering the plate.

    plate_xy_mm: (n, 2) positions, mm from the reference corner; deviation_mm: (n,) signed, mm;
    plate_size_mm: (2,) length and width, mm. Points outside the plate (edge noise) are dropped;
    non-finite deviations are ignored. One pass of ``np.bincount``, no loop over points.
    """
    xy = np.asarray(plate_xy_mm, dtype=np.float64)
    d = np.asarray(deviation_mm, dtype=np.float64)
    size = np.asarray(plate_size_mm, dtype=np.float64).reshape(-1)
    if xy.ndim != 2 or xy.shape[1] != 2:
        raise ReworkError(f"plate_xy_mm must be (n, 2), got {xy.shape}")
    if d.shape != (xy.shape[0],):
        raise ReworkError(f"deviation_mm must be ({xy.shape[0]},) like plate_xy_mm, got {d.shape}")
    if size.shape != (2,) or not np.all(np.isfinite(size)) or np.any(size <= 0):
        raise ReworkError(f"plate_size_mm must be two positive finite numbers, got {size.tolist()}")
    if not (np.isfinite(cell_mm) and cell_mm > 0):
        raise ReworkError(f"cell_mm must be positive, got {cell_mm!r}")
    nx, ny = (int(v) for v in np.maximum(np.ceil(size / cell_mm), 1))
    ok = np.isfinite(d) & np.all(np.isfinite(xy), axis=1)
    ok &= (xy[:, 0] >= 0) & (xy[:, 0] <= size[0]) & (xy[:, 1] >= 0) & (xy[:, 1] <= size[1])
    ij = np.minimum((xy[ok] / cell_mm).astype(np.int64), [nx - 1, ny - 1])
    flat = ij[:, 0] * ny + ij[:, 1]
    count = np.bincount(flat, minlength=nx * ny)
    total = np.bincount(flat, weights=d[ok], minlength=nx * ny)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    return GriddedField(
        mean.reshape(nx, ny), count.reshape(nx, ny), float(cell_mm), (float(size[0]), float(size[1]))
    )


def find_rework_regions(
    field: GriddedField,
    standard_mm: float,
    limit_mm: float | None = None,
    *,
    min_area_mm2: float = 50.0,
) -> list[ReworkRegion]:
    """Connected regions where the cell-mean deviation lies beyond ``standard_mm`` in magnitude.

    Regions of each sign are found separately (8-connectivity on the grid) and those smaller than
    ``min_area_mm2`` are dropped (a single noisy cell is not a place to heat). ``limit_mm`` (the
    allowable limit) only sets ``beyond_limit``. Returned worst first (by |peak|), labelled R1, R2...
    """
    if not (np.isfinite(standard_mm) and standard_mm > 0):
        raise ReworkError(f"standard_mm must be positive, got {standard_mm!r}")
    mean = field.mean_mm
    c = field.cell_mm
    regions: list[ReworkRegion] = []
    finite = np.where(np.isfinite(mean), mean, 0.0)
    for sign, mask in ((BELOW, finite > standard_mm), (ABOVE, finite < -standard_mm)):
        labels, n = ndimage.label(mask, structure=np.ones((3, 3), dtype=bool))
        if n == 0:
            continue
        idx = np.arange(1, n + 1)
        cells = ndimage.sum_labels(mask, labels, idx)
        mag = np.abs(finite)
        peak_pos = ndimage.maximum_position(mag, labels, idx)
        means = ndimage.mean(finite, labels, idx)
        # weights |d| so the centre leans towards the deepest part, where heating starts
        cx = ndimage.sum_labels(mag * (np.arange(mean.shape[0])[:, None] + 0.5), labels, idx)
        cy = ndimage.sum_labels(mag * (np.arange(mean.shape[1])[None, :] + 0.5), labels, idx)
        wsum = ndimage.sum_labels(mag, labels, idx)
        slices = ndimage.find_objects(labels)
        for k in range(n):
            area = float(cells[k]) * c * c
            if area < min_area_mm2:
                continue
            pi, pj = peak_pos[k]
            peak = float(finite[pi, pj])
            sx, sy = slices[k]
            regions.append(
                ReworkRegion(
                    label="",
                    sign=sign,
                    peak_mm=peak,
                    peak_xy_mm=(float((pi + 0.5) * c), float((pj + 0.5) * c)),
                    centre_xy_mm=(float(cx[k] / wsum[k] * c), float(cy[k] / wsum[k] * c)),
                    bbox_mm=(
                        float(sx.start * c),
                        float(sy.start * c),
                        min(sx.stop * c, field.size_mm[0]),
                        min(sy.stop * c, field.size_mm[1]),
                    ),
                    area_mm2=area,
                    mean_mm=float(means[k]),
                    beyond_limit=limit_mm is not None and abs(peak) > limit_mm,
                )
            )
    regions.sort(key=lambda r: -abs(r.peak_mm))
    return [ReworkRegion(**{**r.__dict__, "label": f"R{i + 1}"}) for i, r in enumerate(regions)]
