"""The PostgreSQL store (``--db postgresql://...``): the tables and guarantees of the
SQLite store, shared by several tuners.

:class:`PgStore` runs :class:`~service.daemon.store.Store`'s queries through an
adapter that translates SQLite's ``?`` placeholders, and differs where a server
differs from a file:

- No journal: a step batch's gains and audit rows are written to the ``loops`` and
  ``audit`` tables in the commit before publishing (one statement, :data:`RECORD_SQL`:
  one round trip), so another tuner taking a loop over reads them at once. Commits are
  durable (``synchronous_commit`` on) except snapshots.
- Fencing: a member of a cluster passes the lease tokens of the shards a commit
  touches; the commit locks those lease rows (``FOR SHARE``), writes nothing and fails with
  :class:`Fenced` unless each is still this member's, with that token, unexpired by the
  database's clock. A takeover updates the lease row, so it waits for a commit in
  flight, and a commit after it fails: a tuner that lost a lease (paused, partitioned)
  can neither commit nor, since it publishes only what it committed, publish.
- Changes of loops (registered, patched, deleted) are announced with
  ``NOTIFY pitune_loops`` in their transaction, so the owning member picks them up
  when they commit (see :mod:`service.daemon.cluster`).
- A lost connection (server restart, failover of the database) is reopened at the
  next transaction; the failed one raises, and the tuner retries it like any failing
  commit. A snapshot chunk that finds its connection lost goes again at once on a new
  one (:meth:`PgStore.snapshot`).
"""

from __future__ import annotations

import collections
import contextlib
import re
import threading
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from urllib.parse import urlsplit

import psycopg
from psycopg.conninfo import conninfo_to_dict
from pydantic import ValidationError

from service.daemon import migrations
from service.daemon.shards import GATEWAY_SHARD
from service.daemon.store import EpochAhead, JournalEntry, Store, StoredLoop, with_epoch
from service.engine.audit import AUDIT_COLUMNS, AUDIT_TYPES, AuditRow
from service.engine.config import LoopConfig
from service.engine.saved import Saved
from service.wire.protocol import UpdateReason

CHANNEL = "pitune_loops"
"""The NOTIFY channel of loop changes; the payload is comma-separated loop ids."""
NOTIFY_BYTES = 7000
"""Most payload bytes per NOTIFY (PostgreSQL's limit is 8,000)."""
CONNECT_TIMEOUT_S = 5
AHEAD_ROWS = 1000
"""Rows fetched at a time when parsing ahead of a takeover (~1.5 MB)."""


class Fenced(Exception):
    """A commit touched shards whose lease this member no longer holds."""

    def __init__(self, shards: list[str]) -> None:
        super().__init__(f"lease lost for {len(shards)} shards: {', '.join(shards[:5])}")
        self.shards = shards


def is_url(location: object) -> bool:
    return isinstance(location, str) and location.startswith(("postgresql://", "postgres://"))


def redacted(url: str) -> str:
    """The URL without its password, in the user part or a ``password`` query parameter
    (libpq takes either), for logs, messages and the console."""
    parts = urlsplit(url)
    if parts.password is not None:
        netloc = parts.netloc.replace(f":{parts.password}@", ":***@", 1)
        url = url.replace(f"//{parts.netloc}", f"//{netloc}", 1)
    head, mark, query = url.partition("?")
    return head + mark + re.sub(r"(^|&)password=[^&#]*", r"\1password=***", query)


LOCK_TIMEOUT_S = 5
"""Longest a statement of the store's connections (the commits', the snapshots') waits
for a lock: a table locked by another session (VACUUM FULL, ALTER TABLE, a LOCK TABLE)
blocked the worker's commit, and the worker with it, for as long as the lock was held,
with nothing failing. Past it the commit fails like any store error: retried every
COMMIT_RETRY_S, ``/healthz`` 503, the tuner exits after ``store_failure_exit_s`` (60 s
by default). Row locks between members (the leases' fence) last milliseconds."""
STATEMENT_TIMEOUT_S = 60
"""Longest a statement of the store's connections runs (a bulk registration, a load of a
takeover's loops: seconds): no longer than the default ``store_failure_exit_s``, after
which ``/healthz`` calls a worker still in one iteration stuck anyway."""
KEEPALIVES = {"keepalives": 1, "keepalives_idle": 10, "keepalives_interval": 5,
              "keepalives_count": 3}  # fmt: skip
"""TCP keepalives of the store's connections: a server that vanished without closing
them (a host down, a network cut) is found in ~25 s, not the kernel's two hours;
settings in the URL win."""


