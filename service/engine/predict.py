"""The predicted effect of a proposal (shadow mode): the identified model's step response
under the gains in force and under the proposal, compared by IAE per unit move.

Only an identified FOPTD model predicts: a hint gives a gain and a time constant but no
dead time, and a prediction without the dead time would flatter aggressive gains.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from plant_sim.loop import step_test
from service.engine import monitor

if TYPE_CHECKING:
    from service.engine.table import LoopTable

STEPS = 400
"""Simulation steps over the judging window (2 RL periods)."""


def predictions(
    tb: LoopTable, slots: list[int], old: np.ndarray, new: np.ndarray, models: list | None = None
) -> list[str]:
    """For each slot a ``key=value`` text: ``pred_iae=<old>-><new> pred_change=<%>`` (IAE
    per unit move, s), or ``prediction=none(no identified model)``. ``models``: the model
    each decision was made on (a model's tuning: the identified one, which on a hinted
    loop whose hint it contradicts is not the one in force); default the one in force."""
    if models is None:
        models = [tb.ident[s].in_force for s in slots]
    out = ["prediction=none(no identified model)"] * len(slots)
    rows = [i for i, m in enumerate(models) if m is not None]
    if not rows:
        return out
    models = [models[i] for i in rows]
    K = np.array([m.k for m in models])
    tau = np.array([m.tau for m in models])
    theta = np.array([m.theta for m in models])
    horizon = np.array([monitor.RESPONSE_PERIODS * tb.period[slots[i]] for i in rows])
    # each row at its own step, horizon / STEPS: one simulation of the loops in time units
    # of their step (tau and theta over it, ki times it), the IAE back in seconds. One dt
    # for the batch (the longest horizon's) simulated a tau 5 s loop stepped with a
    # tau 1000 s one at dt 10 s: unstable, pred_iae 5e53 -> 9e149 instead of 6.1 -> 4.2.
    step = np.tile(horizon / STEPS, 2)
    gains = np.concatenate([old[rows], new[rows]])
    with np.errstate(all="ignore"):
        trace = step_test(
            np.tile(K, 2), np.tile(tau, 2) / step, np.tile(theta, 2) / step, gains[:, 0],
            gains[:, 1] * step, dt=1.0, horizon=float(STEPS),
        )  # fmt: skip
        iae = np.abs(trace.e).sum(axis=1) * step / 2.0  # the step test moves by 2
    before, after = iae[: len(rows)], iae[len(rows) :]
    for j, i in enumerate(rows):
        b, a = float(before[j]), float(after[j])
        change = (a / b - 1.0) * 100.0 if b > 0 and math.isfinite(a) else math.inf
        out[i] = f"pred_iae={b:.4g}->{a:.4g} pred_change={change:+.1f}%"
    return out
