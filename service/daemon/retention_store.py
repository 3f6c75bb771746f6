"""The audit history's retention and export, a mixin of :class:`~service.daemon.store.Store`
(SQLite and, through its adapter, PostgreSQL).

A retention pass deletes each loop's rows below one audit id (:meth:`Retention._cut`),
found by the ``(loop_id, id)`` index, so a loop costs what it deletes: a condition on
``wall_time`` read every kept row of the loop (46 ms a loop at the 10,000-row cap, four
seconds of the worker's time per 200 loops, session 40).
"""

from __future__ import annotations

import contextlib
import os
import sqlite3
import time
from collections.abc import Iterable
from pathlib import Path

import orjson

from service.engine.audit import AUDIT_COLUMNS

EXPORT_CHUNK = 10_000
"""Audit rows an export reads per query: each its own read transaction, so an export of
a large history holds no snapshot that keeps the write-ahead log growing meanwhile, nor
(the tuner's) the store's lock for long."""

AUDIT_IDS = (
    "WITH RECURSIVE ids(x) AS (SELECT MIN(loop_id) FROM audit UNION ALL "
    "SELECT (SELECT MIN(loop_id) FROM audit WHERE loop_id > ids.x) FROM ids "
    "WHERE x IS NOT NULL) SELECT x FROM ids WHERE x IS NOT NULL"
)
"""The distinct loop ids of the audit table, in order, one index lookup each."""