def connect(url: str) -> psycopg.Connection:
    return psycopg.connect(url, autocommit=True, connect_timeout=CONNECT_TIMEOUT_S)


def store_connect(url: str) -> psycopg.Connection:
    """A connection of the store's own (not the cluster's nor its LISTEN's): a statement
    on it fails rather than blocks (LOCK_TIMEOUT_S, STATEMENT_TIMEOUT_S, KEEPALIVES)."""
    given = conninfo_to_dict(url)
    keepalives = {k: v for k, v in KEEPALIVES.items() if k not in given}
    conn = psycopg.connect(url, autocommit=True, connect_timeout=CONNECT_TIMEOUT_S, **keepalives)
    conn.execute(f"SET lock_timeout = '{LOCK_TIMEOUT_S}s'")
    conn.execute(f"SET statement_timeout = '{STATEMENT_TIMEOUT_S}s'")
    return conn


class Adapter:
    """A psycopg connection with sqlite3's ``execute``/``executemany`` (``?`` placeholders)."""

    def __init__(self, conn: psycopg.Connection) -> None:
        self.conn = conn

    def execute(self, sql: str, params: Iterable = ()) -> psycopg.Cursor:
        return self.conn.execute(sql.replace("?", "%s"), tuple(params))

    def executemany(self, sql: str, rows: Iterable) -> psycopg.Cursor:
        cur = self.conn.cursor()
        rows = list(rows)
        if rows:
            cur.executemany(sql.replace("?", "%s"), rows)
        return cur


FENCE_CTE = (
    "WITH f AS (SELECT l.shard FROM leases l "
    "JOIN unnest(%b::text[], %b::int8[]) AS f(shard, token) "
    "ON l.shard = f.shard AND l.token = f.token "
    "WHERE l.owner = %s AND l.expires > clock_timestamp() ORDER BY l.shard FOR SHARE OF l), "
    "ok AS (SELECT count(*) = %s AS ok FROM f), "
)
"""The fence of a one-statement write (parameters: shards, tokens, member, how many):
the lease rows locked ``FOR SHARE`` (a takeover waits for it), ``ok`` true only if
every one is still the member's with that token, unexpired. Locked in shard order (the
sort comes before the locking), the order in which another member's claim of free
shards locks them (:meth:`service.daemon.cluster.Cluster._take`): in any other order a
commit or snapshot and a concurrent claim could each hold a row the other waits for
(PostgreSQL aborts one: a registration failed with ``deadlock detected`` once the
periodic snapshot was written concurrently with the claims, see
:mod:`service.daemon.snapwriter`)."""
RECORD_SQL = (
    FENCE_CTE + "u AS (UPDATE loops l SET kp = u.kp, ki = u.ki, seq = u.seq, epoch = u.epoch "
    "FROM unnest(%b::float8[], %b::float8[], %b::int8[], %b::text[], %b::int8[]) "
    "AS u(kp, ki, seq, id, epoch), ok "
    "WHERE l.id = u.id AND ok.ok RETURNING 1), "
    f"a AS (INSERT INTO audit ({AUDIT_COLUMNS}) SELECT a.* FROM unnest("
    "%b::text[], %b::float8[], %b::float8[], %b::int8[], %b::text[], %b::text[], "
    "%b::float8[], %b::float8[], %b::float8[], %b::float8[], %b::text[]) "
    f"AS a({AUDIT_COLUMNS}), ok WHERE ok.ok RETURNING 1) "
    "SELECT array_agg(shard) FROM f"
)
"""A step batch's commit as one statement (its own transaction: the connection is in
autocommit): the gains and audit rows written only if every lease is held (the
data-modifying parts run whether or not the result reads them); returns the leases
found held."""
SNAPSHOT_SQL = (
    FENCE_CTE + "w AS (INSERT INTO snapshots (id, hidden, runtime) "
    "SELECT u.* FROM unnest(%b::text[], %b::bytea[], %b::text[]) AS u(id, hidden, runtime), "
    "ok WHERE ok.ok ON CONFLICT (id) DO UPDATE SET hidden = excluded.hidden, "
    "runtime = excluded.runtime RETURNING 1) "
    "SELECT array_agg(shard) FROM f"
)
"""A chunk of snapshots as one fenced statement, as :data:`RECORD_SQL` (binary
parameters: the text form's escaping of the JSON cost 4 times as much)."""

