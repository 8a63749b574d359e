"""The product's one cloud type, :class:`ScanCloud`, and scan clouds on disk (PLY, PCD, text, NPZ).

The cloud vocabulary, from the acquisition to the analysis (the daemon builds a ScanCloud from its
assembled scan, the wire codec carries the same arrays, the worker hands a ScanCloud to the
analysis):

* names: ``xyz_mm`` (n, 3) points (robot base / bed frame, mm) and, when the scanner recorded the
  organisation, ``pass_id`` (raster or edge pass), ``profile_index`` (profile, running within the
  scan), ``point_index`` (index along the laser line), and optionally ``t_s`` (exposure time, s
  from the scan's first profile);
* dtypes: in memory ``xyz_mm`` float64, or float32 kept as given (a cloud decoded from the wire or
  taken from the acquisition: its float32 values are the measurement, and a float64 copy would add
  24 bytes a point and hold no more information), the indices int32, ``t_s`` float64; stored and
  sent, ``xyz`` float32 (half a micrometre at 10 m), the indices as the format holds them. Code that
  does arithmetic on ``xyz_mm`` (sums, means, transforms, differences of large coordinates) does it
  in float64 or about a local origin (docs/operations.md "float32: where and where not");
* transit: the moves between passes are no pass of the scan grid; their profiles are filed under
  pass 0 (pass ids are >= 0 in every cloud). Files written before this convention marked transit
  with pass -1: reading maps it to 0.

``segment`` triangulates organised clouds on their scan grid and falls back to Delaunay otherwise.

File layouts written and read here:

* PLY (binary little endian), the one organised-PLY writer :func:`write_cloud_ply`: vertex
  properties ``x, y, z`` float32, when organised ``pass``, ``profile``, ``point`` int32, ``t_s``
  float64 when known, plus any extra per-point columns (the registered cloud's ``deviation``).
  Reading accepts float or double coordinates, ASCII or binary, ``pass_id`` as an alias of ``pass``.
* PCD (ASCII or binary; ``binary_compressed`` is refused with a clear message): fields x y z.
* Text (``.xyz``, ``.txt``, ``.csv``, ``.asc``): one point per line, comma/space/semicolon
  separated, the first three columns are x y z; a header line with names ``x,y,z[,pass,profile,
  point]`` is understood; ``#`` starts a comment.
* NPZ: array ``xyz_mm`` (older files: ``points_mm``, ``points`` or ``xyz``) (n, 3) and optional
  ``pass_id``, ``profile_index``, ``point_index`` (older: ``profile``, ``point``) (n,) integer arrays.

Every failure raises :class:`CloudError` naming the file and what is wrong with it.
"""

from __future__ import annotations

import io
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = [
    "ORGANISATION",
    "CloudError",
    "ScanCloud",
    "organised_cloud",
    "ply_header_overclaims",
    "read_cloud",
    "write_cloud_npz",
    "write_cloud_ply",
    "write_ply_vertices",
]

TEXT_SUFFIXES = {".xyz", ".txt", ".csv", ".asc", ".pts"}
SUFFIXES = {".ply", ".pcd", ".npz", *TEXT_SUFFIXES}


class CloudError(ValueError):
    """A cloud file that cannot be used: missing, unreadable, empty, or of the wrong shape."""


