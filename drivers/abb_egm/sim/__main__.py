"""``python -m drivers.abb_egm.sim``: the controller simulator as a stand-alone process."""

import sys

import structlog

from drivers.abb_egm.sim.controller import main

if __name__ == "__main__":
    if not structlog.is_configured():
        # stdout carries the one machine-readable line with the addresses; logs go to stderr
        structlog.configure(logger_factory=structlog.PrintLoggerFactory(sys.stderr))
    sys.exit(main())
