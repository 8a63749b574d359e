"""Clouds for the metrology tools: LAS 1.4 through laspy, E57 through pye57, PLY with the scalar
fields CloudCompare takes, each written block by block and naming its frame and units.

A cloud to export is a :data:`Blocks` source: a callable returning an iterator of blocks, each a dict
of the cloud vocabulary (:mod:`analysis.cloud_io`) for a run of points: ``xyz_mm`` (m, 3) and any of
``pass_id``, ``profile_index``, ``point_index``, ``t_s``, ``deviation_mm`` (every block the same
keys). The writers call it twice (extent and counts first, then the records), so a file costs one
block's records in memory, never a copy of the whole cloud: the caller holds its cloud (a memory map
of cloud.ply, an assembled scan) and nothing the size of it is added.

Layouts (docs/operations.md, "Cloud files for metrology tools"):

* **LAS 1.4**, point format 6, coordinates scaled integers at 0.001 mm from an offset at the cloud's
  minimum (int32 covers +-2 km); ``gps_time`` the exposure time (s from the scan's first profile);
  extra dimensions (the standard extra-bytes VLR) ``pass`` u16, ``profile`` u32, ``point`` u16,
  ``deviation`` f32 (mm, NaN off the design). The frame: a ``LOCAL_CS`` WKT (the CRS VLR, units
  millimetre) and a ``cellctl`` VLR whose description and text name it.
* **E57** (ASTM E2807): one scan; ``cartesianX/Y/Z`` single precision in the scan's own frame, its
  ``pose`` (a rigid transform, quaternion and translation in double) to the file's frame, which the
  root's ``coordinateMetadata`` names; ``rowIndex`` the profile, ``columnIndex`` the point,
  ``timeStamp`` the exposure time. E57 has no custom point fields, so the deviation is the
  ``intensity``, unscaled (intensity = deviation in mm, ``intensityLimits`` its range) and
  ``isIntensityInvalid`` 1 (intensity NaN) off the design: the one per-point scalar every E57
  reader (CloudCompare, Cyclone, pye57) loads. The pass is not stored (no E57 field means it).
* **PLY**, binary: ``x, y, z`` (float32, or float64 where the frame's coordinates are large, as a
  ship's are) and scalar properties named ``scalar_<name>`` (``scalar_deviation`` float32 and the
  organisation's ``scalar_pass``...): CloudCompare loads a property as a scalar field only under
  that prefix. The comment names the frame and units.

Every failure raises :class:`~analysis.cloud_io.CloudError` naming the file.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from analysis.cloud_io import CloudError

__all__ = [
    "BLOCK_POINTS",
    "LAS_SCALE_MM",
    "Blocks",
    "CloudFrame",
    "apply_rigid_blocks",
    "read_e57",
    "read_las",
    "write_e57",
    "write_las",
    "write_ply_blocks",
]

Block = dict[str, np.ndarray]
Blocks = Callable[[], Iterable[Block]]

LAS_SCALE_MM = 0.001
#: the fields a block may carry beside ``xyz_mm``
FIELDS = ("pass_id", "profile_index", "point_index", "t_s", "deviation_mm")
#: LAS extra dimension of each field (name, dtype, description); ``t_s`` is gps_time
_LAS_EXTRA = {
    "pass_id": ("pass", np.uint16, "scan pass (0: transit)"),
    "profile_index": ("profile", np.uint32, "running profile index"),
    "point_index": ("point", np.uint16, "column in the profile"),
    "deviation_mm": ("deviation", np.float32, "mm, z_design - z_measured"),
}
_LAS_FIELD = {las: field for field, (las, _, _) in _LAS_EXTRA.items()}
#: the PLY name of each field (CloudCompare's ``scalar_`` prefix) and its dtype
_PLY_FIELD = {
    "pass_id": ("scalar_pass", "<i4"),
    "profile_index": ("scalar_profile", "<i4"),
    "point_index": ("scalar_point", "<i4"),
    "t_s": ("scalar_t_s", "<f8"),
    "deviation_mm": ("scalar_deviation", "<f4"),
}
_PLY_TYPES = {"<f4": "float", "<f8": "double", "<i4": "int"}
#: points of a block the writers move and write at a time (about 25 MB of temporaries)
BLOCK_POINTS = 1 << 18
_VLR_USER = "cellctl"
#: the generating software of the LAS files cellctl wrote by hand (pass + 1 in point_source_id)
_OLD_LAS_SOFTWARE = "cellctl acquisition"


@dataclass(frozen=True)
class CloudFrame:
    """The frame a file's coordinates are in, named in its header.

    name: e.g. "robot base frame", "design frame", "design file (ship) frame";
    detail: one sentence more (where it comes from); units are always millimetres."""

    name: str
    detail: str = ""

    def text(self) -> str:
        return f"{self.name}, mm" + (f"; {self.detail}" if self.detail else "")

    def wkt(self) -> str:
        """A local engineering CRS (no geodetic datum): the frame's name and millimetres."""
        name = self.name.replace('"', "'")
        return (
            f'LOCAL_CS["{name}",LOCAL_DATUM["{name}",0],UNIT["millimetre",0.001],'
            'AXIS["X",OTHER],AXIS["Y",OTHER],AXIS["Z",OTHER]]'
        )


