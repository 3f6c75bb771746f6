"""The table's lock handed from the worker to another thread between two messages.

The worker holds the table's lock through a whole batch of messages (seconds, when it
works off a backlog), and Python's locks are not fair: the worker takes the lock again
before a waiting thread wakes. A cluster member taking over a dead member's shards
inserts their loops chunk by chunk, each chunk under the lock; on a busy survivor each
chunk waited for the end of a batch (at 30,000 loops: 7.9 s of a 15.2 s failover).
A thread that takes the lock through :meth:`Handoff.hold` is let in by the worker at
its next message (:meth:`Handoff.let_in`), and the worker goes on when it is done.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager

LET_IN_WAIT_S = 0.05
"""Longest the worker waits for a waiting thread to take the lock it released (the
thread needs the interpreter to wake; if it is gone, the worker goes on)."""


class Handoff:
    """Fair turns at ``lock`` (an RLock the worker holds once) for other threads."""

    def __init__(self, lock: threading.RLock) -> None:
        self.lock = lock
        self._waiting = 0
        self._count = threading.Lock()
        self._taken = threading.Event()

    @contextmanager
    def hold(self) -> Iterator[None]:
        """The lock, taken at the worker's next message rather than at the end of its
        batch (not from the worker's thread)."""
        with self._count:
            self._waiting += 1
        try:
            self.lock.acquire()
        finally:
            with self._count:
                self._waiting -= 1
        self._taken.set()
        try:
            yield
        finally:
            self.lock.release()

    def let_in(self) -> None:
        """The worker, holding the lock once: let the threads waiting in :meth:`hold` have
        it, then take it back."""
        if not self._waiting:
            return
        self._taken.clear()
        self.lock.release()
        try:
            self._taken.wait(LET_IN_WAIT_S)
        finally:
            self.lock.acquire()
