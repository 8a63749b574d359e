"""Design input: what a yard hands over, read into the types the analysis works on.

Triangle meshes (:mod:`~analysis.design.mesh`), IGES and STEP surfaces (read by :mod:`~analysis.design.cad`: the
file's facts in :mod:`~analysis.design.cad_facts`, OpenCASCADE's shape in :mod:`~analysis.design.occ_read`,
the exact surface in :mod:`~analysis.design.cad_surface` of :mod:`~analysis.design.nurbs` patches;
written by :mod:`~analysis.design.cad_write`), the design's outline, corners and own frame
(:mod:`~analysis.design.outline`), the moulded side and thickness (:mod:`~analysis.design.moulded`),
a yard's template table (:mod:`~analysis.design.template_table`) and the project's analytic plate
shapes with their forming errors (:mod:`~analysis.design.plates`).
"""
