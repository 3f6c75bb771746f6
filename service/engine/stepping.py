"""One batched RL step of the due loops: the agent, then the safety guard.

Safety guard, per loop: new gains are clipped to the loop's absolute bounds, then to at
most a relative change ``r`` per update ([old / (1 + r), old * (1 + r)], symmetric in log
space), so a gain outside its bounds (an operator's choice) is walked back gradually.
``auto`` loops take the guarded gains at once (an update in flight until the gateway
reports them); ``advisory`` loops are stepped and their proposals published, but their
gains change only when the gateway reports new ones.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from service.engine.modes import AUTO
from service.engine.rules import GAIN_RTOL
from service.engine.updates import MODE_VALUES, StepResult

if TYPE_CHECKING:
    from service.engine.table import LoopTable


def step(tb: LoopTable, slots: np.ndarray, wall: float) -> StepResult:
    """One batched agent step of the loops in ``slots`` (each due, each once)."""
    kp_unit, ki_unit = tb.kp_unit[slots], tb.ki_unit[slots]
    old = np.column_stack([tb.kp[slots], tb.ki[slots]])
    obs = np.column_stack(
        [
            old[:, 0] / kp_unit,
            old[:, 1] / ki_unit,
            tb.last_e[slots] * tb.e_scale[slots],
            tb.int_e[slots],
        ]
    )
    if tb._policy is not None:
        state = tb.hidden[slots]  # a contiguous copy, updated in place
        delta = tb._policy.step_inplace(obs, state, tb.forgetting[slots])
        tb.hidden[slots] = state
    else:
        delta, tb.hidden[slots] = tb.agent.act(obs, tb.hidden[slots], tb.forgetting[slots])
    proposed = np.column_stack(
        [(obs[:, 0] + delta[:, 0]) * kp_unit, (obs[:, 1] + delta[:, 1]) * ki_unit]
    )
    grow = 1.0 + tb.max_rel[slots, None]
    lo = np.column_stack([tb.kp_min[slots], tb.ki_min[slots]])
    hi = np.column_stack([tb.kp_max[slots], tb.ki_max[slots]])
    new = np.clip(np.clip(proposed, lo, hi), old / grow, old * grow)

    auto = slots[tb.mode[slots] == AUTO]
    applied = tb.mode[slots] == AUTO
    tb.prev_kp[auto], tb.prev_ki[auto] = old[applied, 0], old[applied, 1]
    tb.kp[auto], tb.ki[auto] = new[applied, 0], new[applied, 1]
    tb.pending[auto] = True
    tb.seq[slots] += 1
    tb.n_steps[slots] += 1
    tb.n_updates[slots] += 1
    tb._gains_dirty.update(slots.tolist())

    ids, gateways, listed = tb.ids, tb.gateways, slots.tolist()
    result = StepResult(
        [ids[s] for s in listed],
        tb.last_t[slots],
        tb.seq[slots],
        tb.mode[slots],
        old,
        proposed,
        new,
        [gateways[s] for s in listed],
    )
    limited = np.flatnonzero(~np.isclose(proposed, new, rtol=GAIN_RTOL, atol=0.0).all(axis=1))
    details = [""] * len(slots)
    # formatting Python floats, not numpy scalars: a cold loop is limited in most steps
    for i, (kp, ki) in zip(limited.tolist(), proposed[limited].tolist(), strict=True):
        details[i] = _guard_detail(kp, ki)
    mode_names = [MODE_VALUES[c] for c in result.mode.tolist()]
    tb._audit.extend(
        zip(
            result.loop_ids, [wall] * len(slots), result.t.tolist(), result.seq.tolist(),
            mode_names, ["agent"] * len(slots), old[:, 0].tolist(), old[:, 1].tolist(),
            new[:, 0].tolist(), new[:, 1].tolist(), details, strict=True,
        )
    )  # fmt: skip
    return result


def _guard_detail(kp: float, ki: float) -> str:
    return f"limited by the safety guard (proposed kp={kp:.6g}, ki={ki:.6g})"
