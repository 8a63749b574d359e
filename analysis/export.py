"""A results directory's cloud and lines for the metrology tools and the yard's CAD: LAS, E57 and PLY
in the design frame and in the design file's own frame (the ship's coordinates).

The design frame is the analysis' own: the design as loaded and laid (:mod:`analysis.design.outline`,
:mod:`analysis.design.moulded`). ``report.json``'s ``design.T_design_file`` maps the design file's
coordinates (mm) into it, so its inverse takes a result back to the file's frame, the hull's
coordinates in a yard's CAD (``null``: a mesh given in its own frame, the two frames one).

Written by the worker into every results directory: ``cloud.ply`` (design frame, the deviation as
``scalar_deviation``) and ``lines-ship.csv`` (every judged line's ends in the file's frame). Written
on demand by :func:`export_results` (``cellctl export``), since each is as large as cloud.ply again and
the results bundle is bounded: ``cloud.las``, ``cloud.e57`` (design frame) and ``cloud-ship.ply``,
``cloud-ship.las``, ``cloud-ship.e57`` (the file's frame). docs/operations.md, "Cloud files for
metrology tools", lists them.
"""

from __future__ import annotations

import csv
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from analysis import cloud_export
from analysis.cloud_export import CloudFrame, apply_rigid_blocks, write_e57, write_las, write_ply_blocks
from analysis.cloud_io import CloudError
from analysis.contracts.job import Report

__all__ = [
    "DESIGN_FRAME",
    "EXPORT_FORMATS",
    "EXPORT_FRAMES",
    "T_file_design",
    "export_results",
    "read_results_cloud",
    "ship_frame",
    "write_lines_ship",
]

DESIGN_FRAME = CloudFrame(
    "cellctl design frame",
    "the design as the analysis laid it; report.json design.T_design_file maps the file into it",
)
EXPORT_FORMATS = ("ply", "las", "e57")
EXPORT_FRAMES = ("design", "ship")
#: the deviation's name in cloud.ply (``deviation`` in results written before CloudCompare's name)
DEVIATION_NAMES = ("scalar_deviation", "deviation")


def _rigid(T: np.ndarray) -> bool:
    R = T[:3, :3]
    return bool(np.allclose(R @ R.T, np.eye(3), atol=1e-9) and np.linalg.det(R) > 0)


def T_file_design(report: Report) -> np.ndarray:
    """4x4: design frame -> the design file's frame (mm), the inverse of ``T_design_file`` (the
    identity when the report has none: a mesh given in its own frame)."""
    T = report.design.T_design_file
    return np.eye(4) if T is None else np.linalg.inv(np.asarray(T, dtype=np.float64))


def ship_frame(report: Report) -> CloudFrame:
    """The design file's frame, named with the file (and its units) as the report records them."""
    design = Path(report.inputs.design).name if report.inputs.design else "the design file"
    how = (
        "the design was given in its own frame (design frame = file frame)"
        if report.design.T_design_file is None
        else "inverse of report.json design.T_design_file applied to the design frame"
    )
    units = f" (file units {report.design.file_units})" if report.design.kind == "cad" else ""
    return CloudFrame("design file frame (ship)", f"coordinates of {design}{units}, in mm; {how}")


def write_lines_ship(path: str | Path, report: Report, ends_design_mm: np.ndarray) -> Path:
    """``lines-ship.csv``: one row per line of ``report`` (report order), its start and end (mm) in the
    design file's frame, from ``ends_design_mm`` (k, 2, 3) in the design frame; a first ``#`` line
    names the frame."""
    path = Path(path)
    ends = np.asarray(ends_design_mm, dtype=np.float64).reshape(-1, 3)
    if len(ends) != 2 * len(report.lines):
        raise ValueError(f"{len(report.lines)} lines, {len(ends)} ends")
    T = T_file_design(report)
    ends = (ends @ T[:3, :3].T + T[:3, 3]).reshape(-1, 2, 3)
    with path.open("w", newline="", encoding="utf-8") as f:
        f.write(f"# frame: {ship_frame(report).text()}\n")
        w = csv.writer(f)
        w.writerow(["line", "start_x_mm", "start_y_mm", "start_z_mm", "end_x_mm", "end_y_mm", "end_z_mm"])
        for line, (a, b) in zip(report.lines, ends, strict=True):
            w.writerow([line.name, *(f"{v:.3f}" for v in (*a, *b))])
    return path


