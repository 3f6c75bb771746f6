"""Issue 13's envelope-guard bar: a plant whose time constant ramps to 5x during tuning
gets paused before its step-test MSE exceeds 3x its best.

One hint-free loop, identified and tuned by the shipped agent, then its time constant
ramps from tau0 to 5 tau0. At every change of the gains in force or of the plant, the
step-test MSE of the gains in force is computed on the plant as it is then (the paper's
step test, in the agent units of the initial plant: K and tau0 appear as 0.5).

Measured (docs/identification.md): the loop is paused at tau = 4 tau0 (apparent tau 2.0
against the envelope's 1.5), but the MSE line of the bar is missed for a reason the guard
cannot see: the loop's best is the model's tuning on the unchanged plant (step-test MSE
2.1e-5), and the shipped agent's steps after it, before the ramp, take the MSE to 1,200x
that (within the model band of 1.5x, whose corners allow 0.02-0.04; 5,000x without the
band). That line is reported as missed (the numbers are printed by the fixture), not
asserted here."""

from __future__ import annotations

import numpy as np
import pytest

from plant_sim.foptd import FOPTDBatch
from plant_sim.loop import step_test_mse
from plant_sim.pi import PIBatch
from service.agent import DEFAULT_WEIGHTS, load_agent
from service.engine import LoopConfig, TuningEngine
from service.engine.box import ENVELOPE_MARGIN, TRAINING_BOX
from tests.test_identify import gains

pytestmark = [
    pytest.mark.timeout(300),
    pytest.mark.skipif(not DEFAULT_WEIGHTS.exists(), reason="no trained agent"),
]

K, TAU, THETA, H = 2.0, 40.0, 10.0, 4.0
NOISE, SIZE = 0.5, 20.0
SETTLE_MOVES, RAMP_MOVES, EVERY = 14, 16, 6.0
"""Moves before the ramp (identification and tuning), moves over the ramp (tau0 -> 5
tau0 in steps at each move), a move every EVERY time constants of the plant as it is."""


def agent_mse(kp: float, ki: float, tau: float) -> float:
    """The step-test MSE of engineering gains on the plant with time constant ``tau``, in
    the agent units of the initial plant."""
    kp_a, ki_a = kp * K / 0.5, ki * K / 0.5 * TAU / 0.5
    return float(step_test_mse(0.5, 0.5 * tau / TAU, 0.5 * THETA / TAU, kp_a, ki_a)[0])


@pytest.fixture(scope="module")
def ramp() -> dict:
    engine = TuningEngine(load_agent())
    kp, ki = gains()
    engine.register(LoopConfig(id="L", kp=kp, ki=ki, sample_period_s=H), wall=0.0)
    plant = FOPTDBatch(K, TAU / H, THETA / H, dt=1.0, noise_std=NOISE, seed=0)
    plant.reset(50.0)
    pi = PIBatch(kp, ki * H, dt=1.0)
    pi.initialise(50.0 / K)
    rng = np.random.default_rng(1)
    tb = engine.table
    s = tb.slot("L")
    sp, tau, j, moves, next_move = 50.0, TAU, 0, 0, int(EVERY * TAU / H)
    best, key, mse = np.inf, None, np.inf
    out = {"paused_at": None, "before_ramp": 0.0, "on_ramp": 0.0, "best": np.inf}
    while moves < SETTLE_MOVES + RAMP_MOVES:
        if j == next_move:
            moves += 1
            sp = 50.0 + SIZE * (1 if moves % 2 else -1) * rng.uniform(0.5, 1.0)
            next_move = j + int(EVERY * tau / H)
        if moves > SETTLE_MOVES:
            tau = min(5.0 * TAU, TAU * (1.0 + 4.0 * (moves - SETTLE_MOVES) / RAMP_MOVES))
            plant.set_params(tau=tau / H)
        y = float(plant.measure()[0])
        sample = {"loop_id": "L", "t": j * H, "sp": sp, "pv": y, "kp": float(pi.kp[0]),
                  "ki": float(pi.ki[0] / H)}  # fmt: skip
        for up in engine.ingest([sample], wall=float(j)):
            pi.set_gains(up.kp, up.ki * H)
        if tb.n_identified[s] and out["paused_at"] is None:
            if (now := (float(pi.kp[0]), float(pi.ki[0] / H), tau)) != key:
                mse, key = agent_mse(*now), now
                best = min(best, mse)
                phase = "on_ramp" if moves > SETTLE_MOVES else "before_ramp"
                out[phase] = max(out[phase], mse / best)
            if tb.out_env[s]:
                out["paused_at"] = tau / TAU
                out["ratio_at_pause"] = mse / best
        plant.step(pi.step(sp - y))
        j += 1
    out["view"] = engine.view("L", wall=float(j))
    out["best"] = best
    print({k: v for k, v in out.items() if k != "view"})
    return out


def test_a_plant_slowing_down_5x_is_paused_soon_after_it_leaves_the_envelope(ramp):
    view = ramp["view"]
    assert view.counters.identified >= 1 and view.counters.steps > 10
    assert view.counters.envelope_pauses >= 1 and view.identification.out_of_envelope
    # out of the envelope from tau = 3 tau0 (apparent 1.5); caught within a quarter more
    edge = 2 * TRAINING_BOX["tau"][1] * ENVELOPE_MARGIN
    assert ramp["paused_at"] is not None and edge < ramp["paused_at"] <= edge + 1.0
