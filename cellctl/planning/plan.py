"""The scan plan: what the planner hands to the executor, the daemon and the ``cellctl plan`` command.

A :class:`ScanPlan` is plain data (numpy arrays and numbers) and round-trips through JSON
(:meth:`ScanPlan.to_json` / :meth:`ScanPlan.from_json`). Frames: ``base`` is the robot base frame
(mm, z up), ``plate`` the design frame of the plate (see ``analysis.design.plates``), ``sensor`` the line
laser's frame (rays along +z, the laser line along x, the pass along +/-y).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from analysis.contracts.placement import Placement
from cellctl.motion.trajectory import TimedTrajectory

__all__ = [
    "PASS_AXES",
    "SEGMENT_KINDS",
    "CoverageReport",
    "PlanInputError",
    "PlanRefused",
    "ScanPlan",
    "Segment",
    "pose_matrix",
    "rotation_angle_deg",
    "slerp_frames",
]

SegmentKind = Literal["approach", "scan", "edge", "link", "retract"]
SEGMENT_KINDS: tuple[str, ...] = ("approach", "scan", "edge", "link", "retract")
#: segments during which the sensor records (constant TCP speed)
SWEEP_KINDS: tuple[str, ...] = ("scan", "edge")
#: the footprint axis the raster passes run along (``PlannerSettings.pass_axis`` adds "fastest")
PASS_AXES: tuple[str, ...] = ("longer", "shorter")


class PlanInputError(ValueError):
    """Input the planner cannot use (bad placement, empty design, inconsistent settings); names the field."""


class PlanRefused(Exception):
    """The plate cannot be scanned with this cell: the reason names the pass, the point and the limit.

    Attributes:
        reason: one readable sentence.
        pass_label: e.g. ``"scan 3"``, ``"edge 1"``, ``"link 4"`` (None when not tied to a pass).
        point_index: waypoint index inside that pass (None when not tied to a point).
        limit: the limit that was hit, e.g. ``"joint_3 upper 73.0 deg"``, ``"reach"``, ``"depth range"``.
        pos_mm: (3,) base-frame sensor position of the offending point, or None.
    """

    def __init__(
        self,
        reason: str,
        *,
        pass_label: str | None = None,
        point_index: int | None = None,
        limit: str | None = None,
        pos_mm: np.ndarray | None = None,
    ) -> None:
        self.reason = reason
        self.pass_label = pass_label
        self.point_index = point_index
        self.limit = limit
        self.pos_mm = None if pos_mm is None else np.asarray(pos_mm, dtype=np.float64).copy()
        where = ""
        if pass_label is not None:
            where = f"{pass_label}" + (f", point {point_index}" if point_index is not None else "") + ": "
        super().__init__(where + reason + (f" [limit: {limit}]" if limit else ""))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description of the refusal."""
        return {
            "reason": self.reason,
            "pass": self.pass_label,
            "point": self.point_index,
            "limit": self.limit,
            "pos_mm": None if self.pos_mm is None else self.pos_mm.round(3).tolist(),
            "message": str(self),
        }


def pose_matrix(pos_mm: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Stack positions (n, 3) mm and rotations (n, 3, 3) into transforms (n, 4, 4)."""
    n = pos_mm.shape[0]
    T = np.zeros((n, 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = pos_mm
    T[:, 3, 3] = 1.0
    return T


def slerp_frames(R0: np.ndarray, R1: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Rotations (m, 3, 3) on the geodesic from R0 to R1 at fractions ``u`` (m,)."""
    dR = R0.T @ R1
    angle = float(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1.0, 1.0)))
    if angle < 1e-9:
        return np.broadcast_to(R0, (u.size, 3, 3)).copy()
    if np.pi - angle < 1e-6:
        # half turn: the axis is the eigenvector of dR for eigenvalue 1
        w, vecs = np.linalg.eigh(dR + dR.T)
        axis = vecs[:, np.argmax(w)]
    else:
        axis = np.array([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]]) / (2 * np.sin(angle))
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    th = u * angle
    Rs = (
        np.eye(3)[None]
        + np.sin(th)[:, None, None] * K[None]
        + (1 - np.cos(th))[:, None, None] * (K @ K)[None]
    )
    return R0[None] @ Rs


