"""The proposal track of advisory and shadow loops (``adv_kp``/``adv_ki``, arrays of
:data:`service.engine.verify.F64`), and what keeps a pending proposal safe to accept.

The agent observes the gains in force (what the plant runs with), and its step is added
to the previous proposal instead of to the gains in force, with the safety guard applied
from the previous proposal. Successive proposals thus walk where the agent's steps point,
as its updates would in ``auto``, instead of repeating one guard-limited step from gains
that never move. An operator accepting one (``POST /loops/{id}/proposals/{seq}/accept``)
has it published as an ``auto`` message (reason ``accepted``;
:mod:`service.engine.proposals`); rejecting it restarts the track from the gains in
force and holds the agent for the cool-down. Gains of the operator's own, adopted from
the samples, restart the track too: proposals walked from gains no longer in force would
start a guard step from nothing the plant runs (12-15x the gains in force, session 35's
review).

**Reach.** While a proposal waits, the agent still sees the gains in force, so its step
does not vanish where the proposal has got to: unbounded, the track walked on every RL
period (session 41's review: kp 0.025 -> 7.1 in 3 h, 285x the gains in force in one
accepted message, on a loop stable only up to kp 6). The agent's steps therefore take a
proposal no farther than :data:`REACH_STEPS` guard steps from the gains in force
(:func:`within_reach`); there it waits for a decision (the view's ``proposal.at_reach``),
and an accept re-checks it against the gains in force then (:func:`refusal`). A model's
tuning, a rollback (to verified gains) or a reset's (the registered gains) has its own
premise and may lie farther: the agent does not walk it (its step is no judgement of
those gains).

**Premise.** A proposal carries the plant time it was made (``adv_t``; the view's
``made_t``). An accept is refused (:func:`refusal`) when the loop has shown since that the
plant is not the one it was made for: the oscillation detector flagged the loop after
it was made, or the loop is paused oscillating, out of the agent's envelope, or on a hint
mismatch. A rollback proposal is exempt: going back to the verified gains is the cure.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from service.engine.monitor import GAIN_RTOL, same_gains
from service.engine.updates import REASON_CODE
from service.wire.protocol import UpdateReason

if TYPE_CHECKING:
    from service.engine.table import LoopTable

REACH_STEPS = 3
"""Guard steps (``max_rel_change`` each) a walked proposal may lie from the gains in
force: 3.4x at the default 0.5. Three steps is what an ``auto`` loop moves in three RL
periods, each of which it would have judged; a loop 100x off its good gains (session 41's
review, loop P1) gets there in 4 accepts (docs/tuner.md, Advisory workflow)."""


def reach(tb: LoopTable, slots) -> np.ndarray:
    """The factor a walked proposal may lie from the gains in force, per loop."""
    return (1.0 + tb.max_rel[slots]) ** REACH_STEPS


def within_reach(tb, slots, track, old, base, new) -> tuple[np.ndarray, np.ndarray]:
    """The tracked loops' (``track``) new proposals ``new`` (n, 2) clipped to their reach
    of the gains in force ``old``; a previous proposal ``base`` beyond it (a model's
    tuning, a rollback) is not walked. Returns the proposals and where the reach kept
    the proposal where it was (a step held: the proposal waits at its reach)."""
    r = reach(tb, slots)[:, None]
    lo, hi = old / r, old * r
    beyond = ((base < lo / (1 + GAIN_RTOL)) | (base > hi * (1 + GAIN_RTOL))).any(axis=1)
    clipped = np.where(beyond[:, None], base, np.clip(new, lo, hi))
    clipped = np.where(track[:, None], clipped, new)

    def same(a, b):
        return np.isclose(a, b, rtol=GAIN_RTOL, atol=0.0).all(axis=1)

    return clipped, track & ~same(clipped, new) & same(clipped, base)


def _spread(tb: LoopTable, s: int) -> float:
    """How far (log units, the larger of kp's and ki's) slot ``s``'s pending proposal
    lies from the gains in force."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return float(np.nanmax(np.abs(np.log(
            [tb.adv_kp[s] / tb.kp[s], tb.adv_ki[s] / tb.ki[s]]
        ))))  # fmt: skip


def at_reach(tb: LoopTable, s: int) -> bool:
    """Whether slot ``s``'s pending proposal lies at (or beyond) its reach."""
    return _spread(tb, s) >= math.log(float(reach(tb, s))) - math.log1p(GAIN_RTOL)


def propose(tb: LoopTable, s, kp, ki, seq, reason: UpdateReason) -> None:
    """A proposal pending at slot(s) ``s``, made at the loop's last plant time."""
    tb.adv_kp[s], tb.adv_ki[s], tb.adv_seq[s] = kp, ki, seq
    tb.adv_why[s], tb.adv_t[s] = REASON_CODE[reason], tb.last_t[s]


def pending(tb: LoopTable, s: int, gains: tuple[float, float], reason: UpdateReason) -> bool:
    """Whether slot ``s``'s pending proposal is already ``gains`` for ``reason``: made
    again, it would only take a new seq (an oscillation goes on failing the gains in
    force: 7 rollback proposals in 1,300 s, an operator's approval of the one read a 409)."""
    return bool(
        tb.adv_why[s] == REASON_CODE[reason]
        and same_gains(tb.adv_kp[s], gains[0]) & same_gains(tb.adv_ki[s], gains[1])
    )


def restart(tb: LoopTable, s) -> None:
    """No proposal pending: the track restarts from the gains in force (``s``: slots)."""
    tb.adv_kp[s] = tb.adv_ki[s] = tb.adv_seq[s] = tb.adv_why[s] = tb.adv_t[s] = math.nan


def refusal(tb: LoopTable, s: int) -> str | None:
    """Why slot ``s``'s pending proposal may not be accepted now (None: it may)."""
    kp, ki = float(tb.adv_kp[s]), float(tb.adv_ki[s])
    if bool(same_gains(kp, tb.g_kp[s]) & same_gains(ki, tb.g_ki[s])):
        return None  # a rollback: back to the verified gains
    made = float(tb.adv_t[s])
    if made < tb.osc_seen[s]:
        return (
            f"the loop oscillated at t = {float(tb.osc_seen[s]):.10g}, after the proposal "
            f"was made (t = {made:.10g}): the plant is not the one it was made for; reject it"
        )
    flags = [
        ("a model identified since lies out of the agent's envelope", tb.out_env[s]),
        ("a model identified since mismatches the hint", tb.mismatch[s]),
    ]
    for text, on in flags:
        if on:
            return f"{text}: the plant is not the one the proposal was made for; reject it"
    r = float(reach(tb, s))
    walked = tb.adv_why[s] not in (REASON_CODE[UpdateReason.model], REASON_CODE[UpdateReason.reset])
    if walked and _spread(tb, s) > math.log(r) + math.log1p(GAIN_RTOL):
        return (
            f"it lies more than {r:.4g}x (its reach: {REACH_STEPS} guard steps) from the "
            f"gains in force (kp {float(tb.kp[s]):.6g}, ki {float(tb.ki[s]):.6g}), changed "
            "since it was made; reject it"
        )
    return None
