"""A loop's reset by mode (:meth:`service.engine.table.LoopTable.reset`): its gains go
back to the registered ones as an agent step's would, or, where the tuner may not set
them, are proposed (``advisory``) or left (``shadow``, ``frozen``)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from service.engine import track, verify
from service.engine.audit import audit_row
from service.engine.modes import AUTO, PUBLISHING
from service.engine.updates import MODE_VALUES, StepResult
from service.wire.protocol import UpdateReason

if TYPE_CHECKING:
    from service.engine.table import LoopTable

PROPOSED = "a proposal: the gains change when it is accepted and the gateway reports them"
"""The audit detail of an advisory loop's reset (docs/tuner.md, Advisory workflow)."""


def reset(tb: LoopTable, s: int, wall: float, actor: str) -> StepResult | None:
    """Slot ``s``'s reset: a fresh episode, and the gains to publish or None."""
    loop_id, mode = tb.ids[s], tb.mode[s]
    who = f"actor={actor}" if actor else ""
    old = (float(tb.kp[s]), float(tb.ki[s]))
    new = (float(tb.reg_kp[s]), float(tb.reg_ki[s]))
    t = None if math.isnan(tb.last_t[s]) else float(tb.last_t[s])
    tb._restart(s)
    verify.reset(tb, s)
    if mode not in PUBLISHING:  # (the history gives such a row no verdict)
        detail = f"agent state only: a {MODE_VALUES[mode]} loop's gains are not published"
        detail = f"{detail}; {who}" if who else detail
        tb._audit.append(
            audit_row(loop_id, wall, t, int(tb.seq[s]), MODE_VALUES[mode], "reset", old, old,
                      detail)
        )  # fmt: skip
        return None
    if mode == AUTO:
        (tb.prev_kp[s], tb.prev_ki[s]), (tb.kp[s], tb.ki[s]) = old, new
        tb.pending[s], tb.auto_seq[s] = True, tb.seq[s] + 1
    tb.seq[s] += 1
    if mode != AUTO:  # advisory: it replaces the proposal pending (a rollback's too)
        track.propose(tb, s, *new, tb.seq[s], UpdateReason.reset)
        who = f"{PROPOSED}; {who}" if who else PROPOSED
    tb._gains_dirty.add(s)
    tb._audit.append(
        audit_row(loop_id, wall, t, int(tb.seq[s]), MODE_VALUES[mode], "reset", old, new, who)
    )
    why = f"reason=reset basis=registered verdict={'pending' if mode == AUTO else 'proposal'}"
    return verify.single(tb, s, 0.0 if t is None else t, old, new, UpdateReason.reset, why,
                         int(mode))  # fmt: skip