def read_results_cloud(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """cloud.ply of a results directory, memory-mapped: (n, 3) float32 points (a view of the file's
    records) and (n,) float32 deviation; :class:`CloudError` for a file without them."""
    import plyfile

    path = Path(path)
    try:
        ply = plyfile.PlyData.read(str(path), mmap="r")
        v = ply["vertex"].data
    except FileNotFoundError:
        raise CloudError(f"{path}: no such file") from None
    except (plyfile.PlyParseError, KeyError, ValueError, OSError) as exc:
        raise CloudError(f"{path}: not a readable PLY cloud ({exc})") from None
    names = v.dtype.names or ()
    dev = next((n for n in DEVIATION_NAMES if n in names), None)
    if dev is None or not {"x", "y", "z"} <= set(names):
        raise CloudError(f"{path}: not a results cloud: needs x, y, z and {DEVIATION_NAMES[0]}, has {names}")
    if v.dtype["x"] != np.float32:
        raise CloudError(f"{path}: x, y, z are {v.dtype['x']}, a results cloud's are float32")
    xyz = np.ndarray(
        (len(v), 3), np.float32, buffer=v, offset=v.dtype.fields["x"][1], strides=(v.strides[0], 4)
    )
    return xyz, v[dev]


def export_results(
    results_dir: str | Path,
    out_dir: str | Path | None = None,
    *,
    formats: tuple[str, ...] = EXPORT_FORMATS,
    frames: tuple[str, ...] = EXPORT_FRAMES,
) -> dict[str, Path]:
    """Write the results' cloud (``results_dir``/cloud.ply and report.json) in ``formats`` and
    ``frames`` into ``out_dir`` (default ``results_dir``); returns the written files by name.

    ``cloud.<fmt>`` in the design frame (cloud.ply is the worker's own and not written again),
    ``cloud-ship.<fmt>`` in the file's frame; the E57 file in the file's frame holds the design-frame
    points with the scan's pose to the file's frame (single-precision coordinates stay small; every
    E57 reader applies the pose). The cloud is read through a memory map and written a block at a
    time: nothing the size of the cloud is held."""
    from analysis.contracts.results import read_report

    results = Path(results_dir)
    out = Path(out_dir) if out_dir is not None else results
    bad = [f for f in formats if f not in EXPORT_FORMATS] + [f for f in frames if f not in EXPORT_FRAMES]
    if bad:
        raise CloudError(
            f"unknown export format or frame {bad}: formats {EXPORT_FORMATS}, frames {EXPORT_FRAMES}"
        )
    report = read_report(results / "report.json")
    xyz, dev = read_results_cloud(results / "cloud.ply")
    out.mkdir(parents=True, exist_ok=True)

    def design_blocks() -> Iterator[dict[str, np.ndarray]]:
        step = cloud_export.BLOCK_POINTS
        for lo in range(0, max(len(xyz), 1), step):
            yield {"xyz_mm": xyz[lo : lo + step], "deviation_mm": dev[lo : lo + step]}

    T = T_file_design(report)
    ship = ship_frame(report)
    ship_blocks = apply_rigid_blocks(design_blocks, T)
    written: dict[str, Path] = {}
    for frame_name in frames:
        stem, frame = ("cloud", DESIGN_FRAME) if frame_name == "design" else ("cloud-ship", ship)
        for fmt in formats:
            path = out / f"{stem}.{fmt}"
            if frame_name == "design" and fmt == "ply":
                if out.resolve() == results.resolve():
                    continue  # the worker's own cloud.ply
                written[path.name] = write_ply_blocks(path, design_blocks, frame)
            elif fmt == "ply":  # ship coordinates reach hundreds of metres: float32 would round to 0.03 mm
                written[path.name] = write_ply_blocks(path, ship_blocks, frame, double=True)
            elif fmt == "las":
                written[path.name] = write_las(
                    path, design_blocks if frame_name == "design" else ship_blocks, frame
                )
            elif frame_name == "design":
                written[path.name] = write_e57(path, design_blocks, frame, name=report.plate_id)
            elif _rigid(T):  # the design-frame points and their pose to the file's frame
                written[path.name] = write_e57(path, design_blocks, frame, pose=T, name=report.plate_id)
            else:  # a pose is a rotation and a translation: otherwise the points moved, pose the identity
                written[path.name] = write_e57(path, ship_blocks, frame, name=report.plate_id)
    return written
