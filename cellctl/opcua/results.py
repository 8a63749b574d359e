"""A plate's report as an OPC 40210 result: the verdict as the result's evaluation, and every
detection line's six figures as characteristics (nominal, tolerance limits, value, evaluation).

GMS models a characteristic as an object type (``CharacteristicType``), not a structure, and leaves
``ResultDataType.ResultContent`` to the application. The content here is one JSON document (its
``FileFormat`` says so): :class:`GmsCharacteristics`, whose field names are CharacteristicType's.
"""

from __future__ import annotations

import math
from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict

from analysis.contracts.job import LineReport, Report

Evaluation = Literal["Undefined", "OK", "NotOK", "NotDecidable"]

#: the report's verdict -> Machinery/Result's ResultEvaluationEnum
VERDICT_EVALUATION: dict[str, Evaluation] = {"pass": "OK", "fail": "NotOK", "incomplete": "NotDecidable"}
#: ResultEvaluationEnum's values (Machinery/Result 1.00, 10.2)
EVALUATION_VALUE: dict[Evaluation, int] = {"Undefined": 0, "OK": 1, "NotOK": 2, "NotDecidable": 3}

CONTENT_FORMAT = "application/vnd.cellctl.gms-characteristics+json"


class GmsCharacteristic(BaseModel):
    """One figure of one detection line, named as OPC 40210's CharacteristicType names its parts.
    A limit of None: the figure has no tolerance (its evaluation is then Undefined)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    CharacteristicIdentifier: str  # "<line>.<figure>", e.g. "T1.Zmax"
    Line: str
    Figure: Literal["Zmax", "SZ", "SZ-average", "CI", "SC-average", "Cmax"]
    EngineeringUnits: str  # UNECE symbol-like text: mm, mm2, 1, 1/mm
    Nominal: float
    LowerToleranceLimit: float | None
    UpperToleranceLimit: float | None
    ResultValue: float
    ResultEvaluation: Evaluation
    IsValid: bool


class GmsCharacteristics(BaseModel):
    """The result content: the plate, its verdict and every line's characteristics."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    plate_id: str
    job_id: str
    verdict: Literal["pass", "fail", "incomplete"]
    standard: str
    characteristics: list[GmsCharacteristic]


def _judged(value: float, upper: float | None) -> Evaluation:
    if upper is None:
        return "Undefined"
    if not math.isfinite(value):
        return "NotDecidable"
    return "OK" if value <= upper else "NotOK"


def line_characteristics(line: LineReport, report: Report) -> list[GmsCharacteristic]:
    """The six figures of ``line``; Zmax is held to the limit the report was judged at, Cmax to
    its limit when there is one; the other four figures carry no tolerance in the standard."""
    tol = report.tolerances
    zmax_upper = tol.deviation_limit_mm if tol.judge_at == "limit" else tol.deviation_standard_mm
    rows: list[tuple[str, str, float, float | None]] = [
        ("Zmax", "mm", line.zmax_mm, zmax_upper),
        ("SZ", "mm2", line.sz_mm2, None),
        ("SZ-average", "mm", line.sz_avg_mm, None),
        ("CI", "1", line.ci, None),
        ("SC-average", "1/mm", line.sc_avg_per_mm, None),
        ("Cmax", "1/mm", line.cmax_per_mm, tol.cmax_limit_per_mm),
    ]
    return [
        GmsCharacteristic(
            CharacteristicIdentifier=f"{line.name}.{figure}",
            Line=line.name,
            Figure=figure,  # type: ignore[arg-type]
            EngineeringUnits=unit,
            Nominal=0.0,
            LowerToleranceLimit=None if upper is None else 0.0,
            UpperToleranceLimit=upper,
            ResultValue=value,
            ResultEvaluation=_judged(value, upper),
            IsValid=math.isfinite(value),
        )
        for figure, unit, value, upper in rows
    ]


def report_characteristics(report: Report) -> GmsCharacteristics:
    return GmsCharacteristics(
        plate_id=report.plate_id, job_id=report.job_id, verdict=report.verdict, standard=report.standard,
        characteristics=[c for line in report.lines for c in line_characteristics(line, report)],
    )  # fmt: skip


def result_data(ua: Any, report: Report, job_id: str) -> Any:
    """``report`` as a Machinery/Result ``ResultDataType`` (``ua``: asyncua's ``ua`` module once the
    server or client has loaded the models' data type definitions)."""
    created = None
    if report.created_utc:
        try:
            created = datetime.fromisoformat(report.created_utc.replace("Z", "+00:00"))
        except ValueError:
            created = None
    meta = ua.ResultMetaDataType(
        ResultId=job_id,
        HasTransferableDataOnFile=False,
        IsPartial=report.verdict == "incomplete",
        IsSimulated=False,
        PartId=report.plate_id,
        JobId=job_id,
        CreationTime=created,
        ResultEvaluation=ua.ResultEvaluationEnum(EVALUATION_VALUE[VERDICT_EVALUATION[report.verdict]]),
        ResultEvaluationDetails=ua.LocalizedText(f"verdict {report.verdict} ({report.standard})", "en"),
        FileFormat=[CONTENT_FORMAT],
    )
    content = report_characteristics(report.model_copy(update={"job_id": report.job_id or job_id}))
    return ua.ResultDataType(
        ResultMetaData=meta, ResultContent=[ua.Variant(content.model_dump_json(), ua.VariantType.String)]
    )
