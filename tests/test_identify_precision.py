"""Tau's precision rule (service/engine/identify.py, ``tau_limit``): from fewer than
``FULL_EVENTS`` setpoint moves tau must be pinned down as tightly as K; from the
``FULL_EVENTS`` th move's response on, its looser limit applies."""

from __future__ import annotations

import numpy as np
import pytest

from plant_sim.foptd import FOPTDBatch
from plant_sim.pi import PIBatch
from service.engine.identify import (
    FULL_EVENTS,
    IMPRECISE,
    MAX_PREDICTION,
    MAX_REL_SE,
    MAX_TAU_SE,
    assess,
    reconstruct_op,
)
from tests.test_identify import TAU, THETA, H, K, gains

EVERY = 100
"""Samples between setpoint moves: 10 time constants."""


def segment(seed: int, moves: int, tail: int):
    """``moves`` setpoint moves of +-10 under noise 1 (tau's standard error 0.14-0.17
    from three: between K's limit and tau's), the last followed by ``tail`` samples."""
    kp, ki = gains()
    plant = FOPTDBatch(K, TAU / H, THETA / H, dt=1.0, noise_std=1.0, seed=seed,
                       max_theta=THETA / H)  # fmt: skip
    plant.reset(50.0)
    pi = PIBatch(kp, ki * H, dt=1.0)
    pi.initialise(50.0 / K)
    starts = [1 + EVERY * i for i in range(moves)]
    n = starts[-1] + tail
    sp = np.full(n, 50.0)
    for i, a in enumerate(starts):
        sp[a:] += 10.0 if i % 2 == 0 else -10.0
    pv = np.empty(n)
    for k in range(n):
        pv[k] = plant.measure()[0]
        plant.step(pi.step(sp[k] - pv[k]))
    t = np.arange(n) * H
    return t, sp, pv, reconstruct_op(t, sp - pv, np.full(n, kp), np.full(n, ki)), starts


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_tau_needs_k_s_precision_until_the_data_hold_the_fourth_move(seed):
    assert FULL_EVENTS == 4
    result = assess(*segment(seed, FULL_EVENTS - 1, EVERY))  # three whole responses
    m = result.model
    assert not m.confident and result.why.startswith(IMPRECISE), result.why
    # every other check passes: only tau's tighter limit from three moves holds it back
    assert m.k_rse <= MAX_REL_SE < m.tau_rse <= MAX_TAU_SE
    assert m.prediction <= MAX_PREDICTION and m.events == FULL_EVENTS - 1
    result = assess(*segment(seed, FULL_EVENTS, 30))  # 3 tau into the fourth move
    m = result.model
    assert m.confident, result.why
    assert m.tau_rse <= MAX_TAU_SE and abs(m.tau / TAU - 1) <= 0.3