@dataclass
class _Extent:
    n: int
    keys: tuple[str, ...]
    lo: np.ndarray
    hi: np.ndarray
    field_lo: dict[str, float]
    field_hi: dict[str, float]
    any_nan: bool


def _sliced(blocks: Blocks) -> Iterator[Block]:
    """The blocks cut to at most :data:`BLOCK_POINTS` points (views): a writer's temporaries are a
    slice's, whatever block the caller hands over (an assembled scan's block of 16 384 profiles)."""
    step = BLOCK_POINTS
    for b in blocks():
        n = len(b["xyz_mm"])
        if n <= step:
            yield b
            continue
        for lo in range(0, n, step):
            yield {k: v[lo : lo + step] for k, v in b.items()}


def _extent(path: Path, blocks: Blocks) -> _Extent:
    """One pass over the blocks: the count, the fields, the extent and each field's finite range."""
    n, keys = 0, None
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    flo: dict[str, float] = {}
    fhi: dict[str, float] = {}
    any_nan = False
    for b in _sliced(blocks):
        got = tuple(k for k in FIELDS if k in b)
        if keys is None:
            keys = got
        elif got != keys:
            raise CloudError(f"{path}: blocks with different fields ({keys} then {got})")
        xyz = b["xyz_mm"]
        if len(xyz) == 0:
            continue
        n += len(xyz)
        lo = np.minimum(lo, xyz.min(axis=0).astype(np.float64))
        hi = np.maximum(hi, xyz.max(axis=0).astype(np.float64))
        for k in keys:
            a = b[k]
            fin = a[np.isfinite(a)] if a.dtype.kind == "f" else a
            any_nan |= k == "deviation_mm" and len(fin) < len(a)
            if len(fin):
                flo[k] = min(flo.get(k, np.inf), float(fin.min()))
                fhi[k] = max(fhi.get(k, -np.inf), float(fin.max()))
    if n == 0:
        lo = hi = np.zeros(3)
    if not np.all(np.isfinite(lo) & np.isfinite(hi)):
        raise CloudError(f"{path}: the cloud has non-finite coordinates")
    return _Extent(n, keys or (), lo, hi, flo, fhi, any_nan)


def _check_fits(path: Path, ext: _Extent, limits: dict[str, type]) -> None:
    for k, dt in limits.items():
        if k in ext.keys and k in ext.field_hi:
            info = np.iinfo(dt)
            if ext.field_lo[k] < info.min or ext.field_hi[k] > info.max:
                raise CloudError(
                    f"{path}: {k} {ext.field_lo[k]:g}..{ext.field_hi[k]:g} does not fit {np.dtype(dt)}"
                )


def _atomic(path: Path, write: Callable[[Path], None]) -> Path:
    """Write through ``.<name>.tmp`` and rename: a reader never meets half a file."""
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


# ------------------------------------------------------------------------------------------- LAS


