"""An advisory loop's proposals decided by an operator (``POST /loops/{id}/proposals/
{seq}/accept`` or ``/reject``): the proposal track is :mod:`service.engine.track`'s."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from service.engine.fences import REJECTED, cool, fence_rollback
from service.engine.modes import ADVISORY, AUTO
from service.engine.monitor import same_gains
from service.engine.oscillation import forget_lobes
from service.engine.track import refusal, restart
from service.engine.updates import REASON_CODE, StepResult
from service.engine.verify import _audit, single
from service.wire.protocol import UpdateReason

if TYPE_CHECKING:
    from service.engine.table import LoopTable


def accept(tb: LoopTable, s: int, seq: int, wall: float, actor: str) -> StepResult:
    """An operator accepts the advisory proposal ``seq``: published as an ``auto``
    message (the gateway applies it), in flight until the gateway reports it.
    ValueError if ``seq`` is not the loop's pending proposal, or it may not be accepted
    now (:func:`service.engine.track.refusal`)."""
    _check_proposal(tb, s, seq)
    old, new = (float(tb.kp[s]), float(tb.ki[s])), (float(tb.adv_kp[s]), float(tb.adv_ki[s]))
    lo, hi = (float(tb.kp_min[s]), float(tb.ki_min[s])), (float(tb.kp_max[s]), float(tb.ki_max[s]))
    if not all(a <= g <= b for a, g, b in zip(lo, new, hi, strict=True)):
        # the bounds changed after the proposal was made (PATCH): the guard in force rules
        raise ValueError(
            f"proposal {seq} (kp {new[0]:.6g}, ki {new[1]:.6g}) is outside the guard's bounds "
            f"in force (kp {lo[0]:.6g}..{hi[0]:.6g}, ki {lo[1]:.6g}..{hi[1]:.6g}): reject it"
        )
    refused = refusal(tb, s)
    if refused:
        raise ValueError(f"proposal {seq} may not be accepted now: {refused}")
    t = float(tb.last_t[s]) if math.isfinite(tb.last_t[s]) else 0.0
    if same_gains(new[0], tb.g_kp[s]) & same_gains(new[1], tb.g_ki[s]):
        fence_rollback(tb, s, old, new, t)  # a rollback proposal taken: as in auto,
        forget_lobes(tb, s)  # and the failed gains' ringing is not the restored gains'
    ident = tb.ident[s]
    if tb.adv_why[s] == REASON_CODE[UpdateReason.model] and ident is not None:
        ident.tuned_seq = int(tb.seq[s]) + 1  # the model's tuning now runs: its verdict refutes
    tb.prev_kp[s], tb.prev_ki[s] = old
    tb.kp[s], tb.ki[s] = new
    tb.pending[s], tb.auto_seq[s] = True, tb.seq[s] + 1
    restart(tb, s)
    tb.seq[s] += 1
    tb._gains_dirty.add(s)
    tb._verify_dirty.add(s)
    _audit(tb, s, wall, "accepted", old, new, {"proposal": seq, "actor": actor}, t=t)
    why = f"reason=accepted proposal={seq} verdict=pending"
    return single(tb, s, t, old, new, UpdateReason.accepted, why, AUTO)


def reject(tb: LoopTable, s: int, seq: int, wall: float, actor: str) -> None:
    """An operator rejects the advisory proposal ``seq``: the track restarts from the
    gains in force and the agent is held for the cool-down."""
    _check_proposal(tb, s, seq)
    gains, proposed = (float(tb.kp[s]), float(tb.ki[s])), (float(tb.adv_kp[s]), float(tb.adv_ki[s]))
    restart(tb, s)
    t = float(tb.last_t[s]) if math.isfinite(tb.last_t[s]) else 0.0
    cool(tb, s, t, REJECTED)
    tb._verify_dirty.add(s)
    _audit(tb, s, wall, "rejected", gains, gains, {
        "proposal": seq, "kp": proposed[0], "ki": proposed[1], "actor": actor,
    }, t=t)  # fmt: skip


def _check_proposal(tb: LoopTable, s: int, seq: int) -> None:
    if tb.mode[s] != ADVISORY:
        raise ValueError("only an advisory loop has proposals to accept or reject")
    if math.isnan(tb.adv_seq[s]):
        raise ValueError("no proposal is pending")
    if int(tb.adv_seq[s]) != seq:
        raise ValueError(f"proposal {seq} is not the pending one ({int(tb.adv_seq[s])})")
