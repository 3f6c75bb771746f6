"""The tuner worker's heartbeat: how long it has been busy in its current iteration.

The worker is idle (waiting for messages, age 0) or busy in one iteration (samples,
steps, commits, snapshot and journal chunks). An iteration takes milliseconds; one that
does not end (a store statement blocked on a lock another session holds, a defect)
leaves the daemon alive and answering HTTP while nothing is tuned, committed or
published. ``/healthz`` answers 503 once the age passes ``store_failure_exit_s`` (the
longest the store may fail before the tuner exits: a worker blocked as long is as
stuck), and ``pitune_worker_heartbeat_age_seconds`` shows it at every scrape.
"""

from __future__ import annotations

import time

from prometheus_client import CollectorRegistry, Gauge


class Heartbeat:
    def __init__(self, registry: CollectorRegistry) -> None:
        self._busy_since: float | None = None
        """Monotonic time the worker's current iteration began (None: it waits)."""
        Gauge(
            "pitune_worker_heartbeat_age_seconds",
            "Seconds the worker has been busy in its current iteration (0 while it waits "
            "for messages); /healthz fails past store_failure_exit_s.",
            registry=registry,
        ).set_function(self.age)

    def busy(self) -> None:
        """An iteration begins."""
        self._busy_since = time.monotonic()

    def idle(self) -> None:
        """The worker waits for messages."""
        self._busy_since = None

    def age(self) -> float:
        since = self._busy_since  # one read: the worker may change it meanwhile
        return 0.0 if since is None else time.monotonic() - since
