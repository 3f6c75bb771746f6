"""SQLite persistence: loop configs, current gains and mode, the audit log, and snapshots
of the per-loop runtime state (agent hidden state, error integral, counters).

Gains and audit entries are committed before the matching gains message is published,
so a daemon killed at any moment has every published change on disk. WAL journaling
with ``synchronous=NORMAL`` survives a killed process (not a power cut, which would need
``FULL``). Hidden states are only snapshotted (periodically and at shutdown): losing a
few RL steps of memory is harmless, while writing 800 bytes per loop per step is not.
"""

from __future__ import annotations

import sqlite3
import threading
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from service.schemas import AuditEntry, LoopConfig

SCHEMA = """
CREATE TABLE IF NOT EXISTS loops (
    id TEXT PRIMARY KEY,
    config TEXT NOT NULL,
    kp REAL NOT NULL,
    ki REAL NOT NULL,
    seq INTEGER NOT NULL
);
CREATE TABLE IF NOT EXISTS snapshots (
    id TEXT PRIMARY KEY REFERENCES loops(id) ON DELETE CASCADE,
    hidden BLOB NOT NULL,
    runtime TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS audit (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    loop_id TEXT NOT NULL,
    wall_time REAL NOT NULL,
    t REAL,
    seq INTEGER NOT NULL,
    mode TEXT NOT NULL,
    reason TEXT NOT NULL,
    kp_old REAL, ki_old REAL, kp_new REAL, ki_new REAL,
    detail TEXT NOT NULL DEFAULT ''
);
CREATE INDEX IF NOT EXISTS audit_loop ON audit (loop_id, id);
"""

AUDIT_COLUMNS = "loop_id, wall_time, t, seq, mode, reason, kp_old, ki_old, kp_new, ki_new, detail"


@dataclass
class StoredLoop:
    config: LoopConfig
    kp: float
    ki: float
    seq: int
    hidden: bytes | None
    runtime: str | None
    """JSON of the runtime snapshot (see :meth:`service.loops.LoopTable.snapshot`)."""


AuditRow = tuple
"""Values in :data:`AUDIT_COLUMNS` order; build with :func:`audit_row`."""


def audit_row(
    loop_id: str,
    wall_time: float,
    t: float | None,
    seq: int,
    mode: str,
    reason: str,
    old: tuple[float, float] | None,
    new: tuple[float, float] | None,
    detail: str = "",
) -> AuditRow:
    kp_old, ki_old = old or (None, None)
    kp_new, ki_new = new or (None, None)
    return (loop_id, wall_time, t, seq, mode, reason, kp_old, ki_old, kp_new, ki_new, detail)


class Store:
    """One SQLite connection shared by the worker and the API threads (serialised by a lock)."""

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)
        if str(path) != ":memory:":
            self.path.parent.mkdir(parents=True, exist_ok=True)
        self._db = sqlite3.connect(str(path), check_same_thread=False, isolation_level=None)
        self._lock = threading.Lock()
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=NORMAL")
        self._db.execute("PRAGMA foreign_keys=ON")
        self._db.executescript(SCHEMA)

    def close(self) -> None:
        with self._lock:
            self._db.close()

    @contextmanager
    def transaction(self) -> Iterator[sqlite3.Connection]:
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                yield self._db
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
            self._db.execute("COMMIT")

    # -- loops ------------------------------------------------------------------------
    def load(self) -> list[StoredLoop]:
        with self._lock:
            rows = self._db.execute(
                "SELECT l.config, l.kp, l.ki, l.seq, s.hidden, s.runtime "
                "FROM loops l LEFT JOIN snapshots s ON s.id = l.id ORDER BY l.rowid"
            ).fetchall()
        return [
            StoredLoop(LoopConfig.model_validate_json(c), kp, ki, seq, h, rt)
            for c, kp, ki, seq, h, rt in rows
        ]

    def insert_loop(self, config: LoopConfig, audit: AuditRow) -> None:
        with self.transaction() as db:
            db.execute(
                "INSERT INTO loops (id, config, kp, ki, seq) VALUES (?, ?, ?, ?, 0)",
                (config.id, config.model_dump_json(), config.kp, config.ki),
            )
            self._audit(db, [audit])

    def insert_loops(self, configs: list[LoopConfig], audit: list[AuditRow]) -> None:
        """Register many loops in one transaction (all or none)."""
        with self.transaction() as db:
            db.executemany(
                "INSERT INTO loops (id, config, kp, ki, seq) VALUES (?, ?, ?, ?, 0)",
                [(c.id, c.model_dump_json(), c.kp, c.ki) for c in configs],
            )
            self._audit(db, audit)

    def update_config(self, config: LoopConfig, audit: AuditRow) -> None:
        with self.transaction() as db:
            db.execute(
                "UPDATE loops SET config = ? WHERE id = ?", (config.model_dump_json(), config.id)
            )
            self._audit(db, [audit])

    def delete_loop(self, loop_id: str, audit: AuditRow) -> None:
        with self.transaction() as db:
            db.execute("DELETE FROM loops WHERE id = ?", (loop_id,))
            self._audit(db, [audit])

    def record_gains(self, gains: Iterable[tuple[float, float, int, str]], audit: list) -> None:
        """New (kp, ki, seq, id) of loops and their audit rows, in one transaction."""
        with self.transaction() as db:
            db.executemany("UPDATE loops SET kp = ?, ki = ?, seq = ? WHERE id = ?", gains)
            self._audit(db, audit)

    def snapshot(self, rows: Iterable[tuple[str, bytes, str]]) -> None:
        """Replace the runtime snapshots of (id, hidden, runtime JSON)."""
        with self.transaction() as db:
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
