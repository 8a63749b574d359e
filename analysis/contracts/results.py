"""A results directory's two data files, read and written in one place.

``report.json`` is a :class:`~analysis.contracts.job.Report`; :func:`read_report` is its one reader (the report
renderer, the plate history, the HMI, the demo and ``cellctl`` read it through here). ``results.npz``
holds the arrays the plots are drawn from; :class:`ResultsArrays` is its layout, written by
:func:`analysis.pipeline.write_results` (:meth:`ResultsArrays.save`) and read by the report renderer
and the HMI's map (:func:`read_results_arrays`).

Which ``report.json`` files load: every one the pipeline has written since its first version
(2026-11-22; every key any version wrote is a field of the schema). The report's shape has only
grown, each new field with a default: the reports of before the schema (before 2026-12-01, commit
51d72ca: no ``inputs.placement``, ``design``, ``template_fit``, ``registration.rest_surface``,
``lines[].line_fit``), of the schema's first version, of the CAD and moulded-side reports
(``design``), of the template fits (``template_fit``, ``template_fit_compare``, ``rest_surface``,
``line_fit``), of the locate run (``inputs.placement_found``) and of partial scans
(``coverage.partial``, ``coverage.lines_not_scanned``). A line without a ``name`` (a report written
by hand: the pipeline always names its lines) gets the one its family and index give (``T3``), as
the renderer's hand check did. A field the schema does not know is refused, as is a missing one the
schema requires: the error names the file and the field (``report.json: lines[1].zmax_mm: ...``).

This module imports no plotting library: the HMI and the daemon read through it without matplotlib.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import ValidationError

from analysis.contracts.job import Report

__all__ = [
    "LineSeries",
    "ReportError",
    "ResultsArrays",
    "parse_report",
    "read_report",
    "read_results_arrays",
    "write_report_json",
]


class ReportError(ValueError):
    """A results directory's file that cannot be read: missing, not JSON or npz, a missing or unknown
    field, a wrong value or array. The message names the file and the field
    (``report.json: lines[3].zmax_mm: ...``)."""


def _where(loc: tuple[Any, ...]) -> str:
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or "(top level)"


def parse_report(obj: Any, name: str = "report.json") -> Report:
    """A parsed ``report.json`` (any JSON value) as a :class:`Report`; :class:`ReportError` naming the
    first wrong field when it is not one (``name``: the file, for the message)."""
    if isinstance(obj, Report):
        return obj
    if not isinstance(obj, dict):
        raise ReportError(f"{name}: expected an object at the top level, got {type(obj).__name__}")
    try:
        # strict, as JSON: a number written as a string, or true for a number, is not one
        return Report.model_validate_json(json.dumps(obj), strict=True)
    except ValidationError as exc:
        first = exc.errors(include_url=False)[0]
        more = exc.error_count() - 1
        raise ReportError(
            f"{name}: {_where(tuple(first['loc']))}: {first['msg']}" + (f" (and {more} more)" if more else "")
        ) from None


def _read_json_text(path: Path) -> Any:
    return json.loads(path.read_text(encoding="utf-8"))


def read_report(path: str | Path, load: Callable[[Path], Any] = _read_json_text) -> Report:
    """Read ``report.json`` at ``path`` (a file, or a results directory holding one) as a :class:`Report`.

    ``load``: how the file is parsed (default: the whole file as JSON); the daemon passes its guarded
    reader (:func:`cellctl.jobstore.records.read_json_file`: size, depth and file-type limits), whose
    errors it handles itself. Raises :class:`ReportError` for a missing file, text that is not
    JSON, or a document that is not a report (naming the field).
    """
    p = Path(path)
    if p.is_dir():
        p = p / "report.json"
    try:
        obj = load(p)
    except FileNotFoundError:
        raise ReportError(f"{p}: missing (is this a results directory?)") from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ReportError(f"{p}: not valid JSON: {exc}") from None
    return parse_report(obj, p.name)


def write_report_json(report: Report, path: str | Path) -> Path:
    """``report.json`` written atomically (a temporary file renamed: its presence marks a complete
    results directory). NaN or infinity in a figure raise ValueError: JSON has none."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(report.model_dump(mode="json"), indent=2, allow_nan=False), encoding="utf-8")
    tmp.replace(path)
    return path


@dataclass(frozen=True)
class LineSeries:
    """One detection line's sampled sections (all (m,) float64, mm; NaN where a surface has no data).

    s_mm: position along the line from its start; design_z_mm, measured_z_mm: section heights;
    deviation_mm: d = design - measured.
    """

    s_mm: np.ndarray
    design_z_mm: np.ndarray
    measured_z_mm: np.ndarray
    deviation_mm: np.ndarray

    def decimated(self, max_samples: int) -> LineSeries:
        """The series cut to at most ``max_samples`` samples for a plot, keeping what the eye reads.

        The samples are split into equal bins; each bin keeps its lowest and its highest deviation
        (so the envelope of the curve, and the line's Zmax, survive any decimation) and, when it
        holds a sample without data, its first such sample (so a gap in the scan stays a gap). The
        first and last samples are always kept: the plot's range is the line's. The heights are
        taken at the same samples. A series within the budget is returned as it is.
        """
        n = len(self.s_mm)
        if max_samples < 5:
            raise ValueError(f"max_samples must be at least 5, got {max_samples}")
        if n <= max_samples:
            return self
        bins = (max_samples - 2) // 3
        dev = np.asarray(self.deviation_mm, dtype=np.float64)
        seg = np.arange(n) * bins // n  # the bin of each sample: equal bins, in order
        starts = np.searchsorted(seg, np.arange(bins))
        nan = np.isnan(dev)
        lo = np.lexsort((np.where(nan, np.inf, dev), seg))[starts]
        hi = np.lexsort((np.where(nan, np.inf, -dev), seg))[starts]
        gaps = np.flatnonzero(nan)
        first_gap = gaps[np.unique(seg[gaps], return_index=True)[1]]
        idx = np.unique(np.concatenate([[0, n - 1], lo, hi, first_gap]))
        return LineSeries(*(getattr(self, name)[idx] for name in _SERIES))