def write_las(path: str | Path, blocks: Blocks, frame: CloudFrame, *, software: str = "cellctl") -> Path:
    """Write the cloud of ``blocks`` as LAS 1.4 (module docstring); returns the path."""
    import laspy

    path = Path(path)
    ext = _extent(path, blocks)
    _check_fits(path, ext, {k: dt for k, (_, dt, _) in _LAS_EXTRA.items() if np.dtype(dt).kind == "u"})
    offset = np.floor(ext.lo)
    if np.rint((ext.hi - offset) / LAS_SCALE_MM).max() > np.iinfo(np.int32).max:
        raise CloudError(f"{path}: cloud extent {ext.hi - ext.lo} mm does not fit int32 at {LAS_SCALE_MM} mm")
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = np.full(3, LAS_SCALE_MM)
    header.offsets = offset
    header.system_identifier = frame.name[:32]
    header.generating_software = software[:32]
    header.add_extra_dims(
        [
            laspy.ExtraBytesParams(las, dt, description=d)
            for k, (las, dt, d) in _LAS_EXTRA.items()
            if k in ext.keys
        ]
    )
    header.vlrs.append(laspy.VLR("LASF_Projection", 2112, "OGC WKT", frame.wkt().encode() + b"\0"))
    header.vlrs.append(laspy.VLR(_VLR_USER, 1, frame.text()[:32], frame.text().encode()))
    header.global_encoding.wkt = True

    def write(tmp: Path) -> None:
        with laspy.open(tmp, mode="w", header=header) as w:
            for b in _sliced(blocks):
                m = len(b["xyz_mm"])
                if not m:
                    continue
                rec = laspy.ScaleAwarePointRecord.zeros(m, header=header)
                for i, axis in enumerate("XYZ"):  # scaled integers, from float64 a column at a time
                    rec[axis] = np.rint(
                        (b["xyz_mm"][:, i].astype(np.float64) - offset[i]) / LAS_SCALE_MM
                    ).astype(np.int32)
                rec.return_number[:] = 1
                rec.number_of_returns[:] = 1
                if "t_s" in b:
                    rec["gps_time"] = b["t_s"]
                for k, (las, dt, _) in _LAS_EXTRA.items():
                    if k in b:
                        rec[las] = b[k].astype(dt, copy=False)
                w.write_points(rec)

    return _atomic(path, write)


def read_las(path: str | Path, require: Iterable[str] = ()) -> dict[str, np.ndarray]:
    """Read a LAS file (any that laspy reads): ``xyz_mm`` (n, 3) float64 and, where the file has
    them, ``pass_id``, ``profile_index``, ``point_index``, ``deviation_mm`` (its extra dimensions),
    ``t_s`` (gps_time, point formats with it), plus ``frame`` (the cellctl VLR's text, or "").

    require: fields that must be there (a :class:`CloudError` names the missing one)."""
    import laspy

    path = Path(path)
    try:
        las = laspy.read(path)
    except FileNotFoundError:
        raise CloudError(f"{path}: no such file") from None
    except Exception as exc:  # laspy raises LaspyException, ValueError, struct errors on a bad file
        raise CloudError(f"{path}: not a readable LAS file ({type(exc).__name__}: {exc})") from None
    if len(las.points) != las.header.point_count:
        raise CloudError(f"{path}: truncated: {len(las.points)} of {las.header.point_count} points")
    out: dict[str, np.ndarray] = {"xyz_mm": np.column_stack([las.x, las.y, las.z]).astype(np.float64)}
    for name in las.point_format.extra_dimension_names:
        if name in _LAS_FIELD:
            out[_LAS_FIELD[name]] = np.asarray(las[name])
    if "gps_time" in las.point_format.dimension_names:
        out["t_s"] = np.asarray(las.gps_time, dtype=np.float64)
    if "pass_id" not in out and las.header.generating_software.startswith(_OLD_LAS_SOFTWARE):
        # cellctl's own writer before laspy: the pass + 1 in point_source_id (0: transit then)
        out["pass_id"] = np.maximum(np.asarray(las.point_source_id, dtype=np.int32) - 1, 0)
    frame = next((v.record_data.decode(errors="replace") for v in las.vlrs if v.user_id == _VLR_USER), "")
    out["frame"] = np.asarray(frame)
    _require(path, out, require)
    return out


def _require(path: Path, out: dict[str, np.ndarray], require: Iterable[str]) -> None:
    missing = [k for k in require if k not in out]
    if missing:
        raise CloudError(f"{path}: no {', '.join(missing)} in the file (it has {', '.join(sorted(out))})")


# ------------------------------------------------------------------------------------------- E57


