"""The periodic snapshot's database writes, off the tuner's worker thread.

A cluster member's periodic snapshot writes a chunk of loops' state (~1.4 KB of JSON a
loop) in one statement on a connection of its own. The worker used to wait for it:
50-130 ms a chunk of 1,000 loops on a loaded 2-core box, a chunk every 0.2 s for half
of every snapshot interval, while the member's samples queued behind it (at 150,000
loops the update latency's p99 was made of these stalls). Now the worker builds a
chunk's rows (reading the table, under its lock: a few ms) and hands them to a
:class:`SnapshotWriter`, whose thread writes them while the worker goes on with the
samples.

Order still holds. A row written here is older than any the worker writes itself
afterwards (the snapshots a commit, a release or a shutdown needs on disk at once, and a
loop's delete), so those first :meth:`SnapshotWriter.discard` their loops from the
chunks still queued (the newer rows replace them) and wait for the chunk being written,
which then lands before theirs. A chunk waits for no commit: a lost periodic snapshot
costs a loop the agent state since the one before, as before (and a fenced one, its
leases lost meanwhile, is refused by the store as before).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterable

from service.daemon.store_pg import Fenced

log = logging.getLogger("pitune.tuner")
QUEUED_CHUNKS = 2
"""Chunks waiting at most; the worker's next one waits for room (a store slower than
the snapshot's pace holds the worker rather than the memory of every chunk)."""

Rows = list[tuple[str, bytes, str]]


class SnapshotWriter:
    """A thread writing chunks of snapshot rows with ``write(rows, fence)``, in order."""

    def __init__(self, write: Callable[[Rows, object], None]) -> None:
        self._write = write
        self._queue: list[tuple[Rows, object]] = []
        self._busy = False
        self._closing = False
        self._cond = threading.Condition()
        self.written = 0
        """Rows written (or refused by the fence) since start."""
        self.thread = threading.Thread(target=self._run, name="pitune-snapshots", daemon=True)
        self.thread.start()

    def submit(self, rows: Rows, fence: object) -> None:
        """Queue a chunk (waits while :data:`QUEUED_CHUNKS` are queued)."""
        if not rows:
            return
        with self._cond:
            while len(self._queue) >= QUEUED_CHUNKS and not self._closing:
                self._cond.wait()
            self._queue.append((rows, fence))
            self._cond.notify_all()

    def discard(self, loop_ids: Iterable[str] | None) -> None:
        """Drop ``loop_ids`` (None: every loop) from the queued chunks and wait for the
        chunk being written: the caller's rows, newer, go to the store after it."""
        with self._cond:
            if loop_ids is None:
                self._queue.clear()
            else:
                gone = set(loop_ids)
                self._queue = [
                    ([r for r in rows if r[0] not in gone], fence) for rows, fence in self._queue
                ]
            while self._busy:
                self._cond.wait()
            self._cond.notify_all()

    def idle(self) -> bool:
        with self._cond:
            return not self._queue and not self._busy

    def drain(self, timeout: float | None = None) -> bool:
        """Wait until every queued chunk is written; False on timeout."""
        with self._cond:
            return self._cond.wait_for(lambda: not self._queue and not self._busy, timeout)

    def close(self, timeout: float = 10.0) -> None:
        """Write what is queued, then end the thread."""
        with self._cond:
            self._closing = True
            self._cond.notify_all()
        self.thread.join(timeout)

    def _run(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._queue or self._closing)
                if not self._queue:
                    return
                rows, fence = self._queue.pop(0)
                self._busy = True
                self._cond.notify_all()
            try:
                if rows:
                    self._write(rows, fence)
            except Fenced as exc:  # the leases lost: the loops' state is not ours to save
                log.warning("snapshot fenced: %s", exc)
            except Exception:
                log.exception("writing a snapshot chunk of %d loops failed", len(rows))
            finally:
                with self._cond:
                    self.written += len(rows)
                    self._busy = False
                    self._cond.notify_all()
