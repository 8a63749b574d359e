"""Check a run's skips (the JSON-lines file tests/support/skiplog.py writes) against tests/skip_allowlist.txt.

Prints every skip with the entry that allows it, the count of fallbacks, and exits 1 when a skip is
not allowed, when more than ``--max-fallbacks`` fallbacks happened in all, or more than
``--max-fallbacks-per-module`` in one test module (one module's retries must not use up the run's). An entry of kind "retry" is a
fallback a case took without skipping (it ran a scan again after a starved simulator lost one): it
is allowed and counted like a skip."""

from __future__ import annotations

import argparse
import fnmatch
import json
import sys
from pathlib import Path

FALLBACK = "fallback:"


def load_allowlist(path: Path) -> list[tuple[str, str, str]]:
    entries = []
    for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        fields = [f.strip() for f in line.split(" | ")]
        if len(fields) != 3 or not all(fields):
            raise SystemExit(f"{path}:{n}: want 'test id pattern | reason beginning | why', got {line!r}")
        entries.append((fields[0], fields[1], fields[2]))
    return entries


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("skip_log", type=Path)
    ap.add_argument("--allowlist", type=Path, default=Path("tests/skip_allowlist.txt"))
    ap.add_argument("--max-fallbacks", type=int, required=True)
    ap.add_argument("--max-fallbacks-per-module", type=int, default=1)
    args = ap.parse_args(argv)
    allow = load_allowlist(args.allowlist)
    skips = []
    if args.skip_log.exists():
        skips = [json.loads(line) for line in args.skip_log.read_text(encoding="utf-8").splitlines() if line]
    refused, fallbacks = [], []
    for s in skips:
        entry = next(
            (e for e in allow if fnmatch.fnmatch(s["nodeid"], e[0]) and s["reason"].startswith(e[1])), None
        )
        what = "retry" if s.get("kind") == "retry" else "skip"
        if entry is None:
            refused.append(s)
            print(f"ci: {what} NOT allowed: {s['nodeid']}: {s['reason']}", file=sys.stderr)
        else:
            print(f"ci: {what} allowed ({entry[1]}): {s['nodeid']}: {s['reason']}")
        if s["reason"].startswith(FALLBACK):
            fallbacks.append(s)
    retries = sum(1 for s in skips if s.get("kind") == "retry")
    print(
        f"ci: {len(skips) - retries} skipped, {len(fallbacks)} fallbacks ({retries} of them retries that "
        f"went on) (at most {args.max_fallbacks} allowed)"
    )
    if refused:
        print(f"ci: {len(refused)} skips are not on {args.allowlist}", file=sys.stderr)
    if len(fallbacks) > args.max_fallbacks:
        print(f"ci: {len(fallbacks)} fallbacks, more than {args.max_fallbacks}", file=sys.stderr)
    per_module: dict[str, int] = {}
    for s in fallbacks:
        module = s["nodeid"].split("::", 1)[0]
        per_module[module] = per_module.get(module, 0) + 1
    crowded = {m: n for m, n in per_module.items() if n > args.max_fallbacks_per_module}
    for m, n in sorted(crowded.items()):
        print(
            f"ci: {m}: {n} fallbacks, more than {args.max_fallbacks_per_module} in a module", file=sys.stderr
        )
    return 1 if refused or len(fallbacks) > args.max_fallbacks or crowded else 0


if __name__ == "__main__":
    sys.exit(main())
