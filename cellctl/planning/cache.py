"""The plan cache: a plan for the same design, placement and settings is reused, never trusted.

A scan of the same plate at the same placement with the same cell settings plans the same passes;
planning them again costs seconds before anything moves (issue 22, item 2). :class:`PlanCache`
keeps plans on disk (the daemon's ``<data_dir>/plan-cache/``), one ``<key>.npz`` per key: the
plan's arrays as they are (float64, bit for bit: the segments' waypoints, orientations and joints
concatenated, the timed trajectory) and a small JSON header (version, key, placement, the figures
and each segment's kind, label, times and length), an uncompressed numpy archive whose members
carry a CRC-32 that is checked when read; the header is a pydantic model (:class:`EntryHeader`, no
unknown fields) validated on every read. The 6 m plate's plan (87 k trajectory samples) is
written in about 0.05 s and read in 0.02 s, where its JSON took 2-3 s (issue 42).

The key (:func:`plan_key`) is a SHA-256 over everything the plan depends on: the design's content
(its vertices and triangles, not its file name), the placement, every planner setting (the track's
too, when there is one), the options of the call (coverage prediction, EGM cycle) and
:data:`PLAN_CACHE_VERSION`, bumped whenever the planner's output for the same inputs changes.

A file on disk is never trusted: a hit is parsed, its key and placement must match, and its timed
trajectory passes the same safety-envelope check at the EGM cycle as a fresh plan
(:func:`~cellctl.planning.planner.check_plan_envelope`) against the *current* settings before it is
returned. An entry that is unreadable, of another version, for another key or outside the envelope
is ignored with a log line (``plan_cache_ignored`` and the reason: ``corrupt``, ``foreign`` (an
archive that is not an entry), ``stale``, another key, the envelope), removed, and the plate planned
again. The cache holds at most ``max_entries`` plans; the least recently used go first. Entries of
the JSON format (``<key>.json``, versions up to 7) are not read: they are removed when the cache
prunes.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import zipfile
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Literal

import numpy as np
import structlog
from pydantic import BaseModel, ConfigDict

from analysis.contracts.placement import Placement
from analysis.design.mesh import TriMesh
from cellctl.motion.trajectory import TimedTrajectory
from cellctl.planning.plan import CoverageReport, PlanInputError, PlanRefused, ScanPlan, Segment, SegmentKind
from cellctl.planning.planner import check_plan_envelope, plan_scan
from cellctl.planning.settings import PlannerSettings
from drivers.abb_egm.limits import EGM_CYCLE_S

__all__ = ["PLAN_CACHE_VERSION", "CachedPlan", "PlanCache", "plan_key"]

log = structlog.get_logger(__name__)

#: bump when the planner plans differently from the same inputs (or the stored plan's format changes)
PLAN_CACHE_VERSION = (
    # 2: the carriage holds when it can; 3: flying turnarounds; 4: the passes along either axis;
    # 5: timed with 80 % of the jerk limits (was 60 %); 6: the U-turn, links that turn the sensor
    # at rest as lines in joint space timed along the line, the start corner; 7: the closed-form
    # IK (joints within 3e-5 deg of the damped solver's), toppra's bound on every other grid point;
    # 8: a binary entry (npz arrays and a JSON header; the JSON entries of 7 are not read), toppra's
    # bound every 5th grid point on the sweeps; 9: the design surface's own bicubic evaluation (heights
    # within 2e-12 mm of FITPACK's), the header a validated model
    "cellctl.plan_cache/9+npz"
)
#: the file name's suffix of an entry; older formats' entries (JSON) are removed when the cache prunes
_SUFFIX = ".npz"
_OLD_SUFFIXES = (".json",)


def _plain(value: Any) -> Any:
    """A setting as JSON-ready numbers (arrays and tuples as lists, a track as its fields)."""
    if value is None or isinstance(value, bool | int | float | str):
        return value
    if isinstance(value, np.ndarray | tuple | list):
        return np.asarray(value, dtype=np.float64).tolist()
    if hasattr(value, "__dataclass_fields__"):
        return {f.name: _plain(getattr(value, f.name)) for f in fields(value)}
    raise PlanInputError(f"plan cache: cannot key a setting of type {type(value).__name__}")


def plan_key(
    design: TriMesh, placement: Placement, settings: PlannerSettings, *, with_coverage: bool, cycle_s: float
) -> str:
    """Hex SHA-256 of everything a plan depends on (see the module's docstring)."""
    h = hashlib.sha256()
    h.update(PLAN_CACHE_VERSION.encode())
    for arr in (design.vertices_mm, design.triangles):
        h.update(str(arr.shape).encode())
        h.update(np.ascontiguousarray(arr).tobytes())
    inputs = {
        "placement": placement.model_dump(mode="json"),
        "settings": {f.name: _plain(getattr(settings, f.name)) for f in fields(settings)},
        "with_coverage": bool(with_coverage),
        "cycle_s": float(cycle_s),
    }
    h.update(json.dumps(inputs, sort_keys=True).encode())
    return h.hexdigest()


@dataclass(frozen=True)
class CachedPlan:
    """A plan and where it came from: ``hit`` True when it was read from the cache."""

    plan: ScanPlan
    hit: bool
    key: str


class PlanCache:
    """Plans on disk under ``root`` (created private when missing), at most ``max_entries``."""

    def __init__(self, root: str | Path, *, max_entries: int = 32) -> None:
        if max_entries < 1:
            raise PlanInputError(f"plan cache: max_entries must be >= 1, got {max_entries}")
        self.root = Path(root)
        self.max_entries = max_entries
        self.root.mkdir(mode=0o700, parents=True, exist_ok=True)

    def path(self, key: str) -> Path:
        """The file of ``key``."""
        return self.root / f"{key}{_SUFFIX}"

    def load(
        self, key: str, placement: Placement, settings: PlannerSettings, *, cycle_s: float = EGM_CYCLE_S
    ) -> ScanPlan | None:
        """The cached plan of ``key`` after the envelope check against ``settings``; None on a miss
        (no entry, or one ignored and removed with a log line naming the reason)."""
        path = self.path(key)
        try:
            data = path.read_bytes()
        except FileNotFoundError:
            return None
        except OSError as exc:
            return self._ignore(key, f"unreadable: {exc}")
        try:
            raw, arrays = _read_entry(data)
            if raw.get("version") != PLAN_CACHE_VERSION:
                return self._ignore(
                    key, f"stale: version {raw.get('version')!r}, expected {PLAN_CACHE_VERSION!r}"
                )
            header = EntryHeader.model_validate(raw)
            if header.key != key:
                return self._ignore(key, "the entry is for another key")
            plan = plan_from_arrays(header.plan, arrays)
        except ForeignEntry as exc:
            return self._ignore(key, f"foreign: {exc}")
        except (ValueError, KeyError, TypeError, OSError, zipfile.BadZipFile) as exc:
            # PlanInputError, JSON and pydantic's ValidationError are ValueErrors; a bad CRC or a cut
            # archive BadZipFile
            return self._ignore(key, f"corrupt: {type(exc).__name__}: {_first_line(exc)}")
        if plan.placement.model_dump() != placement.model_dump():
            return self._ignore(key, "the entry's placement differs from the requested one")
        try:
            check_plan_envelope(plan.trajectory, plan.segments, settings, cycle_s)
        except PlanRefused as exc:
            return self._ignore(key, f"refused by the envelope of the current settings: {exc}")
        with contextlib.suppress(OSError):
            os.utime(path)  # recently used: pruned last
        return plan

    def store(self, key: str, plan: ScanPlan) -> None:
        """Write ``plan`` under ``key`` (atomically), then prune the oldest entries beyond the bound.
        A write that fails is logged and forgotten: the cache only saves time."""
        path = self.path(key)
        tmp = path.with_suffix(".tmp")
        try:
            meta, arrays = plan_to_arrays(plan)
            header = EntryHeader(version=PLAN_CACHE_VERSION, key=key, plan=meta)
            tmp.write_bytes(_entry_bytes(header.model_dump(mode="json"), arrays))
            os.replace(tmp, path)
        except OSError as exc:
            log.warning("plan_cache_write_failed", key=key[:12], error=str(exc))
            with contextlib.suppress(OSError):
                tmp.unlink()
            return
        self._prune()

    def plan(
        self,
        design: TriMesh,
        placement: Placement,
        settings: PlannerSettings,
        *,
        with_coverage: bool = True,
        cycle_s: float = EGM_CYCLE_S,
        store: bool = True,
    ) -> CachedPlan:
        """The cached plan for these inputs, or :func:`plan_scan`'s (then stored, unless ``store`` is
        False: the caller then writes it with :meth:`store` and the returned key when it has the time;
        the daemon does once the arm is at rest, not between the plan and the motion).

        Raises what :func:`plan_scan` raises (a refusal is not cached)."""
        key = plan_key(design, placement, settings, with_coverage=with_coverage, cycle_s=cycle_s)
        cached = self.load(key, placement, settings, cycle_s=cycle_s)
        if cached is not None:
            log.info("plan_cache_hit", key=key[:12])
            return CachedPlan(cached, True, key)
        plan = plan_scan(design, placement, settings, with_coverage=with_coverage, cycle_s=cycle_s)
        if store:
            self.store(key, plan)
        return CachedPlan(plan, False, key)

    def _ignore(self, key: str, reason: str) -> None:
        log.warning("plan_cache_ignored", key=key[:12], reason=reason)
        with contextlib.suppress(OSError):
            self.path(key).unlink()
        return None

    def _prune(self) -> None:
        for suffix in _OLD_SUFFIXES:  # an older format's entries: never read
            for p in self.root.glob(f"*{suffix}"):
                with contextlib.suppress(OSError):
                    p.unlink()
        entries = []
        for p in self.root.glob(f"*{_SUFFIX}"):
            with contextlib.suppress(OSError):
                entries.append((p.stat().st_mtime, p))
        entries.sort()
        for _, p in entries[: max(0, len(entries) - self.max_entries)]:
            with contextlib.suppress(OSError):
                p.unlink()


#: the arrays of an entry: the segments' (concatenated, in order) and the timed trajectory's
_ARRAYS = ("seg_pos_mm", "seg_R", "seg_q_deg", "t_s", "q_deg", "qd_deg_s", "qdd_deg_s2", "segment")


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class EntrySegment(_Strict):
    """One segment of a cached plan in the entry's header; its waypoints (``n`` rows) are in the
    arrays."""

    kind: SegmentKind
    label: str
    n: int
    solved: bool
    t_start_s: float
    duration_s: float
    length_mm: float
    flying: bool
    joint_line: bool


class EntryPlan(_Strict):
    """Everything of a cached plan that is not an array."""

    placement: Placement
    footprint_mm: tuple[float, float, float, float]
    coverage: CoverageReport
    figures: dict[
        Literal[
            "scan_speed_mm_s", "sweep_length_mm", "sweep_time_s", "scan_time_s", "sweep_ratio", "margin_mm",
            "scan_speed_deviation", "toppra_time_s",
        ],
        float,
    ]  # fmt: skip
    timings_s: dict[str, float]
    choices: dict[str, Any]
    segments: list[EntrySegment]


class EntryHeader(_Strict):
    """The JSON header of a cache entry (the ``header`` member of its npz), validated on every read."""

    version: str
    key: str
    plan: EntryPlan


def plan_to_arrays(plan: ScanPlan) -> tuple[EntryPlan, dict[str, np.ndarray]]:
    """``plan`` as its header part and its arrays (:data:`_ARRAYS`), float64 as they are."""
    segs = plan.segments
    axes = plan.trajectory.q_deg.shape[1]
    q = [s.q_deg if s.q_deg is not None else np.full((s.pos_mm.shape[0], axes), np.nan) for s in segs]
    meta = {
        "placement": plan.placement,
        "footprint_mm": [float(v) for v in plan.footprint_mm],
        "coverage": plan.coverage,
        "figures": {
            k: float(getattr(plan, k))
            for k in (
                "scan_speed_mm_s",
                "sweep_length_mm",
                "sweep_time_s",
                "scan_time_s",
                "sweep_ratio",
                "margin_mm",
                "scan_speed_deviation",
                "toppra_time_s",
            )
        },
        "timings_s": dict(plan.timings_s),
        "choices": plan.choices,
        "segments": [
            {
                "kind": s.kind,
                "label": s.label,
                "n": int(s.pos_mm.shape[0]),
                "solved": s.q_deg is not None,
                "t_start_s": s.t_start_s,
                "duration_s": s.duration_s,
                "length_mm": s.length_mm,
                "flying": s.flying,
                "joint_line": s.joint_line,
            }
            for s in segs
        ],
    }
    tr = plan.trajectory
    arrays = {
        "seg_pos_mm": np.concatenate([s.pos_mm for s in segs]),
        "seg_R": np.concatenate([s.R_base_sensor for s in segs]),
        "seg_q_deg": np.concatenate(q),
        "t_s": tr.t_s,
        "q_deg": tr.q_deg,
        "qd_deg_s": tr.qd_deg_s,
        "qdd_deg_s2": tr.qdd_deg_s2,
        "segment": tr.segment,
    }
    return EntryPlan.model_validate(meta), {k: np.ascontiguousarray(v) for k, v in arrays.items()}


def plan_from_arrays(meta: EntryPlan, arrays: dict[str, np.ndarray]) -> ScanPlan:
    """Inverse of :func:`plan_to_arrays`.

    Raises:
        PlanInputError: missing arrays, or shapes that do not fit the header or each other.
    """
    missing = [k for k in _ARRAYS if k not in arrays]
    if missing:
        raise PlanInputError(f"plan cache entry: arrays {missing} missing")
    pos, R, q = arrays["seg_pos_mm"], arrays["seg_R"], arrays["seg_q_deg"]
    t, qt = arrays["t_s"], arrays["q_deg"]
    n = sum(s.n for s in meta.segments)
    m = t.shape[0]
    axes = qt.shape[1] if qt.ndim == 2 else -1
    shapes_ok = (
        pos.shape == (n, 3)
        and R.shape == (n, 3, 3)
        and q.shape == (n, axes)
        and axes in (6, 7)
        and t.ndim == 1
        and qt.shape == (m, axes)
        and arrays["qd_deg_s"].shape == (m, axes)
        and arrays["qdd_deg_s2"].shape == (m, axes)
        and arrays["segment"].shape == (m,)
        and all(a.dtype == np.float64 for a in (pos, R, q, t, qt, arrays["qd_deg_s"], arrays["qdd_deg_s2"]))
        and arrays["segment"].dtype == np.int64
    )
    if not shapes_ok:
        raise PlanInputError("plan cache entry: the arrays' shapes or types do not fit the header")
    segments = []
    start = 0
    for s in meta.segments:
        k = slice(start, start + s.n)
        start = k.stop
        segments.append(
            Segment(
                kind=s.kind,
                label=s.label,
                pos_mm=pos[k],
                R_base_sensor=R[k],
                q_deg=q[k] if s.solved else None,
                t_start_s=s.t_start_s,
                duration_s=s.duration_s,
                length_mm=s.length_mm,
                flying=s.flying,
                joint_line=s.joint_line,
            )
        )
    return ScanPlan(
        placement=meta.placement,
        footprint_mm=meta.footprint_mm,
        segments=segments,
        trajectory=TimedTrajectory(
            t_s=t,
            q_deg=qt,
            qd_deg_s=arrays["qd_deg_s"],
            qdd_deg_s2=arrays["qdd_deg_s2"],
            segment=arrays["segment"],
        ),
        coverage=meta.coverage,
        timings_s=dict(meta.timings_s),
        choices=dict(meta.choices),
        **meta.figures,
    )


def _entry_bytes(header: dict[str, Any], arrays: dict[str, np.ndarray]) -> bytes:
    """An entry: an uncompressed npz of ``arrays`` and the JSON ``header`` as uint8 bytes."""
    buf = io.BytesIO()
    head = np.frombuffer(json.dumps(header, separators=(",", ":")).encode(), dtype=np.uint8)
    np.savez(buf, header=head, **arrays)
    return buf.getvalue()


def _read_entry(data: bytes) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """The header and arrays of an entry (no pickles; every member read whole, so its CRC-32 is
    checked). Raises ValueError, zipfile.BadZipFile or OSError on a damaged entry, :class:`ForeignEntry`
    on an archive that is not an entry."""
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    head = arrays.pop("header", None)
    if head is None or head.dtype != np.uint8 or head.ndim != 1:
        raise ForeignEntry(f"a numpy archive without a plan cache header (members {sorted(arrays)[:8]})")
    header = json.loads(head.tobytes().decode())
    if not isinstance(header, dict) or not isinstance(header.get("plan"), dict):
        raise ForeignEntry("the header is not a plan cache entry's")
    return header, arrays


class ForeignEntry(ValueError):
    """The file is a readable archive, but not a plan cache entry (no entry header)."""


def _first_line(exc: Exception) -> str:
    """An error's message cut to its first lines (pydantic lists every field it refused)."""
    text = str(exc)
    lines = text.splitlines()
    return text if len(lines) <= 3 else " ".join(lines[:3]) + " ..."