LAST_MESSAGE_ROWS = 8
"""A loop's newest audit rows in which :data:`LAST_MESSAGE_SQL` looks for its last
message: one its owner committed but never published before a failover is the loop's
last commit, followed at most by a verdict or two at its seq; one further back went out
long ago."""
LAST_MESSAGE_SQL = (
    "SELECT l.id, m.t, m.reason, m.kp_old, m.ki_old FROM loops l CROSS JOIN LATERAL ("
    "SELECT w.* FROM (SELECT r.*, lead(r.seq) OVER (ORDER BY r.id DESC) AS before, "
    "bool_or(r.reason = 'registered' AND r.seq = l.seq) OVER () AS registered FROM ("
    "SELECT id, seq, t, mode, reason, kp_old, ki_old, kp_new, ki_new FROM audit "
    "WHERE loop_id = l.id ORDER BY id DESC LIMIT %s) AS r) AS w "
    "WHERE w.seq = l.seq ORDER BY w.id LIMIT 1) AS m "
    "WHERE l.shard = ANY(%s) AND l.seq > 0 AND l.epoch IS NOT NULL AND m.before < l.seq "
    "AND NOT m.registered AND m.reason = ANY(%s) AND (m.mode = 'auto' OR m.reason = %s) "
    "AND m.kp_new = l.kp AND m.ki_new = l.ki"
)
"""Of each loop of some shards whose last message (its ``seq``) is one the plant applies:
the message's audit row (``t``, reason, the gains before). That row is the first at the
loop's ``seq`` (the row before it has a lower one: later rows at the same seq are
verdicts, faults, a step the model check held), written by an update (a registration
again at that seq is a new loop, nothing sent), in ``auto`` or an accepted proposal, and
its gains are still those in force (gains adopted from the gateway since: the plant has
them, nothing to send)."""


def _typed(values, kind: type) -> list:
    """``values`` as a list of ``kind`` (None kept): a binary array parameter of mixed
    ints and floats cannot be dumped."""
    return [None if v is None else kind(v) for v in values]


