"""Cloud files of an assembled scan: PLY for internal work, LAS 1.4 and E57 for metrology tools.

* **PLY**: the product's one organised-PLY layout (:func:`analysis.cloud_io.write_cloud_ply`, read
  back by ``cellctl inspect``): ``float x, y, z`` (robot base frame, mm), ``int pass`` (transit
  filed under pass 0), ``int profile`` (running profile index), ``int point`` (column in the
  profile) and ``double t_s`` (exposure time from the first profile). Float32 coordinates, as
  CloudCompare, PCL and Open3D's tensor reader expect (line-laser-and-sync.md section 6). Written
  here block of rows by block of rows.
* **LAS 1.4** through laspy and **E57** through pye57: :mod:`analysis.cloud_export` (the layouts,
  the reader of each), fed the scan block of rows by block of rows.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from analysis import cloud_export
from analysis.cloud_io import CloudError
from cellctl.acquisition.assembly import AssembledScan

__all__ = ["ROBOT_BASE", "CloudFileError", "write_e57", "write_las", "write_ply"]

#: the frame of an assembled scan's points, as the files' headers name it
ROBOT_BASE = cloud_export.CloudFrame("cellctl robot base frame", "the scan as acquired, before registration")


class CloudFileError(CloudError):
    """A cloud file cannot be written or read (names the file and the field)."""


#: the organised-PLY vertex of :func:`analysis.cloud_io.write_cloud_ply`, as :func:`write_ply` streams it
_PLY_VERTEX = np.dtype(
    [
        ("x", "<f4"),
        ("y", "<f4"),
        ("z", "<f4"),
        ("pass", "<i4"),
        ("profile", "<i4"),
        ("point", "<i4"),
        ("t_s", "<f8"),
    ]
)
_PLY_COMMENT = "cellctl scan cloud: robot base frame, mm"


def write_ply(scan: AssembledScan, path: str | Path) -> Path:
    """Write the valid points of ``scan`` as binary PLY (the layout of
    :func:`analysis.cloud_io.write_cloud_ply`, byte for byte); returns the path.

    Written block of rows by block of rows (:meth:`AssembledScan.cloud_blocks`): a 6 m plate's
    170 M points need a block's records in memory, not 7 GB of float64 copies."""
    path = Path(path)
    if len(scan) and int(scan.profile_index.max()) > np.iinfo(np.int32).max:
        raise CloudFileError(f"{path}: profile index {int(scan.profile_index.max())} does not fit int32")
    props = "".join(
        f"property {'float' if n in 'xyz' else 'double' if n == 't_s' else 'int'} {n}\n"
        for n in _PLY_VERTEX.names
    )
    head = f"ply\nformat binary_little_endian 1.0\ncomment {_PLY_COMMENT}\nelement vertex {scan.n_valid}\n"
    with path.open("wb") as f:
        f.write((head + props + "end_header\n").encode("ascii"))
        for b in scan.cloud_blocks():
            rec = np.empty(len(b["t_s"]), _PLY_VERTEX)
            rec["x"], rec["y"], rec["z"] = b["xyz_mm"].T
            rec["pass"], rec["profile"], rec["point"] = b["pass_id"], b["profile_index"], b["point_index"]
            rec["t_s"] = b["t_s"]
            f.write(rec.tobytes())
    return path


def write_las(scan: AssembledScan, path: str | Path) -> Path:
    """Write the valid points of ``scan`` as LAS 1.4 through laspy (:func:`analysis.cloud_export.write_las`:
    point format 6, pass / profile / point as extra dimensions, gps_time the exposure time, the robot
    base frame named in its VLRs); returns the path. A block of rows in memory at a time."""
    return cloud_export.write_las(path, scan.cloud_blocks, ROBOT_BASE)


def write_e57(scan: AssembledScan, path: str | Path) -> Path:
    """Write the valid points of ``scan`` as one E57 scan through pye57
    (:func:`analysis.cloud_export.write_e57`: its pose the identity, the profile and point as
    rowIndex / columnIndex, timeStamp the exposure time); returns the path."""
    return cloud_export.write_e57(path, scan.cloud_blocks, ROBOT_BASE, name="cellctl scan")
