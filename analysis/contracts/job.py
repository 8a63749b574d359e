"""The analysis' contract with whoever runs it: the job it is given and the report it returns.

:class:`AnalysisJob` is what an analysis needs besides the cloud (the design, the operator's
nominal :class:`~analysis.contracts.placement.Placement`, the settings, where to write the results);
:class:`Report` is the schema of ``report.json``. Both are pydantic models that refuse unknown
fields: the daemon builds the job and validates the report it gets back, the worker validates the
job it receives and the report it returns, and :func:`analysis.pipeline.inspect_cloud` validates
the report it makes. The analysis package owns them because it never imports ``cellctl``, while
``cellctl.api`` carries them inside its messages (``JobSpec``, ``ReportEnvelope``).
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    SerializerFunctionWrapHandler,
    model_serializer,
    model_validator,
)

from analysis.contracts.placement import Placement
from analysis.contracts.settings import InspectionSettings, TemplateFit
from analysis.metrics import Tolerances

__all__ = [
    "AnalysisJob",
    "CompareLine",
    "LineFitReport",
    "LineNotScanned",
    "LineReport",
    "PlacementFinding",
    "RegistrationReport",
    "Report",
    "ReportInputs",
    "RestSurfaceReport",
    "ScanCoverage",
    "SurfaceReport",
    "TemplateFitCompare",
]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class PlacementFinding(_Strict):
    """Where the placement the scan was planned from came from, and how well the outline fitted.

    source: ``given`` (the trigger's, not checked), ``located`` (found by the locate run, none
    given), ``checked`` (given, and confirmed by the locate run; the found one is used).
    given: the trigger's placement (None when none was given). rms_mm: RMS of the outline fit of the
    locate run (mm); coverage: fraction of the design's outline its passes saw; offset_mm /
    offset_deg: the found placement's distance from the given one; resolved_by: how a half turn was
    decided (``fit``, ``hint``, ``convention``); locate_s: the locate run's time (motion and fit).
    """

    source: Literal["given", "located", "checked"]
    given: Placement | None = None
    rms_mm: float | None = None
    height_rms_mm: float | None = None
    coverage: float | None = None
    boundary_points: int | None = None
    offset_mm: float | None = None
    offset_deg: float | None = None
    resolved_by: str | None = None
    locate_s: float | None = None


class AnalysisJob(_Strict):
    """One analysis to run on one cloud (the job parameters a worker receives).

    design: path of the design surface (absolute, or relative to the worker's directory).
    placement: the operator's nominal placement of the design on the bed; it decides the reference
    corner of a design that looks the same after a half turn (None: the bed convention decides).
    placement_found: how that placement was found (the locate run), recorded in the report's inputs.
    out_dir: where to write the results directory (None: only the report is returned).
    """

    job_id: str = ""
    plate_id: str = ""
    cell_id: str = ""
    design: Annotated[str, Field(min_length=1)]
    placement: Placement | None = None
    placement_found: PlacementFinding | None = None
    settings: InspectionSettings = InspectionSettings()
    out_dir: str | None = None


Vec2 = Annotated[list[float], Field(min_length=2, max_length=2)]
Vec3 = Annotated[list[float], Field(min_length=3, max_length=3)]


class RestSurfaceReport(_Strict):
    """The surface the design rests on (``analysis.register.rest_surface``): patches, noise, the bias bound (mm)."""

    estimator: str
    patches: int
    cell_mm: float
    min_points: int
    noise_mm: float
    standard_error_mm: float
    bound_mm: float
    confidence: float
    target_sigmas: float
    target_met: bool


class RegistrationReport(_Strict):
    """How the design was laid on the measured plate (rms in mm, ``transform`` design -> measured)."""

    coarse_rms_mm: float
    icp_rms_mm: float
    nonpen_rms_mm: float
    penetration_points: int
    penetration_points_before: int
    surface_points: int
    surface_cell_mm: float
    raw_points_below_4sigma: int
    transform: Annotated[
        list[Annotated[list[float], Field(min_length=4, max_length=4)]], Field(min_length=4, max_length=4)
    ]
    corner_shift: int
    candidates_icp_rms_mm: dict[str, float] = {}
    rest_surface: RestSurfaceReport | None = None


class LineFitReport(_Strict):
    """A per-line template's motion in its section plane (``template_fit = "per_line"``)."""

    angle_deg: float
    shift_s_mm: float
    shift_h_mm: float
    rms_mm: float
    rest_points: int
    penetration_points: int
    converged: bool


class CompareLine(_Strict):
    """One line's figures under the template fit that did not judge the plate."""

    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True, serialize_by_alias=True)

    name: str
    family: Literal["transverse", "longitudinal", "diagonal"]
    index: Annotated[int, Field(ge=1)]
    sz_avg_mm: float
    zmax_mm: float
    cmax_per_mm: float
    grade: str = ""
    passed: bool = Field(alias="pass")