def rotation_angle_deg(R0: np.ndarray, R1: np.ndarray) -> float:
    """The angle (deg) of the rotation taking orientation ``R0`` (3, 3) to ``R1``."""
    return float(np.rad2deg(np.arccos(np.clip((np.trace(R0.T @ R1) - 1) / 2, -1.0, 1.0))))


@dataclass
class Segment:
    """One piece of the plan, in execution order.

    kind: approach, scan (raster pass), edge (edge pass), link (between passes), retract.
    label: e.g. ``"scan 3"`` (1-based pass numbers), used in refusals and progress events.
    pos_mm: (n, 3) sensor origin waypoints, base frame (the world frame with a track), mm.
    R_base_sensor: (n, 3, 3) sensor orientations, base frame (world frame with a track; the base
        keeps the world's orientation, so the two agree).
    q_deg: (n, 6) joint configurations (filled by the joint path), deg; with a track (n, 7)
        ``axes_mm_deg``: the track position in mm, then the joints.
    t_start_s / duration_s: when the segment runs in the timed trajectory (filled by the timing).
    length_mm: path length of the sensor origin.
    flying: a turnaround joined to the passes before and after it at speed (continuous direction
        and zero curvature at both ends): the timing runs the three as one path without stopping.
    joint_line: a link at rest at both ends whose joints run on a line in joint space (lifted at its
        middle): the timing parameterises it by the joints' progress along that line, not by the
        sensor's path, so its time law is the line's own (the slowest axis at its limits).
    """

    kind: str
    label: str
    pos_mm: np.ndarray
    R_base_sensor: np.ndarray
    q_deg: np.ndarray | None = None
    t_start_s: float = 0.0
    duration_s: float = 0.0
    length_mm: float = 0.0
    flying: bool = False
    joint_line: bool = False

    def __post_init__(self) -> None:
        if self.kind not in SEGMENT_KINDS:
            raise PlanInputError(f"segment.kind: {self.kind!r} is not one of {SEGMENT_KINDS}")
        if self.length_mm == 0.0 and self.pos_mm.shape[0] > 1:
            self.length_mm = float(np.linalg.norm(np.diff(self.pos_mm, axis=0), axis=1).sum())

    @property
    def is_sweep(self) -> bool:
        """True for segments during which the sensor records."""
        return self.kind in SWEEP_KINDS


