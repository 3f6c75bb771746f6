"""A loop's refused samples, as its view shows them: the run of refusals for one reason
up to now (``refused``) and the counts by reason since the loop was registered
(``refused_counts``), a fixed row of :data:`REASONS` counters per loop (no dict per
loop: 112 bytes a slot, allocated with the table's arrays). The snapshot keeps the
counts by reason name, so they survive a restart or a handover to another cluster
member (as far as the last snapshot, as ``counters.rejected`` does)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from service.engine import monitor
from service.engine.figures import Refused
from service.wire.clip import clipped
from service.wire.decode import Rejection
from service.wire.protocol import RejectReason

if TYPE_CHECKING:
    from service.engine.table import LoopTable

REASONS = tuple(RejectReason)
"""The reject reasons by their code, the column of :attr:`n_refused` (the enum's order:
codes live only in memory, the snapshot names the reasons)."""
_CODE = {reason: code for code, reason in enumerate(REASONS)}


def allocate(tb: LoopTable, capacity: int, old: int) -> None:
    """The counts by reason of ``capacity`` slots, the first ``old`` kept."""
    counts = np.zeros((capacity, len(REASONS)), np.int64)
    if old:
        counts[:old] = tb.n_refused
    tb.n_refused = counts


def book(tb: LoopTable, s: int, rejection: Rejection, wall: float) -> None:
    """Book ``rejection`` on the loop at slot ``s``: its counters, its rejected share and
    its run of refusals (:class:`Refused`, one reason: another starts a new run)."""
    tb.n_rejected[s] += rejection.count
    tb.n_refused[s, _CODE[rejection.reason]] += rejection.count
    monitor.rejected(tb, s)
    run = tb.refused.get(s)
    same = run is not None and run.reason == rejection.reason
    tb.refused[s] = Refused.model_construct(  # (no validation: per sample)
        reason=rejection.reason, detail=clipped(rejection.detail), last_wall=wall,
        count=(run.count if same else 0) + rejection.count,
        since_wall=run.since_wall if same else wall,
    )  # fmt: skip


def counts(tb: LoopTable, s: int) -> dict[RejectReason, int]:
    """The loop's refusals by reason, those with any."""
    row = tb.n_refused[s].tolist()
    return {REASONS[code]: n for code, n in enumerate(row) if n}


def dumps(tb: LoopTable, slots: np.ndarray) -> list[dict[str, int]]:
    """Each loop's refusals by reason name for the snapshot (an empty dict for most)."""
    rows = tb.n_refused[slots]
    out: list[dict[str, int]] = [{} for _ in range(len(slots))]
    for i, code in zip(*np.nonzero(rows), strict=True):
        out[i][REASONS[code].value] = int(rows[i, code])
    return out


def load(tb: LoopTable, slots: np.ndarray, saved: list[dict[str, int]]) -> None:
    """The counts :func:`dumps` wrote (a reason this version does not know is dropped)."""
    for s, named in zip(slots.tolist(), saved, strict=True):
        for name, n in named.items():
            code = _CODE.get(name)  # (a StrEnum's members are found by their str)
            if code is not None:
                tb.n_refused[s, code] = n
