"""The clock the engine's elapsed-time rules measure on: staleness (``stale_gap`` after
the last sample) and the flood limit's token bucket (not the identification budget's
refill: :mod:`service.engine.fit_budget` says why).

A wall clock steps (an NTP correction, an operator's ``date``): stepped back an hour, a
dead gateway's loops would read fresh for that hour. A table given a step-free clock
(:attr:`LoopTable.clock`, the daemon's :meth:`~service.daemon.clock.Clock.steady`)
measures on it, and the ``wall`` each call passes is kept only for what is shown and
recorded (audit rows' ``wall_time``). Without one (tests, scripts that pass their own
walls) the ``wall`` passed is the clock.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from service.engine.table import LoopTable


def now(tb: LoopTable, wall: float) -> float:
    """The time now on ``tb``'s step-free clock, or ``wall`` if it has none."""
    return wall if tb.clock is None else tb.clock()
