"""The table slots of a batch's loop ids, remembered per batch.

A gateway sends the same loops in the same order scan after scan (a phase group of its
loops per message), and looking each id up in the table's dict of every loop was the
largest single cost of a cluster member's worker at 150,000 loops (py-spy: 16 % of its
CPU, a cache miss or two per sample). :class:`SlotMemo` keeps the slots of each batch
seen, by (length, first id, last id), and reuses them while the ids are the same, in
order (one comparison of two lists, in C), and no loop was added or removed since
(the table's ``version``).
"""

from __future__ import annotations

from itertools import repeat

import numpy as np

KEPT = 4096
"""Batches remembered (a member's gateways send a few hundred distinct ones a second at
1 Hz in the bench's 100 phase groups; a cache that misses on every one is cleared)."""


class SlotMemo:
    """Slots of loop ids in one table (see the module doc)."""

    def __init__(self, table) -> None:
        self.table = table
        self._memo: dict[tuple, tuple[int, list[str], np.ndarray]] = {}

    def slots(self, ids: list[str]) -> np.ndarray:
        """(n,) int64 table slots of ``ids`` (-1: not registered); read-only (shared
        with the next batch of the same ids)."""
        n = len(ids)
        version = self.table.version
        key = (n, ids[0], ids[-1]) if n else None
        hit = self._memo.get(key)
        if hit is not None and hit[0] == version and hit[1] == ids:
            return hit[2]
        slots = np.fromiter(map(self.table.slot_of.get, ids, repeat(-1, n)), np.int64, n)
        slots.flags.writeable = False
        if len(self._memo) >= KEPT:
            self._memo.clear()
        self._memo[key] = (version, ids, slots)
        return slots
