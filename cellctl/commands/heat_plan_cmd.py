"""`cellctl heat-plan JOB_OR_DIR`: the line-heating plan of an analysed job, from its stored results.

Writes heating-plan.json (always: the plan, or why none) and heating-plan.dxf (with a plan) into the
results directory and prints one sentence per line. Exit 0 when the files are written (a plan, or the
reason there is none), 2 when nothing could be written: not a results directory, a bad cell.toml, a
disk that refuses.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from cellctl.commands.report_cmd import resolve_results_dir
from cellctl.config import DEFAULT_CONFIG_PATH, ConfigError, FormingSection, load_config, parse_config

if TYPE_CHECKING:
    from analysis.forming.plan_file import HeatingPlanFile

__all__ = ["register", "run"]


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "heat-plan",
        help="make the line-heating plan of an analysed job: heating-plan.json and heating-plan.dxf",
        description=(
            "Plan the next round of line heating from a results directory (report.json and results.npz) "
            "with the crew's rules of cell.toml [forming]: heating-plan.json (the lines, the predicted "
            "Zmax per line, or why no plan) and heating-plan.dxf (the lines in the plate frame, to mark "
            "the plate) beside report.json. JOB_OR_DIR is a directory, or a job id looked up in "
            "<[cell] data_dir>/jobs/<JOB>. Exit 0 when the files are written, 2 when not."
        ),
    )
    p.add_argument("target", metavar="JOB_OR_DIR", help="results directory or job id")
    p.add_argument(
        "--config",
        default=None,
        help="cell.toml for the [forming] rules and job ids (default: ./cell.toml, or the defaults without one)",
    )
    p.add_argument(
        "--forming",
        metavar="JSON",
        default=None,
        help="the [forming] section as JSON, in place of cell.toml's (the daemon passes its own)",
    )
    p.add_argument("--json", action="store_true", help="print the written files as one JSON object")
    p.set_defaults(func=run)


def _settings(args: argparse.Namespace) -> FormingSection:
    """The [forming] settings: --forming, else the config file's, else the defaults (no ./cell.toml)."""
    if args.forming is not None:
        try:
            section = json.loads(args.forming)
        except json.JSONDecodeError as exc:
            raise ConfigError("--forming", [f"not JSON: {exc}"]) from None
        # validated as cell.toml's section is: the same refusals, the same words
        return parse_config({"forming": section}, "--forming").forming
    if args.config is None and not DEFAULT_CONFIG_PATH.exists():
        return FormingSection()
    return load_config(args.config or DEFAULT_CONFIG_PATH).forming


def run(args: argparse.Namespace) -> int:
    # Imported here: `cellctl --help` must not pay for the planner's imports.
    from analysis.heating_plan import write_job_plan

    try:
        settings = _settings(args)
        results_dir = resolve_results_dir(args.target, args.config or str(DEFAULT_CONFIG_PATH))
    except ConfigError as err:
        for problem in err.problems:
            print(f"{err.source}: {problem}", file=sys.stderr)
        return 2
    except FileNotFoundError as exc:
        print(f"cellctl heat-plan: {exc}", file=sys.stderr)
        return 2
    if not (Path(results_dir) / "report.json").is_file():
        print(
            f"cellctl heat-plan: {results_dir}: no report.json (is this a results directory?)",
            file=sys.stderr,
        )
        return 2
    try:
        out = write_job_plan(results_dir, settings, enabled=settings.enabled)
    except OSError as exc:
        print(f"cellctl heat-plan: {results_dir}: cannot write the plan: {exc}", file=sys.stderr)
        return 2
    plan = out.plan
    if args.json:  # the daemon's plan child: its answer to the daemon (cellctl.daemon.heat_plan)
        from cellctl.daemon.heat_plan import HeatPlanAnswer

        print(
            HeatPlanAnswer(
                json_path=str(out.json_path), dxf_path=str(out.dxf_path) if out.dxf_path else None,
                status=plan.status, reason=plan.reason, lines=len(plan.lines), planning_s=plan.planning_s,
            ).model_dump_json()
        )  # fmt: skip
        return 0
    for text in plan_text(plan):
        print(text)
    print(out.json_path)
    if out.dxf_path is not None:
        print(out.dxf_path)
    return 0


def plan_text(plan: HeatingPlanFile) -> list[str]:
    """What the crew reads of a plan: one sentence a line, the predicted largest Zmax and verdict after
    the round, the planner's notes; or why there is no plan."""
    if plan.status == "no_plan":
        return [f"no heating plan: {plan.reason}"]
    out = [line.sentence() for line in plan.lines]
    if plan.predicted is not None:
        worst = max((z for z in plan.predicted.zmax_mm.values() if z is not None), default=None)
        after = f"largest Zmax {worst:.2f} mm, " if worst is not None else ""
        out.append(f"predicted after the round: {after}verdict {plan.predicted.verdict}")
    out += [f"note: {note}" for note in plan.notes]
    return out