class Retention:
    """Mixin of :class:`~service.daemon.store.Store`: its ``_db``, ``_lock``,
    ``transaction`` and ``apply_journal``."""

    def audit_ids(self, *, deleted_only: bool = False) -> list[str]:
        """Every loop id with audit rows (deleted loops included); ``deleted_only``: those
        of no registered loop. Found by skipping through the ``(loop_id, id)`` index from
        one id to the next, a step per loop: ``SELECT DISTINCT`` read every index entry
        (176-355 ms under the store's lock at 2 M rows, at each pass's start; 5 ms so)."""
        where = " AND x NOT IN (SELECT id FROM loops)" if deleted_only else ""
        with self._lock:
            return [r[0] for r in self._db.execute(AUDIT_IDS + where)]

    def prune(
        self,
        loop_ids: Iterable[str],
        *,
        older_than: float | None,
        keep_rows: int | None,
        keep_rows_deleted: int | None,
        archive: Path | None = None,
        budget_s: float | None = None,
    ) -> int:
        """Delete the audit rows of ``loop_ids`` that the retention policy lets go: those
        beyond the newest ``keep_rows`` of a registered loop (``keep_rows_deleted`` of a
        deleted one), and those of the loop's oldest rows that were all written before the
        wall time ``older_than`` (:meth:`_cut`). The newest row of every id is always kept:
        it carries the id's last ``seq``, from which a loop registered again under that id
        continues. With ``archive``, a loop's rows are appended to that JSON-lines file
        (fsynced) before they are deleted. ``budget_s``: stop taking ids from ``loop_ids``
        once that long was spent (at least one id; an iterator keeps the ids not taken).
        Returns the rows deleted."""
        self.apply_journal()
        deleted = 0
        began = time.perf_counter()
        for loop_id in loop_ids:
            with self._lock:
                cut = self._cut(loop_id, older_than, keep_rows, keep_rows_deleted)
                if cut is not None:
                    if archive is not None:
                        self._archive(archive, loop_id, cut)
                    # a transaction per loop: a loop's rows are spread over the whole table,
                    # so one for many loops would write most of its pages to the WAL at once
                    with self.transaction(durable=False) as db:
                        deleted += db.execute(
                            "DELETE FROM audit WHERE loop_id = ? AND id < ?", (loop_id, cut)
                        ).rowcount
            if budget_s is not None and time.perf_counter() - began >= budget_s:
                break
        return deleted

    def _cut(
        self, loop_id: str, older_than: float | None, keep: int | None, keep_deleted: int | None
    ) -> int | None:
        """The audit id below which the loop's rows go (None: none go), each bound found
        by the ``(loop_id, id)`` index, so a loop costs what it deletes, not what it keeps.

        The row cap cuts below the newest ``keep`` rows. The age cuts below the first row
        (in append order) written at or after ``older_than``: only an unbroken run of the
        oldest rows all older than the horizon goes. A row's wall time is the host clock
        when it was written: rows written while that clock was set back (a host booted at
        2000-01-01 until NTP fixed it) look old, but they follow younger rows in append
        order, so they stay until those rows age out too (docs/tuner.md, Retention)."""
        db = self._db
        bounds = db.execute(
            "SELECT (SELECT id FROM audit WHERE loop_id = ? ORDER BY id LIMIT 1), "
            "(SELECT id FROM audit WHERE loop_id = ? ORDER BY id DESC LIMIT 1), "
            "EXISTS (SELECT 1 FROM loops WHERE id = ?)",
            (loop_id,) * 3,
        ).fetchone()
        oldest, newest, registered = bounds
        if oldest is None or oldest == newest:
            return None
        keep = keep if registered else keep_deleted
        cut = oldest
        if keep is not None:
            row = db.execute(
                "SELECT id FROM audit WHERE loop_id = ? ORDER BY id DESC LIMIT 1 OFFSET ?",
                (loop_id, max(keep, 1) - 1),
            ).fetchone()
            cut = row[0] if row else oldest
        if older_than is not None:
            row = db.execute(
                "SELECT id FROM audit WHERE loop_id = ? AND id >= ? AND wall_time >= ? "
                "ORDER BY id LIMIT 1",
                (loop_id, cut, older_than),
            ).fetchone()
            cut = row[0] if row else newest
        return min(cut, newest) if cut > oldest else None

    def _archive(self, archive: Path, loop_id: str, cut: int) -> None:
        """Append the loop's rows below ``cut`` to the JSON-lines file ``archive``, fsynced
        (before they are deleted)."""
        names = ("id", *AUDIT_COLUMNS.replace(" ", "").split(","))
        rows = self._db.execute(
            f"SELECT id, {AUDIT_COLUMNS} FROM audit WHERE loop_id = ? AND id < ? ORDER BY id",
            (loop_id, cut),
        )
        with open(archive, "ab") as out:
            for row in rows:
                out.write(orjson.dumps(dict(zip(names, row, strict=True))) + b"\n")
            out.flush()
            os.fsync(out.fileno())

    def checkpoint(self) -> None:
        """Copy the write-ahead log into the database and empty it, if no reader holds an
        older snapshot (else it does what it can without waiting: the worker calls it)."""
        with self._lock:
            (waits,) = self._db.execute("PRAGMA busy_timeout").fetchone()
            self._db.execute("PRAGMA busy_timeout=0")
            try:
                self._db.execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchall()
            finally:
                self._db.execute(f"PRAGMA busy_timeout={int(waits)}")

    def export(self, out, loop_id: str | None = None, since_id: int = 0) -> int:
        """Write audit rows (all, or one loop's) after ``since_id``, oldest first, as JSON
        lines to the binary file ``out``; returns how many."""
        self.apply_journal()
        return export_audit(self._db, out, loop_id, since_id, self._lock)


def export_audit(
    db: sqlite3.Connection,
    out,
    loop_id: str | None = None,
    since_id: int = 0,
    lock: contextlib.AbstractContextManager | None = None,
) -> int:
    """Audit rows after ``since_id`` (all loops, or one), oldest first, as JSON lines (one
    object per row: id, loop_id, wall_time, t, seq, mode, reason, gains, detail), read
    EXPORT_CHUNK rows at a time, each chunk under ``lock`` (the store's, if given)."""
    lock = lock or contextlib.nullcontext()
    names = ("id", *AUDIT_COLUMNS.replace(" ", "").split(","))
    query = f"SELECT id, {AUDIT_COLUMNS} FROM audit WHERE id > ?"
    if loop_id is not None:
        query += " AND loop_id = ?"
    query += " ORDER BY id LIMIT ?"
    n = 0
    while True:
        params = (since_id,) if loop_id is None else (since_id, loop_id)
        with lock:
            rows = db.execute(query, (*params, EXPORT_CHUNK)).fetchall()
        for row in rows:
            out.write(orjson.dumps(dict(zip(names, row, strict=True))) + b"\n")
        n += len(rows)
        if len(rows) < EXPORT_CHUNK:
            return n
        since_id = rows[-1][0]
