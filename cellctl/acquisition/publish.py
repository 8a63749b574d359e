"""The cloud the cell publishes to the analysis: the live scan, thinned along the line, encoded once.

The HD8 delivers 500 points at 0.1 mm along its 50 mm line; the analysis averages the plate's
surface over cells of 1-3 mm (``analysis.pipeline.surface_cell_mm``), so it needs far fewer points
across the line than the sensor gives. Measured on the synthetic 1200 x 800 mm sail (1 mm profile
spacing): keeping every 5th point (0.5 mm) changes each line's Zmax by less than 0.05 mm and the
corners by less than 0.02 mm, and cuts the analysis from 17 s to 6 s (14.9 M -> 3.0 M points).
The raw files keep every point, so a re-analysis at full density stays possible.

Thinning keeps the scan grid: the kept columns of a profile are renumbered 0, 1, 2, ... so the
segmentation's scan-grid route sees a dense grid, as it would from a sensor with fewer points.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import structlog

from cellctl.acquisition.assembly import AssembledScan, AssemblyError
from cellctl.api.cloud_codec import FIELDS, Cloud, CloudFormatError, CloudMeta, allocate_cloud

if TYPE_CHECKING:
    from cellctl.config import CellConfig

__all__ = [
    "PublishSettings",
    "budget_steps",
    "column_steps",
    "encode_scan",
    "pass_end_cut",
    "publication_cloud",
]

log = structlog.get_logger(__name__)

_WIRE_DTYPES = {"pass_id": np.uint16, "profile_index": np.uint32, "point_index": np.uint16}
#: points per slice of the published arrays checked for finite values
_CHECK_ROWS = 1 << 22


@dataclass(frozen=True)
class PublishSettings:
    """How densely the scan is published.

    Attributes:
        native_pitch_mm: the sensor's point pitch along the line (line width / (points - 1)), mm.
        pitch_mm: published pitch on raster passes and transit, mm (0: every point).
        edge_pitch_mm: published pitch on edge passes, mm (0: every point).
    """

    native_pitch_mm: float = 50.0 / 499
    pitch_mm: float = 0.5
    edge_pitch_mm: float = 0.5

    def __post_init__(self) -> None:
        if not self.native_pitch_mm > 0:
            raise ValueError(f"native_pitch_mm: must be positive, got {self.native_pitch_mm!r}")
        for name in ("pitch_mm", "edge_pitch_mm"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"{name}: must be finite and >= 0, got {v!r}")

    @classmethod
    def from_config(cls, cfg: CellConfig) -> PublishSettings:
        """From a CellConfig: ``[laser] line_width_mm, points_per_profile`` and ``[scan]
        publish_pitch_mm, edge_publish_pitch_mm``."""
        return cls(
            native_pitch_mm=cfg.laser.line_width_mm / max(cfg.laser.points_per_profile - 1, 1),
            pitch_mm=cfg.scan.publish_pitch_mm,
            edge_pitch_mm=cfg.scan.edge_publish_pitch_mm,
        )

    def step(self, pitch_mm: float) -> int:
        """Columns per kept column for a wanted pitch (1: every point)."""
        return max(1, round(pitch_mm / self.native_pitch_mm))


def column_steps(pass_id: np.ndarray, first_edge_pass: int | None, settings: PublishSettings) -> np.ndarray:
    """(n,) int64 column step per profile: edge passes (``pass_id >= first_edge_pass``) at the edge
    pitch, raster passes and transit (-1) at the raster pitch. ``first_edge_pass`` None: no edge passes."""
    pid = np.asarray(pass_id)
    raster, edge = settings.step(settings.pitch_mm), settings.step(settings.edge_pitch_mm)
    if first_edge_pass is None or raster == edge:
        return np.full(pid.shape, raster, dtype=np.int64)
    return np.where(pid >= first_edge_pass, edge, raster).astype(np.int64)


def budget_steps(steps: np.ndarray, valid_per_profile: np.ndarray, max_points: int) -> np.ndarray:
    """``steps`` (per profile) raised by one whole factor when the points they keep would exceed
    ``max_points`` (``[scan] publish_max_points``; 0: no budget), so the analysis of any plate stays
    within the memory and time measured for that many points (docs/operations.md, a 6 m plate). The
    ratio of the edge to the raster pitch is kept; the raw files keep every point whatever this says.

    valid_per_profile: (n,) valid points of each profile at full density."""
    steps = np.asarray(steps, dtype=np.int64)
    if max_points <= 0 or not steps.size:
        return steps
    kept = float(np.sum(np.asarray(valid_per_profile, dtype=np.float64) / steps))
    # the sum of n fractions carries rounding (10 profiles of 13 points at step 10: 13.000000000000002
    # for 13), which must not thin a publication that fits exactly
    slack = 1.0 + 1e-9
    if kept <= max_points * slack:
        return steps
    factor = int(np.ceil(kept / (max_points * slack)))
    log.info("publication_thinned_to_budget", points=round(kept), max_points=max_points, factor=factor)
    return steps * factor


def publication_cloud(
    scan: AssembledScan,
    *,
    job_id: str,
    plate_id: str,
    column_step: int | np.ndarray = 1,
    meta: CloudMeta | None = None,
    t0_ns: int | None = None,
) -> Cloud:
    """The valid points of ``scan`` as a :class:`~cellctl.api.cloud_codec.Cloud`, thinned by ``column_step``
    (see :meth:`AssembledScan.points`), in the cloud vocabulary (:meth:`AssembledScan.cloud_arrays`:
    transit under pass 0, exposure times in s from the first profile, or from ``t0_ns`` for a part
    of a scan) at the codec's dtypes."""
    # filled at the wire's dtypes block by block: no whole-scan int64 temporaries (a 6 m plate's 33 M points)
    pts = scan.cloud_arrays(column_step, t0_ns, dtypes=_WIRE_DTYPES)
    for name in ("pass_id", "point_index"):
        if pts[name].size and int(pts[name].max()) > 65535:
            raise AssemblyError(f"{name} {int(pts[name].max())} does not fit the cloud's u16")
    return Cloud(
        xyz_mm=pts["xyz_mm"],
        job_id=job_id,
        plate_id=plate_id,
        pass_id=pts["pass_id"].astype(np.uint16, copy=False),
        profile_index=pts["profile_index"].astype(np.uint32, copy=False),
        point_index=pts["point_index"].astype(np.uint16, copy=False),
        t_s=pts["t_s"],
        meta=meta or CloudMeta(),
    )


