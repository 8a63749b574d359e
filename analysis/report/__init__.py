"""The inspection report's files, made from a results directory.

A results directory (one per job or per ``cellctl inspect --out DIR``) holds ``report.json`` (a
:class:`~analysis.contracts.job.Report`), ``results.npz`` (arrays for plots) and ``cloud.ply``, both read
through :mod:`analysis.contracts.results`. This package turns them into what people read:

* ``report.html`` (:mod:`~analysis.report.html_page`): one self-contained page (inline CSS, inline
  SVG plots with their raster parts as data: URLs, no script, no web font, nothing fetched), so it
  opens from a USB stick;
* ``report.pdf`` (:mod:`~analysis.report.pdf`): the same content on A4 pages for the QA archive
  (matplotlib's PdfPages);
* ``report.csv`` (:mod:`~analysis.report.csv_table`): the paper's Tables 3-5, one row per
  detection line.

:func:`analysis.report.write.write_report` writes them all from what
:func:`analysis.report.load.load_results` reads; :mod:`~analysis.report.plots` draws the figures and
:mod:`~analysis.report.text` holds the words and number formats the page and the PDF share.

Everything is computed from the stored results, so ``cellctl report DIR`` regenerates the same
report at any time. Plots use matplotlib's object API (no pyplot, no global figure state), which
keeps the functions safe to call from a worker thread.

Plate frame: x along the plate's length and y along its width, in mm from the reference corner.
Deviation: ``d = z_design - z_measured`` (mm); d > 0 means the plate lies below the template.
"""