@dataclass(frozen=True)
class ScanCloud:
    """A scanned point cloud, optionally with its scan organisation (see the module docstring).

    xyz_mm: (n, 3) float64, or float32 kept as given (no copy), millimetres (robot base / bed frame).
    pass_id, profile_index, point_index: (n,) int32 each (>= 0), or all None for an unorganised cloud.
    t_s: (n,) float64 exposure times (s from the scan's first profile), or None.
    """

    xyz_mm: np.ndarray
    pass_id: np.ndarray | None = None
    profile_index: np.ndarray | None = None
    point_index: np.ndarray | None = None
    t_s: np.ndarray | None = None

    def __post_init__(self) -> None:
        p = np.asarray(self.xyz_mm)
        p = p if p.dtype == np.float32 else np.asarray(p, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise CloudError(f"xyz_mm must be (n, 3), got {p.shape}")
        object.__setattr__(self, "xyz_mm", p)
        org = [self.pass_id, self.profile_index, self.point_index]
        if any(a is not None for a in org):
            if any(a is None for a in org):
                raise CloudError("pass_id, profile_index and point_index must be given together")
            for name in ORGANISATION:
                a = np.asarray(getattr(self, name))
                if a.shape != (len(p),):
                    raise CloudError(f"{name} must be ({len(p)},), got {a.shape}")
                if a.size and (not np.issubdtype(a.dtype, np.integer) and not np.all(a == np.round(a))):
                    raise CloudError(f"{name} must hold integers")
                if a.size and a.min() < 0:
                    raise CloudError(f"{name} has negative indices")
                object.__setattr__(self, name, a.astype(np.int32, copy=False))
        if self.t_s is not None:
            t = np.asarray(self.t_s, dtype=np.float64)
            if t.shape != (len(p),):
                raise CloudError(f"t_s must be ({len(p)},), got {t.shape}")
            object.__setattr__(self, "t_s", t)

    @property
    def organised(self) -> bool:
        """True when every point carries (pass_id, profile_index, point_index)."""
        return self.pass_id is not None

    def __len__(self) -> int:
        return len(self.xyz_mm)

    def subset(self, mask: np.ndarray) -> ScanCloud:
        """The points where ``mask`` (bool (n,) or index array) selects, organisation and times kept."""
        t = None if self.t_s is None else self.t_s[mask]
        if not self.organised:
            return ScanCloud(self.xyz_mm[mask], t_s=t)
        return ScanCloud(
            self.xyz_mm[mask], self.pass_id[mask], self.profile_index[mask], self.point_index[mask], t
        )


#: the organisation arrays of a ScanCloud, in order
ORGANISATION = ("pass_id", "profile_index", "point_index")


def organised_cloud(xyz_mm: np.ndarray, pass_id: np.ndarray, profile_index: np.ndarray,
                    point_index: np.ndarray, t_s: np.ndarray | None = None) -> ScanCloud:  # fmt: skip
    """A ScanCloud from arrays as files of any age hold them: transit marked pass -1 goes to pass 0."""
    return ScanCloud(xyz_mm, np.maximum(np.asarray(pass_id), 0), profile_index, point_index, t_s)


def read_cloud(path: str | Path) -> ScanCloud:
    """Read a scan cloud (PLY, PCD, XYZ/CSV text, NPZ; see the module docstring).

    Raises CloudError for a missing, unreadable or empty file, or non-finite coordinates.
    """
    path = Path(path)
    if not path.is_file():
        raise CloudError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if suffix not in SUFFIXES:
        raise CloudError(f"{path}: unsupported cloud format {suffix!r} (use {', '.join(sorted(SUFFIXES))})")
    if path.stat().st_size == 0:
        raise CloudError(f"{path}: empty file")
    try:
        if suffix == ".ply":
            cloud = _read_ply(path)
        elif suffix == ".pcd":
            cloud = _read_pcd(path)
        elif suffix == ".npz":
            cloud = _read_npz(path)
        else:
            cloud = _read_text(path)
    except CloudError as exc:
        if str(exc).startswith(str(path)):
            raise
        raise CloudError(f"{path}: {exc}") from None  # ScanCloud's own checks do not know the file
    except Exception as exc:  # a parser's own error: say which file and why, in one line
        raise CloudError(
            f"{path}: unreadable {suffix[1:].upper()} file ({type(exc).__name__}: {exc})"
        ) from exc
    if len(cloud) == 0:
        raise CloudError(f"{path}: the cloud holds no points")
    if not np.isfinite(cloud.xyz_mm).all():
        bad = int(np.count_nonzero(~np.isfinite(cloud.xyz_mm).all(axis=1)))
        raise CloudError(f"{path}: {bad} points with non-finite coordinates")
    return cloud


_PLY_SIZES = {"char": 1, "int8": 1, "uchar": 1, "uint8": 1, "short": 2, "int16": 2, "ushort": 2, "uint16": 2,
              "int": 4, "int32": 4, "uint": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}  # fmt: skip


def ply_header_overclaims(path: str | Path) -> str | None:
    """Why a PLY header's element counts cannot fit in the file, or None when they can (or it is no PLY).

    A 200-byte file may declare 10^8 vertices; parsers then allocate and loop for seconds to minutes
    before failing. Checked against the smallest possible encoding of each element (one byte per
    ASCII value plus its separator, the type size in binary), so a valid file always passes.
    """
    path = Path(path)
    with path.open("rb") as f:
        head = f.read(65536)
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        return None  # the parser reports what is wrong
    binary = False
    elements: list[list] = []  # [name, count, bytes per item]
    try:
        for line in head[:end].decode("ascii", "replace").splitlines():
            tok = line.split()
            if not tok:
                continue
            if tok[0] == "format":
                binary = tok[1].startswith("binary")
            elif tok[0] == "element":
                elements.append([tok[1], int(tok[2]), 0])
            elif tok[0] == "property" and elements:
                # a list property holds at least its count; a scalar its value
                t = tok[2] if tok[1] == "list" else tok[1]
                elements[-1][2] += _PLY_SIZES.get(t, 1) if binary else 2
    except (IndexError, ValueError):
        return None
    need = sum(max(count, 0) * max(per_item, 1) for _, count, per_item in elements)
    available = path.stat().st_size - (end + len(b"end_header"))
    if need > available:
        counts = ", ".join(f"{count} {name}" for name, count, _ in elements)
        return f"PLY header declares {counts}: at least {need} bytes, but only {available} follow the header"
    return None


def _read_ply(path: Path) -> ScanCloud:
    from plyfile import PlyData

    with path.open("rb") as f:
        head = f.read(3)
    if head != b"ply":
        raise CloudError(f"{path}: not a PLY file (no 'ply' magic at the start)")
    overclaim = ply_header_overclaims(path)
    if overclaim:
        raise CloudError(f"{path}: unreadable PLY file ({overclaim})")
    ply = PlyData.read(str(path))
    if "vertex" not in ply:
        raise CloudError(f"{path}: PLY has no 'vertex' element")
    v = ply["vertex"].data
    names = set(v.dtype.names or ())
    missing = {"x", "y", "z"} - names
    if missing:
        raise CloudError(f"{path}: PLY vertex lacks properties {sorted(missing)}")
    pts = np.column_stack([np.asarray(v[c], dtype=np.float64) for c in ("x", "y", "z")])
    pass_name = "pass" if "pass" in names else ("pass_id" if "pass_id" in names else None)
    if pass_name and {"profile", "point"} <= names:
        t_name = "t_s" if "t_s" in names else ("time_s" if "time_s" in names else None)
        t_s = None if t_name is None else np.asarray(v[t_name])
        return organised_cloud(
            pts, np.asarray(v[pass_name]), np.asarray(v["profile"]), np.asarray(v["point"]), t_s
        )
    return ScanCloud(pts)


_PCD_TYPES = {("F", 4): "<f4", ("F", 8): "<f8", ("I", 1): "<i1", ("I", 2): "<i2", ("I", 4): "<i4",
              ("I", 8): "<i8", ("U", 1): "<u1", ("U", 2): "<u2", ("U", 4): "<u4", ("U", 8): "<u8"}  # fmt: skip


def _read_pcd(path: Path) -> ScanCloud:
    raw = path.read_bytes()
    header: dict[str, list[str]] = {}
    pos = 0
    while True:
        end = raw.find(b"\n", pos)
        if end < 0:
            raise CloudError(f"{path}: PCD header ends before DATA")
        line = raw[pos:end].decode("ascii", errors="replace").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *vals = line.split()
        header[key.upper()] = vals
        if key.upper() == "DATA":
            break
    for key in ("FIELDS", "SIZE", "TYPE", "POINTS", "DATA"):
        if key not in header:
            raise CloudError(f"{path}: PCD header lacks {key}")
    fields = header["FIELDS"]
    counts = [int(c) for c in header.get("COUNT", ["1"] * len(fields))]
    if not {"x", "y", "z"} <= set(fields):
        raise CloudError(f"{path}: PCD fields {fields} lack x, y or z")
    n = int(header["POINTS"][0])
    data_kind = header["DATA"][0].lower()
    if data_kind == "ascii":
        table = np.loadtxt(io.BytesIO(raw[pos:]), ndmin=2) if n else np.zeros((0, sum(counts)))
        cols, c0 = {}, 0
        for f, c in zip(fields, counts, strict=True):
            cols[f] = table[:, c0]
            c0 += c
        pts = np.column_stack([cols["x"], cols["y"], cols["z"]])
    elif data_kind == "binary":
        dtype = []
        for f, s, t, c in zip(fields, header["SIZE"], header["TYPE"], counts, strict=True):
            key = (t.upper(), int(s))
            if key not in _PCD_TYPES:
                raise CloudError(f"{path}: PCD field {f!r} has unsupported type {t}{s}")
            name = f if f != "_" else f"_pad{len(dtype)}"
            dtype.append((name, _PCD_TYPES[key], (c,)) if c > 1 else (name, _PCD_TYPES[key]))
        dt = np.dtype(dtype)
        if len(raw) - pos < n * dt.itemsize:
            raise CloudError(
                f"{path}: PCD binary data truncated ({len(raw) - pos} of {n * dt.itemsize} bytes)"
            )
        rec = np.frombuffer(raw, dtype=dt, count=n, offset=pos)
        pts = np.column_stack([rec["x"], rec["y"], rec["z"]]).astype(np.float64)
    else:
        raise CloudError(f"{path}: PCD DATA {data_kind!r} not supported (use ascii or binary)")
    # NaN points are how PCD marks missing returns in organised clouds; they are not points.
    return ScanCloud(pts[np.isfinite(pts).all(axis=1)])


def _read_text(path: Path) -> ScanCloud:
    text = path.read_text(errors="replace")
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith(("#", "//"))]
    if not lines:
        raise CloudError(f"{path}: the cloud holds no points")
    split = re.compile(r"[,;\s]+")
    first = [t for t in split.split(lines[0].strip()) if t]
    names: list[str] | None = None
    try:
        [float(t) for t in first]
    except ValueError:
        names = [t.lower() for t in first]
        lines = lines[1:]
    if not lines:
        raise CloudError(f"{path}: the cloud holds no points")
    n_cols = len([t for t in split.split(lines[0].strip()) if t])
    if n_cols < 3:
        raise CloudError(f"{path}: {n_cols} columns per line, need at least x y z")
    named = names is not None and len(names) == n_cols and {"x", "y", "z"} <= set(names)
    try:
        # Without a header only x y z are read, so extra columns (intensity, ...) may vary per line.
        table = np.loadtxt(
            io.StringIO("\n".join(split.sub(" ", ln.strip()) for ln in lines)),
            ndmin=2,
            usecols=None if named else (0, 1, 2),
        )
    except ValueError as exc:
        raise CloudError(f"{path}: not a table of numbers ({exc})") from exc
    if named:
        col = {n: i for i, n in enumerate(names)}
        pts = table[:, [col["x"], col["y"], col["z"]]]
        pname = "pass" if "pass" in col else ("pass_id" if "pass_id" in col else None)
        if pname and "profile" in col and "point" in col:
            return organised_cloud(
                pts, table[:, col[pname]], table[:, col["profile"]], table[:, col["point"]]
            )
        return ScanCloud(pts)
    return ScanCloud(table[:, :3])


