"""The tuner worker's upkeep between messages: the periodic snapshot of every loop's
state, the journal applied to the store's tables, and the retention policy.

Retention: in idle time (or, when a pass is a whole interval late, on a busy worker
too) the worker prunes the audit history by the settings'
``history_*`` policy (:meth:`Store.prune`), PRUNE_BUDGET_S per iteration; a
cluster's member prunes only its own loops (and one member the deleted loops'), ages
on the database's clock (:meth:`Upkeep._retention_ids`).

A snapshot or journal write that fails (disk full, database locked) is not a failed
commit (no step is lost: it is written again later) but it is no less a broken store,
one a tuner whose loops rarely step would otherwise show nowhere: ``/healthz`` answers
503 with :attr:`Upkeep.write_failure` until a write of each kind that failed goes
through (a journal chunk rewriting pages the file has may pass while a snapshot that
grows it fails: not a recovery), ``pitune_store_write_failures`` counts them, and the
log has one error when the first fails (tracebacks at debug level) and one warning
when they work again. The journal is retried COMMIT_RETRY_S after a failure, snapshots
at their next chunk.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import time
from collections.abc import Iterator

from service.daemon.admin import freeze_survivors
from service.daemon.delivery import COMMIT_RETRY_S
from service.daemon.snapwriter import SnapshotWriter
from service.daemon.store_pg import Fenced

log = logging.getLogger("pitune.tuner")
SNAPSHOT_CHUNK = 250
"""Loops snapshotted per worker iteration by the periodic snapshot. A cluster's member
reads a chunk's rows on its worker (under the table's lock) and writes them on another
thread (:mod:`service.daemon.snapwriter`). Reading costs less per loop in smaller
chunks (measured alone: 1.9 ms for 250 loops, 7.4 µs a loop; 21 ms for 1,000, 21 µs a
loop, the chunk's arrays no longer in cache), and the samples behind a chunk wait a
few ms instead of tens."""
SNAPSHOT_SPREAD = 0.5
"""Share of ``snapshot_interval_s`` the periodic snapshot's chunks are spread over. A
chunk written on the worker (SQLite) costs it up to tens of milliseconds; back to back,
the 30 chunks of a 30,000-loop member took it 1.5 s behind its samples every interval
(latency p99 0.6 s). Spread, they cost it a steady few percent."""
SNAPSHOT_ROTATION = 4
"""A loop whose state moved only by its samples' running sums (no step, update, model,
pause or mode change) is written by every SNAPSHOT_ROTATION-th periodic snapshot, not by
each: most loops step every 30-170 s (an RL period), so at the default 30 s interval
about a third of them moved, and the snapshot's cost (the tuner's and PostgreSQL's, ~10 %
and ~15 % of a core at 150,000 loops a member) falls by about half. What a crash then
loses of such a loop is its sample sums of up to SNAPSHOT_ROTATION intervals instead of
one; its agent state, gains and models are as recent as before."""
JOURNAL_CHUNK = 1000
"""Journal rows applied to the store's tables per idle worker iteration (~5 ms)."""
JOURNAL_BACKLOG = 100_000
"""Journal rows pending above which they are applied even while messages wait."""
PRUNE_BUDGET_S = 0.05
"""Worker time a retention pass takes per iteration (the store's lock held meanwhile):
the loop ids it gets through in that time. A fixed count of ids cost the worker ~4 s an
iteration at the row cap when a loop's rows were scanned (p99 sample latency 3.7 s,
session 40); by id ranges a loop costs what it deletes: 25 ms for 500 rows, 0.8 ms for none
(docs/tuner.md, Retention and disk use)."""


