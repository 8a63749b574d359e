"""`cellctl report JOB_OR_DIR [--open]`: regenerate a job's report (HTML, PDF, CSV) from its stored results.

`cellctl export JOB_OR_DIR [--formats ply,las,e57] [--frames design,ship] [--out DIR]`: the registered
cloud with its deviation as LAS / E57 / PLY for the metrology tools, in the design frame and in the
design file's own frame (the ship's coordinates) (:func:`analysis.export.export_results`)."""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import webbrowser
from pathlib import Path

from cellctl.config import DEFAULT_CONFIG_PATH, ConfigError, load_config


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "report",
        help="regenerate report.html, report.pdf and report.csv from a job's stored results",
        description=(
            "Make the inspection report again from a results directory (report.json and results.npz). "
            "JOB_OR_DIR is a directory, or a job id looked up in <[cell] data_dir>/jobs/<JOB>. A job's report "
            "shows the plate's previous round (its latest earlier job with a report) per line."
        ),
    )
    p.add_argument("target", metavar="JOB_OR_DIR", help="results directory or job id")
    p.add_argument("--open", action="store_true", help="open report.html in the desktop's browser")
    p.add_argument(
        "--json",
        action="store_true",
        help="print the written files as one JSON object (csv, html, pdf) instead of one path a line",
    )
    p.add_argument(
        "--config", default=str(DEFAULT_CONFIG_PATH), help="cell.toml for job ids (default: ./cell.toml)"
    )
    p.set_defaults(func=run)

    e = sub.add_parser(
        "export",
        help="the registered cloud as LAS / E57 / PLY, in the design frame and the design file's (ship) frame",
        description=(
            "Write a job's registered cloud and its deviation for metrology tools and the yard's CAD: "
            "cloud.las, cloud.e57 (design frame) and cloud-ship.ply, cloud-ship.las, cloud-ship.e57 (the "
            "design file's frame, from report.json's design.T_design_file). The job's results already "
            "hold cloud.ply (design frame) and lines-ship.csv (docs/operations.md, 'Cloud files for "
            "metrology tools')."
        ),
    )
    e.add_argument("target", metavar="JOB_OR_DIR", help="results directory or job id")
    e.add_argument("--formats", default="ply,las,e57", help="comma-separated: ply, las, e57 (default: all)")
    e.add_argument("--frames", default="design,ship", help="comma-separated: design, ship (default: both)")
    e.add_argument("--out", default=None, help="where the files go (default: the results directory)")
    e.add_argument(
        "--config", default=str(DEFAULT_CONFIG_PATH), help="cell.toml for job ids (default: ./cell.toml)"
    )
    e.set_defaults(func=run_export)


def run_export(args: argparse.Namespace) -> int:
    from analysis.cloud_io import CloudError
    from analysis.contracts.results import ReportError
    from analysis.export import export_results

    split = lambda text: tuple(v.strip() for v in text.split(",") if v.strip())  # noqa: E731
    try:
        results_dir = resolve_results_dir(args.target, args.config)
        written = export_results(
            results_dir, args.out, formats=split(args.formats), frames=split(args.frames)
        )
    except ConfigError as err:
        for problem in err.problems:
            print(f"{err.source}: {problem}", file=sys.stderr)
        return 2
    except (FileNotFoundError, ReportError, CloudError) as exc:
        print(f"cellctl export: {exc}", file=sys.stderr)
        return 2
    for path in written.values():
        print(path)
    return 0


def resolve_results_dir(target: str, config_path: str) -> Path:
    """The results directory a JOB_OR_DIR argument names.

    An existing directory wins; otherwise ``target`` is a job id under ``<data_dir>/jobs/``.
    Raises FileNotFoundError (with the places looked at) or ConfigError.
    """
    as_dir = Path(target)
    if as_dir.is_dir():
        return _results_of(as_dir)
    if any(sep in target for sep in ("/", os.sep)) or target in (".", ".."):
        raise FileNotFoundError(f"{target}: no such directory")
    config = load_config(config_path)
    job_dir = config.cell.data_dir / "jobs" / target
    if not job_dir.is_dir():
        raise FileNotFoundError(f"{target}: neither a directory nor a job in {config.cell.data_dir / 'jobs'}")
    return _results_of(job_dir)


def _results_of(directory: Path) -> Path:
    """A job directory (``<data_dir>/jobs/<JOB>``) stands for its ``results/``; a results directory
    (or any other directory) for itself."""
    results = directory / "results"
    if (results / "report.json").exists():
        return results
    return directory


def _open(path: Path) -> bool:
    """Open ``path`` in the desktop's browser; False when there is no desktop to open it on."""
    if sys.platform.startswith("linux") and not (
        os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
    ):
        return False
    opener = shutil.which("xdg-open")
    if opener:
        # detached: the browser must outlive this command
        subprocess.Popen(
            [opener, str(path)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True
        )
        return True
    return webbrowser.open(path.resolve().as_uri())


def run(args: argparse.Namespace) -> int:
    # Imported here: `cellctl --help` must not pay for matplotlib.
    from analysis.contracts.results import ReportError
    from analysis.report.write import write_report
    from cellctl.jobstore.history import previous_round_for

    try:
        results_dir = resolve_results_dir(args.target, args.config)
    except ConfigError as err:
        for problem in err.problems:
            print(f"{err.source}: {problem}", file=sys.stderr)
        return 2
    except FileNotFoundError as exc:
        print(f"cellctl report: {exc}", file=sys.stderr)
        return 2
    try:
        # the plate's previous round (a job directory of the same plate before this one), if any
        written = write_report(results_dir, previous_round_for(results_dir))
    except ReportError as exc:
        print(f"cellctl report: {exc}", file=sys.stderr)
        return 2
    by_kind = {p.suffix.lstrip("."): p for p in written}
    if args.json:  # the daemon's render child: its answer to the daemon (cellctl.daemon.render)
        from cellctl.daemon.render import RenderAnswer

        print(RenderAnswer(**{kind: str(p) for kind, p in by_kind.items()}).model_dump_json())
    else:
        for path in written:
            print(path)
    html_path = by_kind["html"]
    if args.open and not _open(html_path):
        print(f"no desktop browser available; open {html_path.resolve()}")
    return 0
