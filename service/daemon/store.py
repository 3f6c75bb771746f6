"""SQLite persistence: loop configs, current gains and mode, the audit log, and snapshots
of the per-loop runtime state (agent hidden state, error integral, counters).

Gains and audit entries are committed before the matching gains message is published,
so a daemon killed at any moment has every published change on disk. WAL journaling
with ``synchronous=FULL`` for those commits and every other change of loops and audit
log: each is on the disk (fsync) before it returns, so it survives a power cut too.
Applying the journal and writing snapshots use ``NORMAL`` (no fsync): losing those to a
power cut loses nothing published, the journal rows stay until applied. Hidden states
are only snapshotted (periodically and at shutdown): losing a few RL steps of memory is
harmless, while writing 800 bytes per loop per step is not.

The commit before publishing is one row: :meth:`Store.record_gains` writes a step
batch's gains and audit rows as one JSON blob to the ``journal`` table (~7 ms for
10,000 loops, where updating 10,000 loops and inserting 10,000 audit rows takes
70-140 ms). :meth:`Store.apply_journal` moves the journal into the ``loops`` and
``audit`` tables later, a chunk per transaction, when the tuner has nothing else to do.
A crash leaves the rest in the journal, and opening the store applies it before loading
the loops, so a restart sees every published change. Every other write (registration,
patch, delete) and every history read applies the whole journal first, so the audit ids
still follow the order of events.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import sqlite3
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import orjson
from pydantic import ValidationError

from service.daemon import migrations
from service.daemon.retention_store import Retention
from service.daemon.schemas import AuditEntry
from service.daemon.shards import shard_gateway, shard_of
from service.engine.audit import AUDIT_COLUMNS, AuditRow
from service.engine.config import LoopConfig
from service.engine.saved import Saved
from service.wire.protocol import EPOCH_AHEAD_MS

log = logging.getLogger("pitune.store")
WAL_LIMIT_BYTES = 64 << 20
"""What the write-ahead log is cut back to when it restarts (``journal_size_limit``): a
reader holding a snapshot (a backup, an sqlite3 shell) keeps every write since in it,
and the file kept its peak size after (241 MB, session 40). :meth:`Store.checkpoint`
empties it when a retention pass ends."""
EpochAhead = Literal["refuse", "reset", "keep"]
"""What :meth:`Store.next_epoch` does with a stored epoch far ahead of the clock."""


class EpochAheadError(RuntimeError):
    """The stored epoch is more than EPOCH_AHEAD_MS ahead of the clock (a start refused)."""

    def __init__(self, epoch: int, hours: float) -> None:
        super().__init__(
            f"the stored epoch {epoch} is {hours:.1f} h ahead of the clock: fix this host's "
            "clock if it is behind (NTP) and start again; if instead an earlier start had "
            "its clock ahead, set PITUNE_EPOCH_RESET=1 for one start and then restart every "
            "gateway that took the old epoch (docs/deploy.md, Clocks)"
        )


UPDATE_GAINS = "UPDATE loops SET kp = ?1, ki = ?2, seq = ?3, epoch = ?5 WHERE id = ?4"
"""A gains row (kp, ki, seq, id, epoch) applied (:func:`with_epoch`)."""


def with_epoch(gains: list) -> list[tuple]:
    """Gains rows as (kp, ki, seq, id, epoch): a row without its epoch (a journal row of
    schema version 3 and before) gets None (NULL: not recorded)."""
    return [(*g, None)[:5] for g in gains]


@dataclass
class StoredLoop:
    config: LoopConfig
    kp: float
    ki: float
    seq: int
    hidden: bytes | None
    runtime: str | None
    """JSON of the runtime snapshot (see :meth:`service.engine.table.LoopTable.snapshot`)."""
    epoch: int | None = None
    """The epoch its gains were last committed under (None: not recorded)."""


@dataclass
class JournalEntry:
    """One step batch's changes, committed as one row, not yet applied to the tables."""

    id: int
    gains: list
    audit: list
    done: int = 0

    @property
    def size(self) -> int:
        return len(self.gains) + len(self.audit)


