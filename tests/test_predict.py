"""The shadow prediction (service.engine.predict): each loop's predicted IAE is its own,
whatever other loops step in the same pass."""

from __future__ import annotations

import math
import re

import numpy as np

from plant_sim.loop import step_test
from service.agent import untrained_agent
from service.engine import LoopConfig, TuningEngine, monitor, predict
from service.engine.identify import Model

FAST = (1.0, 5.0, 1.0, (0.8, 0.16), (1.2, 0.24))
"""(K, tau s, theta s, gains in force, proposal): a flow-like loop."""
SLOW = (1.0, 1000.0, 200.0, (1.0, 0.001), (1.5, 0.0015))
"""A temperature-like loop, 200x slower."""


def _engine():
    engine = TuningEngine(untrained_agent(0))
    slots = []
    for name, (k, tau, theta, old, _) in {"F": FAST, "S": SLOW}.items():
        scaling = {"k_hat": k, "tau_hat": tau, "pv_scale": 1.0}
        engine.register(LoopConfig(id=name, kp=old[0], ki=old[1], sample_period_s=tau / 50,
                                   scaling=scaling), wall=0.0)  # fmt: skip
        s = engine.table.slot(name)
        model = Model(k=k, tau=tau, theta=theta, noise=0.01, move=1.0, r2=0.99,
                      k_rse=0.01, tau_rse=0.01)  # fmt: skip
        engine.table.ident[s].in_force = model
        slots.append(s)
    return engine.table, slots


def _iae(text: str) -> tuple[float, float]:
    before, after = re.match(r"pred_iae=(\S+)->(\S+) ", text).groups()
    return float(before), float(after)


def test_a_loops_prediction_does_not_depend_on_the_loops_stepped_with_it():
    """A tau 5 s loop (RL period 10 s) stepped in one pass with a tau 1000 s loop (RL
    period 2000 s): its IAE per unit move is the one it has alone, 6.12 -> 4.16 s, as a
    fine simulation gives (the batch was simulated at the slow loop's step, 10 s:
    5.1e53 -> 9.5e149). The slow loop's is unchanged, 993.7 -> 666.4 s."""
    tb, slots = _engine()
    assert tb.period[slots[1]] / tb.period[slots[0]] == 200.0
    old = np.array([FAST[3], SLOW[3]])
    new = np.array([FAST[4], SLOW[4]])
    both = predict.predictions(tb, slots, old, new)
    for j, (k, tau, theta, before, after) in enumerate((FAST, SLOW)):
        alone = predict.predictions(tb, [slots[j]], old[j : j + 1], new[j : j + 1])[0]
        assert both[j] == alone
        horizon = monitor.RESPONSE_PERIODS * tb.period[slots[j]]
        dt = horizon / 4000
        for gains, got in zip((before, after), _iae(both[j]), strict=True):
            fine = step_test(k, tau, theta, *gains, dt=dt, horizon=horizon)
            assert math.isclose(got, float(np.abs(fine.e).sum()) * dt / 2.0, rel_tol=0.01)
