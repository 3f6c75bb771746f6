"""Several tuners sharing one PostgreSQL store: membership, shard leases, fencing.

Each member keeps a row in ``members`` (its API URL, live until ``expires``) and holds a lease
in ``leases`` for every shard it owns (see :mod:`service.daemon.shards`). A member's thread,
every ``lease_s / 5`` seconds (:data:`TICKS_PER_LEASE`):

1. renews its member row and its leases (one transaction, the database's clock); a
   lease it no longer finds (another member took it) is lost: its loops are dropped
   (by the tick; the shard is not taken again before);
2. reads the live members, the shards of the stored loops and the plant-wide hold
   (:mod:`service.daemon.holds`), and computes who wins each shard (rendezvous hashing);
3. releases the shards it holds but no longer wins (a member joined): it commits and
   snapshots their loops, drops them, and ends their leases at once, so the winner
   takes them on its next tick (a gap of one tick);
4. acquires the shards it wins whose lease is free, expired or a dead member's (see
   below): a new fencing token (the store's epoch counter, so larger than every earlier
   token and epoch), then the shards' loops are loaded from the store (gains, seq, last
   snapshot) into the engine (a failed load lets the leases go: taken again);
5. waits for ``NOTIFY pitune_loops`` (loops registered, patched or deleted through any
   member) until the next tick, and reloads those loops it owns (a failed reload: again).

Fencing: every commit carries the tokens of the shards it touches (:meth:`Cluster.fence`); the
store refuses it unless this member still holds each lease unexpired
(:class:`~service.daemon.store_pg.Fenced`); refused, the member renews its leases at once
(:meth:`Cluster.revive`) and drops only the loops of those another member took. Publishing
is allowed only while the leases are valid by this process's monotonic clock
(:meth:`Cluster.may_publish`): from the start of the last successful renewal plus
``lease_s`` minus :data:`SAFETY_S`. A member paused past its lease (SIGSTOP, a VM freeze)
finds on waking that it may no longer publish, its commits fail, and its renewal finds the
leases gone: it drops those loops and, still a member, gets shards again by the hashing.
Gains messages carry the shard's token as their ``epoch``, so a gateway orders the new
owner's messages after any of the old owner's; the new owner sends each loop's last
committed message again, which the old owner may have left unpublished
(:meth:`Ownership.adopt_shards <service.daemon.ownership.Ownership.adopt_shards>`).

A dead member's leases are taken before they expire when the database and the bus agree that it
is dead: its Zenoh liveliness token is gone (a crashed process's connections close at once; a
paused or starved one keeps its token) and its leases have not been renewed for
:data:`DEAD_AFTER_TICKS` ticks, by the database's clock, in the statement that takes them
(:meth:`Cluster._take`), so a member that still renews is never overrun, whatever the others
believe (:mod:`service.daemon.suspects`). The others time their tick to that moment: loops move
about 2-3 s after a crash plus the load (the last renewal was up to a tick before it).
Otherwise (a token still there: a host that lost power or its network keeps it at the peers
until Zenoh's transport lease, 10 s by default, runs out) they take the leases when they
expire, ``lease_s`` after the last renewal.

The store unreachable for every member (a restart of PostgreSQL) lets every lease run out:
once it is back, each member renews its own (nobody took them) and takes none for a while
(:mod:`service.daemon.outage`), so the cluster stays as it was.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import threading
import time
from typing import TYPE_CHECKING

import psycopg

from service.daemon import shards as sharding
from service.daemon.metrics import cluster_totals
from service.daemon.notifies import Notifies
from service.daemon.outage import SETTLE_TICKS, StoreOutage
from service.daemon.store_pg import CHANNEL, Fenced, connect
from service.daemon.survey import survey
from service.daemon.suspects import DEAD_AFTER_TICKS, Suspects

if TYPE_CHECKING:
    from service.daemon.tuner import Tuner

log = logging.getLogger("pitune.cluster")
TICKS_PER_LEASE = 5
ADOPTIONS_KEPT = 16
EXPIRY_MARGIN_S = 0.05
"""A tick timed to another member's expiry comes this long after it (a member's leases
expire a few milliseconds after its row: renewed in the same transaction, later)."""
SAFETY_S = 0.5
"""Publishing stops this long before the leases run out by the local clock (clock rate
differences between the hosts, the time a put takes)."""


class Cluster(Suspects, Notifies):
    """This tuner's membership of the cluster sharing its PostgreSQL store."""

    def __init__(self, tuner: Tuner, url: str) -> None:
        settings = tuner.settings
        self.tuner = tuner
        self.url = url
        self.member = settings.instance_id
        self.api_url = settings.cluster_url or f"http://{settings.api_host}:{settings.api_port}"
        self.lease_s = settings.cluster_lease_s
        self.tick_s = self.lease_s / TICKS_PER_LEASE
        self._lock = threading.Lock()
        self._leasing = threading.Lock()
        """Serialises the lease writes (renewals, releases, acquisitions): a renewal must
        not extend a lease released meanwhile. Loading loops happens outside it."""
        self.held: dict[str, int] = {}
        """Shard -> lease token, of the shards whose loops are in the engine."""
        self.shard_of: dict[str, str] = {}
        """Loop id -> shard, of the loops in the engine."""
        self.floors: dict[str, int] = {}
        """Loop id -> the least epoch of its messages, of loops that came from another shard,
        whose token may have been the higher (:meth:`token`)."""
        self.valid_until = 0.0
        """Monotonic time until which the held leases are valid (publishing allowed)."""
        self.members: list[str] = []
        self.moves = 0
        """Shards acquired since start (after a failover or a rebalance)."""
        self.takeovers = 0
        """Shards the ticks acquired after the first (``pitune_cluster_takeovers_total``)."""
        self.adoptions: collections.deque[dict] = collections.deque(maxlen=ADOPTIONS_KEPT)
        """The last acquisitions: wall time begun, shards, loops, store load and engine
        insert seconds, and of those the turns at the table's lock awaited (``GET /cluster``:
        where a failover's time goes)."""
        self._stop = threading.Event()
        self._conn: psycopg.Connection | None = None
        self._beat_conn: psycopg.Connection | None = None
        self._threads: list[threading.Thread] = []
        self._ahead: set[str] = set()
        """Shards whose configs and snapshots are parsed ahead (:meth:`_parse_ahead`)."""
        self._parsing: tuple[threading.Thread, threading.Event] | None = None
        """The thread parsing them, and the event that stops it."""
        self._lost: set[str] = set()
        """Shards a renewal found taken whose loops are still in the engine: the tick drops
        them (:meth:`Ownership.drop_shards
        <service.daemon.ownership.Ownership.drop_shards>` takes them off this set), and
        none is taken again before (:meth:`_acquire`)."""
        self._reload_todo: set[str] = set()  # loops whose reload failed: again until it works
        self.ready = threading.Event()
        """Set after the first tick (this member holds what it wins, as far as free)."""
        self._left: dict[str, float] = {}
        """Member -> monotonic time its liveliness token went (events of the bus)."""
        self._wake = threading.Event()
        """Set when a member's token goes: the tick comes at once, not up to a tick later."""
        self.outage = StoreOutage(SETTLE_TICKS * self.tick_s)
        tuner.metrics.totals(cluster_totals(self))

    # -- lifecycle --------------------------------------------------------------------
    def start(self) -> None:
        """Join, then two threads: the renewals (never held up by loading loops, which
        can take seconds for large shards) and the ticks (everything else)."""
        self._conn = connect(self.url)
        self._conn.execute(f"LISTEN {CHANNEL}")
        self.tuner.load_gateway_shards()  # listening first: no change falls in between
        self._beat_conn = connect(self.url)
        self._join()
        self.tuner.bus.on_member = self.token_changed
        self._threads = [
            threading.Thread(target=target, name=name, daemon=True)
            for target, name in ((self._beat, "pitune-lease"), (self._run, "pitune-cluster"))
        ]
        for thread in self._threads:
            thread.start()

    def halt(self) -> None:
        """Stop the threads (no more acquisitions, renewals or reloads)."""
        self._stop.set()
        self._stop_parsing()
        for thread in self._threads:
            thread.join(timeout=10.0)

    def leave(self) -> None:
        """Release every lease at once (the others take the loops on their next tick)
        and delete the member row."""
        self.halt()
        with contextlib.suppress(psycopg.Error), connect(self.url) as conn, conn.transaction():
            conn.execute(
                "UPDATE leases SET expires = clock_timestamp() - interval '1 second' "
                "WHERE owner = %s",
                (self.member,),
            )
            conn.execute("DELETE FROM members WHERE instance_id = %s", (self.member,))
        for conn in (self._conn, self._beat_conn):
            if conn is not None:
                conn.close()
        with self._lock:
            self.held.clear()
            self.valid_until = 0.0

    def _join(self) -> None:
        self._beat_conn.execute(
            "INSERT INTO members (instance_id, api_url, started, expires) VALUES "
            "(%s, %s, %s, clock_timestamp() + make_interval(secs => %s)) "
            "ON CONFLICT (instance_id) DO UPDATE SET api_url = excluded.api_url, "
            "started = excluded.started, expires = excluded.expires",
            (self.member, self.api_url, time.time(), self.lease_s),
        )

    def _run(self) -> None:
        while not self._stop.is_set():
            started = time.monotonic()
            until = started + self.tick_s
            try:
                due = self.tick()
                self.outage.worked("tick")
                if due is not None:  # a member stopped renewing: be there when it ends
                    until = min(until, time.monotonic() + due + EXPIRY_MARGIN_S)
            except psycopg.Error as exc:  # the database unreachable: retried next tick
                self.outage.failed("tick", exc)
                self._reconnect()
            except Exception:
                log.exception("cluster tick failed; retrying")
            finally:
                self.ready.set()
            self._wait_notifies(until)

    def _reconnect(self) -> None:
        with contextlib.suppress(psycopg.Error):
            if self._conn.closed or self._conn.broken:
                self._conn = connect(self.url)
                self._conn.execute(f"LISTEN {CHANNEL}")
                # changes made while not listening came with no notification
                self.tuner.load_gateway_shards()

    def _beat(self) -> None:
        """Renew the member row and the leases every tick, whatever else is going on."""
        while not self._stop.is_set():
            started = time.monotonic()
            try:
                self._renew(started)
                self.outage.worked("renewal")
                took = time.monotonic() - started
                if took > self.tick_s:  # the leases survive a delay of lease_s - tick_s only
                    log.warning("lease renewal took %.1f s (tick %.1f s)", took, self.tick_s)
            except psycopg.Error as exc:  # the database unreachable: the leases run out
                self.outage.failed("renewal", exc)
                if self._beat_conn.closed or self._beat_conn.broken:
                    with contextlib.suppress(psycopg.Error):
                        self._beat_conn = connect(self.url)
                        continue  # reconnected: renew now, not a tick later (others wait)
            self._stop.wait(max(0.0, started + self.tick_s - time.monotonic()))

    # -- one tick ---------------------------------------------------------------------
    def tick(self) -> float | None:
        """One tick (see the module doc); seconds until the next expiry of another
        member's row or lease (None: none live)."""
        with self._lock:
            lost = set(self._lost)  # (off the set once dropped, not before: see _acquire)
        if lost:
            log.warning("leases lost (taken by another member): %s", ", ".join(sorted(lost)))
            self.tuner.drop_shards(lost, commit=False)
        live, stored, lasts = survey(self._conn, self.member)
        self.tuner.sync_hold()  # a hold set or released through another member
        # this member is alive whatever its row says: a renewal that came late (a starved
        # process) let the row run out, and releasing every shard it holds only to take
        # them back a tick later cost a 75,000-loop member 40 s of loading; its leases
        # still fence it if they ran out too
        live.setdefault(self.member, 0.0)
        gone = self._gone(live)
        dead = {m for m in gone if live[m] < self.lease_s - DEAD_AFTER_TICKS * self.tick_s}
        self.members = sorted(set(live) - dead)
        settling = self.outage.settling()
        if settling is not None:  # after a store outage every row ran out: none is taken
            return settling
        wins = {s for s, m in sharding.assign(stored, self.members).items() if m == self.member}
        with self._lock:
            held = set(self.held)
        release = held - wins
        if release:
            self._release(release)
        self._acquire(wins - set(self.held), dead=dead)
        with self._lock:
            held = set(self.held)
        self._parse_ahead(live, stored, held, gone)  # after the acquisitions, which use them
        return self._next_due(lasts, gone)

    def _renew(self, started: float) -> None:
        with self._leasing:
            self._renew_held(started)

    def revive(self, shards: set[str]) -> set[str]:
        """Those of ``shards`` (leases a commit found not held) that another member took,
        after renewing the leases now: the others only ran out (the store was unreachable
        longer than the lease, or the renewals late), and the renewal extends a lease
        still this member's with its token whether or not it ran out (a lease taken has
        another token: lost). Raises psycopg.Error if the store fails."""
        self._renew(time.monotonic())
        with self._lock:
            return {shard for shard in shards if shard not in self.held}

    def _renew_held(self, started: float) -> None:
        """Renew the member row and the held leases; a lease found taken is held no more
        and its shard waits in :attr:`_lost` for its loops to be dropped."""
        with self._lock:
            held = dict(self.held)
            loops = len(self.shard_of)  # for GET /cluster (service.daemon.directory)
        conn = self._beat_conn
        with conn.transaction():
            renewed = conn.execute(
                "UPDATE members SET expires = clock_timestamp() + make_interval(secs => %s), "
                "loops = %s WHERE instance_id = %s",
                (self.lease_s, loops, self.member),
            ).rowcount
            kept = {
                r[0]
                for r in conn.execute(
                    "UPDATE leases l SET expires = clock_timestamp() + make_interval(secs => %s) "
                    "FROM unnest(%s::text[], %s::int8[]) AS h(shard, token) "
                    "WHERE l.shard = h.shard AND l.token = h.token AND l.owner = %s "
                    "RETURNING l.shard",
                    (self.lease_s, list(held), list(held.values()), self.member),
                )
            }
        if not renewed:  # our row was deleted (we were taken for dead): join again
            self._join()
        with self._lock:
            for shard in set(held) - kept:
                if self.held.get(shard) == held[shard]:  # (not lost to a commit meanwhile)
                    self.held.pop(shard)
                    # at once, as it stops being held: a tick that read the lost shards
                    # before this renewal took them again, wakening from a pause, with the
                    # loops from before it still in the engine (a takeover keeps a loop it
                    # has): it stepped them under the new lease, then dropped them and kept
                    # the leases, loading nothing (a CI run, session 40)
                    self._lost.add(shard)
            self.valid_until = started + self.lease_s - SAFETY_S

    def _release(self, shards: set[str]) -> None:
        """Hand shards to the member that now wins them: commit and snapshot their loops
        while the leases are ours, drop them, end the leases."""
        self.tuner.drop_shards(shards, commit=True)
        log.info("released %d shards to other members", len(self._let_go(shards)))

    def _unadopt(self, shards: list[str]) -> None:
        """A takeover whose load failed: let go, for a later tick to take and load again
        (held, they stayed leased and were never loaded)."""
        self.tuner.drop_shards(set(shards), commit=False)
        log.warning("loading %d taken shards failed", len(self._let_go(shards, store_down=True)))

    def _let_go(self, shards, *, store_down: bool = False) -> dict[str, int]:
        """Hold the shards no more, end their leases (or, ``store_down``, let them lapse)."""
        with self._leasing:
            with self._lock:
                tokens = {s: self.held.pop(s) for s in shards if s in self.held}
            with contextlib.suppress(*(psycopg.Error,) * store_down):  # (): nothing
                self._conn.execute(
                    "UPDATE leases l SET expires = clock_timestamp() - interval '1 second' "
                    "FROM unnest(%s::text[], %s::int8[]) AS h(shard, token) "
                    "WHERE l.shard = h.shard AND l.token = h.token AND l.owner = %s",
                    (list(tokens), list(tokens.values()), self.member),
                )
        return tokens

    def claim(self, shards: set[str]) -> None:
        """Acquire now those of ``shards`` no member holds (a registration through this
        member of loops in a new shard); the hashing moves them later if another member
        wins them. Just after a store outage, none (the tick takes them once it settles)."""
        if self.outage.settling() is not None:
            return
        with connect(self.url) as conn:
            self._acquire(shards - set(self.held), conn)

    def _acquire(
        self, shards: set[str], conn: psycopg.Connection | None = None, dead: set[str] = frozenset()
    ) -> None:
        if not shards:
            return
        started = time.time()
        token = self.tuner.store.next_epoch(started, "keep")  # checked at the start
        with self._leasing:  # (a renewal's finding a lease taken comes before or after)
            with self._lock:
                shards = shards - self._lost  # their old loops out of the engine first
            taken = self._take(shards, token, conn or self._conn, dead) if shards else []
        if not taken:
            return
        if conn is None:  # (the cluster's thread: the parsing ahead's owner)
            self._stop_parsing()
        try:
            timing = self.tuner.adopt_shards(taken, token)
        except Exception:
            self._unadopt(taken)
            raise
        self._count_loops(conn or self._conn)
        self.moves += len(taken)
        if conn is None and self.ready.is_set():  # a tick's, not the start's or a claim's
            self.takeovers += len(taken)
        self.adoptions.append({"at": started, "shards": len(taken), **timing})
        log.info(
            "acquired %d shards (token %d): %d loops, store load %.2f s, engine insert %.2f s "
            "(%.2f s of it waiting for the table's lock)",
            len(taken), token, timing["loops"], timing["load_s"], timing["insert_s"],
            timing["lock_wait_s"],
        )  # fmt: skip

    def _count_loops(self, conn: psycopg.Connection) -> None:
        """This member's loop count in its row now (``GET /cluster`` right after a
        takeover; the renewals keep it up to date), between two renewals: one that read
        the count before the takeover cannot overwrite it after."""
        with self._leasing:
            with self._lock:
                loops = len(self.shard_of)
            conn.execute(
                "UPDATE members SET loops = %s WHERE instance_id = %s", (loops, self.member)
            )

    def _take(
        self, shards: set[str], token: int, conn: psycopg.Connection, dead: set[str] = frozenset()
    ) -> list[str]:
        """The leases of those ``shards`` that are free or expired, or held by a ``dead``
        member (:meth:`_gone`) and not renewed for :data:`DEAD_AFTER_TICKS` by the
        database's clock, now this member's (held, so renewed, from here on; their loops
        are loaded next). A member that renews keeps its leases whatever this member
        believes: the database decides, in the statement that takes them."""
        taken = [
            r[0]
            for r in conn.execute(
                "INSERT INTO leases (shard, owner, token, expires) "
                "SELECT s, %s, %s, clock_timestamp() + make_interval(secs => %s) "
                "FROM unnest(%s::text[]) AS s "
                "ON CONFLICT (shard) DO UPDATE SET owner = excluded.owner, "
                "token = excluded.token, expires = excluded.expires "
                "WHERE leases.expires < clock_timestamp() OR (leases.owner = ANY(%s::text[]) "
                "AND leases.expires < clock_timestamp() + make_interval(secs => %s)) "
                "RETURNING shard",
                (
                    self.member,
                    token,
                    self.lease_s,
                    sorted(shards),
                    sorted(dead),
                    self.lease_s - DEAD_AFTER_TICKS * self.tick_s,
                ),
            )
        ]
        if dead and taken:
            # its row too, on the same condition (GET /cluster: not live, its loops 0);
            # a member that comes back renews it
            conn.execute(
                "UPDATE members SET expires = clock_timestamp() WHERE instance_id = ANY(%s) "
                "AND expires < clock_timestamp() + make_interval(secs => %s)",
                (sorted(dead), self.lease_s - DEAD_AFTER_TICKS * self.tick_s),
            )
        with self._lock:
            for shard in taken:
                self.held[shard] = token
        return taken

    # -- for the tuner ----------------------------------------------------------------
    def owns(self, shard: str) -> bool:
        return shard in self.held

    def lose(self, shards: set[str]) -> None:
        """Leases the store says are no longer this member's."""
        with self._lock:
            for shard in shards:
                self.held.pop(shard, None)

    def adopted(self, shard: str, token: int, loop_ids: list[str], floor: int | None = None):
        """``floor``: the loops' least epoch from now on (0: none; None: as it was)."""
        with self._lock:
            self.held[shard] = token
            for loop_id in loop_ids:
                self.shard_of[loop_id] = shard
                if floor is not None:
                    self.floors[loop_id] = floor

    def dropped(self, shards: set[str]) -> None:
        """The shards' loops are out of the engine: lost ones may be taken again."""
        with self._lock:
            self._lost -= shards

    def forget(self, loop_ids: list[str]) -> None:
        with self._lock:
            for loop_id in loop_ids:
                self.shard_of.pop(loop_id, None)
                self.floors.pop(loop_id, None)

    def fence(self, loop_ids) -> tuple[str, dict[str, int]]:
        """(member, shard -> token) for a commit touching ``loop_ids``: Fenced if one of
        them is in no shard this member holds."""
        with self._lock:
            tokens, missing = {}, set()
            for loop_id in loop_ids:
                shard = self.shard_of.get(loop_id)
                if shard is None or shard not in self.held:
                    missing.add(shard or f"loop:{loop_id}")
                else:
                    tokens[shard] = self.held[shard]
        if missing:
            raise Fenced(sorted(missing))
        return self.member, tokens

    def token(self, loop_id: str) -> int | None:
        """The epoch of the messages of a loop this member owns: its shard's lease token,
        or its floor where that is higher. A loop whose gateway was patched, or whose id
        was deleted and registered again under another gateway, came from a shard whose
        token may be the higher, and a gateway drops a message whose ``(epoch, seq)`` is
        not above the last it took; its floor, a fresh epoch, is above every earlier
        token, and every later token is above it (a takeover's too)."""
        shard = self.shard_of.get(loop_id)
        held = None if shard is None else self.held.get(shard)
        return None if held is None else max(held, self.floors.get(loop_id, 0))

    def may_publish(self) -> bool:
        """The leases are valid by the local clock (see the module doc)."""
        return time.monotonic() < self.valid_until
