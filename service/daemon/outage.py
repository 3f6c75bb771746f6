"""A cluster member's view of its store's outages (:mod:`service.daemon.cluster`).

While PostgreSQL is unreachable, both of the member's threads (the renewals and the
ticks) fail every tick: one warning when the first fails, one when both work again
(with how long it lasted); each failure's traceback at debug level only (a traceback
per tick and thread flooded the log for the outage's length).

After an outage the member takes no lease for a while (:attr:`StoreOutage.settling`):
every member's row and leases ran out during it, and the first tick of a member back
before the others had renewed found itself the only live member and took every
expired lease, which the others then found taken (their loops dropped, taken again a
tick later from older snapshots: 182-196 adoptions of 120 loops after an 8 s
outage). Its own leases it renews as they were (same token: nobody took them), as the
others do theirs once they reconnect, within a tick.
"""

from __future__ import annotations

import logging
import threading
import time

log = logging.getLogger("pitune.cluster")
SETTLE_TICKS = 2
"""Ticks after an outage (both threads working again) during which no lease is taken:
the others reconnect and renew within a tick of the database coming back (their
renewal retries at once after reconnecting), one more for a busy box."""


class StoreOutage:
    """The outage in course, if any, and the settling after it."""

    def __init__(self, settle_s: float) -> None:
        self.settle_s = settle_s
        self._lock = threading.Lock()
        self._since: float | None = None
        """Monotonic time the outage began (None: none in course)."""
        self._failing: set[str] = set()
        """The threads whose last attempt failed."""
        self._settled_at = 0.0
        """Monotonic time until which no lease is taken (after the last outage)."""

    def failed(self, part: str, exc: BaseException) -> None:
        """``part`` (the renewal, the tick) failed on the store."""
        with self._lock:
            self._failing.add(part)
            began, self._since = self._since is None, self._since or time.monotonic()
        if began:
            log.warning("store unreachable (%s failed: %s); retried every tick", part, exc)
        log.debug("%s failed", part, exc_info=exc)

    def worked(self, part: str) -> None:
        """``part`` worked: the outage ends once every part that failed works again."""
        with self._lock:
            self._failing.discard(part)
            if self._since is None or self._failing:
                return
            now = time.monotonic()
            lasted, self._since = now - self._since, None
            self._settled_at = now + self.settle_s
        log.warning(
            "store reachable again after %.1f s; taking no lease for %.1f s (the other "
            "members renew theirs meanwhile)", lasted, self.settle_s,
        )  # fmt: skip

    def settling(self) -> float | None:
        """Seconds until leases may be taken again (None: they may now)."""
        with self._lock:
            if self._since is not None:  # in course: until it ends and settles
                return self.settle_s
            left = self._settled_at - time.monotonic()
        return left if left > 0 else None
