"""The samples a gateway holds for the tuner, sent at a pace the tuner takes them all.

The tuner's flood limit (:data:`~service.wire.flood.MAX_SAMPLE_RATE_HZ`, its
``--max-sample-rate``) is a bucket per loop of R samples refilled at R per second of its
wall clock, whatever the samples' ``t``. Samples held through an outage and sent at once
lost all but about R of each loop, and the newest at that (an hour of one loop at 1 s:
2,499 of 3,600 rejected as ``flood``). Here each loop's samples go out under a bucket of
the same rule at :data:`PACE_SHARE` of the tuner's rate: at most R/4 at once and R/4 a
second, so the tuner's bucket never empties even if it takes 3 s of them at once (a
worker held up, messages queued).

Order. A loop's samples go in time order: the tuner rejects a sample older than the
loop's last one (``out_of_order``), and takes ten increasing older ones for a new plant
clock, so live samples sent ahead of the backlog would lose it or put the loop's clock
back. Loops are paced apart: a loop without a backlog sends its live samples at the next
flush, whatever the others hold; a loop's live samples wait behind its own backlog only,
at most :data:`CATCH_UP_S`. A loop holding more than the pace sends in that time drops
its oldest (counted as ``samples_cut``, logged once until its backlog is gone): that
far behind, the agent is better served by the loop's present. Beyond ``max_samples``
held in all, the oldest of all are dropped (``samples_dropped``).
"""

from __future__ import annotations

import logging
from collections import Counter, deque

from service.wire.flood import MAX_SAMPLE_RATE_HZ, burst

log = logging.getLogger("pitune.gateway")
PACE_SHARE = 0.25
"""The share of the tuner's flood limit a loop's samples are sent at (rate and burst)."""
CATCH_UP_S = 60.0
"""The longest a loop's live samples wait behind its backlog: a loop holds at most what
the pace sends in this time (15,000 samples at the default limit: 4 h of 1 s samples)."""


class Backlog:
    """Samples held per loop, released by :meth:`take` at the pace; ``len`` is how many."""

    def __init__(self, max_samples: int, tuner_rate_hz: float = MAX_SAMPLE_RATE_HZ) -> None:
        self.max_samples = max_samples
        self.rate = tuner_rate_hz * PACE_SHARE
        self.burst = burst(self.rate)  # the tuner's rule
        self.loop_max = max(int(self.rate * CATCH_UP_S), 1)
        self._held: dict[str, deque[dict]] = {}
        """Per loop with samples held, the samples, oldest first."""
        self._order: deque[str] = deque()
        """The loop of every sample held, in arrival order (the oldest of all is the
        first live entry), and of some gone: a loop's first ``_gone[loop]`` entries are
        of samples sent or cut (a loop's oldest go first), at most as many as are held
        (:meth:`_trim`)."""
        self._gone: Counter[str] = Counter()
        self._tokens: dict[str, tuple[float, float]] = {}
        """Per loop, (tokens, when counted) of its pace's bucket."""
        self._size = 0
        self._told: set[str] = set()
        """Loops cutting their backlog, logged once until it is gone."""

    def __len__(self) -> int:
        return self._size

    def append(self, loop_id: str, sample: dict) -> str | None:
        """Hold ``sample``; the counter name of a sample dropped for it (or None)."""
        held = self._held.setdefault(loop_id, deque())
        held.append(sample)
        self._order.append(loop_id)
        self._size += 1
        dropped = None
        if len(held) > self.loop_max:
            self._forget(loop_id)
            self._gone[loop_id] += 1  # its first live entry in _order is stale now
            if loop_id not in self._told:
                self._told.add(loop_id)
                log.warning(
                    "%s: more samples held than go to the tuner in %.0f s at %g/s (%d): "
                    "its oldest are dropped (samples_cut)",
                    loop_id, CATCH_UP_S, self.rate, self.loop_max,
                )  # fmt: skip
            dropped = "samples_cut"
        elif self._size > self.max_samples:  # the oldest of all: the first live entry's
            while self._gone[oldest := self._order.popleft()]:
                self._gone[oldest] -= 1
            self._forget(oldest)
            dropped = "samples_dropped"
        self._trim()
        return dropped

    def take(self, now: float) -> list[dict]:
        """The samples due at ``now`` (time.monotonic()): each loop's oldest, as many as
        its bucket holds; one of each loop in turn, so the tuner takes each round of
        distinct loops in one pass (docs/protocol.md, Samples)."""
        rounds: list[list[dict]] = []
        for loop_id, held in list(self._held.items()):
            tokens, at = self._tokens.get(loop_id, (self.burst, now))
            tokens = min(self.burst, tokens + (now - at) * self.rate)
            n = min(int(tokens), len(held))
            self._tokens[loop_id] = (tokens - n, now)
            for k in range(n):
                if k == len(rounds):
                    rounds.append([])
                rounds[k].append(held.popleft())
            self._gone[loop_id] += n
            self._size -= n
            if not held:
                del self._held[loop_id]
                self._told.discard(loop_id)
        self._trim()
        return [sample for batch in rounds for sample in batch]

    def put_back(self, samples: list[dict]) -> None:
        """Hold again, first, samples :meth:`take` gave that could not be sent."""
        for sample in reversed(samples):
            loop_id = sample["loop_id"]
            self._held.setdefault(loop_id, deque()).appendleft(sample)
            self._order.appendleft(loop_id)
            self._size += 1

    def _trim(self) -> None:
        """Drop the stale entries of ``_order``: at its left end (a loop's cut or sent
        samples are its oldest, most often the oldest of all), and all of them once they
        outnumber the samples held (a loop whose samples are the oldest held and are not
        cut keeps the others' behind its own). Before, they stayed while no tuner took
        samples: 144,000 an hour of 4 loops at 10 Hz, all gone through by the first
        :meth:`take` after the outage (3.3 s). Amortized O(1) a sample: a full pass
        comes after as many stale entries as are held, and stops at the last of them."""
        order, gone = self._order, self._gone
        while order and gone[order[0]]:
            gone[order.popleft()] -= 1
        if len(order) <= 2 * self._size:
            return
        stale = {loop_id: n for loop_id, n in gone.items() if n}
        gone.clear()
        live: deque[str] = deque()
        entries = iter(order)
        for loop_id in entries:
            if loop_id not in stale:
                live.append(loop_id)
            elif stale[loop_id] > 1:
                stale[loop_id] -= 1
            else:
                del stale[loop_id]
                if not stale:
                    break
        live.extend(entries)  # the rest are live: a loop's stale entries are its first
        self._order = live

    def _forget(self, loop_id: str) -> None:
        """Drop the loop's oldest sample (its entry in ``_order``: the caller's)."""
        held = self._held[loop_id]
        held.popleft()
        self._size -= 1
        if not held:
            del self._held[loop_id]