def _quaternion_wxyz(path: Path, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    from scipy.spatial.transform import Rotation

    R = np.asarray(T, dtype=np.float64)[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-9) or np.linalg.det(R) < 0:
        raise CloudError(f"{path}: an E57 pose must be a rotation and a translation, got {T.tolist()}")
    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return np.array([w, x, y, z]), np.asarray(T, dtype=np.float64)[:3, 3].copy()


def write_e57(
    path: str | Path, blocks: Blocks, frame: CloudFrame, *, pose: np.ndarray | None = None, name: str = "scan"
) -> Path:
    """Write the cloud of ``blocks`` as one E57 scan (module docstring); returns the path.

    pose: 4x4 rigid transform from the blocks' coordinates (the scan's own frame) to ``frame``, the
    file's frame (default: the identity, the blocks are in ``frame``)."""
    import pye57
    from pye57 import libe57

    path = Path(path)
    ext = _extent(path, blocks)
    _check_fits(path, ext, {"profile_index": np.uint32, "point_index": np.uint32})
    q, t = _quaternion_wxyz(path, np.eye(4) if pose is None else pose)
    metadata = frame.text() + (
        "" if "deviation_mm" not in ext.keys else "; intensity = deviation in mm, unscaled"
    )

    class _Out(pye57.E57):
        def write_default_header(self) -> None:  # pye57's, with the frame in coordinateMetadata
            imf, root = self.image_file, self.image_file.root()
            imf.extensionsAdd("", libe57.E57_V1_0_URI)
            root.set("formatName", libe57.StringNode(imf, "ASTM E57 3D Imaging Data File"))
            root.set("guid", libe57.StringNode(imf, f"{{{uuid.uuid4()}}}"))
            root.set("versionMajor", libe57.IntegerNode(imf, libe57.E57_FORMAT_MAJOR))
            root.set("versionMinor", libe57.IntegerNode(imf, libe57.E57_FORMAT_MINOR))
            root.set("e57LibraryVersion", libe57.StringNode(imf, libe57.E57_LIBRARY_ID))
            root.set("coordinateMetadata", libe57.StringNode(imf, metadata))
            created = libe57.StructureNode(imf)
            created.set("dateTimeValue", libe57.FloatNode(imf, 0.0))
            created.set("isAtomicClockReferenced", libe57.IntegerNode(imf, 0))
            root.set("creationDateTime", created)
            root.set("data3D", libe57.VectorNode(imf, True))
            root.set("images2D", libe57.VectorNode(imf, True))

    def write(tmp: Path) -> None:
        f = _Out(str(tmp), mode="w")
        try:
            _write_e57_scan(f, libe57, blocks, ext, metadata, name, q, t)
        finally:
            f.close()

    try:
        return _atomic(path, write)
    except (RuntimeError, libe57.E57Exception) as exc:
        raise CloudError(f"{path}: E57 not written: {exc}") from None


def _widened(lo: float, hi: float) -> tuple[float, float]:
    pad = 1e-6 * max(abs(lo), abs(hi), 1.0)
    return float(lo) - pad, float(hi) + pad


def _write_e57_scan(f, libe57, blocks: Blocks, ext: _Extent, description: str, name: str,
                    q: np.ndarray, t: np.ndarray) -> None:  # fmt: skip
    imf = f.image_file
    node = lambda v: libe57.FloatNode(imf, float(v))  # noqa: E731
    scan = libe57.StructureNode(imf)
    scan.set("guid", libe57.StringNode(imf, f"{{{uuid.uuid4()}}}"))
    scan.set("name", libe57.StringNode(imf, name))
    scan.set("description", libe57.StringNode(imf, description))
    pose, rot, tr = (libe57.StructureNode(imf) for _ in range(3))
    for k, v in zip("wxyz", q, strict=True):
        rot.set(k, node(v))
    for k, v in zip("xyz", t, strict=True):
        tr.set(k, node(v))
    pose.set("rotation", rot)
    pose.set("translation", tr)
    scan.set("pose", pose)
    bounds = libe57.StructureNode(imf)
    for i, axis in enumerate("xyz"):
        bounds.set(f"{axis}Minimum", node(ext.lo[i]))
        bounds.set(f"{axis}Maximum", node(ext.hi[i]))
    scan.set("cartesianBounds", bounds)

    proto = libe57.StructureNode(imf)
    fields: list[tuple[str, str, str | None]] = []  # (E57 name, buffer dtype, block key)
    for i, axis in enumerate("XYZ"):
        lo, hi = _widened(ext.lo[i], ext.hi[i])  # the float32 values rounded from float64 stay inside
        proto.set(f"cartesian{axis}", libe57.FloatNode(imf, lo, libe57.E57_SINGLE, lo, hi))
        fields.append((f"cartesian{axis}", "f4", None))
    flo, fhi = ext.field_lo, ext.field_hi
    if "deviation_mm" in ext.keys:
        dlo, dhi = flo.get("deviation_mm", 0.0), fhi.get("deviation_mm", 0.0)
        proto.set("intensity", libe57.FloatNode(imf, dlo, libe57.E57_SINGLE, *_widened(dlo, dhi)))
        limits = libe57.StructureNode(imf)
        limits.set("intensityMinimum", node(dlo))
        limits.set("intensityMaximum", node(dhi))
        scan.set("intensityLimits", limits)
        fields.append(("intensity", "f4", "deviation_mm"))
        proto.set("isIntensityInvalid", libe57.IntegerNode(imf, 0, 0, 1))
        fields.append(("isIntensityInvalid", "i1", None))
    for key, e57 in (("profile_index", "rowIndex"), ("point_index", "columnIndex")):
        if key in ext.keys:
            lo, hi = int(flo.get(key, 0)), int(fhi.get(key, 0))
            proto.set(e57, libe57.IntegerNode(imf, lo, lo, hi))
            fields.append((e57, "q", key))  # "q": the wrapper takes "l" as 32 bits
    if "t_s" in ext.keys:
        proto.set("timeStamp", libe57.FloatNode(imf, 0.0, libe57.E57_DOUBLE))
        fields.append(("timeStamp", "f8", "t_s"))
    points = libe57.CompressedVectorNode(imf, proto, libe57.VectorNode(imf, True))
    scan.set("points", points)
    f.data3d.append(scan)

    cap = BLOCK_POINTS
    arrays = {e57: np.zeros(cap, dt) for e57, dt, _ in fields}
    buffers = libe57.VectorSourceDestBuffer()
    for e57, _, _ in fields:
        buffers.append(libe57.SourceDestBuffer(imf, e57, arrays[e57], cap, True, False))
    writer = points.writer(buffers)
    try:
        for b in _sliced(blocks):
            for lo in range(0, len(b["xyz_mm"]), cap):
                xyz = b["xyz_mm"][lo : lo + cap]
                m = len(xyz)
                for i, axis in enumerate("XYZ"):
                    arrays[f"cartesian{axis}"][:m] = xyz[:, i]
                for e57, _, key in fields:
                    if key is not None:
                        arrays[e57][:m] = b[key][lo : lo + m]
                if "isIntensityInvalid" in arrays:
                    arrays["isIntensityInvalid"][:m] = ~np.isfinite(arrays["intensity"][:m])
                writer.write(m)
    finally:
        writer.close()


def read_e57(path: str | Path, require: Iterable[str] = (), *, scan: int = 0) -> dict[str, np.ndarray]:
    """Read one scan of an E57 file: ``xyz_mm`` (n, 3) float64 in the file's frame (the scan's pose
    applied), ``deviation_mm`` (the intensity, NaN where ``isIntensityInvalid``), ``profile_index``
    (rowIndex), ``point_index`` (columnIndex), ``t_s`` (timeStamp) where present, ``frame`` (the
    root's coordinateMetadata) and ``pose`` (4x4, the scan's own frame -> the file's)."""
    import pye57
    from pye57 import libe57

    path = Path(path)
    if not path.is_file():
        raise CloudError(f"{path}: no such file")
    try:
        f = pye57.E57(str(path))
    except Exception as exc:  # libE57's RuntimeError on a bad file
        raise CloudError(f"{path}: not a readable E57 file ({exc})") from None
    try:
        if f.scan_count <= scan:
            raise CloudError(f"{path}: no scan {scan} (the file has {f.scan_count})")
        header = f.get_header(scan)
        node = header.points
        proto = libe57.StructureNode(node.prototype())
        names = [proto.get(i).elementName() for i in range(proto.childCount())]
        n = node.childCount()
        dtypes = {"cartesianX": "f8", "cartesianY": "f8", "cartesianZ": "f8", "intensity": "f4",
                  "isIntensityInvalid": "i1", "rowIndex": "q", "columnIndex": "q", "timeStamp": "f8"}  # fmt: skip
        wanted = [k for k in dtypes if k in names]
        if not {"cartesianX", "cartesianY", "cartesianZ"} <= set(wanted):
            raise CloudError(f"{path}: scan {scan} has no cartesian coordinates (fields {names})")
        arrays = {k: np.zeros(n, dtypes[k]) for k in wanted}
        buffers = libe57.VectorSourceDestBuffer()
        for k in wanted:
            buffers.append(libe57.SourceDestBuffer(f.image_file, k, arrays[k], n, True, True))
        reader = node.reader(buffers)
        got = reader.read()
        reader.close()
        if got != n:
            raise CloudError(f"{path}: truncated: {got} of {n} points")
        T = np.eye(4)
        T[:3, :3] = header.rotation_matrix
        T[:3, 3] = header.translation
        root = f.root
        frame = (
            libe57.StringNode(root.get("coordinateMetadata")).value()
            if root.isDefined("coordinateMetadata")
            else ""
        )
    except (RuntimeError, libe57.E57Exception) as exc:
        raise CloudError(f"{path}: not a readable E57 file ({exc})") from None
    finally:
        f.close()
    local = np.column_stack([arrays["cartesianX"], arrays["cartesianY"], arrays["cartesianZ"]])
    out: dict[str, np.ndarray] = {
        "xyz_mm": local @ T[:3, :3].T + T[:3, 3],
        "pose": T,
        "frame": np.asarray(frame),
    }
    if "intensity" in arrays:
        dev = arrays["intensity"]
        if "isIntensityInvalid" in arrays:
            dev[arrays["isIntensityInvalid"] != 0] = np.nan
        out["deviation_mm"] = dev
    for e57, key in (("rowIndex", "profile_index"), ("columnIndex", "point_index"), ("timeStamp", "t_s")):
        if e57 in arrays:
            out[key] = arrays[e57]
    _require(path, out, require)
    return out


# ------------------------------------------------------------------------------------------- PLY


def write_ply_blocks(
    path: str | Path, blocks: Blocks, frame: CloudFrame, *, double: bool = False, comment: str = ""
) -> Path:
    """Write the cloud of ``blocks`` as binary PLY: ``x, y, z`` float32 (float64 with ``double``),
    then each field present as its CloudCompare scalar field (``scalar_deviation`` float32, ...);
    the header's comments name the frame (and ``comment``, when given)."""
    path = Path(path)
    ext = _extent(path, blocks)
    _check_fits(path, ext, {k: np.int32 for k, (_, dt) in _PLY_FIELD.items() if dt == "<i4"})
    xyz_dt = "<f8" if double else "<f4"
    dtype = np.dtype([(a, xyz_dt) for a in "xyz"] + [_PLY_FIELD[k] for k in FIELDS if k in ext.keys])
    props = "".join(f"property {_PLY_TYPES[dtype[n].str]} {n}\n" for n in dtype.names)
    comments = f"comment frame: {frame.text()}\n" + (f"comment {comment}\n" if comment else "")
    head = f"ply\nformat binary_little_endian 1.0\n{comments}element vertex {ext.n}\n{props}end_header\n"

    def write(tmp: Path) -> None:
        with tmp.open("wb") as f:
            f.write(head.encode("ascii"))
            for b in _sliced(blocks):
                rec = np.empty(len(b["xyz_mm"]), dtype)
                rec["x"], rec["y"], rec["z"] = b["xyz_mm"].T
                for k in ext.keys:
                    rec[_PLY_FIELD[k][0]] = b[k]
                f.write(memoryview(rec).cast("B"))

    return _atomic(path, write)


# ------------------------------------------------------------------------------------- transforms


def apply_rigid_blocks(blocks: Blocks, T: np.ndarray, block_points: int | None = None) -> Blocks:
    """``blocks`` moved by the 4x4 ``T`` (float64 arithmetic a block at a time; the other fields as
    they are); blocks larger than ``block_points`` are cut, so a memory-mapped cloud given as one
    block is still read and moved a slice at a time."""
    T = np.asarray(T, dtype=np.float64)

    def moved() -> Iterator[Block]:
        step = block_points or BLOCK_POINTS
        for b in blocks():
            for lo in range(0, max(len(b["xyz_mm"]), 1), step):
                part = {k: v[lo : lo + step] for k, v in b.items()}
                p = part["xyz_mm"].astype(np.float64)
                part["xyz_mm"] = p @ T[:3, :3].T + T[:3, 3]
                yield part

    return moved
