"""`cellctl scan`, `status`, `watch`, `abort` and `reset`: the cell's Zenoh API from the command line.

``scan`` triggers an inspection and, with ``--wait``, shows its place in the daemon's queue while it
waits for the robot, then a progress bar fed by the daemon's state publication, and prints the
per-line verdict table (the paper's Tables 3-5) when the report arrives. ``abort`` stops the scan
in progress or cancels a queued job; ``reset`` clears an emergency stop or a fault once the
controller is healthy. Exit codes: 0 accepted / pass, 1 fail verdict, 2 refused or error, 3 no
answer from the daemon.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import sys
import time
from typing import TYPE_CHECKING, Any

from cellctl.config import DEFAULT_CONFIG_PATH, ConfigError, load_config

if TYPE_CHECKING:
    from analysis.contracts.job import Report

EXIT_OK, EXIT_FAIL, EXIT_ERROR, EXIT_NO_DAEMON = 0, 1, 2, 3
_FINAL = ("done", "failed", "aborted", "interrupted", "cancelled")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("scan", help="trigger an inspection over Zenoh; --wait shows progress and the verdict")
    p.add_argument("--plate", required=True, help="plate id (letters, digits, '-', '_', '.')")
    p.add_argument(
        "--design", required=True, help="design (IGES, STEP, PLY, STL or OBJ), relative to [cell] designs_dir"
    )
    p.add_argument(
        "--placement",
        default=None,
        help="X,Y,ANGLE_DEG or X,Y,Z,ANGLE_DEG of the plate frame on the bed (mm, deg); without it the "
        "cell finds the plate by a locate run (with it, the locate run checks it: docs/locate.md)",
    )
    p.add_argument("--note", default="", help="free text stored with the job")
    p.add_argument(
        "--template-table",
        default=None,
        metavar="CSV",
        help="the yard's template table of this plate (read here, sent as rows): one named line per template",
    )
    add_design_side_arguments(p)
    p.add_argument("--wait", action="store_true", help="wait for the report and print the verdict table")
    p.add_argument(
        "--timeout-s", type=float, default=1800.0, help="give up waiting after this (default 1800)"
    )
    p.add_argument("--config", default=str(DEFAULT_CONFIG_PATH), help="cell.toml (default: ./cell.toml)")
    p.set_defaults(func=run_scan)

    s = sub.add_parser("status", help="state of the cell, its current job and its workers")
    s.add_argument("--config", default=str(DEFAULT_CONFIG_PATH))
    s.add_argument("--json", action="store_true", help="one JSON object")
    s.add_argument("--timeout-s", type=float, default=3.0)
    s.set_defaults(func=run_status)

    w = sub.add_parser("watch", help="print every state publication of the cell until Ctrl-C")
    w.add_argument("--config", default=str(DEFAULT_CONFIG_PATH))
    w.add_argument("--json", action="store_true", help="raw JSON lines")
    w.set_defaults(func=run_watch)

    a = sub.add_parser("abort", help="stop the scan in progress (smoothly), or cancel a queued job")
    a.add_argument("--job", default=None, help="the job id (default: the scan in progress)")
    a.add_argument("--config", default=str(DEFAULT_CONFIG_PATH))
    a.set_defaults(func=run_abort)

    r = sub.add_parser(
        "reset", help="clear emergency_stopped / faulted once the controller is released and reset"
    )
    r.add_argument("--config", default=str(DEFAULT_CONFIG_PATH))
    r.set_defaults(func=run_reset)


def _config(path: str):
    try:
        return load_config(path)
    except ConfigError as err:
        for problem in err.problems:
            print(f"{err.source}: {problem}", file=sys.stderr)
        return None


def placement_payload(text: str, default_z_mm: float) -> dict[str, Any]:
    """``X,Y,ANGLE`` / ``X,Y,Z,ANGLE`` -> the trigger's ``placement`` object (ValueError if malformed)."""
    from cellctl.commands.plan_cmd import parse_placement

    return parse_placement(text, default_z_mm).model_dump()


