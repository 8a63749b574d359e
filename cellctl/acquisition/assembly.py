"""Cloud assembly: stamped profiles + sensor poses -> organised base-frame points.

The scan keeps its organisation: one row per profile (with its pass id, exposure time, frame
index and a running profile index) and one column per point of the profile, so the analysis can
triangulate it as a grid. Invalid points (no return, or no robot pose at that time) stay in the grid
as NaN with ``valid`` False. All work is per batch on whole arrays.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import structlog

from analysis.cloud_io import ScanCloud
from cellctl.acquisition.poses import interpolate_poses, transform_profiles_within
from cellctl.acquisition.spill import SpillArray, release

log = structlog.get_logger(__name__)

#: |coordinate| beyond this (mm, base frame) is not a measurement: 100 m, far beyond any rail cell
MAX_ABS_MM = 1.0e5

#: storage dtypes of :meth:`AssembledScan.cloud_arrays` unless asked otherwise
CLOUD_DTYPES: dict[str, type] = {
    "xyz_mm": np.float32,
    "pass_id": np.int32,
    "profile_index": np.int64,
    "point_index": np.int32,
    "t_s": np.float64,
}
#: rows per block when the cloud's arrays are filled (x 500 points: 8 M points' temporaries at most)
_BLOCK_ROWS = 16384
#: a spilled scan's rows are taken out of memory each time this many bytes of ``xyz_mm`` were written
_RELEASE_BYTES = 32 << 20

__all__ = [
    "CLOUD_DTYPES",
    "AssembledBatch",
    "AssembledScan",
    "AssemblyError",
    "PassSchedule",
    "ScanBuilder",
    "assemble_batch",
]


class AssemblyError(ValueError):
    """Inputs to assembly disagree in shape or are out of order."""


class PassSchedule:
    """Pass intervals on the host time base: ``begin(pass_id, t_ns)`` ... ``end(t_ns)``.

    A profile belongs to the pass whose interval holds its exposure time, else to -1 (transit).
    An open pass (begun, not ended yet) extends to infinity.
    """

    def __init__(self) -> None:
        self._start_ns: list[int] = []
        self._end_ns: list[int] = []
        self._ids: list[int] = []

    def begin(self, pass_id: int, t_ns: int) -> None:
        """Open pass ``pass_id`` at ``t_ns`` (closes an open one there)."""
        if self._ids and self._end_ns[-1] == np.iinfo(np.int64).max:
            self._end_ns[-1] = t_ns
        if self._start_ns and t_ns < self._start_ns[-1]:
            raise AssemblyError(f"pass {pass_id} begins at {t_ns} ns, before the previous pass")
        self._start_ns.append(int(t_ns))
        self._end_ns.append(int(np.iinfo(np.int64).max))
        self._ids.append(int(pass_id))

    def end(self, t_ns: int) -> None:
        """Close the open pass at ``t_ns``."""
        if not self._ids or self._end_ns[-1] != np.iinfo(np.int64).max:
            raise AssemblyError("end of pass without an open pass")
        self._end_ns[-1] = int(t_ns)

    def assign(self, t_ns: np.ndarray) -> np.ndarray:
        """(n,) int64 times -> (n,) int32 pass ids (-1 outside every pass)."""
        t = np.asarray(t_ns, dtype=np.int64)
        if not self._ids:
            return np.full(t.shape, -1, dtype=np.int32)
        starts = np.asarray(self._start_ns, dtype=np.int64)
        ends = np.asarray(self._end_ns, dtype=np.int64)
        k = np.searchsorted(starts, t, side="right") - 1
        kk = np.clip(k, 0, len(starts) - 1)
        inside = (k >= 0) & (t < ends[kk])
        return np.where(inside, np.asarray(self._ids, dtype=np.int32)[kk], -1).astype(np.int32)


@dataclass(frozen=True, slots=True)
class AssembledBatch:
    """``n`` profiles of ``w`` points in the robot base frame.

    Attributes:
        profile_index: (n,) int64 running index of the profile in the scan.
        frame_index: (n,) uint64 sensor frame index.
        pass_id: (n,) int32 pass of each profile, -1 for transit.
        t_ns: (n,) int64 exposure time on the host time base, ns.
        xyz_mm: (n, w, 3) float32 base-frame points, mm; NaN where not valid.
        valid: (n, w) bool.
        sensor_pos_mm: (n, 3) float32 sensor origin at each exposure, base frame, mm (NaN without pose):
            the viewpoint of the profile, and what the time-offset calibration differentiates.
    """

    profile_index: np.ndarray
    frame_index: np.ndarray
    pass_id: np.ndarray
    t_ns: np.ndarray
    xyz_mm: np.ndarray
    valid: np.ndarray
    sensor_pos_mm: np.ndarray


def assemble_batch(
    *,
    x_mm: np.ndarray,
    z_mm: np.ndarray,
    valid: np.ndarray,
    frame_index: np.ndarray,
    t_ns: np.ndarray,
    sample_t_ns: np.ndarray,
    sample_T_base_sensor: np.ndarray,
    epoch_ns: int,
    pass_id: np.ndarray,
    first_profile_index: int,
    max_gap_ns: int | None = None,
) -> AssembledBatch:
    """Assemble one batch of profiles.

    Args:
        x_mm, z_mm: (n, w) sensor-frame profile coordinates, mm.
        valid: (n, w) bool, sensor returns.
        frame_index: (n,) sensor frame indices.
        t_ns: (n,) exposure times on the host base, ns (clock fit applied, latency removed).
        sample_t_ns: (m,) int64 robot sample times on the host base, ns.
        sample_T_base_sensor: (m, 3, 4) sensor pose at each sample (measured joints, FK, hand-eye), mm.
        epoch_ns: fixed float origin for the interpolation.
        pass_id: (n,) int32.
        first_profile_index: running index of the first profile.
        max_gap_ns: profiles between robot samples further apart than this get no pose (invalid).
    """
    n = len(t_ns)
    if x_mm.shape != z_mm.shape or valid.shape != x_mm.shape or x_mm.shape[0] != n:
        raise AssemblyError(
            f"x_mm {x_mm.shape}, z_mm {z_mm.shape}, valid {valid.shape}, t_ns ({n},) disagree"
        )
    # only the samples around this batch: same bracketing pairs, far less work than the whole history
    lo = max(int(np.searchsorted(sample_t_ns, t_ns.min(), side="right")) - 2, 0)
    hi = min(int(np.searchsorted(sample_t_ns, t_ns.max(), side="left")) + 2, len(sample_t_ns))
    if hi - lo < 2:
        lo, hi = max(0, hi - 2), max(hi, min(2, len(sample_t_ns)))
    T, inside = interpolate_poses(sample_t_ns[lo:hi], sample_T_base_sensor[lo:hi], t_ns, epoch_ns, max_gap_ns)
    all_inside = bool(inside.all())
    ok = valid if all_inside else valid & inside[:, None]
    # the source's z is NaN where it has no return; only profiles without a pose need masking here
    z = z_mm if all_inside else np.where(ok, z_mm, np.float32(np.nan))
    # A point this far from the robot base is not a measurement (a corrupted value upstream, seen on
    # fault-injected runs as 1e20-1e36 mm); it must not reach the analysis as a plate point.
    xyz, within = transform_profiles_within(T, x_mm, z, MAX_ABS_MM)
    absurd = ok & ~within
    if absurd.any():
        log.warning("absurd_points_dropped", points=int(absurd.sum()), first_profile=first_profile_index)
        ok = ok & ~absurd
        xyz[absurd] = np.nan
    return AssembledBatch(
        profile_index=np.arange(first_profile_index, first_profile_index + n, dtype=np.int64),
        frame_index=np.asarray(frame_index, dtype=np.uint64),
        pass_id=np.asarray(pass_id, dtype=np.int32),
        t_ns=np.asarray(t_ns, dtype=np.int64),
        xyz_mm=xyz,
        valid=ok,
        sensor_pos_mm=np.where(inside[:, None], T[:, :3, 3], np.nan).astype(np.float32),
    )


@dataclass(frozen=True, slots=True)
class AssembledScan:
    """The whole organised scan: the rows of every :class:`AssembledBatch`, concatenated.

    Attributes: as :class:`AssembledBatch` with ``n`` = profiles in the scan (``pass_id`` -1 marks
    transit rows: the daemon schedules by it). :meth:`cloud_arrays` / :meth:`scan_cloud` give the
    product's cloud (``analysis.cloud_io``'s vocabulary) that files and the analysis get.
    """

    profile_index: np.ndarray
    frame_index: np.ndarray
    pass_id: np.ndarray
    t_ns: np.ndarray
    xyz_mm: np.ndarray
    valid: np.ndarray
    sensor_pos_mm: np.ndarray

    @classmethod
    def concat(cls, batches: Sequence[AssembledBatch], width: int = 0) -> AssembledScan:
        """Concatenate batches (an empty scan of ``width`` points per profile if there are none)."""
        if not batches:
            return cls(
                np.empty(0, np.int64),
                np.empty(0, np.uint64),
                np.empty(0, np.int32),
                np.empty(0, np.int64),
                np.empty((0, width, 3), np.float32),
                np.empty((0, width), bool),
                np.empty((0, 3), np.float32),
            )
        return cls(*(np.concatenate([getattr(b, f) for b in batches]) for f in cls.__slots__))

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    @property
    def n_valid(self) -> int:
        """Number of valid points (counted block by block: a spilled scan's pages released)."""
        return int(self.valid_per_profile().sum())

    def points(self, column_step: int | np.ndarray = 1) -> dict[str, np.ndarray]:
        """Valid points flattened: ``xyz_mm`` (k, 3) float32, ``pass_id``, ``profile_index``,
        ``point_index`` (int32, column in the profile) and ``t_ns`` per point.

        column_step: keep every k-th column (0, k, 2k, ...) of each profile; an int for the whole
            scan or (n,) ints, one per profile. ``point_index`` is then the column divided by the
            profile's step, so the kept columns stay a dense grid (a sensor with fewer points).
        """
        step = np.asarray(column_step, dtype=np.int64)
        if step.ndim == 1 and step.size and step.shape == (len(self),) and step.min() == step.max():
            step = step[0]  # one step for every profile: the strided view below is 5x cheaper
        if step.ndim == 0:
            k = int(step)
            if k < 1:
                raise AssemblyError(f"column_step must be >= 1, got {k}")
            # a strided view: the selection costs one pass over the kept columns only
            r, c = np.nonzero(self.valid[:, ::k]) if k > 1 else np.nonzero(self.valid)
            col, point = c * k, c
        else:
            if step.shape != (len(self),):
                raise AssemblyError(f"column_step must be an int or ({len(self)},), got {step.shape}")
            if step.size and step.min() < 1:
                raise AssemblyError(f"column_step must be >= 1, got {int(step.min())}")
            w = self.valid.shape[1]
            kept = self.valid & (np.arange(w, dtype=np.int64)[None, :] % step[:, None] == 0)
            r, col = np.nonzero(kept)
            point = col // step[r]
        return {
            "xyz_mm": self.xyz_mm[r, col],
            "pass_id": self.pass_id[r],
            "profile_index": self.profile_index[r],
            "point_index": point.astype(np.int32),
            "t_ns": self.t_ns[r],
        }

    def _column_step(self, column_step: int | np.ndarray) -> np.ndarray:
        n = len(self)
        step = np.asarray(column_step, dtype=np.int64)
        if step.ndim == 1 and step.shape == (n,) and n and step.min() == step.max():
            step = step[0]  # one step for every profile: strided views, 5x cheaper
        if step.ndim == 1 and step.shape != (n,):
            raise AssemblyError(f"column_step must be an int or ({n},), got {step.shape}")
        if step.size and int(step.min()) < 1:
            raise AssemblyError(f"column_step must be >= 1, got {int(step.min())}")
        return step

    def _kept(self, lo: int, step: np.ndarray) -> np.ndarray:
        """Valid and kept points of rows ``lo`` .. ``lo + _BLOCK_ROWS``: (rows, kept columns) bool."""
        v = self.valid[lo : lo + _BLOCK_ROWS]
        if step.ndim == 0:
            k = int(step)
            return v[:, ::k] if k > 1 else v
        w = v.shape[1]
        s = step[lo : lo + _BLOCK_ROWS]
        return v & (np.arange(w, dtype=np.int32)[None, :] % s[:, None].astype(np.int32) == 0)

    def _block(
        self, lo: int, step: np.ndarray, t0: int, transit_apart: bool = False
    ) -> dict[str, np.ndarray]:
        """The cloud arrays (default dtypes) of rows ``lo`` .. ``lo + _BLOCK_ROWS``."""
        r, col = np.nonzero(self._kept(lo, step))
        if step.ndim == 0:
            point, col = col, col * int(step)
        else:
            point = col // step[lo : lo + _BLOCK_ROWS][r]
        rows = r + lo
        return {
            "xyz_mm": self.xyz_mm[rows, col],
            "pass_id": self.pass_id[rows] + 1 if transit_apart else np.maximum(self.pass_id[rows], 0),
            "profile_index": self.profile_index[rows],
            "point_index": point.astype(np.int32),
            "t_s": (self.t_ns[rows] - t0) * 1e-9,
        }

    def _check_fits(self, dt: dict[str, np.dtype | type]) -> None:
        n, w = len(self), self.valid.shape[1] if self.valid.ndim == 2 else 0
        for name, top in (("pass_id", int(self.pass_id.max()) + 1 if n else 0), ("point_index", max(w - 1, 0)),
                          ("profile_index", int(self.profile_index.max()) if n else 0)):  # fmt: skip
            kind = np.dtype(dt[name])
            if kind.kind in "iu" and top > np.iinfo(kind).max:
                raise AssemblyError(f"{name} {top} does not fit the cloud's {kind}")

    def _release_rows(self, lo: int) -> None:
        """Rows ``lo`` .. ``lo + _BLOCK_ROWS`` of a spilled scan out of memory (read: see
        :class:`ScanBuilder`); nothing for a scan in memory."""
        release(self.xyz_mm[lo : lo + _BLOCK_ROWS], self.valid[lo : lo + _BLOCK_ROWS])

    def valid_per_profile(self) -> np.ndarray:
        """(n,) int64 valid points of each profile, block of rows by block of rows."""
        out = np.empty(len(self), np.int64)
        for lo in range(0, len(self), _BLOCK_ROWS):
            out[lo : lo + _BLOCK_ROWS] = np.count_nonzero(self.valid[lo : lo + _BLOCK_ROWS], axis=1)
            self._release_rows(lo)
        return out

    def cloud_blocks(self, column_step: int | np.ndarray = 1) -> Iterator[dict[str, np.ndarray]]:
        """:meth:`cloud_arrays` block of rows by block of rows (times from the scan's first profile):
        what a file writer streams, a block's points in memory at a time."""
        step = self._column_step(column_step)
        t0 = int(self.t_ns.min()) if len(self) else 0
        for lo in range(0, len(self), _BLOCK_ROWS):
            block = self._block(lo, step, t0)
            self._release_rows(lo)
            yield block

    def cloud_arrays(
        self,
        column_step: int | np.ndarray = 1,
        t0_ns: int | None = None,
        dtypes: dict[str, np.dtype | type] | None = None,
        *,
        transit_apart: bool = False,
        out: Callable[[int], dict[str, np.ndarray]] | None = None,
    ) -> dict[str, np.ndarray]:
        """The valid points (thinned as in :meth:`points`) in the cloud vocabulary of
        :mod:`analysis.cloud_io`: ``xyz_mm`` float32, ``pass_id`` with transit filed under pass 0,
        ``profile_index``, ``point_index``, ``t_s`` (s from ``t0_ns``, by default this scan's first
        profile; a part of a scan gives its scan's).

        dtypes: the storage dtype of each array (default :data:`CLOUD_DTYPES`; the publication asks for
        the wire's u16/u32): the arrays are filled block of rows by block of rows at those dtypes, so a
        whole scan (a 6 m plate: 33 M published points of 170 M) costs its output and one block's
        temporaries, not int64 indices and times for every point. A value beyond the dtype's range
        raises :class:`AssemblyError`.

        transit_apart: the plan's passes numbered from 1 and the transit alone under pass 0 (the
        locate run's clouds, read pass by pass), instead of the scan's first pass sharing pass 0
        with the transit.

        out: given the number of points, the arrays to fill (for example views into an encoded
        message, :func:`cellctl.api.cloud_codec.allocate_cloud`: the points are then written once,
        where they go); None: new arrays at ``dtypes``."""
        dt = {**CLOUD_DTYPES, **(dtypes or {})}
        step = self._column_step(column_step)
        self._check_fits(dt)
        t0 = t0_ns if t0_ns is not None else int(self.t_ns.min()) if len(self) else 0
        blocks = range(0, len(self), _BLOCK_ROWS)
        counts = []
        for lo in blocks:
            counts.append(int(np.count_nonzero(self._kept(lo, step))))
            self._release_rows(lo)
        total = sum(counts)
        if out is None:
            arrays = {
                "xyz_mm": np.empty((total, 3), dt["xyz_mm"]),
                **{f: np.empty(total, dt[f]) for f in ("pass_id", "profile_index", "point_index", "t_s")},
            }
        else:
            arrays = out(total)
        at = 0
        for lo, c in zip(blocks, counts, strict=True):
            if c:
                for f, a in self._block(lo, step, t0, transit_apart).items():
                    arrays[f][at : at + c] = a
                self._release_rows(lo)
                at += c
        return arrays

    def scan_cloud(self, column_step: int | np.ndarray = 1, *, transit_apart: bool = False) -> ScanCloud:
        """:meth:`cloud_arrays` as the analysis' :class:`~analysis.cloud_io.ScanCloud`."""
        return ScanCloud(**self.cloud_arrays(column_step, transit_apart=transit_apart))

    def digest(self) -> str:
        """SHA-256 over every array's bytes: equal digests mean bit-for-bit equal clouds."""
        h = hashlib.sha256()
        for f in self.__slots__:
            a = np.ascontiguousarray(getattr(self, f))
            h.update(f.encode())
            h.update(str(a.shape).encode())
            h.update(a.tobytes())
        return h.hexdigest()


class ScanBuilder:
    """The whole scan's rows, appended batch by batch into one set of arrays (no list of batches to
    concatenate at the end: :meth:`scan` is a view, the scan's points exist once).

    A 6000 x 2000 mm plate is about 340 000 profiles of 500 points: 2.2 GB of ``xyz_mm`` + ``valid``
    (13 bytes a point). With ``spill_dir`` those two are :class:`~cellctl.acquisition.spill.SpillArray`
    s (an unlinked file beside the raw files, memory-mapped): rows written are taken out of the
    process' memory every :data:`_RELEASE_BYTES`, readers take them back a block at a time (and
    release them, :func:`~cellctl.acquisition.spill.release`), growing costs no copy, and what the
    scan holds in memory is its per-profile arrays (44 bytes a profile, 0.09 bytes a point). Without
    it (replays of small scans, tests) the arrays are in memory, sized from ``expected_profiles`` and
    grown by half again when a scan runs longer.

    Args:
        expected_profiles: rows to reserve (0: start small and grow).
        spill_dir: where the per-point arrays' file goes (a disk: the job's raw directory), or None.
    """

    _FIELDS = AssembledScan.__slots__
    #: the per-point arrays (the rest are per profile)
    _SPILLED = ("xyz_mm", "valid")

    def __init__(self, expected_profiles: int = 0, spill_dir: str | Path | None = None) -> None:
        self._reserve = max(int(expected_profiles), 0)
        self._spill_dir = spill_dir
        self._spills: dict[str, SpillArray] = {}
        self._arrays: dict[str, np.ndarray] | None = None
        self.n = 0
        self._released = 0  # rows below this were released after they were written
        self._ends: list[int] = []  # the row after each appended batch

    def _allocate(
        self, like: AssembledBatch, rows: int, old: dict[str, np.ndarray] | None = None
    ) -> dict[str, np.ndarray]:
        """Arrays of ``rows`` rows, the first :attr:`n` those of ``old`` (a spilled array grows in its
        file: nothing is copied). A spill that cannot grow (a full disk: the raw files stop the scan
        then) leaves that array in memory, logged, rather than failing the scan."""
        out = {}
        for f in self._FIELDS:
            a = getattr(like, f)
            if self._spill_dir is not None and f in self._SPILLED:
                try:
                    if f not in self._spills:
                        self._spills[f] = SpillArray(self._spill_dir, a.shape[1:], a.dtype, rows)
                    self._spills[f].reserve(rows)
                    out[f] = self._spills[f].array
                    continue
                except OSError as exc:
                    log.warning("scan_spill_failed", field=f, rows=rows, error=str(exc))
                    self._spill_dir = None
                    self._spills.pop(f, None)
            out[f] = np.empty((rows, *a.shape[1:]), a.dtype)
            if old is not None:
                out[f][: self.n] = old[f][: self.n]
        return out

    def append(self, batch: AssembledBatch) -> None:
        """Append one batch's rows (their width must be the scan's)."""
        k = len(batch.t_ns)
        if self._arrays is None:
            self._arrays = self._allocate(batch, max(self._reserve, k, 256))
        a = self._arrays
        if batch.xyz_mm.shape[1:] != a["xyz_mm"].shape[1:]:
            raise AssemblyError(
                f"batch of {batch.xyz_mm.shape[1]} points per profile in a scan of {a['xyz_mm'].shape[1]}"
            )
        cap = len(a["t_ns"])
        if self.n + k > cap:
            self._arrays = a = self._allocate(batch, max(self.n + k, cap + cap // 2), a)
        for f in self._FIELDS:
            a[f][self.n : self.n + k] = getattr(batch, f)
        self.n += k
        self._ends.append(self.n)
        if self._spills and (self.n - self._released) * a["xyz_mm"][0].nbytes >= _RELEASE_BYTES:
            release(*(a[f][self._released : self.n] for f in self._spills))
            self._released = self.n

    def batches_since(self, k: int) -> list[AssembledBatch]:
        """The batches appended after the first ``k``, in order, as views of the rows (no copy)."""
        if self._arrays is None:
            return []
        a = self._arrays
        starts = [0, *self._ends[:-1]]
        return [
            AssembledBatch(*(a[f][lo:hi] for f in self._FIELDS))
            for lo, hi in zip(starts[k:], self._ends[k:], strict=True)
        ]

    def scan(self, width: int = 0) -> AssembledScan:
        """The rows so far as an :class:`AssembledScan` of views (no copy; an empty scan of ``width``
        points per profile before the first batch)."""
        if self._arrays is None:
            return AssembledScan.concat([], width)
        if self._spills:
            release(*(self._arrays[f][self._released : self.n] for f in self._spills))
            self._released = self.n
        return AssembledScan(*(self._arrays[f][: self.n] for f in self._FIELDS))
