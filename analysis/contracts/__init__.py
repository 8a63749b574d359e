"""The analysis' typed contracts with whoever runs it: the job, its settings, the placement and the report.

:mod:`~analysis.contracts.job` (``AnalysisJob``, ``Report``), :mod:`~analysis.contracts.settings`
(``InspectionSettings``), :mod:`~analysis.contracts.placement` (``Placement``) and
:mod:`~analysis.contracts.results` (``report.json`` and ``results.npz`` read and written in one
place). ``cellctl`` carries them inside its messages; they are built from the stages' own types
(``Tolerances``, ``DetectionLayout``), so they import those stages and no stage imports them back
except for a constant.
"""
