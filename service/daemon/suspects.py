"""Which other members of a cluster look dead, and the parsing ahead of a takeover of
their shards: a part of :class:`~service.daemon.cluster.Cluster` (a mixin).

A member is *gone* when its Zenoh liveliness token is: seen going (a crashed process's
connections close, its token goes at once; the bus's event wakes the cluster's tick,
:meth:`Suspects.token_changed`), or found missing after it missed a renewal. The shards
this member would win without the gone members are parsed ahead on a thread of their
own. A gone member is *dead* once its leases went :data:`DEAD_AFTER_TICKS` ticks
without a renewal: :meth:`Cluster._take <service.daemon.cluster.Cluster._take>` takes
them then, the database checking that condition itself (docs/deploy.md, Failover).
"""

from __future__ import annotations

import logging
import threading
import time

import psycopg

from service.daemon import shards as sharding

log = logging.getLogger("pitune.cluster")
SUSPECT_AFTER_TICKS = 1.5
"""A member whose row has less than ``lease_s`` minus this many ticks left missed a
renewal; if its Zenoh liveliness token is gone too, it is *gone* (probably dead: see
:meth:`Suspects._gone`), and the shards this member would win without it are parsed
ahead (:meth:`Suspects._parse_ahead`)."""
DEAD_AFTER_TICKS = 3
"""A gone member whose leases have not been renewed for this many ticks (two renewals
missed, by the database's clock) is dead: its leases are taken then, ``lease_s`` minus
this many ticks before they run out (:meth:`Cluster._take
<service.daemon.cluster.Cluster._take>`; docs/deploy.md, Failover, for why fencing
still holds)."""


class Suspects:
    """The gone and dead members (see the module doc), for :class:`Cluster
    <service.daemon.cluster.Cluster>`, which holds the state these methods use."""

    def token_changed(self, member: str, there: bool) -> None:
        """The bus saw ``member``'s liveliness token come (``there``) or go: a crashed
        member's goes at once, and the tick comes now to parse its shards ahead."""
        with self._lock:
            if there:
                self._left.pop(member, None)
            else:
                self._left[member] = time.monotonic()
        if not there:
            self._wake.set()

    def _gone(self, live: dict[str, float]) -> set[str]:
        """The other members whose Zenoh liveliness token is gone: seen going (a process
        that died lost its token when its connections closed), or not found when asked
        after a missed renewal (:data:`SUSPECT_AFTER_TICKS`; a token that went before
        this member joined). One that is only slow renews late but keeps its token; one
        cut off from the bus is gone, but keeps renewing its row (so never dead), and is
        no longer gone ``lease_s`` after its token went (a dead one's leases are taken
        by then): the loops parsed ahead for it are let go."""
        recent = time.monotonic() - self.lease_s
        with self._lock:
            self._left = {m: t for m, t in self._left.items() if m in live and t > recent}
            gone = set(self._left) - {self.member}
        fresh = self.lease_s - SUSPECT_AFTER_TICKS * self.tick_s
        late = {m for m, left in live.items() if left < fresh and m != self.member} - gone
        return gone | (late - self.tuner.bus.live_tuners() if late else set())

    def _next_due(self, lasts: dict[str, float], gone: set[str]) -> float | None:
        """Seconds until the next tick that may take leases: another member's last expiry,
        or for a gone member the moment it counts as dead (:data:`DEAD_AFTER_TICKS`) if
        that is still to come (None: no other member live)."""
        early = self.lease_s - DEAD_AFTER_TICKS * self.tick_s
        dues = list(lasts.values())
        dues += [lasts[m] - early for m in gone if m in lasts and lasts[m] - early > 0]
        return min(dues, default=None)

    def _parse_ahead(
        self, live: dict[str, float], stored: list[str], held: set[str], suspects: set[str]
    ) -> None:
        """``suspects``, the gone members (:meth:`_gone`), are probably dead: parse the
        configs and snapshots of the shards this member would win without them until
        their leases are taken, on a thread of its own (:meth:`PgStore.parse_ahead
        <service.daemon.store_pg.PgStore.parse_ahead>`; the takeover stops it and parses
        what is left). An overloaded member renews late but keeps its token: parsing its
        loops for nothing would load this member too."""
        ahead = set()
        if suspects:
            rest = [m for m in live if m not in suspects]
            ahead = {s for s, m in sharding.assign(stored, rest).items() if m == self.member}
            ahead -= held
        if ahead != self._ahead and not (ahead and ahead <= self._ahead):
            # (fewer shards than parsed: those are parsed already, a load takes them)
            self._ahead = ahead
            self._stop_parsing()
            if not ahead:
                self.tuner.store.parse_ahead([])
                return
            log.info("%s stopped renewing: parsing the loops of %d shards ahead of a takeover",
                     ", ".join(sorted(suspects)), len(ahead))  # fmt: skip
            stop = threading.Event()
            thread = threading.Thread(
                target=self._parse,
                args=(sorted(ahead), stop),
                name="pitune-parse-ahead",
                daemon=True,
            )
            self._parsing = (thread, stop)
            thread.start()

    def _stop_parsing(self) -> None:
        """Stop the parsing ahead (what it parsed stays for the load): a takeover
        begins, or the suspects changed. It ran on a thread of its own, as parsing
        150,000 loops takes the seconds the tick must be there when the leases end."""
        parsing, self._parsing = self._parsing, None
        if parsing is not None:
            parsing[1].set()
            parsing[0].join()

    def _parse(self, shards: list[str], stop: threading.Event) -> None:
        try:
            n = self.tuner.store.parse_ahead(shards, stop)
        except psycopg.Error:  # the takeover parses them itself
            log.exception("parsing ahead of a takeover failed")
            return
        log.info("%d loops parsed ahead of a takeover%s", n, " (stopped)" * stop.is_set())
