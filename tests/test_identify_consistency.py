"""The consistency test between events (service/engine/identify.py): an event that has
just begun, its response barely shown, is not the event the earlier events' model must
predict (it tests next to nothing); the event before it is, until the new one has run
the model's theta + tau."""

from __future__ import annotations

import numpy as np
import pytest

from plant_sim.foptd import FOPTDBatch
from plant_sim.pi import PIBatch
from service.engine.identify import assess, reconstruct_op
from tests.test_identify import TAU, THETA, K, gains

H = 2.0


def segment(seed: int, tau_after: float, tail: int):
    """Three setpoint moves 200 samples apart, the plant's tau changed to ``tau_after`` at
    the second (the events disagree), and ``tail`` samples of the third move."""
    kp, ki = gains()
    plant = FOPTDBatch(K, TAU / H, THETA / H, dt=1.0, noise_std=0.5, seed=seed,
                       max_theta=THETA / H)  # fmt: skip
    plant.reset(50.0)
    pi = PIBatch(kp, ki * H, dt=1.0)
    pi.initialise(50.0 / K)
    starts = [1, 201, 401]
    n = starts[-1] + tail
    sp = np.full(n, 50.0)
    for a, size in zip(starts, (20.0, -20.0, 20.0), strict=True):
        sp[a:] += size
    pv = np.empty(n)
    for k in range(n):
        if k == starts[1]:
            plant.set_params(tau=tau_after / H)
        pv[k] = plant.measure()[0]
        plant.step(pi.step(sp[k] - pv[k]))
    t = np.arange(n) * H
    return t, sp, pv, reconstruct_op(t, sp - pv, np.full(n, kp), np.full(n, ki)), starts


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_just_excited_event_does_not_let_disagreeing_events_pass(seed):
    t, sp, pv, op, starts = segment(seed, 1.4 * TAU, tail=16)  # 32 s into the third move
    result = assess(t, sp, pv, op, starts)
    assert [ev.excited for ev in result.events] == [True, True, True]
    m = result.model
    assert not m.confident and "events disagree" in result.why, result.why
    assert t[-1] - t[starts[-1]] < m.theta + m.tau  # the third has not shown its response