_SERIES = ("s_mm", "design_z_mm", "measured_z_mm", "deviation_mm")


@dataclass(frozen=True)
class ResultsArrays:
    """``results.npz``: the arrays the report's plots and the HMI's map are drawn from.

    plate_xy_mm: (n, 2) positions from the reference corner (plate frame, mm); plate_deviation_mm:
    (n,) their deviation d (mm); plate_size_mm: (2,) length, width (mm); lines: the sections of the
    report's lines in report order (stored as ``line{k}_s_mm``, ``line{k}_design_z_mm``,
    ``line{k}_measured_z_mm``, ``line{k}_deviation_mm``; None where a line has none); holes_xy_mm:
    (h, 2) centres of the 5 mm design cells the scan did not see (absent from the earliest files:
    read as none).
    """

    plate_xy_mm: np.ndarray
    plate_deviation_mm: np.ndarray
    plate_size_mm: np.ndarray
    lines: list[LineSeries | None]
    holes_xy_mm: np.ndarray

    def save(self, path: str | Path) -> Path:
        """Write the arrays (uncompressed: zlib took 0.2 s of the time to the report for 2 MB saved
        beside cloud.ply's 37). The map's arrays are stored as float32, the sections as given."""
        arrays: dict[str, np.ndarray] = {
            "plate_xy_mm": np.asarray(self.plate_xy_mm, dtype=np.float32).reshape(-1, 2),
            "plate_deviation_mm": np.asarray(self.plate_deviation_mm, dtype=np.float32),
            "plate_size_mm": np.asarray(self.plate_size_mm, dtype=np.float64),
            "coverage_holes_xy_mm": np.asarray(self.holes_xy_mm, dtype=np.float32).reshape(-1, 2),
        }
        for k, series in enumerate(self.lines):
            if series is not None:
                for name in _SERIES:
                    arrays[f"line{k}_{name}"] = getattr(series, name)
        path = Path(path)
        np.savez(path, **arrays)
        return path


def _array(z: Any, key: str, ndim: int, cols: int | None = None) -> np.ndarray:
    if key not in z.files:
        raise ReportError(f"results.npz: {key}: array is missing")
    a = np.asarray(z[key], dtype=np.float64)
    if a.ndim != ndim or (cols is not None and a.shape[1] != cols):
        want = f"(n, {cols})" if cols else "(n,)"
        raise ReportError(f"results.npz: {key}: expected shape {want}, got {a.shape}")
    return a


def read_results_arrays(path: str | Path, n_lines: int | None = None) -> ResultsArrays:
    """Read and check ``results.npz`` (a file, or a results directory holding one).

    n_lines: the report's line count (a line without sections reads as None); None: the lines stored,
    ``line0`` up to the first missing one. Raises :class:`ReportError` naming the array at fault.
    """
    p = Path(path)
    if p.is_dir():
        p = p / "results.npz"
    try:
        z = np.load(p, allow_pickle=False)
    except FileNotFoundError:
        raise ReportError(f"{p}: missing") from None
    except (OSError, ValueError) as exc:
        raise ReportError(f"{p}: not a readable npz file: {exc}") from None
    with z:
        xy = _array(z, "plate_xy_mm", 2, 2)
        dev = _array(z, "plate_deviation_mm", 1)
        if len(dev) != len(xy):
            raise ReportError(
                f"results.npz: plate_deviation_mm: {len(dev)} values for {len(xy)} plate_xy_mm positions"
            )
        size = _array(z, "plate_size_mm", 1)
        if size.shape != (2,) or not np.all(np.isfinite(size)) or np.any(size <= 0):
            raise ReportError(
                f"results.npz: plate_size_mm: expected (length, width) > 0, got {size.tolist()}"
            )
        series: list[LineSeries | None] = []
        k = 0
        while (n_lines is None and f"line{k}_s_mm" in z.files) or (n_lines is not None and k < n_lines):
            if f"line{k}_s_mm" not in z.files:
                series.append(None)
            else:
                arrs = [_array(z, f"line{k}_{name}", 1) for name in _SERIES]
                if len({len(a) for a in arrs}) != 1:
                    raise ReportError(
                        f"results.npz: line{k}_*: arrays of different lengths {[len(a) for a in arrs]}"
                    )
                series.append(LineSeries(*arrs))
            k += 1
        holes = (
            _array(z, "coverage_holes_xy_mm", 2, 2) if "coverage_holes_xy_mm" in z.files else np.zeros((0, 2))
        )
    return ResultsArrays(xy, dev, size, series, holes)