@dataclass
class CoverageReport:
    """Predicted coverage of the design's top surface by the plan (ray cast of the laser fans).

    fraction: seen cells / surface cells at the nominal placement.
    worst_fraction: the smallest fraction over the placement-uncertainty corners (shift and rotation).
    cell_mm: size of the square cells the footprint is divided into.
    profiles / rays: how many simulated profiles and rays were cast.
    """

    fraction: float
    worst_fraction: float
    cells_total: int
    cells_seen: int
    cell_mm: float
    profiles: int
    rays: int

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict."""
        return dict(self.__dict__)


@dataclass
class ScanPlan:
    """A complete, timed scan plan for one plate placement.

    scan_speed_mm_s: TCP speed on sweep segments. sweep_length_mm: total length of the sweep
    segments. sweep_time_s = sweep_length_mm / scan_speed_mm_s. scan_time_s: the whole timed
    trajectory, approach to retract. sweep_ratio = scan_time_s / sweep_time_s.
    """

    placement: Placement
    footprint_mm: tuple[float, float, float, float]
    segments: list[Segment]
    trajectory: TimedTrajectory
    coverage: CoverageReport
    scan_speed_mm_s: float
    sweep_length_mm: float
    sweep_time_s: float
    scan_time_s: float
    sweep_ratio: float
    margin_mm: float
    scan_speed_deviation: float
    toppra_time_s: float = 0.0
    timings_s: dict[str, float] = field(default_factory=dict)
    #: what the planner chose where it had a choice: with a track, ``track`` (``{"mode": "hold",
    #: "hold_mm": ...}`` or ``{"mode": "follow", "lead_mm": ...}``); ``edge_tilt_deg`` for edge passes
    #: tilted less than the setting to stay in reach (by label)
    choices: dict[str, Any] = field(default_factory=dict)

    @property
    def passes(self) -> list[Segment]:
        """The sweep segments (raster and edge passes), in execution order."""
        return [s for s in self.segments if s.is_sweep]

    def pass_times(self) -> list[dict[str, Any]]:
        """Per pass, in execution order: its label, when it starts, how long it runs (s), and
        ``transition_s``, the planned time from the previous pass's end to its start (the links and
        turnarounds between them; 0 for the first pass, which the approach leads to)."""
        out: list[dict[str, Any]] = []
        between = 0.0
        for seg in self.segments:
            if seg.is_sweep:
                out.append(
                    {
                        "label": seg.label,
                        "t_start_s": round(seg.t_start_s, 3),
                        "duration_s": round(seg.duration_s, 3),
                        "transition_s": round(between if out else 0.0, 3),
                    }
                )
                between = 0.0
            elif seg.kind == "link":
                between += seg.duration_s
        return out

    def time_parts_s(self) -> dict[str, float]:
        """The planned scan time in parts (s): ``approach_s``, ``sweep_s`` (on the passes, ramps
        included), ``transitions_s`` (links and turnarounds between passes) and ``retract_s``; they
        add up to ``scan_time_s`` (within one trajectory sample at each segment joint)."""
        parts = {"approach_s": 0.0, "sweep_s": 0.0, "transitions_s": 0.0, "retract_s": 0.0}
        name = {"approach": "approach_s", "link": "transitions_s", "retract": "retract_s"}
        for seg in self.segments:
            parts["sweep_s" if seg.is_sweep else name[seg.kind]] += seg.duration_s
        return parts

    def summary(self) -> dict[str, Any]:
        """A short JSON-ready summary (what ``cellctl plan`` prints)."""
        return {
            "passes": sum(1 for s in self.segments if s.kind == "scan"),
            "edge_passes": sum(1 for s in self.segments if s.kind == "edge"),
            "coverage": round(self.coverage.fraction, 5),
            "coverage_worst": round(self.coverage.worst_fraction, 5),
            "scan_speed_mm_s": round(self.scan_speed_mm_s, 3),
            "scan_speed_deviation": round(self.scan_speed_deviation, 5),
            "toppra_time_s": round(self.toppra_time_s, 3),
            "sweep_length_mm": round(self.sweep_length_mm, 1),
            "sweep_time_s": round(self.sweep_time_s, 3),
            "scan_time_s": round(self.scan_time_s, 3),
            "sweep_ratio": round(self.sweep_ratio, 4),
            **{k: round(v, 3) for k, v in self.time_parts_s().items()},
            "pass_times": self.pass_times(),
            "margin_mm": round(self.margin_mm, 2),
            "timings_s": {k: round(v, 4) for k, v in self.timings_s.items()},
            "choices": self.choices,
        }

    def to_dict(self) -> dict[str, Any]:
        """Everything, as plain lists and numbers."""
        tr = self.trajectory
        return {
            "format": "cellctl.scan_plan/1",
            "placement": self.placement.model_dump(),
            "footprint_mm": list(self.footprint_mm),
            "summary": self.summary(),
            "coverage": self.coverage.to_dict(),
            "segments": [
                {
                    "kind": s.kind,
                    "label": s.label,
                    "t_start_s": s.t_start_s,
                    "duration_s": s.duration_s,
                    "length_mm": s.length_mm,
                    "pos_mm": s.pos_mm.round(4).tolist(),
                    "R_base_sensor": s.R_base_sensor.round(9).tolist(),
                    "q_deg": None if s.q_deg is None else s.q_deg.round(6).tolist(),
                    "flying": s.flying,
                    "joint_line": s.joint_line,
                }
                for s in self.segments
            ],
            "trajectory": {
                "t_s": tr.t_s.round(6).tolist(),
                "q_deg": tr.q_deg.round(6).tolist(),
                "qd_deg_s": tr.qd_deg_s.round(6).tolist(),
                "qdd_deg_s2": tr.qdd_deg_s2.round(5).tolist(),
                "segment": tr.segment.tolist(),
            },
        }

    def to_json(self, path: str | Path | None = None) -> str:
        """Serialise to JSON; writes ``path`` when given. Returns the text."""
        text = json.dumps(self.to_dict(), separators=(",", ":"))
        if path is not None:
            Path(path).write_text(text)
        return text

    @classmethod
    def from_json(cls, text_or_path: str | Path) -> ScanPlan:
        """Inverse of :meth:`to_json` (a JSON string or a file path)."""
        text = str(text_or_path)
        if not text.lstrip().startswith("{"):
            text = Path(text_or_path).read_text()
        try:
            d = json.loads(text)
            if d.get("format") != "cellctl.scan_plan/1":
                raise PlanInputError(f"format: expected 'cellctl.scan_plan/1', got {d.get('format')!r}")
            segs = [
                Segment(
                    kind=s["kind"],
                    label=s["label"],
                    pos_mm=np.asarray(s["pos_mm"], dtype=np.float64).reshape(-1, 3),
                    R_base_sensor=np.asarray(s["R_base_sensor"], dtype=np.float64).reshape(-1, 3, 3),
                    q_deg=None if s["q_deg"] is None else np.asarray(s["q_deg"], dtype=np.float64),
                    t_start_s=float(s["t_start_s"]),
                    duration_s=float(s["duration_s"]),
                    length_mm=float(s["length_mm"]),
                    flying=bool(s.get("flying", False)),
                    joint_line=bool(s.get("joint_line", False)),
                )
                for s in d["segments"]
            ]
            tr = d["trajectory"]
            n_t = len(tr["t_s"])
            sm = d["summary"]
            return cls(
                placement=_placement(d["placement"]),
                footprint_mm=tuple(d["footprint_mm"]),
                segments=segs,
                trajectory=TimedTrajectory(
                    t_s=np.asarray(tr["t_s"], dtype=np.float64),
                    q_deg=_samples(tr["q_deg"], n_t),
                    qd_deg_s=_samples(tr["qd_deg_s"], n_t),
                    qdd_deg_s2=_samples(tr["qdd_deg_s2"], n_t),
                    segment=np.asarray(tr["segment"], dtype=np.int64),
                ),
                coverage=CoverageReport(**d["coverage"]),
                scan_speed_mm_s=float(sm["scan_speed_mm_s"]),
                sweep_length_mm=float(sm["sweep_length_mm"]),
                sweep_time_s=float(sm["sweep_time_s"]),
                scan_time_s=float(sm["scan_time_s"]),
                sweep_ratio=float(sm["sweep_ratio"]),
                margin_mm=float(sm["margin_mm"]),
                scan_speed_deviation=float(sm["scan_speed_deviation"]),
                toppra_time_s=float(sm.get("toppra_time_s", 0.0)),
                timings_s=dict(sm.get("timings_s", {})),
                choices=dict(sm.get("choices", {})),
            )
        except (KeyError, TypeError, ValueError) as exc:
            if isinstance(exc, PlanInputError):
                raise
            raise PlanInputError(f"not a scan plan: {exc}") from exc


def _samples(rows: Any, n_t: int) -> np.ndarray:
    """(n_t, axes) trajectory samples: 6 joints, or with a track 7 axes (track mm, then joints)."""
    a = np.asarray(rows, dtype=np.float64)
    if a.ndim != 2 or a.shape[0] != n_t or a.shape[1] not in (6, 7):
        raise PlanInputError(f"trajectory: expected ({n_t}, 6 or 7) samples, got shape {a.shape}")
    return a


def _placement(d: dict[str, Any]) -> Placement:
    """A stored plan's placement; plans written before the one Placement type held x/y/z/angle."""
    if "angle_deg" in d:
        return Placement.on_bed(d["x_mm"], d["y_mm"], d["angle_deg"], z_mm=d["z_mm"])
    return Placement.model_validate(d)
