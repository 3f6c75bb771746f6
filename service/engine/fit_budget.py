"""The identification budget: how much of a core the model fits may take.

An assessment (the fit, :func:`service.engine.identify.assess`, and what a confident
model then decides) costs 7-20 ms of CPU on this box and runs under the table's lock. A
site that identifies every loop (``PITUNE_IDENTIFY_HINTED_LOOPS``) with its setpoints
moved every 20-60 s asks for about 250 assessments a second at 10,000 loops, more than a
core: with every assessment made in the sample path when due, the worker fell behind
the samples (p99 update latency 4.1 s in ``pitune bench``, docs/identification.md).

With a budget the fits take at most ``share`` of one core over time: a token bucket of
CPU seconds, refilled with the wall time each message is handled at (read once per
message, not per ingest: refilled from a clock read at every ingest, the budget of the
accelerated retention bench (``clock_speed`` 360) refilled within each pass and let the
fits starve the worker: the load generator fell 12-15 s behind against 1-4 s, session 40),
holding at most ``share`` x :data:`WINDOW_S`.
In one ingest of samples (a message, usually) they take at most :data:`PASS_S` (and the
one fit that overdraws it); an assessment beyond is *owed*: the loop's segment keeps recording, and
owed loops are assessed in turn, on their latest data, by :meth:`TuningEngine.catch_up
<service.engine.engine.TuningEngine.catch_up>`, which the tuner's worker calls when it
has no samples waiting. Loops that cannot tune without a model (identifying, flagged or
paused) go before loops whose hint is merely being checked. A segment that ends (manual,
saturated, a gap) on a spent budget is released unassessed (:func:`service.engine.watch.
_close`): a plant trip ends thousands at once.

Without a share (``None``: the engine's default, and every evaluation) each assessment
is made when due and nothing is owed, so an evaluation's numbers do not depend on the
speed of the box.
"""

from __future__ import annotations

import time
from collections import deque

PASS_S = 0.01
"""CPU seconds of fits one pass may take (and the one fit that overdraws it): samples
never wait behind more, however many loops fall due at once (a plant-wide setpoint
change)."""
WINDOW_S = 2.0
"""Seconds of the share the bucket holds: what idle moments may spend at once."""


class FitBudget:
    """The token bucket and the loops owed an assessment (slots, in order, each once)."""

    def __init__(self, share: float | None) -> None:
        if share is not None and not share > 0.0:
            raise ValueError(f"identification budget share must be positive, not {share}")
        self.share = share
        """Share of one core the fits may take (None: no limit)."""
        self.tokens = 0.0 if share is None else self.cap
        self.pass_left = PASS_S
        self.wall: float | None = None
        self.urgent: deque[int] = deque()
        """Owed loops that cannot tune without a model (identifying, flagged, paused)."""
        self.checks: deque[int] = deque()
        """Owed loops tuning on a scaling in force (a hint or a model being checked)."""
        self.owed: set[int] = set()
        self.deferred = 0
        """Assessments deferred so far (each owed loop counts once per deferral)."""
        self.spent_s = 0.0
        """CPU seconds the fits took so far (measured with or without a share)."""

    @property
    def cap(self) -> float:
        return 0.0 if self.share is None else max(PASS_S, self.share * WINDOW_S)

    def refill(self, wall: float) -> None:
        """A new pass at ``wall`` (seconds): the bucket refilled, the pass's own limit new."""
        self.pass_left = PASS_S
        if self.share is None:
            return
        if self.wall is not None and wall > self.wall:
            self.tokens = min(self.cap, self.tokens + (wall - self.wall) * self.share)
        self.wall = wall  # a clock stepped back (NTP) refills nothing, and stalls nothing

    def allows(self) -> bool:
        return self.share is None or (self.tokens > 0.0 and self.pass_left > 0.0)

    def wait_s(self, wall: float) -> float | None:
        """Seconds from ``wall`` until an owed loop can be assessed (0: now; None: none
        is owed)."""
        if not self.owed:
            return None
        if self.share is None or self.wall is None:
            return 0.0
        return max(0.0, (-self.tokens) / self.share - max(0.0, wall - self.wall))

    def owe(self, s: int, urgent: bool) -> None:
        if s in self.owed:
            return
        self.owed.add(s)
        (self.urgent if urgent else self.checks).append(s)
        self.deferred += 1

    def next_owed(self) -> int | None:
        """The next owed loop to assess (urgent ones first), or None."""
        for queue in (self.urgent, self.checks):
            if queue:
                s = queue.popleft()
                self.owed.discard(s)
                return s
        return None

    def forget(self, s: int) -> None:
        """Slot ``s`` no longer owed (its segment ended, was restarted or removed)."""
        if s in self.owed:
            self.owed.discard(s)
            for queue in (self.urgent, self.checks):
                if s in queue:
                    queue.remove(s)

    def timed(self, fit, *args):
        """Run ``fit(*args)`` and charge its CPU time (this thread's) to the bucket."""
        started = time.thread_time()
        try:
            return fit(*args)
        finally:
            spent = time.thread_time() - started
            self.spent_s += spent
            self.pass_left -= spent
            if self.share is not None:
                self.tokens -= spent

    @property
    def waiting(self) -> int:
        return len(self.owed)
