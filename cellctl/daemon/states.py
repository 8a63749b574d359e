"""The daemon's state machine: allowed transitions, each one logged and handed to a publisher.

States are :class:`cellctl.api.CellState`. The machine only checks and records; the service decides
when to move. A refused transition raises :class:`StateError` naming both states (a bug in the
service, never a user error).
"""

from __future__ import annotations

import collections
import time
from collections.abc import Callable
from dataclasses import dataclass

import structlog

from cellctl.api import CellState

log = structlog.get_logger(__name__)

S = CellState

#: from -> the states it may go to. ``stopping`` and ``emergency_stopped`` are reachable from anywhere.
ALLOWED: dict[CellState, frozenset[CellState]] = {
    S.STARTING: frozenset({S.IDLE, S.FAULTED}),
    S.IDLE: frozenset({S.PLANNING, S.FAULTED}),
    S.PLANNING: frozenset({S.SCANNING, S.IDLE, S.FAULTED}),
    S.SCANNING: frozenset({S.PAUSED, S.ANALYSING, S.IDLE, S.FAULTED}),
    S.PAUSED: frozenset({S.SCANNING, S.ANALYSING, S.IDLE, S.FAULTED}),
    S.ANALYSING: frozenset({S.IDLE, S.FAULTED}),
    S.FAULTED: frozenset({S.IDLE, S.PLANNING}),
    S.EMERGENCY_STOPPED: frozenset({S.IDLE, S.FAULTED}),
    S.STOPPING: frozenset(),
}
_ANYWHERE = frozenset({S.STOPPING, S.EMERGENCY_STOPPED})


class StateError(RuntimeError):
    """A transition the state machine does not allow."""


@dataclass(frozen=True)
class Transition:
    """One recorded change: from, to, why, when (UTC epoch s)."""

    old: CellState
    new: CellState
    reason: str
    t_utc_s: float


#: transitions kept in :attr:`CellStateMachine.history`
HISTORY_MAX = 1000


class CellStateMachine:
    """Current state plus transition checks; ``on_change(Transition)`` runs after every change.

    Args:
        on_change: called synchronously after each transition (the service publishes from it).
    """

    def __init__(self, on_change: Callable[[Transition], None] | None = None) -> None:
        self.state = S.STARTING
        self.message = ""
        # the recent transitions (for tests and debugging); bounded: the daemon runs for months
        self.history: collections.deque[Transition] = collections.deque(maxlen=HISTORY_MAX)
        self._on_change = on_change

    @property
    def busy(self) -> bool:
        """A scan job holds the robot (planning, scanning, paused) or its analysis is pending."""
        return self.state in (S.PLANNING, S.SCANNING, S.PAUSED, S.ANALYSING)

    def can(self, new: CellState) -> bool:
        """Whether ``new`` is reachable from the current state (a no-op move counts as allowed)."""
        return new == self.state or new in _ANYWHERE or new in ALLOWED[self.state]

    def to(self, new: CellState, reason: str = "") -> Transition | None:
        """Move to ``new``; returns the transition (None when already there).

        Raises:
            StateError: the move is not allowed from the current state.
        """
        new = CellState(new)
        if new == self.state:
            return None
        if not self.can(new):
            raise StateError(f"cell state {self.state.value} -> {new.value} is not allowed ({reason})")
        tr = Transition(self.state, new, reason, time.time())
        self.state = new
        self.message = reason
        self.history.append(tr)
        log.info("cell_state", old=tr.old.value, new=new.value, reason=reason)
        if self._on_change is not None:
            try:
                self._on_change(tr)
            except Exception:  # a failed publication must not stop the cell
                log.exception("cell_state_publish_failed")
        return tr
