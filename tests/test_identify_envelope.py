"""Issue 13's envelope-guard bar: a plant whose time constant ramps to 5x during tuning
gets paused before its step-test MSE exceeds 3x its best.

One hint-free loop, identified and tuned by the shipped agent, then its time constant
ramps from tau0 to 5 tau0 (in steps of tau0 / 4 at each setpoint move). At every change
of the gains in force or of the plant, the step-test MSE of the gains in force is
computed on the plant as it is then (the paper's step test, in the agent units of the
initial plant: K and tau0 appear as 0.5); "its best" is the lowest so far.

Measured (docs/identification.md, Model check): the loop's best is the identified
model's tuning on the unchanged plant (1.9e-4). Before the ramp the MSE stays within 1.0x
of it: the model check (``guard.model_check``) holds the shipped agent's steps that the
model predicts worse (27 of 29; without the check they took the MSE to 134-1,200x, inside
the model band). The loop is paused at tau = 3.75 tau0 (apparent tau 1.9 against the
envelope's 1.5). The MSE line is met on the unchanged plant and **missed on the ramp**,
for a reason no pause can fix: the step-test MSE is so sharp around its optimum that the
ramp's first step (tau 1.25 tau0, before any sample of the new plant exists) takes the
gains in force to 17x their best; at the pause it is about 1,600x. Asserted: the pause,
the MSE before the ramp, and that first step; the ratios are printed."""

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
                if phase == "on_ramp" and "first_ramp_step" not in out:
                    out["first_ramp_step"] = mse / best
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


def test_the_model_check_keeps_the_unchanged_plant_within_3x_of_its_best(ramp):
    """The bar's MSE line before the ramp: the agent's steps the identified model predicts
    worse are held (without the check: 134-1,200x)."""
    assert ramp["view"].counters.model_holds > 0
    assert ramp["before_ramp"] <= 3.0


def test_the_ramps_first_step_alone_takes_the_best_gains_beyond_3x(ramp):
    """Why the line is missed on the ramp: the plant's first step (tau0 -> 1.25 tau0) puts
    the gains in force above 3x their best at once, before the tuner has one sample of the
    new plant; no guard can pause before that."""
    assert ramp["first_ramp_step"] > 3.0