def _read_npz(path: Path) -> ScanCloud:
    with np.load(path, allow_pickle=False) as z:
        key = next((k for k in ("xyz_mm", "points_mm", "points", "xyz") if k in z.files), None)
        if key is None:
            raise CloudError(
                f"{path}: NPZ has none of the arrays xyz_mm, points_mm, points, xyz (has {z.files})"
            )
        pts = np.asarray(z[key], dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise CloudError(f"{path}: array {key!r} must be (n, 3), got {pts.shape}")
        for names in (ORGANISATION, ("pass_id", "profile", "point")):
            if all(k in z.files for k in names):
                return organised_cloud(pts, *(z[k] for k in names))
        return ScanCloud(pts)


_PLY_TYPES = {"f4": "float", "f8": "double", "i4": "int", "u4": "uint", "i2": "short", "u2": "ushort",
              "i1": "char", "u1": "uchar"}  # fmt: skip


def write_ply_vertices(path: str | Path, columns: dict[str, np.ndarray], comment: str = "") -> Path:
    """Binary little-endian PLY of one vertex element: one property per column, in order.

    columns: name -> (n,) array; each keeps its dtype (float32, float64, int32, uint16, ...).
    """
    path = Path(path)
    arrays = {name: np.asarray(a) for name, a in columns.items()}
    lengths = {len(a) for a in arrays.values()}
    if len(lengths) != 1:
        raise CloudError(f"{path}: PLY columns of different lengths {sorted(lengths)}")
    dtype = np.dtype([(name, a.dtype.newbyteorder("<")) for name, a in arrays.items()])
    rec = np.empty(lengths.pop(), dtype=dtype)
    props = ""
    for name, a in arrays.items():
        rec[name] = a
        props += f"property {_PLY_TYPES[a.dtype.str[1:]]} {name}\n"
    head = "ply\nformat binary_little_endian 1.0\n" + (f"comment {comment}\n" if comment else "")
    head += f"element vertex {len(rec)}\n{props}end_header\n"
    with path.open("wb") as f:
        f.write(head.encode("ascii"))
        f.write(memoryview(rec).cast("B"))  # the records' own bytes: no second copy of the cloud
    return path


def write_cloud_ply(
    cloud: ScanCloud,
    path: str | Path,
    *,
    extra: dict[str, np.ndarray] | None = None,
    comment: str = "cellctl scan cloud, mm",
) -> Path:
    """Write ``cloud`` as binary PLY, the one organised-PLY layout of the product: x, y, z float32,
    pass, profile, point int32 if organised, t_s float64 if known, then ``extra`` columns (each (n,),
    its own dtype) in order."""
    p = np.asarray(cloud.xyz_mm, dtype=np.float32)  # a float32 cloud as it is
    cols = {"x": p[:, 0], "y": p[:, 1], "z": p[:, 2]}
    if cloud.organised:
        cols |= {"pass": cloud.pass_id.astype(np.int32), "profile": cloud.profile_index.astype(np.int32),
                 "point": cloud.point_index.astype(np.int32)}  # fmt: skip
    if cloud.t_s is not None:
        cols["t_s"] = cloud.t_s.astype(np.float64)
    cols |= extra or {}
    return write_ply_vertices(path, cols, comment)


def write_cloud_npz(cloud: ScanCloud, path: str | Path) -> Path:
    """Write ``cloud`` as NPZ (``xyz_mm`` and, if organised, ``pass_id``, ``profile_index``,
    ``point_index``; ``t_s`` if known)."""
    path = Path(path)
    arrays = {"xyz_mm": cloud.xyz_mm}
    if cloud.organised:
        arrays.update(pass_id=cloud.pass_id, profile_index=cloud.profile_index, point_index=cloud.point_index)
    if cloud.t_s is not None:
        arrays["t_s"] = cloud.t_s
    with path.open("wb") as f:
        np.savez(f, **arrays)
    return path