def add_design_side_arguments(p: argparse.ArgumentParser) -> None:
    """``--design-side`` and ``--thickness`` (``scan`` and ``inspect``; docs/designs.md)."""
    p.add_argument(
        "--design-side",
        choices=("moulded_up", "moulded_down"),
        default="moulded_up",
        help="the design is the plate's moulded face: does it face up on the bed (default), or was the "
        "plate turned over (then the design is offset by --thickness)",
    )
    p.add_argument("--thickness", type=float, default=0.0, metavar="MM",
                   help="plate thickness, needed with --design-side moulded_down")  # fmt: skip


def template_table_rows(path: str | None) -> list[dict[str, Any]]:
    """``--template-table CSV`` -> the trigger's ``template_table`` rows ([] without one;
    TemplateTableError, a ValueError naming the file and line, for a bad table)."""
    if path is None:
        return []
    import dataclasses

    from analysis.design.template_table import read_template_table

    return [dataclasses.asdict(t) for t in read_template_table(path)]


class StatusFollower:
    """Keeps the latest CellStatus, every job it reported on and the reports of a key prefix (Zenoh
    callbacks -> the loop).

    ``jobs`` holds the last JobProgress seen per job id (from ``job``, ``analyses`` and ``recent``),
    ``queue`` the queue positions of the latest publication: a job's end is kept even when the
    next publication (another job's progress) follows it before the reader looks.
    """

    def __init__(self, session: Any, keys: Any) -> None:
        from cellctl.api.session import subscribe

        self._init_state()
        self._subs = [
            subscribe(session, keys.state, self._on_state),
            subscribe(session, keys.report("*"), self._on_report),
        ]

    def _init_state(self) -> None:
        self.latest: Any = None
        self.jobs: dict[str, Any] = {}
        #: per job, how many times it was seen going from an end (or from unseen) to a live state: a
        #: new run (a re-analysis) of a job that had ended. The publication is followed sample by
        #: sample here, so a run is counted even when its end follows before a reader looks.
        self.runs: dict[str, int] = {}
        self.queue: dict[str, int] = {}
        self.reports: dict[str, Any] = {}
        self.changed = asyncio.Event()

    def _on_state(self, sample: Any) -> None:
        from pydantic import ValidationError

        from cellctl.api import CellStatus

        try:
            st = CellStatus.model_validate_json(sample.payload.to_bytes())
        except ValidationError:
            return
        self.feed(st)

    def feed(self, st: Any) -> None:
        """Take one state publication (a :class:`~cellctl.api.CellStatus`)."""
        self.latest = st
        for jp in st.jobs():
            before = self.jobs.get(jp.job_id)
            if jp.state.value not in _FINAL and (before is None or before.state.value in _FINAL):
                self.runs[jp.job_id] = self.runs.get(jp.job_id, 0) + 1
            self.jobs[jp.job_id] = jp
        self.queue = {q.job_id: q.position for q in st.queue}
        self.changed.set()

    def _on_report(self, sample: Any) -> None:
        from pydantic import ValidationError

        from cellctl.api import ReportEnvelope

        try:
            env = ReportEnvelope.model_validate_json(sample.payload.to_bytes())
        except ValidationError:
            return
        self.reports[env.job_id] = env
        self.changed.set()

    async def next(self, timeout_s: float) -> None:
        self.changed.clear()
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self.changed.wait(), timeout_s)

    def close(self) -> None:
        for s in self._subs:
            with contextlib.suppress(Exception):
                s.undeclare()


def _bar(fraction: float, width: int = 30) -> str:
    n = round(max(0.0, min(1.0, fraction)) * width)
    return "[" + "#" * n + "-" * (width - n) + "]"


