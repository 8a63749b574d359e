"""The plan cache: a plan for the same design, placement and settings is reused, never trusted.

A scan of the same plate at the same placement with the same cell settings plans the same passes;
planning them again costs seconds before anything moves (issue 22, item 2). :class:`PlanCache`
keeps plans on disk (the daemon's ``<data_dir>/plan-cache/``), one JSON file per key.

The key (:func:`plan_key`) is a SHA-256 over everything the plan depends on: the design's content
(its vertices and triangles, not its file name), the placement, every planner setting (the track's
too, when there is one), the options of the call (coverage prediction, EGM cycle) and
:data:`PLAN_CACHE_VERSION`, bumped whenever the planner's output for the same inputs changes.

A file on disk is never trusted: a hit is parsed, its key and placement must match, and its timed
trajectory passes the same safety-envelope check at the EGM cycle as a fresh plan
(:func:`~cellctl.planning.planner.check_plan_envelope`) against the *current* settings before it is
returned. An entry that is unreadable, of another version, for another key or outside the envelope
is ignored with a log line (``plan_cache_ignored`` and the reason), removed, and the plate planned
again. The cache holds at most ``max_entries`` plans; the least recently used go first.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
import structlog

from analysis.mesh import TriMesh
from analysis.placement import Placement
from cellctl.planning.plan import PlanInputError, PlanRefused, ScanPlan
from cellctl.planning.planner import check_plan_envelope, plan_scan
from cellctl.planning.settings import PlannerSettings

__all__ = ["PLAN_CACHE_VERSION", "CachedPlan", "PlanCache", "plan_key"]

log = structlog.get_logger(__name__)

#: bump when the planner plans differently from the same inputs (or the stored plan's format changes)
PLAN_CACHE_VERSION = (
    # 2: the carriage holds when it can; 3: flying turnarounds; 4: the passes along either axis;
    # 5: timed with 80 % of the jerk limits (was 60 %); 6: the U-turn, links that turn the sensor
    # at rest as lines in joint space timed along the line, the start corner; 7: the closed-form
    # IK (joints within 3e-5 deg of the damped solver's), toppra's bound on every other grid point
    "cellctl.plan_cache/7+cellctl.scan_plan/1"
)


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
        return self.root / f"{key}.json"

    def load(
        self, key: str, placement: Placement, settings: PlannerSettings, *, cycle_s: float = 0.004032
    ) -> ScanPlan | None:
        """The cached plan of ``key`` after the envelope check against ``settings``; None on a miss
        (no entry, or one ignored and removed with a log line naming the reason)."""
        path = self.path(key)
        try:
            text = path.read_text()
        except FileNotFoundError:
            return None
        except OSError as exc:
            return self._ignore(key, f"unreadable: {exc}")
        try:
            doc = json.loads(text)
            if not isinstance(doc, dict) or doc.get("version") != PLAN_CACHE_VERSION:
                version = doc.get("version") if isinstance(doc, dict) else None
                return self._ignore(key, f"stale: version {version!r}, expected {PLAN_CACHE_VERSION!r}")
            if doc.get("key") != key:
                return self._ignore(key, "the entry is for another key")
            plan = ScanPlan.from_json(json.dumps(doc["plan"]))
        except (ValueError, KeyError, TypeError) as exc:  # PlanInputError and JSON errors are ValueErrors
            return self._ignore(key, f"corrupt: {exc}")
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
            doc = {"version": PLAN_CACHE_VERSION, "key": key, "plan": plan.to_dict()}
            tmp.write_text(json.dumps(doc, separators=(",", ":")))
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
        cycle_s: float = 0.004032,
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
        entries = []
        for p in self.root.glob("*.json"):
            with contextlib.suppress(OSError):
                entries.append((p.stat().st_mtime, p))
        entries.sort()
        for _, p in entries[: max(0, len(entries) - self.max_entries)]:
            with contextlib.suppress(OSError):
                p.unlink()
