"""The recorder's pool: identification's segment buffers, shared by all loops of a table
(a row per open segment, so memory goes only to loops that are recording;
:mod:`service.engine.watch` records into it)."""

from __future__ import annotations

import numpy as np

CAP = 512
"""Samples a segment holds before it halves its resolution (or drops its oldest event)."""
COLUMNS = 4  # t, sp, pv, op


class Recorder:
    """The pool of segment buffers of a table: row r holds (t, sp, pv, op) x CAP."""

    def __init__(self) -> None:
        self.data = np.zeros((0, COLUMNS, CAP))
        self.free: list[int] = []

    def take(self) -> int:
        if not self.free:
            self.reserve(max(4, 2 * self.data.shape[0]))
        return self.free.pop()

    def reserve(self, rows: int) -> None:
        """Room for ``rows`` open segments (a row per identifying loop, reserved as loops
        are configured): growing copies the pool, 0.3 s at 10,000 loops, which in the
        worker's path stalled every loop's samples (``pitune bench``). Rows not yet
        recorded into take no memory (zeroed pages are mapped on first write)."""
        old = self.data.shape[0]
        if rows <= old:
            return
        grown = np.zeros((max(rows, 2 * old), COLUMNS, CAP))
        used = np.setdiff1d(np.arange(old), self.free)  # (copying free rows maps them)
        grown[used] = self.data[used]
        self.data = grown
        self.free[:0] = range(grown.shape[0] - 1, old - 1, -1)

    def give(self, row: int) -> None:
        self.free.append(row)
