"""A loop's status (:class:`LoopStatus`): the first of the conditions that holds, in an
order of precedence (what the safety guard is doing with the loop right now)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from service.engine import reported, verify
from service.engine.modes import FROZEN
from service.wire.protocol import LoopStatus

if TYPE_CHECKING:
    from service.engine.table import LoopTable

STATUSES = [
    LoopStatus.frozen, LoopStatus.waiting, LoopStatus.stale, LoopStatus.gains_out_of_bounds,
    LoopStatus.identifying,
    LoopStatus.out_of_envelope, LoopStatus.manual, LoopStatus.saturated,
    LoopStatus.oscillating, LoopStatus.hint_mismatch, LoopStatus.quiet, LoopStatus.tuning,
]  # fmt: skip
"""Statuses in order of precedence (see :func:`statuses`)."""


def statuses(tb: LoopTable, slots: np.ndarray, wall: float) -> np.ndarray:
    """Each loop's :class:`LoopStatus` as an index into :data:`STATUSES`: the first
    condition that holds, in this order of precedence."""
    t = tb.last_t[slots]
    conditions = [
        tb.mode[slots] == FROZEN,
        np.isnan(t),
        wall - tb.last_wall[slots] > tb.stale_gap[slots],
        reported.held(tb, slots),
        ~tb.scaled[slots],
        tb.out_env[slots],
        tb.manual[slots],
        tb.saturated[slots],
        verify.paused(tb, slots, t),
        tb.mismatch[slots],
        tb.gate_closed(slots, t),  # NaN t: False, and waiting comes first
        np.ones(slots.size, bool),
    ]
    return np.argmax(np.stack(conditions), axis=0)