class Upkeep:
    """Mixin of :class:`service.daemon.tuner.Tuner` (its worker calls these between
    batches of messages)."""

    def snapshot(self) -> None:
        """Snapshot every loop now (shutdown, tests); not while commits fail: the table
        then holds steps the store lacks, and a restart must find the state that was
        published (as after a SIGKILL), not their agent state beside older gains."""
        if self.store_failure is not None:
            log.warning("no snapshot: %s", self.store_failure)
            return
        self._write_snapshot(None)
        self._snapshot_todo = []

    snapshot_writer: SnapshotWriter | None = None
    """Writes the periodic snapshot's chunks off the worker (a cluster's member)."""
    _snapshot_at = 0.0
    """Monotonic time of the periodic snapshot's next chunk."""
    _snapshot_pace = 0.0
    """Seconds between its chunks."""

    _prune_todo: collections.deque[str] = collections.deque()
    """The loop ids the retention pass under way has yet to prune (a new deque per pass:
    this empty one is never added to)."""
    retention_failure: str | None = None
    """Why the last retention pass failed, until a pass goes through (``/healthz``)."""
    prune_failures = 0
    """Retention passes failed since start."""

    write_failure: str | None = None
    """Why the last snapshot or journal write failed, until one goes through (``/healthz``)."""
    write_failures = 0
    """Snapshot and journal writes failed since start."""
    _write_failing: dict[str, float] = {}
    """Kind of write ('snapshot', 'journal') -> monotonic time its failures began."""
    _write_retry_at = 0.0
    """Monotonic time before which the journal is not applied again (after a failure)."""

    _snapshot_turn = 0
    """Periodic snapshots started (the rotation of :data:`SNAPSHOT_ROTATION`)."""

    def upkeep_totals(self) -> dict:
        """Its counters, for :meth:`Metrics.totals`."""
        return {
            "pitune_store_write_failures": (
                "Snapshot and journal writes that failed (/healthz says why until one goes "
                "through); their loops are written again later.",
                lambda: self.write_failures,
            ),
            "pitune_audit_pruned": (
                "Audit rows deleted by the retention policy.",
                lambda: self.pruned,
            ),
            "pitune_audit_prune_failures": (
                "Retention passes that failed and pruned nothing (/healthz says why).",
                lambda: self.prune_failures,
            ),
        }

    def _start_snapshot(self, interval: float) -> None:
        """The loops to snapshot this turn (``LoopTable.snapshot_turn``), a chunk now and
        the others spread over SNAPSHOT_SPREAD of the ``interval``."""
        with self.table.lock:
            self._snapshot_todo = self.table.snapshot_turn(self._snapshot_turn, SNAPSHOT_ROTATION)
        self._snapshot_turn += 1
        chunks = -(-len(self._snapshot_todo) // SNAPSHOT_CHUNK)
        self._snapshot_pace = interval * SNAPSHOT_SPREAD / max(chunks, 1)
        self._snapshot_some()

    def _snapshot_some(self) -> None:
        """The periodic snapshot, SNAPSHOT_CHUNK loops per worker iteration, the next
        chunk due a pace later, so that snapshotting a large site never stalls the
        samples for long."""
        chunk, self._snapshot_todo = (
            self._snapshot_todo[:SNAPSHOT_CHUNK],
            self._snapshot_todo[SNAPSHOT_CHUNK:],
        )
        self._snapshot_at = time.monotonic() + self._snapshot_pace
        if self.snapshot_writer is None:
            with self._store_write("snapshot" if chunk else ""):
                self._write_snapshot(chunk)
        else:  # the rows read here, written by the writer's thread (snapwriter.py)
            with self.table.lock:
                rows = self.table.snapshot(chunk)
                self.snapshot_writer.submit(rows, self._fence(r[0] for r in rows))
        if not self._snapshot_todo:
            freeze_survivors()

    def _write_snapshot(self, loop_ids: list[str] | None) -> None:
        """Snapshot ``loop_ids`` (None: every loop) now, on this thread, after what the
        snapshot writer is writing (their rows still queued there are older: dropped)."""
        # Written under the table lock (a few ms per chunk): a delete between reading the
        # rows and writing them would fail the whole chunk on the foreign key, and a
        # delete and a new registration of the id would give the new loop the old state.
        with self.table.lock:
            if self.snapshot_writer is not None:
                self.snapshot_writer.discard(loop_ids)
            rows = self.table.snapshot(loop_ids)
            if self.cluster is None:
                self.store.snapshot(rows)
                return
            try:
                self.store.snapshot(rows, self._fence(r[0] for r in rows))
            except Fenced as exc:  # the leases lost: the loops' state is not ours to save
                log.warning("snapshot fenced: %s", exc)

    def _prune_overdue(self) -> bool:
        """A pass a whole interval late runs on a busy worker too, a chunk per iteration:
        a tuner that is never idle must still keep the history within its budget."""
        interval = getattr(self.settings, "history_prune_interval_s", 3600.0)
        return self.clock.monotonic() >= self._next_prune + interval

    def _retain(self) -> None:
        """The retention policy, PRUNE_BUDGET_S of loop ids per idle worker iteration, a
        pass every ``history_prune_interval_s`` (see :meth:`Store.prune`)."""
        st = self.settings
        max_age_days = getattr(st, "history_max_age_days", None)
        try:
            if not self._prune_todo:
                now = self.clock.monotonic()
                if now < self._next_prune:
                    return
                self._next_prune = now + getattr(st, "history_prune_interval_s", 3600.0)
                self._prune_todo = collections.deque(self._retention_ids())
            # a cluster's ages go by the database's clock, the one its members share: a
            # member whose clock ran ahead (a bad NTP or RTC step) would prune young rows
            wall = self.clock.wall() if self.cluster is None else self.store.wall_now()
            self.pruned += self.store.prune(
                _popping(self._prune_todo),
                older_than=None if max_age_days is None else wall - max_age_days * 86400.0,
                keep_rows=getattr(st, "history_max_rows_per_loop", None),
                keep_rows_deleted=getattr(st, "history_max_rows_deleted", None),
                archive=getattr(st, "history_archive", None),
                budget_s=PRUNE_BUDGET_S,
            )
        except Exception as exc:
            # The pass is dropped whole and tried again at the next interval: its other
            # chunks would fail alike (the archive's disk full or gone). Shown in /healthz
            # and counted, for the store is no longer bounded while it lasts.
            self._prune_todo = collections.deque()
            self.prune_failures += 1
            self.retention_failure = f"retention pass failed: {exc}"
            retry_s = self.clock.until(self._next_prune)
            debug = log.isEnabledFor(logging.DEBUG)  # the traceback
            log.error("%s; next try in %.0f s", self.retention_failure, retry_s, exc_info=debug)
            return
        if not self._prune_todo:
            self.retention_failure = None  # a whole pass went through
            self.store.checkpoint()  # the write-ahead log back to empty (store.py)

    def _retention_ids(self) -> list[str]:
        """The loop ids of a retention pass: every id with audit rows; in a cluster, the
        loops this member owns, and the deleted loops' ids on the first of the live
        members only. So each loop's rows are pruned (and archived) by one member, not
        by every member every interval, and a member's pass cannot touch the loops of
        another (a loop that moves during a pass is pruned by both, by the same rule)."""
        if self.cluster is None:
            return self.store.audit_ids()
        ids = self.loop_ids()
        if self.cluster.members[:1] == [self.cluster.member]:
            ids += self.store.audit_ids(deleted_only=True)
        return ids

    def _apply_journal(self) -> None:
        """A chunk of the journal into the store's tables, when no message waits (or the
        backlog grew large): off the path from a sample to its gains message."""
        if time.monotonic() < self._write_retry_at:
            return
        if self.inbox.empty() or self.store.journal_rows > JOURNAL_BACKLOG:
            with self._store_write("journal" if self.store.journal_rows else ""):
                self.store.apply_journal(JOURNAL_CHUNK)

    def _writer_snapshot(self, rows: list, fence: object) -> None:
        """The snapshot writer's write, on its thread (:mod:`service.daemon.snapwriter`)."""
        with self._store_write("snapshot"):
            self.store.snapshot(rows, fence)

    @contextlib.contextmanager
    def _store_write(self, what: str):
        """A write of kind ``what`` ('': one with nothing to write, no proof the store
        works): a store error is recorded, not raised (see the module's docstring)."""
        try:
            yield
        except self.store.commit_errors as exc:
            now = time.monotonic()
            first = not self._write_failing
            self._write_failing = {what: now, **self._write_failing}  # (a copy: 2 threads)
            self.write_failures += 1
            self._write_retry_at = now + COMMIT_RETRY_S
            since = min(self._write_failing.values())
            self.write_failure = f"store writes failing for {now - since:.0f} s ({what}): {exc!r}"
            if first:
                log.error("%s; retried until writes work", self.write_failure)
            log.debug("%s write failed", what, exc_info=True)
            return
        failing = self._write_failing
        if what in failing:
            self._write_failing = {k: v for k, v in failing.items() if k != what}
            if not self._write_failing:
                lasted = time.monotonic() - min(failing.values())
                self.write_failure = None
                log.warning("store writes work again after %.1f s of failures", lasted)


def _popping(todo: collections.deque) -> Iterator[str]:
    """The ids of ``todo``, each taken off it only when asked for: those a budgeted
    :meth:`Store.prune` did not get to stay for the next iteration."""
    while todo:
        yield todo.popleft()