async def wait_for_job(
    follower: StatusFollower, job_id: str, timeout_s: float, out=sys.stderr
) -> tuple[str, str, Report | None]:
    """Follow the state publication until job ``job_id`` ends: ``(state, message, report or None)``.

    While the job waits in the daemon's queue, says its position when it changes; then draws a
    one-line progress bar on ``out`` when it is a terminal (a line per stage otherwise).

    The end reported is one after this call: when the job had ended at the call (it was interrupted
    and is now re-analysed), that end, and the same end published again, are not reported; the job
    must first be seen running again (``follower.runs``), and its next end is reported even when it
    is the same as the old one (a re-analysis that fails as the last one did).
    """
    deadline = time.monotonic() + timeout_s
    tty = hasattr(out, "isatty") and out.isatty()
    last_line = ""
    last_position = 0
    at_call = follower.jobs.get(job_id)
    ended_at_call = at_call is not None and at_call.state.value in _FINAL
    runs_at_call = follower.runs.get(job_id, 0)
    while time.monotonic() < deadline:
        await follower.next(1.0)
        position = follower.queue.get(job_id, 0)
        if position and position != last_position:
            out.write(f"queued at position {position}\n")
            out.flush()
        last_position = position
        job = follower.jobs.get(job_id)
        if job is None or (ended_at_call and follower.runs.get(job_id, 0) == runs_at_call):
            continue
        line = f"{job.state.value:<18} {_bar(job.fraction)} {job.fraction:6.1%} {job.stage[:40]:<40} profiles {job.profiles}"
        if tty:
            out.write("\r" + line)
            out.flush()
        elif job.state.value != last_line:
            out.write(line + "\n")
            out.flush()
            last_line = job.state.value
        if job.state.value in _FINAL:
            if tty:
                out.write("\n")
            env = follower.reports.get(job_id)
            # the daemon stores the report before it says done; the publication can trail it
            for _ in range(20):
                if env is not None or job.state.value != "done":
                    break
                await asyncio.sleep(0.1)
                env = follower.reports.get(job_id)
            return job.state.value, job.message, None if env is None else env.report
    return "timeout", f"no end of job {job_id} within {timeout_s} s", None


async def _client_session(cfg, command: str):
    """A client session to the cell's Zenoh, or None after saying why on stderr."""
    from cellctl.api.session import ZenohSetupError, build_zenoh_config, open_session

    try:
        return await asyncio.to_thread(
            open_session, build_zenoh_config(cfg.zenoh, role="connect", key_prefix=cfg.key_prefix)
        )
    except ZenohSetupError as exc:
        print(f"cellctl {command}: error: {exc}", file=sys.stderr)
        return None


def _runner(coro_fn):
    """The command's entry point: load the configuration (exit 2 when bad), then run ``coro_fn``."""

    def run(args: argparse.Namespace) -> int:
        cfg = _config(args.config)
        if cfg is None:
            return EXIT_ERROR
        return asyncio.run(coro_fn(args, cfg))

    return run


async def _scan(args: argparse.Namespace, cfg) -> int:
    from cellctl.api import ApiCallError, Keys, TriggerAccepted, call
    from cellctl.api.session import close_session
    from cellctl.commands.tables import line_table

    try:
        placement = (
            None if args.placement is None else placement_payload(args.placement, cfg.scan.placement_z_mm)
        )
        table = template_table_rows(args.template_table)
    except ValueError as exc:
        print(f"cellctl scan: error: {exc}", file=sys.stderr)
        return EXIT_ERROR
    req = {"plate_id": args.plate, "design": args.design, "note": args.note}
    if placement is not None:
        req["placement"] = placement
    if table:
        req["template_table"] = table
    if args.design_side != "moulded_up":
        req.update(design_side=args.design_side, thickness_mm=args.thickness)
    keys = Keys(cfg.key_prefix)
    session = await _client_session(cfg, "scan")
    if session is None:
        return EXIT_NO_DAEMON
    follower = StatusFollower(session, keys) if args.wait else None
    try:
        try:
            acc = await call(
                session, keys.trigger, json.dumps(req), TriggerAccepted, timeout_s=cfg.zenoh.trigger_timeout_s
            )
        except ApiCallError as exc:
            print(f"cellctl scan: refused: {exc}", file=sys.stderr)
            return EXIT_NO_DAEMON if exc.error is None else EXIT_ERROR
        where = f" at position {acc.queue_position}" if acc.state == "queued" else ""
        print(f"job {acc.job_id} {acc.state}{where}")
        if follower is None:
            return EXIT_OK
        state, message, report = await wait_for_job(follower, acc.job_id, args.timeout_s)
        if state != "done":
            print(f"job {acc.job_id} {state}: {message}", file=sys.stderr)
            return EXIT_ERROR
        if report is not None:
            print(line_table(report))
        print(f"report: {message}")
        return EXIT_OK if report is not None and report.verdict == "pass" else EXIT_FAIL
    finally:
        if follower is not None:
            follower.close()
        await asyncio.to_thread(close_session, session)


run_scan = _runner(_scan)