def encode_scan(
    scan: AssembledScan,
    *,
    job_id: str,
    plate_id: str,
    column_step: int | np.ndarray = 1,
    meta: CloudMeta | None = None,
    t0_ns: int | None = None,
) -> tuple[bytearray, int]:
    """:func:`publication_cloud` encoded as :func:`~cellctl.api.cloud_codec.encode_cloud` encodes it,
    the same bytes: ``(payload, n_points)``. The points are written block of rows by block of rows
    straight into the message (:func:`~cellctl.api.cloud_codec.allocate_cloud`): the payload is the
    only copy of the published points (a 6 m plate: 28 bytes for each of 33 M points, 0.93 GB; the
    cloud and then its encoded copy were twice that). Run it off the event loop."""
    fields = {name: dtype for name, (dtype, _) in FIELDS.items()}
    held: list[bytearray] = []

    def into_message(n: int) -> dict[str, np.ndarray]:
        payload, views = allocate_cloud(job_id, plate_id, meta or CloudMeta(), n, fields)
        held.append(payload)
        return views

    views = scan.cloud_arrays(column_step, t0_ns, dtypes=_WIRE_DTYPES, out=into_message)
    for name in ("xyz_mm", "t_s"):  # as encode_cloud refuses them; a slice at a time (no whole-cloud mask)
        a = views[name]
        for lo in range(0, len(a), _CHECK_ROWS):
            if not np.isfinite(a[lo : lo + _CHECK_ROWS]).all():
                what = "coordinates" if name == "xyz_mm" else "times"
                raise CloudFormatError(f"non-finite {what}", field=name)
    return held[0], len(views["xyz_mm"])


def pass_end_cut(pass_id: np.ndarray) -> tuple[int, int] | None:
    """Where a run of rows (time order, ``pass_id`` -1 for transit) can be cut after a finished pass:
    ``(rows, pass)`` for the last row of pass ``pass >= 0`` followed by a row of another pass or of
    transit (the pass is complete up to there), or None when no pass has ended in these rows."""
    pid = np.asarray(pass_id)
    if pid.size < 2:
        return None
    ends = np.nonzero((pid[:-1] >= 0) & (pid[1:] != pid[:-1]))[0]
    if not ends.size:
        return None
    i = int(ends[-1])
    return i + 1, int(pid[i])
