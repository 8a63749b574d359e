"""`cellctl synth`: a synthetic scan of a formed plate with its design and truth (analysis.synth)."""

from __future__ import annotations

import argparse

from analysis.synth import build_parser, synth_main


def register(sub: argparse._SubParsersAction) -> None:
    # The options are analysis.synth's own; its parser prints them for `cellctl synth --help`.
    p = sub.add_parser(
        "synth",
        help=build_parser().description,
        add_help=False,
        prefix_chars="\0",
    )
    p.add_argument("args", nargs=argparse.REMAINDER)
    p.set_defaults(func=lambda a: synth_main(a.args))
