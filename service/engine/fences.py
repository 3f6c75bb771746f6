"""What holds the agent after a change of the tuner's own: the cool-down (no step until
a plant time, :func:`cool`) and fences (after a rollback, the agent's steps stop short of
the gains that failed).

:mod:`service.engine.verify` puts a fence up at a rollback (the per-loop ``x_*`` and
``cool_*`` arrays are allocated with its own); the stepping clips the agent's gains to it.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from service.engine.table import LoopTable

FENCED = ("overshoot", "oscillation", "operator")
"""The verdicts that put a fence up: the loop rang or oscillated at the failed gains, or
an operator said they were wrong. Not ``iae``: a load step or noise inside the judged
window fails good changes on loaded loops now and then, and a fence after those held the
agent off the gains it needed (robustness suite, load steps: worst 0.027 -> 0.037)."""
COOLED = {
    1.0: "a rollback (or its proposal)",
    2.0: "an operator's rejection of a proposal",
    3.0: "a model's tuning, until its verdict",
}
"""What started a loop's cool-down, by its code in ``tb.cool_why`` (NaN: a snapshot from
before session 40, which did not say)."""
ROLLBACK, REJECTED, MODEL = COOLED


def cool(tb: LoopTable, s: int, t: float, why: float) -> None:
    """Hold the agent of slot ``s`` for the guard's cool-down from plant time ``t``, after
    the change ``why`` (a key of :data:`COOLED`): one change judged at a time."""
    tb.cool_until[s], tb.cool_why[s] = t + tb.v_cool[s], why


FENCE_SHORT = 0.8
"""A fence stands at this share of the failed gain (its inverse for a lowered one), or at
the midpoint when that is nearer to it: the midpoint alone, after a rollback to a
registration's gains 14x below the failed ones, held the agent at a quarter of them for
the whole fence (load random walk, auto-rescale: worst 0.026 -> 0.095)."""
FENCE_MIN_CHANGE = 0.05
"""A gain the failed change moved by less than this (log units, 5 %) is not fenced: the
change failed by the other one."""


def fence_rollback(tb: LoopTable, s: int, failed: tuple, good: tuple, t: float) -> None:
    """After a rollback from ``failed`` to ``good`` (kp, ki; in advisory, a rollback
    proposal accepted): for ``guard.fence_periods`` RL periods the agent's steps stop
    short of the failed gains (:data:`FENCE_SHORT` of them, or halfway in log space when
    that is nearer), on each gain the failed change moved. Without it the agent, its
    memory reset, climbs back to the gains that rang within a few steps (docs/tuner.md,
    Verdicts). A fence still up is narrowed, never widened: the good gains lie inside it."""
    if not tb.v_fence[s] > 0.0:
        return
    moved = [
        (gain, f, g)
        for gain, f, g in (("kp", failed[0], good[0]), ("ki", failed[1], good[1]))
        if f > 0.0 and g > 0.0 and abs(math.log(f / g)) >= FENCE_MIN_CHANGE
    ]
    if not moved:
        return
    if not tb.x_until[s] > t:
        unfence(tb, s)
    for gain, f, g in moved:
        if f > g:
            bound = max(math.sqrt(f * g), f * FENCE_SHORT)
            getattr(tb, f"x_{gain}_hi")[s] = np.fmin(getattr(tb, f"x_{gain}_hi")[s], bound)
        else:
            bound = min(math.sqrt(f * g), f / FENCE_SHORT)
            getattr(tb, f"x_{gain}_lo")[s] = np.fmax(getattr(tb, f"x_{gain}_lo")[s], bound)
    tb.x_until[s] = t + float(tb.v_fence[s])


def unfence(tb: LoopTable, s) -> None:
    """No fence (``s`` a slot or slots): a reset, an operator's gains, a model's tuning."""
    tb.x_kp_lo[s] = tb.x_kp_hi[s] = tb.x_ki_lo[s] = tb.x_ki_hi[s] = math.nan
    tb.x_until[s] = -math.inf


def fence(tb: LoopTable, slots: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The fences of the loops at ``slots`` at plant times ``t``: (lo, hi), each (n, 2)
    [kp, ki], NaN where there is none (or it expired)."""
    up = (tb.x_until[slots] > t)[:, None]
    lo = np.column_stack([tb.x_kp_lo[slots], tb.x_ki_lo[slots]])
    hi = np.column_stack([tb.x_kp_hi[slots], tb.x_ki_hi[slots]])
    return np.where(up, lo, math.nan), np.where(up, hi, math.nan)