class TemplateFitCompare(_Strict):
    """The other template fit's figures, shown beside the judged ones (``template_fit_compare``)."""

    template_fit: TemplateFit
    verdict: Literal["pass", "fail"]
    lines: list[CompareLine]


class LineReport(_Strict):
    """One detection line: its six figures (paper section 2), where it lies, its verdict (``pass``)."""

    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True, serialize_by_alias=True)

    family: Literal["transverse", "longitudinal", "diagonal"]
    index: Annotated[int, Field(ge=1)]
    name: str = ""
    position_mm: float = 0.0
    sz_mm2: float
    sz_avg_mm: float
    zmax_mm: float
    zmax_at_mm: float
    ci: float
    sc_avg_per_mm: float
    cmax_per_mm: float
    length_mm: float
    grade: str = ""
    passed: bool = Field(alias="pass")
    start_plate_mm: Vec2 | None = None
    end_plate_mm: Vec2 | None = None
    noise_mm: float | None = None
    line_fit: LineFitReport | None = None

    @model_validator(mode="before")
    @classmethod
    def _named(cls, data: Any) -> Any:
        # the earliest reports' lines carry no name: the one their family and index give (T3, L1, D2)
        if isinstance(data, dict) and not data.get("name") and isinstance(data.get("family"), str):
            data = {**data, "name": f"{data['family'][:1].upper()}{data.get('index', '')}"}
        return data


class LineNotScanned(_Strict):
    """A detection line a partial scan did not cover (``scanned_fraction`` of its length seen):
    reported, not judged."""

    name: str
    family: Literal["transverse", "longitudinal", "diagonal"]
    index: Annotated[int, Field(ge=1)]
    scanned_fraction: Annotated[float, Field(ge=0, le=1)]


class ScanCoverage(_Strict):
    """Share of the design's footprint the scan saw, and the area it missed. ``partial``: the scan
    saw only part of the plate (cut short): the plate was registered on the placement the scan was
    planned from, and ``lines_not_scanned`` lists the lines it did not cover (absent from a whole
    scan's report)."""

    fraction: float
    holes_mm2: float
    partial: bool = False
    lines_not_scanned: list[LineNotScanned] = []

    @model_serializer(mode="wrap")
    def _whole_scan_shape(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        # a whole scan's report keeps the shape every daemon version reads: no partial-scan fields
        data = handler(self)
        if not self.partial:
            data.pop("partial", None)
            data.pop("lines_not_scanned", None)
        return data


class SurfaceReport(_Strict):
    """The segmented top surface: point count, noise, largest deviation (mm; None off the design)."""

    points: int
    noise_sigma_mm: float
    max_deviation_mm: float | None = None


class ReportInputs(_Strict):
    """What the analysis was given: the cloud's size, the design, the nominal placement it used."""

    points: int
    design: str = ""
    cloud: str | None = None
    placement: Placement | None = None
    placement_found: PlacementFinding | None = None


class DesignReport(_Strict):
    """The design the plate was judged against: a mesh, or a CAD file (:mod:`analysis.design.cad`) with its
    format, file units, faces, the tessellation's measured chord error (registration runs on it),
    where the templates were cut, and ``T_design_file`` (file coordinates in mm -> design frame).
    ``side``: which face of the plate faced the sensor (``moulded_down``: the design was offset
    by ``thickness_mm`` and turned over, :mod:`analysis.design.moulded`)."""

    kind: Literal["mesh", "cad"] = "mesh"
    format: str = ""
    file_units: str = "mm"
    faces: int | None = None
    chord_error_mm: float | None = None
    templates: Literal["mesh", "exact surface"] = "mesh"
    T_design_file: list[list[float]] | None = None
    side: Literal["moulded_up", "moulded_down"] = "moulded_up"
    thickness_mm: float | None = None


class Report(_Strict):
    """``report.json``: one inspected plate (docs/architecture.md, "The report")."""

    plate_id: str
    job_id: str = ""
    cell_id: str = ""
    created_utc: str = ""
    #: ``incomplete``: a partial scan (``coverage.partial``) whose judged lines all pass
    verdict: Literal["pass", "fail", "incomplete"]
    standard: str = ""
    template_fit: TemplateFit = "rigid"
    template_fit_compare: TemplateFitCompare | None = None
    registration: RegistrationReport
    corners_mm: Annotated[list[Vec3], Field(min_length=4, max_length=4)]
    plate_size_mm: Vec2
    lines: list[LineReport]
    tolerances: Tolerances
    coverage: ScanCoverage
    surface: SurfaceReport
    inputs: ReportInputs
    design: DesignReport = DesignReport()
    timings_s: dict[str, float] = {}
