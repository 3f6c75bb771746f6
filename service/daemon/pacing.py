"""When the tuner's worker is busy, it waits a few milliseconds for more batch messages
before a pass, so that the engine's per-pass work is shared by more samples.

A pass over decoded samples costs the engine, the decoder and the console's ring a
fixed ~0.5 ms (a few hundred numpy calls) plus ~2 µs a sample. A cluster's member
receives its gateways' batches as they come, e.g. 400 batches a second of 375 samples
at 150,000 loops: handled one by one, the fixed part is ~40 % of the member's CPU. A
backlog is already handled in one pass (:func:`service.wire.decode.joined`), but a
worker that keeps up has no backlog. So while the worker was busy more than
:data:`LINGER_BUSY` of the last second, it waits up to :data:`LINGER_S` after its first
message for batch messages to reach :data:`LINGER_BYTES`. An idle or lightly loaded
worker never waits: its latency is unchanged, and it has the CPU to spare.
"""

from __future__ import annotations

import time

LINGER_S = 0.005
"""Longest a busy worker waits for more batch messages (added to the update latency
only while it is busy; the bar is 50 ms at p99)."""
LINGER_BYTES = 64 * 1024
"""Batch payload bytes (~1,500 samples) after which a pass starts at once."""
LINGER_BUSY = 0.5
"""Share of the last :data:`WINDOW_S` the worker spent working above which it lingers."""
WINDOW_S = 1.0


class Pacer:
    """The worker's busy share over the last window, and whether it lingers."""

    def __init__(self) -> None:
        self.lingering = False
        self.busy_share = 0.0
        self._busy = 0.0
        self._since = time.perf_counter()

    def worked(self, seconds: float) -> None:
        """The worker spent ``seconds`` on a pass (not waiting for messages)."""
        self._busy += seconds
        now = time.perf_counter()
        if now - self._since >= WINDOW_S:
            self.busy_share = self._busy / (now - self._since)
            self.lingering = self.busy_share > LINGER_BUSY
            self._busy, self._since = 0.0, now