async def _status(args: argparse.Namespace, cfg) -> int:
    from cellctl.api import Keys, list_workers
    from cellctl.api.session import close_session

    keys = Keys(cfg.key_prefix)
    session = await _client_session(cfg, "status")
    if session is None:
        return EXIT_NO_DAEMON
    follower = StatusFollower(session, keys)
    try:
        workers = await list_workers(session, keys, timeout_s=min(args.timeout_s, 2.0))
        deadline = time.monotonic() + args.timeout_s
        while follower.latest is None and time.monotonic() < deadline:
            await follower.next(0.2)
        st = follower.latest
        if args.json:
            print(json.dumps({
                "cell": None if st is None else json.loads(st.to_json()),
                "workers": [json.loads(w.to_json()) for w in workers],
            }))  # fmt: skip
        else:
            if st is None:
                print(
                    f"cell {cfg.cell.id}: no state publication within {args.timeout_s} s (daemon not running?)"
                )
            else:
                print(f"cell {st.cell_id}: {st.state.value}  {st.message}")
                if st.job is not None:
                    j = st.job
                    print(f"  job {j.job_id} ({j.plate_id}): {j.state.value} {j.fraction:.0%} {j.stage}")
                for j in st.analyses:
                    if st.job is None or j.job_id != st.job.job_id:
                        print(f"  job {j.job_id} ({j.plate_id}): {j.state.value} {j.stage}")
                print(f"queue: {st.queued}")
                for q in st.queue:
                    print(f"  {q.position}. job {q.job_id} ({q.plate_id}) since {q.queued_utc}")
            print(f"workers: {len(workers)}")
            for w in workers:
                print(
                    f"  {w.worker_id} on {w.host} pid {w.pid}: {'busy ' + w.busy_job if w.busy_job else 'idle'}, {w.jobs_done} done"
                )
        return EXIT_OK if st is not None else EXIT_NO_DAEMON
    finally:
        follower.close()
        await asyncio.to_thread(close_session, session)


run_status = _runner(_status)


async def _watch(args: argparse.Namespace, cfg) -> int:
    from cellctl.api import Keys
    from cellctl.api.session import close_session

    keys = Keys(cfg.key_prefix)
    session = await _client_session(cfg, "watch")
    if session is None:
        return EXIT_NO_DAEMON
    follower = StatusFollower(session, keys)
    try:
        while True:
            await follower.next(5.0)
            st = follower.latest
            if st is None:
                continue
            if args.json:
                print(st.to_json().decode(), flush=True)
            else:
                j = st.job
                job = (
                    "" if j is None else f"  job {j.job_id} {j.state.value} {_bar(j.fraction, 20)} {j.stage}"
                )
                queued = f"  queued {st.queued}" if st.queued else ""
                print(f"{st.t_utc} {st.state.value:<12} workers {len(st.workers)}{queued}{job}", flush=True)
    finally:
        follower.close()
        await asyncio.to_thread(close_session, session)


run_watch = _runner(_watch)


async def _control(args: argparse.Namespace, cfg, action: str, payload: dict[str, Any]) -> int:
    from cellctl.api import ApiCallError, ControlReply, Keys, call
    from cellctl.api.session import close_session

    keys = Keys(cfg.key_prefix)
    session = await _client_session(cfg, action)
    if session is None:
        return EXIT_NO_DAEMON
    try:
        try:
            reply = await call(
                session, keys.control(action), json.dumps(payload) if payload else b"", ControlReply,
                timeout_s=cfg.zenoh.trigger_timeout_s,
            )  # fmt: skip
        except ApiCallError as exc:
            print(f"cellctl {action}: refused: {exc}", file=sys.stderr)
            return EXIT_NO_DAEMON if exc.error is None else EXIT_ERROR
        job = "" if reply.job_id is None else f"job {reply.job_id} {reply.job_state}, "
        print(f"{action}: {job}cell {reply.state}")
        return EXIT_OK
    finally:
        await asyncio.to_thread(close_session, session)


async def _abort(args: argparse.Namespace, cfg) -> int:
    return await _control(args, cfg, "abort", {} if args.job is None else {"job_id": args.job})


async def _reset(args: argparse.Namespace, cfg) -> int:
    return await _control(args, cfg, "reset", {})


run_abort = _runner(_abort)
run_reset = _runner(_reset)
