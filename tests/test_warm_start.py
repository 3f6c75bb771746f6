"""The agent's warm start on an identified model (service/engine/warm.py, first_tuning.py):
the warm run is training's protocol as the engine observes it, and after a model tuning
the shipped agent continues from where it ends instead of from a zero state."""

from __future__ import annotations

import numpy as np
import pytest

from plant_sim.loop import step_test_mse
from service.agent import DEFAULT_WEIGHTS, load_agent, untrained_agent
from service.engine import LoopConfig, TuningEngine, first_tuning, warm
from service.engine.first_tuning import WARM_PER_PASS, model_gains
from service.engine.identify import Model
from service.learn.env import EnvConfig, TuningEnv
from tests.test_identify import TAU, THETA, H, K, drive, gains

pytestmark = pytest.mark.timeout(300)
trained = pytest.mark.skipif(not DEFAULT_WEIGHTS.exists(), reason="no trained agent")


def test_the_warm_run_is_trainings_protocol_observed_as_the_engine_observes():
    """Same agent, same plants, same start: training's environment (the paper's toggle,
    the error window, the integral) and the warm run give the same observations, hence
    the same hidden states (the gains are in the observation) and integral."""
    agent = untrained_agent(3)
    engine = TuningEngine(agent, inference_precision="reference")
    n, steps = 4, 12
    K_, tau = np.full(n, 0.5), np.array([0.3, 0.5, 0.5, 0.9])
    theta = tau * np.array([0.05, 0.2, 0.6, 1.0])
    kp, ki = np.array([1.0, 2.0, 0.5, 1.2]), np.array([2.0, 3.0, 1.0, 1.5])
    run = warm.WarmRun(engine.table, K_, tau, theta, kp, ki, 0.99, steps=steps)
    run.advance(steps)
    state, int_e = run.result()
    env = TuningEnv(EnvConfig(dt=warm.DT, init_noise=0.0), np.random.default_rng(0))
    obs = env.reset(K_, tau, theta, horizon=steps, sp0=1.0, kp0=kp, ki0=ki)
    ref = agent.initial_state(n)
    for _ in range(steps):
        delta, ref = agent.act(obs, ref, forgetting=0.99)
        obs, _, _ = env.step(delta)
    np.testing.assert_allclose(state, ref, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(int_e, obs[:, 3], rtol=1e-9)
    assert np.abs(int_e).max() > 0.1  # the integral is carried, not zero


@trained
def test_after_a_model_tuning_a_noisy_loop_keeps_the_gains_near_the_models_tuning():
    """A hint-free loop with setpoint moves every 6 tau and noise: the agent, warmed or
    not and hinted or not, walks the gains far below the model's tuning here (ki to 0.27x
    of it, step-test MSE 0.3 against 8e-5); the model band keeps each agent step within
    1.5x either way of the model's tuning, and the warm start gave it a hidden state (the
    model check, which holds most of these steps, off: tests/test_model_check.py)."""
    engine = TuningEngine(load_agent())
    kp, ki = gains(share=0.25)
    guard = {"model_check": None}
    engine.register(LoopConfig(id="L", kp=kp, ki=ki, sample_period_s=H, guard=guard), wall=0.0)
    updates = drive(engine, moves=16, every=6.0, noise=0.5, size=20.0)
    first = next(i for i, u in enumerate(updates) if u.reason == "model")
    model, agent = updates[first], [u for u in updates[first + 1 :] if u.reason == "agent"]
    assert "rule=simc" in model.why and len(agent) >= 5
    view = engine.view("L", wall=1e9)
    m = view.identification.in_force
    assert abs(m.k / K - 1) < 0.3 and abs(m.tau / TAU - 1) < 0.3
    kp_m, ki_m = model_gains(m.k, m.tau, m.theta)
    for u in [model, *agent]:
        assert 1 / 1.5 - 1e-9 <= u.kp / kp_m <= 1.5 + 1e-9
        assert 1 / 1.5 - 1e-9 <= u.ki / ki_m <= 1.5 + 1e-9
    assert view.hidden_norm > 0
    # the step-test MSE of the end gains, in the true plant's agent units (K, tau as 0.5)
    end = agent[-1]
    kp_a, ki_a = end.kp * K / 0.5, end.ki * K / 0.5 * TAU / 0.5
    assert step_test_mse(0.5, 0.5, 0.5 * THETA / TAU, kp_a, ki_a)[0] < 0.04


def test_a_pass_warms_at_most_warm_per_pass_loops_and_the_next_pass_the_rest():
    """Thousands of models put in force in one pass must not stall the worker for
    seconds: one flush warms :data:`WARM_PER_PASS` loops, in queue order, the next the
    rest."""
    engine = TuningEngine(untrained_agent(3), inference_precision="reference")
    tb, n = engine.table, WARM_PER_PASS + 6
    scaling = {"k_hat": K, "tau_hat": TAU, "pv_scale": 20.0}
    for i in range(n):
        engine.register(
            LoopConfig(id=f"L{i}", kp=0.1, ki=0.01, sample_period_s=H, scaling=scaling),
            wall=0.0,
        )
    m = Model(k=K, tau=TAU, theta=THETA, noise=0.1, move=5.0, r2=0.99, k_rse=0.01, tau_rse=0.01)
    slots = [tb.slot(f"L{i}") for i in range(n)]
    for s in slots:  # as identification puts a model in force (model_use._put_in_force)
        tb.ident[s].in_force = m
    tb.warming.extend((s, tb.ids[s], m) for s in slots)
    warmed = lambda: np.abs(tb.hidden[slots]).sum(axis=(1, 2)) > 0  # noqa: E731
    first_tuning.flush(tb)
    assert warmed().tolist() == [True] * WARM_PER_PASS + [False] * 6
    assert len(tb.warming) == 6
    first_tuning.flush(tb)
    assert warmed().all() and not tb.warming


def test_a_budgeted_engine_warms_a_slice_a_pass_to_the_same_state():
    """With an identification budget (the tuner) a warm run takes WARM_SLICE RL steps a
    pass, the loops joining meanwhile wait for the next batch, and the state it leaves
    is the whole run's to the bit; a loop removed meanwhile gets nothing."""
    from service.engine import SiteDefaults
    from service.engine.first_tuning import WARM_SLICE

    def engine_with(n, site=None):
        engine = TuningEngine(untrained_agent(3), inference_precision="reference", site=site)
        scaling = {"k_hat": K, "tau_hat": TAU, "pv_scale": 20.0}
        for i in range(n):
            engine.register(
                LoopConfig(id=f"L{i}", kp=0.1 * (i + 1), ki=0.01, sample_period_s=H,
                           scaling=scaling),
                wall=0.0,
            )  # fmt: skip
        slots = [engine.table.slot(f"L{i}") for i in range(n)]
        for s in slots:  # as identification puts a model in force (model_use._put_in_force)
            engine.table.ident[s].in_force = m
        return engine, engine.table, slots

    m = Model(k=K, tau=TAU, theta=THETA, noise=0.1, move=5.0, r2=0.99, k_rse=0.01, tau_rse=0.01)
    whole, tw, sw = engine_with(3)
    tw.warming.extend((s, tw.ids[s], m) for s in sw[:2])  # the same batch, whole
    first_tuning.flush(tw)
    assert tw.warm_run is None and np.abs(tw.hidden[sw]).sum() > 0

    sliced, tb, slots = engine_with(3, SiteDefaults(fit_share=0.25))
    tb.warming.extend((s, tb.ids[s], m) for s in slots[:2])
    passes = -(-warm.STEPS // WARM_SLICE)
    first_tuning.flush(tb)
    tb.warming.append((slots[2], tb.ids[slots[2]], m))  # joins while the batch runs
    sliced.remove("L1")
    for _ in range(passes - 1):
        assert tb.warm_run is not None and not np.abs(tb.hidden[slots]).any()
        first_tuning.flush(tb)
    assert tb.warm_run is None and tb.fits.spent_s > 0.0
    np.testing.assert_array_equal(tb.hidden[slots[0]], tw.hidden[sw[0]])
    assert tb.int_e[slots[0]] == tw.int_e[sw[0]]
    assert not np.abs(tb.hidden[slots[1:]]).any()  # removed; the third not yet warmed
    assert [s for s, _, _ in tb.warming] == [slots[2]]


def test_a_warm_result_does_not_land_on_a_loop_reset_meanwhile():
    """A sliced warm run spans passes: a loop reset (or stepped, rescaled, identified
    anew) meanwhile keeps its own state; the others get theirs."""
    from service.engine import SiteDefaults

    engine = TuningEngine(untrained_agent(3), inference_precision="reference",
                          site=SiteDefaults(fit_share=0.25))  # fmt: skip
    tb = engine.table
    scaling = {"k_hat": K, "tau_hat": TAU, "pv_scale": 20.0}
    m = Model(k=K, tau=TAU, theta=THETA, noise=0.1, move=5.0, r2=0.99, k_rse=0.01, tau_rse=0.01)
    for i in range(2):
        engine.register(LoopConfig(id=f"L{i}", kp=0.1, ki=0.01, sample_period_s=H,
                                   scaling=scaling), wall=0.0)  # fmt: skip
    slots = [tb.slot("L0"), tb.slot("L1")]
    for s in slots:
        tb.ident[s].in_force = m
    tb.warming.extend((s, tb.ids[s], m) for s in slots)
    first_tuning.flush(tb)
    engine.reset("L0", wall=1.0)
    while tb.warm_run is not None:
        first_tuning.flush(tb)
    assert not np.abs(tb.hidden[slots[0]]).any() and np.abs(tb.hidden[slots[1]]).any()


def test_a_followed_hinted_loop_is_warmed_on_its_model_and_loses_the_old_plants_state():
    """A hinted loop's followed model is its ``hint_model`` (it has none in force): the
    warm result lands while that is still the model the loop is checked on, and not
    once a newer model replaced it or one came in force; either way the state of the
    plant of before is gone from the decision on."""
    from service.engine import SiteDefaults

    engine = TuningEngine(untrained_agent(3), inference_precision="reference",
                          site=SiteDefaults(fit_share=0.25))  # fmt: skip
    tb = engine.table
    scaling = {"k_hat": K, "tau_hat": TAU, "pv_scale": 20.0}
    m = Model(k=K, tau=TAU, theta=THETA, noise=0.1, move=5.0, r2=0.99, k_rse=0.01, tau_rse=0.01)
    later = Model(k=K, tau=TAU, theta=THETA, noise=0.1, move=5.0, r2=0.99, k_rse=0.01,
                  tau_rse=0.01)  # fmt: skip
    for i in range(3):
        engine.register(LoopConfig(id=f"L{i}", kp=0.1, ki=0.01, sample_period_s=H,
                                   scaling=scaling), wall=0.0)  # fmt: skip
    slots = [tb.slot(f"L{i}") for i in range(3)]
    for s in slots:
        tb.ident[s].hint_model = m
        tb.hidden[s], tb.int_e[s] = 1.0, 1.0  # the plant of before's
        first_tuning.apply(tb, s, m, 1.0, "followed")
    assert not np.abs(tb.hidden[slots]).any() and not tb.int_e[slots].any()
    assert [s for s, _, _ in tb.warming] == slots
    first_tuning.flush(tb)
    tb.ident[slots[1]].hint_model = later
    tb.ident[slots[2]].in_force = later
    while tb.warm_run is not None:
        first_tuning.flush(tb)
    landed = np.abs(tb.hidden[slots]).sum(axis=(1, 2)) > 0
    assert landed.tolist() == [True, False, False]
