"""Field tables of the payload models for docs/api.md, generated from the models themselves.

``python -m tests.api.api_doc`` rewrites every block of docs/api.md between ``<!-- fields: Name -->``
and ``<!-- /fields -->`` with the table of model ``Name``; ``--check`` only says whether the file is
current (a test runs it, so the documentation cannot drift from the code).
"""

from __future__ import annotations

import dataclasses
import re
import sys
import types
import typing
from pathlib import Path

from pydantic import BaseModel

from analysis.contracts.job import (
    DesignReport,
    LineReport,
    RegistrationReport,
    Report,
    ReportInputs,
    ScanCoverage,
    SurfaceReport,
)
from analysis.contracts.placement import Placement
from analysis.contracts.settings import InspectionSettings
from analysis.metrics import Tolerances
from analysis.templates import DetectionLayout
from cellctl.api.models import (
    AnalysisJob,
    DaemonStats,
    EgmStats,
    JobEvent,
    JobSpec,
    LiveCloudChunk,
    MotionCounters,
    ReportEnvelope,
    StreamChunk,
    StreamEnd,
    TriggerRequest,
)
from cellctl.api.transfer import DesignRef, ResultChunk, ResultFile, ResultManifest, TransferSpec

__all__ = ["MODELS", "field_table", "render"]

#: the models (and dataclasses inside them) documented in docs/api.md, by name
MODELS: dict[str, type] = {
    m.__name__: m
    for m in (
        TriggerRequest, Placement, JobSpec, AnalysisJob, InspectionSettings, DetectionLayout, Tolerances,
        JobEvent, ReportEnvelope, Report, RegistrationReport, LineReport, ScanCoverage, SurfaceReport,
        ReportInputs, DesignReport, DaemonStats, EgmStats, LiveCloudChunk, TransferSpec, DesignRef, ResultChunk,
        ResultManifest, ResultFile, StreamChunk, StreamEnd, MotionCounters,
    )
}  # fmt: skip
DOC = Path(__file__).resolve().parents[2] / "docs" / "api.md"
_BLOCK = re.compile(r"(<!-- fields: (\w+) -->\n)(.*?)(<!-- /fields -->)", re.S)


def _type_name(tp: object) -> str:
    origin = typing.get_origin(tp)
    if origin is typing.Annotated:
        return _type_name(typing.get_args(tp)[0])
    if origin in (typing.Union, types.UnionType):
        return " \\| ".join(_type_name(a) for a in typing.get_args(tp))
    if origin is typing.Literal:
        return " \\| ".join(f'"{a}"' for a in typing.get_args(tp))
    if origin is not None:
        args = ", ".join(_type_name(a) for a in typing.get_args(tp))
        return f"{getattr(origin, '__name__', str(origin))}[{args}]"
    if tp is type(None):
        return "null"
    return getattr(tp, "__name__", str(tp))


def _default(value: object) -> str:
    if dataclasses.is_dataclass(value) or isinstance(value, BaseModel):
        return f"{type(value).__name__}()"
    return f"`{value!r}`"


def field_table(model: type) -> str:
    """A markdown table of one model's fields: name on the wire, type, default (or required)."""
    rows = ["| field | type | default |", "| --- | --- | --- |"]
    if isinstance(model, type) and issubclass(model, BaseModel):
        hints = typing.get_type_hints(model, include_extras=True)
        for name, f in model.model_fields.items():
            default = "required" if f.is_required() else _default(f.get_default(call_default_factory=True))
            rows.append(f"| `{f.alias or name}` | {_type_name(hints[name])} | {default} |")
    else:
        hints = typing.get_type_hints(model, include_extras=True)
        for f in dataclasses.fields(model):
            if f.default is not dataclasses.MISSING:
                default = _default(f.default)
            elif f.default_factory is not dataclasses.MISSING:
                default = _default(f.default_factory())
            else:
                default = "required"
            rows.append(f"| `{f.name}` | {_type_name(hints[f.name])} | {default} |")
    return "\n".join(rows) + "\n"


def render(text: str) -> str:
    """``text`` with every field block regenerated (an unknown model name raises KeyError)."""
    return _BLOCK.sub(lambda m: m.group(1) + field_table(MODELS[m.group(2)]) + m.group(4), text)


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    text = DOC.read_text(encoding="utf-8")
    new = render(text)
    if "--check" in args:
        if new != text:
            print(f"{DOC}: field tables are out of date; run python -m tests.api.api_doc", file=sys.stderr)
            return 1
        return 0
    DOC.write_text(new, encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