class Store(Retention):
    """One SQLite connection shared by the worker and the API threads (serialised by a lock).

    The queries are written for SQLite (``?`` placeholders) and shared with
    :class:`~service.daemon.store_pg.PgStore`, which translates them.
    """

    dialect = "sqlite"
    ORDER = "l.rowid"
    """The registration order of the loops table."""
    LOCK_ROW = ""
    """What locks a row read for update (SQLite: the transaction locks the database)."""
    integrity_errors: tuple[type[Exception], ...] = (sqlite3.IntegrityError,)
    commit_errors: tuple[type[Exception], ...] = (sqlite3.Error, OSError)
    """What a commit raises when the store cannot take it (locked, disk full, gone)."""

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)
        self.location = str(path)
        """Where the store is, for messages (a password in a URL left out)."""
        if str(path) != ":memory:":
            self.path.parent.mkdir(parents=True, exist_ok=True)
        self._db = sqlite3.connect(str(path), check_same_thread=False, isolation_level=None)
        self._lock = threading.RLock()  # re-entered to update the journal after a commit
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute(f"PRAGMA journal_size_limit={WAL_LIMIT_BYTES}")
        self._durable = True
        self._db.execute("PRAGMA synchronous=FULL")
        self._db.execute("PRAGMA foreign_keys=ON")
        self.migrated_from = migrations.migrate("sqlite", self._db.execute, self.transaction)
        """The schema version the store had when opened (0: a new store)."""
        if self.migrated_from < 2:
            self._fill_shards()
        self._journal: collections.deque[JournalEntry] = collections.deque()
        self.unloadable: list[str] = []
        """Ids of stored loops that :meth:`load` could not parse."""
        pending = self._db.execute("SELECT id, rows, done FROM journal ORDER BY id")
        for entry_id, rows, done in pending:
            changes = orjson.loads(rows)
            self._journal.append(JournalEntry(entry_id, changes["gains"], changes["audit"], done))

    def _fill_shards(self) -> None:
        """The ``shard`` of loops registered before schema version 2 (computed in Python:
        SQLite has no hash function)."""
        with self.transaction() as db:
            rows = db.execute("SELECT id, config FROM loops WHERE shard IS NULL").fetchall()
            db.executemany(
                "UPDATE loops SET shard = ? WHERE id = ?",
                [(shard_of(i, orjson.loads(c).get("gateway")), i) for i, c in rows],
            )

    def close(self) -> None:
        self.apply_journal()
        with self._lock:
            self._db.close()

    @contextlib.contextmanager
    def transaction(self, durable: bool = True) -> Iterator[sqlite3.Connection]:
        """``durable``: the commit reaches the disk (fsync, ``synchronous=FULL``) before it
        returns; else it survives a killed process but maybe not a power cut."""
        with self._lock:
            if durable != self._durable:  # not inside a transaction
                self._db.execute(f"PRAGMA synchronous={'FULL' if durable else 'NORMAL'}")
                self._durable = durable
            self._db.execute("BEGIN IMMEDIATE")
            try:
                yield self._db
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
            self._db.execute("COMMIT")

    @contextlib.contextmanager
    def _ordered(self) -> Iterator[sqlite3.Connection]:
        """A transaction that applies the whole journal first (audit ids in event order)."""
        with self._lock:
            with self.transaction() as db:
                progress = self._apply(db, None)
                yield db
            self._advance(progress)

    # -- epoch ------------------------------------------------------------------------
    def next_epoch(self, wall: float, ahead: EpochAhead = "refuse") -> int:
        """Start a new epoch of this store and return it (committed, fsynced).

        The epoch is above every earlier epoch of this store, and at least the wall clock
        in milliseconds: a tuner started later on a fresh store (a replaced tuner) has a
        larger epoch than the one it replaced, as long as the clocks of the two hosts
        agree to within the time between the two starts. Gateways order a loop's updates
        by (epoch, seq), and drop an epoch more than EPOCH_AHEAD_MS ahead of their clock.
        A stored epoch that far ahead of ``wall`` means one of two clocks is wrong: this
        host's now (behind: continuing is right, and a lower epoch would make every
        gateway drop the new updates as older), or the one of an earlier start (ahead,
        since fixed: every gateway with a right clock drops what it ordered). Nothing
        here tells the two apart, so the epoch never goes backwards by itself:
        ``ahead`` "refuse" (a start) raises :class:`EpochAheadError` for the operator,
        "reset" (the operator's PITUNE_EPOCH_RESET, after fixing a clock that was ahead)
        starts again from ``wall`` with an ERROR in the log, "keep" (a running cluster
        member's lease) continues it (docs/deploy.md, Clocks).
        """
        wall_ms = int(wall * 1000)

        def advance(value_of: Callable[[str], str | None]) -> dict[str, str]:
            prev = int(value_of("epoch"))
            epoch = max(prev + 1, wall_ms)
            if prev > wall_ms + EPOCH_AHEAD_MS and ahead != "keep":
                hours = (prev - wall_ms) / 3.6e6
                if ahead == "refuse":
                    raise EpochAheadError(prev, hours)
                log.error(
                    "EPOCH RESET (PITUNE_EPOCH_RESET): the stored epoch %d, %.1f h ahead of "
                    "this host's clock, is not continued; starting again from the clock. "
                    "Restart every gateway that took the old epoch: until then it drops "
                    "the new updates as older (docs/deploy.md, Clocks)",
                    prev, hours,
                )  # fmt: skip
                epoch = wall_ms
            return {"epoch": str(epoch)}

        return int(self.change_meta("epoch", "0", advance)["epoch"])

    # -- meta -------------------------------------------------------------------------
    def meta(self, key: str) -> str | None:
        """The value of the ``meta`` row ``key`` (None: no such row)."""
        with self._lock:
            rows = self._fetch("SELECT value FROM meta WHERE key = ?", (key,))
        return rows[0][0] if rows else None

    def change_meta(
        self,
        lock: str,
        default: str,
        change: Callable[[Callable[[str], str | None]], dict[str, str]],
    ) -> dict[str, str]:
        """Change ``meta`` rows in one durable commit, the row ``lock`` (created with the
        value ``default`` if missing) locked first, so that the members of a cluster change
        them one at a time: ``change(value_of)`` returns the rows to write (key -> value),
        ``value_of(key)`` reads a row in the transaction (None: none). Returns the rows
        written; ``change`` raising writes nothing."""
        with self.transaction() as db:
            insert = "INSERT INTO meta (key, value) VALUES (?, ?) ON CONFLICT DO NOTHING"
            db.execute(insert, (lock, default))
            db.execute(f"SELECT value FROM meta WHERE key = ?{self.LOCK_ROW}", (lock,))

            def value_of(key: str) -> str | None:
                row = db.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
                return None if row is None else row[0]

            rows = change(value_of)
            db.executemany(
                "INSERT INTO meta (key, value) VALUES (?, ?) "
                "ON CONFLICT (key) DO UPDATE SET value = excluded.value",
                list(rows.items()),
            )
        return rows

    def wall_now(self) -> float:
        """This host's wall clock (seconds since the epoch); a cluster's store has its
        database's, the one clock of the members (:class:`PgStore`)."""
        return time.time()

    # -- journal ----------------------------------------------------------------------
    def apply_journal(self, max_rows: int | None = None) -> int:
        """Apply up to ``max_rows`` journal rows (None: all) in one transaction; returns
        how many are still pending."""
        with self._lock:
            if self._journal:
                with self.transaction(durable=False) as db:  # the journal already is
                    progress = self._apply(db, max_rows)
                self._advance(progress)
            return self.journal_rows

    @property
    def journal_rows(self) -> int:
        return sum(e.size - e.done for e in self._journal)

    def _apply(self, db: sqlite3.Connection, budget: int | None) -> list[tuple[JournalEntry, int]]:
        """Apply journal rows in ``db``'s open transaction; the progress, to be recorded in
        memory by :meth:`_advance` once the transaction committed."""
        progress = []
        for entry in self._journal:
            if budget is not None and budget <= 0:
                break
            start, n_gains = entry.done, len(entry.gains)
            end = entry.size if budget is None else min(entry.size, start + budget)
            gains = entry.gains[min(start, n_gains) : min(end, n_gains)]
            db.executemany(UPDATE_GAINS, with_epoch(gains))
            self._audit(db, entry.audit[max(start - n_gains, 0) : max(end - n_gains, 0)])
            if end == entry.size:
                db.execute("DELETE FROM journal WHERE id = ?", (entry.id,))
            else:
                db.execute("UPDATE journal SET done = ? WHERE id = ?", (end, entry.id))
            progress.append((entry, end))
            if budget is not None:
                budget -= end - start
        return progress

    def _advance(self, progress: list[tuple[JournalEntry, int]]) -> None:
        for entry, end in progress:
            entry.done = end
        while self._journal and self._journal[0].done == self._journal[0].size:
            self._journal.popleft()

    # -- loops ------------------------------------------------------------------------
    def load(
        self, shards: list[str] | None = None, ids: list[str] | None = None
    ) -> list[StoredLoop]:
        """Every loop, with the journal applied first (changes published before a crash).

        A row whose config no longer validates (written by an older version) is skipped
        with an error in the log and kept in the table: one bad row must not stop the
        daemon from tuning every other loop. Its id stays taken until it is repaired or
        deleted in the database; :attr:`unloadable` lists them. ``shards`` or ``ids``:
        only the loops of those shards, or with those ids (a member of a cluster loading
        what it owns), else all.
        """
        self.apply_journal()
        query = (
            "SELECT l.id, l.config, l.kp, l.ki, l.seq, s.hidden, s.runtime, l.epoch "
            "FROM loops l LEFT JOIN snapshots s ON s.id = l.id"
        )
        with self._lock:
            column, keys = ("l.shard", shards) if ids is None else ("l.id", ids)
            if keys is None:
                rows = self._fetch(f"{query} ORDER BY {self.ORDER}", ())
            else:
                rows = []
                for i in range(0, len(keys), 500):
                    chunk = keys[i : i + 500]
                    where = f"{column} IN ({', '.join('?' * len(chunk))})"
                    rows += self._fetch(f"{query} WHERE {where} ORDER BY {self.ORDER}", chunk)
        loops, unloadable = [], []
        for loop_id, config, kp, ki, seq, hidden, runtime, epoch in rows:
            try:
                loops.append(
                    StoredLoop(self._config(loop_id, config), kp, ki, seq, hidden, runtime, epoch)
                )
            except ValidationError as exc:
                unloadable.append(loop_id)
                log.error(
                    "LOOP %r NOT LOADED: its stored config is invalid; the row is kept in %s "
                    "(repair or delete it there): %s",
                    loop_id, self.location, exc,
                )  # fmt: skip
        if shards is None and ids is None:
            self.unloadable = unloadable
        else:
            self.unloadable = sorted(set(self.unloadable) | set(unloadable))
        return loops

    def _fetch(self, sql: str, params) -> list[tuple]:
        """The rows of a query of :meth:`load`."""
        return self._db.execute(sql, params).fetchall()

    def _config(self, loop_id: str, raw: str) -> LoopConfig:
        """A stored config, parsed (ValidationError if it no longer validates)."""
        return LoopConfig.model_validate_json(raw)

    def saved(self, stored: StoredLoop) -> Saved | None:
        """A loaded loop's snapshot, parsed (None: it has none)."""
        if stored.hidden is None or stored.runtime is None:
            return None
        return Saved.parse(stored.hidden, stored.runtime)

    def saved_many(self, stored: list[StoredLoop]) -> list[Saved | None]:
        """:meth:`saved` of each loaded loop."""
        return [self.saved(loop) for loop in stored]

    def last_seqs(self, ids: list[str]) -> dict[str, int]:
        """The highest ``seq`` of each id that ever had one, from the audit log (kept after
        a delete): a loop registered again continues from it, since gateways drop a gains
        message whose seq is not above the last one from the same tuner."""
        self.apply_journal()
        return self._pairs_in(
            "SELECT loop_id, MAX(seq) FROM audit WHERE loop_id IN ({}) GROUP BY loop_id", ids
        )

    def _pairs_in(self, sql: str, ids: list[str]) -> dict:
        """The (key, value) rows of ``sql`` whose ``IN ({})`` takes ``ids``, 500 at a time
        (SQLite's limit on a statement's parameters), as a dict."""
        found = {}
        with self._lock:
            for i in range(0, len(ids), 500):
                chunk = ids[i : i + 500]
                found.update(self._db.execute(sql.format(", ".join("?" * len(chunk))), chunk))
        return found

    def gateways_of(self, ids: list[str]) -> dict[str, str | None]:
        """The gateway of each stored loop among ``ids`` (None: registered without one),
        by its shard: a row that failed to load, or another member's, has one too."""
        found = self._pairs_in("SELECT id, shard FROM loops WHERE id IN ({})", ids)
        return {i: shard_gateway(found[i]) for i in ids if i in found}

    def insert_loops(
        self, configs: list[LoopConfig], audit: list[AuditRow], seqs: list[int]
    ) -> None:
        """Register loops, starting at ``seqs``, in one transaction (all or none)."""
        with self._ordered() as db:
            db.executemany(
                "INSERT INTO loops (id, config, kp, ki, seq, shard) VALUES (?, ?, ?, ?, ?, ?)",
                [
                    (c.id, c.model_dump_json(), c.kp, c.ki, seq, shard_of(c.id, c.gateway))
                    for c, seq in zip(configs, seqs, strict=True)
                ],
            )
            self._audit(db, audit)

    def update_config(self, config: LoopConfig, audit: AuditRow) -> None:
        with self._ordered() as db:
            db.execute(
                "UPDATE loops SET config = ?, shard = ? WHERE id = ?",
                (config.model_dump_json(), shard_of(config.id, config.gateway), config.id),
            )
            self._audit(db, [audit])

    def delete_loop(self, loop_id: str, audit: AuditRow) -> None:
        with self._ordered() as db:
            db.execute("DELETE FROM loops WHERE id = ?", (loop_id,))
            self._audit(db, [audit])

    def record_gains(
        self, gains: list[tuple[float, float, int, str, int]], audit: list, fence: object = None
    ) -> None:
        """New (kp, ki, seq, id, epoch) of loops and their audit rows: committed as one journal
        row, applied to the tables by :meth:`apply_journal`. ``fence``: see
        :meth:`PgStore.record_gains <service.daemon.store_pg.PgStore.record_gains>` (an
        SQLite store has one tuner: nothing to fence)."""
        rows = orjson.dumps({"gains": gains, "audit": audit}, option=orjson.OPT_SERIALIZE_NUMPY)
        with self._lock:
            with self.transaction() as db:
                entry_id = db.execute("INSERT INTO journal (rows) VALUES (?)", (rows,)).lastrowid
            self._journal.append(JournalEntry(entry_id, gains, audit))

    def snapshot(self, rows: Iterable[tuple[str, bytes, str]], fence: object = None) -> None:
        """Replace the runtime snapshots of (id, hidden, runtime JSON)."""
        with self.transaction(durable=False) as db:  # a lost snapshot costs a few RL steps
            db.executemany(
                "INSERT INTO snapshots (id, hidden, runtime) VALUES (?, ?, ?) "
                "ON CONFLICT(id) DO UPDATE SET hidden = excluded.hidden, "
                "runtime = excluded.runtime",
                rows,
            )

    # -- audit ------------------------------------------------------------------------
    @staticmethod
    def _audit(db: sqlite3.Connection, rows: list[AuditRow]) -> None:
        db.executemany(
            f"INSERT INTO audit ({AUDIT_COLUMNS}) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)", rows
        )

    def history(self, loop_id: str, offset: int, limit: int) -> tuple[int, list[AuditEntry]]:
        """(total, entries newest first) of one loop's audit log."""
        self.apply_journal()
        with self._lock:
            (total,) = self._db.execute(
                "SELECT COUNT(*) FROM audit WHERE loop_id = ?", (loop_id,)
            ).fetchone()
            rows = self._db.execute(
                f"SELECT id, {AUDIT_COLUMNS} FROM audit WHERE loop_id = ? "
                "ORDER BY id DESC LIMIT ? OFFSET ?",
                (loop_id, limit, offset),
            ).fetchall()
        names = ("id", *AUDIT_COLUMNS.replace(" ", "").split(","))
        return total, [AuditEntry(**dict(zip(names, row, strict=True))) for row in rows]