class PgStore(Store):
    """A PostgreSQL connection shared by the worker and the API threads (one lock)."""

    dialect = "postgresql"
    ORDER = "l.ord"
    LOCK_ROW = " FOR UPDATE"
    """The epoch's row, locked: :meth:`Store.next_epoch` is atomic between members."""
    integrity_errors = (psycopg.errors.IntegrityError,)
    commit_errors = (psycopg.Error, OSError)

    def __init__(self, url: str) -> None:
        self.url = url
        self.location = redacted(url)
        self.path = None
        self._lock = threading.RLock()
        self._adapter = Adapter(connect(url))  # no statement timeout: a migration may be long
        self.migrated_from = migrations.migrate("postgresql", self._db.execute, self.transaction)
        self._adapter.conn.close()
        self._adapter = Adapter(store_connect(url))
        self._journal: collections.deque[JournalEntry] = collections.deque()  # stays empty
        self._snap_lock = threading.Lock()
        self._snap_conn: psycopg.Connection | None = None
        """The snapshots' connection (:meth:`snapshot`), opened at the first."""
        self.unloadable: list[str] = []
        self._ahead: dict[str, tuple[str, LoopConfig]] = {}
        """Loop id -> (stored JSON, parsed config), parsed ahead of a load (:meth:`parse_ahead`)."""
        self._saved_ahead: dict[str, tuple[bytes, str, Saved]] = {}
        """Loop id -> (stored hidden state, runtime JSON, parsed snapshot), the same way."""

    def parse_ahead(self, shards: list[str], stop: threading.Event | None = None) -> int:
        """Parse the stored configs and snapshots of ``shards``' loops now, on a connection
        of its own (the worker's commits go on), for a :meth:`load` to come: a cluster
        member whose peer stopped renewing its leases does so while the leases run out,
        so that taking them over costs the query and the engine's array writes only
        (validating a config and parsing a snapshot cost ~0.05-0.1 ms each, most of a
        takeover). Parsed entries are used one by one as they come, and only while the
        stored row is still the same (:meth:`_config`, :meth:`saved`); ``stop`` set: no
        more (the takeover has begun and parses the rest itself); ``[]`` forgets them.
        Returns how many configs were parsed."""
        configs: dict[str, tuple[str, LoopConfig]] = {}
        snapshots: dict[str, tuple[bytes, str, Saved]] = {}
        self._ahead, self._saved_ahead = configs, snapshots  # filled in place
        if not shards:
            return 0
        # a server-side cursor: rows parsed as they come (75,000 loops' rows are ~110 MB,
        # and fetching them all first took the seconds the leases had left)
        with connect(self.url) as conn, conn.transaction():
            rows = conn.cursor(name="parse_ahead")
            rows.itersize = AHEAD_ROWS
            rows.execute(
                "SELECT l.id, l.config, s.hidden, s.runtime FROM loops l "
                "LEFT JOIN snapshots s ON s.id = l.id WHERE l.shard = ANY(%s)",
                (shards,),
                binary=True,
            )
            for loop_id, raw, hidden, runtime in rows:
                if stop is not None and stop.is_set():
                    break
                with contextlib.suppress(ValidationError):  # load() logs it
                    configs[loop_id] = (raw, LoopConfig.model_validate_json(raw))
                if hidden is not None and runtime is not None:
                    with contextlib.suppress(ValueError):  # the takeover raises it
                        snapshots[loop_id] = (hidden, runtime, Saved.parse(hidden, runtime))
        return len(configs)

    def _fetch(self, sql: str, params) -> list[tuple]:
        """In binary: the text format sends a snapshot's hidden state (bytea) as hex, twice
        its size, decoded in Python."""
        return self._db.conn.execute(sql.replace("?", "%s"), tuple(params), binary=True).fetchall()

    def _config(self, loop_id: str, raw: str) -> LoopConfig:
        ahead = self._ahead.pop(loop_id, None)
        if ahead is not None and ahead[0] == raw:
            return ahead[1]
        return LoopConfig.model_validate_json(raw)

    def saved(self, stored: StoredLoop) -> Saved | None:
        ahead = self._saved_ahead.pop(stored.config.id, None)
        if ahead is not None and (ahead[0], ahead[1]) == (stored.hidden, stored.runtime):
            return ahead[2]
        return super().saved(stored)

    @property
    def _db(self) -> Adapter:
        """The connection, reopened if it was lost (the statement that found it lost
        failed; the next one runs on a new connection)."""
        conn = self._adapter.conn
        if conn.closed or conn.broken:
            self._adapter = Adapter(store_connect(self.url))
        return self._adapter

    def close(self) -> None:
        with self._lock:
            self._adapter.conn.close()
        with self._snap_lock:
            if self._snap_conn is not None:
                self._snap_conn.close()

    @contextmanager
    def transaction(self, durable: bool = True) -> Iterator[Adapter]:
        with self._lock, self._db.conn.transaction():
            if not durable:
                self._db.execute("SET LOCAL synchronous_commit = off")
            yield self._db

    def checkpoint(self) -> None:
        """Nothing: PostgreSQL recycles its write-ahead log itself."""

    def next_epoch(self, wall: float, ahead: EpochAhead = "refuse") -> int:
        """:meth:`Store.next_epoch` on the database's clock, not ``wall``: the epoch is
        shared, and one member's wrong clock must not move it."""
        return super().next_epoch(self.wall_now(), ahead)

    def wall_now(self) -> float:
        """The database's wall clock (seconds since the epoch): the one clock of a
        cluster, as for the leases (a retention pass's horizon, :mod:`service.daemon.upkeep`)."""
        with self._lock:
            (now,) = self._db.execute("SELECT extract(epoch FROM clock_timestamp())").fetchone()
        return float(now)

    def gateway_shards(self) -> dict[str, str]:
        """Loop id -> shard of every stored loop registered with a gateway (a cluster
        member's map of where the loops it does not hold belong:
        :meth:`~service.daemon.ownership.Ownership.load_gateway_shards`)."""
        with self._lock:
            rows = self._fetch(
                "SELECT id, shard FROM loops WHERE starts_with(shard, ?)", (GATEWAY_SHARD,)
            )
        return dict(rows)

    def last_messages(self, shards: list[str]) -> dict[str, tuple]:
        """Loop id -> (t, reason, kp before, ki before) of the loops of ``shards`` whose
        last committed message is one the plant applies (:data:`LAST_MESSAGE_SQL`); its
        gains, ``seq`` and epoch are the loop's stored ones."""
        reasons = [reason.value for reason in UpdateReason]
        with self._lock:
            rows = self._fetch(
                LAST_MESSAGE_SQL,
                (LAST_MESSAGE_ROWS, shards, reasons, UpdateReason.accepted.value),
            )
        return {row[0]: row[1:] for row in rows}

    # -- writes -------------------------------------------------------------------------
    def insert_loops(
        self, configs: list[LoopConfig], audit: list[AuditRow], seqs: list[int]
    ) -> None:
        with self._notifying([c.id for c in configs]):
            super().insert_loops(configs, audit, seqs)

    def update_config(self, config: LoopConfig, audit: AuditRow) -> None:
        with self._notifying([config.id]):
            super().update_config(config, audit)

    def delete_loop(self, loop_id: str, audit: AuditRow) -> None:
        with self._notifying([loop_id]):
            super().delete_loop(loop_id, audit)

    @contextmanager
    def _notifying(self, loop_ids: list[str]) -> Iterator[None]:
        """One transaction around the write and its NOTIFY (sent when it commits)."""
        with self.transaction() as db:
            yield
            chunk: list[str] = []
            size = 0
            for loop_id in loop_ids:
                if size + len(loop_id) + 1 > NOTIFY_BYTES:
                    db.execute("SELECT pg_notify(?, ?)", (CHANNEL, ",".join(chunk)))
                    chunk, size = [], 0
                chunk.append(loop_id)
                size += len(loop_id) + 1
            if chunk:
                db.execute("SELECT pg_notify(?, ?)", (CHANNEL, ",".join(chunk)))

    def record_gains(
        self,
        gains: list[tuple[float, float, int, str, int]],
        audit: list,
        fence: tuple[str, dict[str, int]] | None = None,
    ) -> None:
        """New (kp, ki, seq, id, epoch) of loops and their audit rows, written to the tables in
        one durable commit; ``fence`` (member id, shard -> lease token): :class:`Fenced`
        (nothing written) unless this member holds every one of those leases.

        One statement (:data:`RECORD_SQL`), so one round trip to the server: a member
        commits every step batch on its worker, and the five round trips of a
        transaction (begin, fence, update, copy, commit) each waited for a busy box to
        schedule the server and then the worker (a third of a member's worker at
        30,000 loops, and the cause of its backlog)."""
        if not gains and not audit:
            return
        member, tokens = fence if fence is not None else ("", {})
        kp, ki, seq, ids, epochs = (
            (list(c) for c in zip(*with_epoch(gains), strict=True)) if gains else ([],) * 5
        )
        columns = (
            [_typed(c, k) for c, k in zip(zip(*audit, strict=True), AUDIT_TYPES, strict=True)]
            if audit
            else [[]] * len(AUDIT_TYPES)
        )
        with self._lock:
            (held,) = self._db.conn.execute(
                RECORD_SQL,
                (
                    list(tokens), list(tokens.values()), member, len(tokens),
                    _typed(kp, float), _typed(ki, float), _typed(seq, int), _typed(ids, str),
                    _typed(epochs, int),
                    *columns,
                ),
            ).fetchone()  # fmt: skip
        if len(held or ()) != len(tokens):
            raise Fenced(sorted(set(tokens) - set(held or ())))

    def snapshot(
        self,
        rows: Iterable[tuple[str, bytes, str]],
        fence: tuple[str, dict[str, int]] | None = None,
    ) -> None:
        """A chunk of snapshots (:data:`SNAPSHOT_SQL`): one round trip on a connection of
        their own, not durable (``synchronous_commit`` off for the session: a snapshot
        lost in a crash costs the state since the one before, as with SQLite); it was a
        transaction of five round trips on the commits' connection, each waiting for a
        busy box to schedule the server and then the worker, a periodic snapshot chunk
        every 0.1 s on a 150,000-loop member."""
        rows = list(rows)
        if not rows:
            return
        ids, hidden, runtime = (list(c) for c in zip(*rows, strict=True))
        member, tokens = fence if fence is not None else ("", {})
        params = (list(tokens), list(tokens.values()), member, len(tokens), ids, hidden, runtime)
        with self._snap_lock:
            try:
                (held,) = self._snap_connection().execute(SNAPSHOT_SQL, params).fetchone()
            except psycopg.OperationalError:
                if not self._snap_conn.broken:  # the statement failed, not the connection
                    raise
                # A lost connection (the server restarted, the backend was terminated) is
                # found lost only by the statement sent on it: once more on a new one,
                # or the chunk's loops would wait a snapshot interval or more. (The
                # statement is an upsert: whatever of it got through, it is written once.)
                (held,) = self._snap_connection().execute(SNAPSHOT_SQL, params).fetchone()
        if len(held or ()) != len(tokens):
            raise Fenced(sorted(set(tokens) - set(held or ())))

    def _snap_connection(self) -> psycopg.Connection:
        """The snapshots' connection, opened again if it was found lost."""
        conn = self._snap_conn
        if conn is None or conn.closed or conn.broken:
            conn = self._snap_conn = store_connect(self.url)
            conn.execute("SET synchronous_commit = off")
        return conn

    @staticmethod
    def _audit(db: Adapter, rows: list[AuditRow]) -> None:
        if not rows:
            return
        with db.conn.cursor().copy(f"COPY audit ({AUDIT_COLUMNS}) FROM STDIN") as copy:
            for row in rows:
                copy.write_row(row)
