"""The stable agent API, the MDP and the training loop."""

import csv
import math

import numpy as np
import pytest
import torch

from plant_sim import PIBatch, run_closed_loop, target_filter
from plant_sim.foptd import FOPTDBatch
from plant_sim.tunings import oracle
from service.agent import (
    DEFAULT_WEIGHTS,
    GAIN_FLOOR,
    forget,
    load_agent,
    save_actor,
    untrained_agent,
)
from service.learn.env import EnvConfig, TuningEnv
from service.learn.oracle import ORACLE_RATIOS, oracle_gains, oracle_table
from service.learn.ppo import gae, ppo_policy_loss
from service.learn.train import Trainer
from service.learn.train_config import TrainConfig
from service.units import AGENT_KI0, AGENT_KP0, DEFAULT_FORGETTING


def _obs(n, rng):
    return np.column_stack(
        [rng.uniform(0.05, 2, n), rng.uniform(0.05, 5, n), rng.normal(0, 1, n), rng.normal(0, 3, n)]
    )


def test_act_shapes_types_and_batching():
    agent = untrained_agent(0)
    rng = np.random.default_rng(0)
    obs = _obs(5, rng)
    state = agent.initial_state(5)
    assert state.shape == (5, 2, 100) and not state.any()
    delta, new_state = agent.act(obs, state)
    assert delta.shape == (5, 2) and isinstance(delta, np.ndarray)
    assert new_state.shape == state.shape and np.abs(new_state).sum() > 0
    # one batched call equals five single-loop calls
    for i in range(5):
        d_i, s_i = agent.act(obs[i : i + 1], state[i : i + 1])
        np.testing.assert_allclose(d_i[0], delta[i], rtol=1e-5, atol=1e-7)
        np.testing.assert_allclose(s_i[0], new_state[i], rtol=1e-5, atol=1e-6)
    # torch in, torch out
    d_t, s_t = agent.act(torch.as_tensor(obs), torch.as_tensor(state))
    assert isinstance(d_t, torch.Tensor) and isinstance(s_t, torch.Tensor)
    np.testing.assert_allclose(d_t.numpy(), delta, rtol=1e-5, atol=1e-7)


def test_forgetting_scales_the_previous_hidden_state():
    agent = untrained_agent(1)
    obs = _obs(3, np.random.default_rng(1))
    _, state = agent.act(obs, agent.initial_state(3))
    d1, _ = agent.act(obs, state, forgetting=1.0)
    d99, s99 = agent.act(obs, state, forgetting=DEFAULT_FORGETTING)
    assert not np.allclose(d1, d99)
    # per-loop forgetting: equal to the scalar where the values agree
    d_mix, s_mix = agent.act(
        obs, state, forgetting=np.array([1.0, DEFAULT_FORGETTING, DEFAULT_FORGETTING])
    )
    np.testing.assert_allclose(d_mix[0], d1[0], rtol=1e-6)
    np.testing.assert_allclose(s_mix[1:], s99[1:], rtol=1e-6)
    # gamma = 0 is the same as a zero state
    d0, _ = agent.act(obs, state, forgetting=0.0)
    dz, _ = agent.act(obs, agent.initial_state(3))
    np.testing.assert_allclose(d0, dz, rtol=1e-6)


def test_forget_scales_each_loops_hidden_state_in_every_layer():
    h = torch.randn(2, 3, 5)
    assert forget(h, 1.0) is h
    torch.testing.assert_close(forget(h, 0.5), 0.5 * h)
    per_loop = forget(h, torch.tensor([1.0, 0.5, 0.0]))
    assert per_loop.shape == h.shape
    torch.testing.assert_close(per_loop[:, 0], h[:, 0])
    torch.testing.assert_close(per_loop[:, 1], 0.5 * h[:, 1])
    assert not per_loop[:, 2].any()


def test_act_rejects_bad_input():
    agent = untrained_agent(0)
    with pytest.raises(ValueError, match="shape"):
        agent.act(np.zeros((2, 3)), agent.initial_state(2))
    with pytest.raises(ValueError, match="state"):
        agent.act(np.ones((2, 4)), agent.initial_state(3))
    with pytest.raises(ValueError, match="finite"):
        agent.act(np.array([[1.0, 1.0, np.nan, 0.0]]), agent.initial_state(1))


def test_delta_keeps_gains_positive():
    agent = untrained_agent(0)
    with torch.no_grad():
        agent.actor.head[-1].bias.fill_(-50.0)  # an agent that wants to slash the gains
    obs = _obs(4, np.random.default_rng(2))
    delta, _ = agent.act(obs, agent.initial_state(4))
    new = obs[:, :2] + delta
    assert np.all(new > 0)
    np.testing.assert_allclose(new, obs[:, :2] * np.exp(-1.0), rtol=1e-5)


def test_save_and_load_roundtrip(tmp_path):
    agent = untrained_agent(3)
    path = tmp_path / "a.pt"
    save_actor(agent.actor, path, {"note": "x"})
    loaded = load_agent(path)
    obs = _obs(2, np.random.default_rng(3))
    np.testing.assert_array_equal(
        loaded.act(obs, loaded.initial_state(2))[0], agent.act(obs, agent.initial_state(2))[0]
    )
    assert loaded.meta == {"note": "x"}
    with pytest.raises(FileNotFoundError):
        load_agent(tmp_path / "missing.pt")


def test_shipped_weights_load():
    assert DEFAULT_WEIGHTS.exists(), "trained weights must ship with the package"
    agent = load_agent()
    assert agent.meta["epoch"] > 0
    assert DEFAULT_WEIGHTS.stat().st_size < 5e6


def test_env_matches_a_direct_closed_loop_simulation():
    K, tau, theta = np.array([0.5, 0.9]), np.array([0.4, 1.0]), np.array([0.1, 0.7])
    cfg = EnvConfig(init_noise=0.0)
    env = TuningEnv(cfg, np.random.default_rng(0))
    env.reset(K, tau, theta, horizon=8, sp0=1.0, kp0=0.8, ki0=0.6)
    mses = [env.step(np.zeros((2, 2)))[2] for _ in range(8)]  # 22 time units: 2 sp toggles
    plant = FOPTDBatch(K, tau, theta, dt=0.01)
    target = target_filter(tau, theta, dt=0.01)
    pi = PIBatch(0.8, 0.6, dt=0.01, n=2)
    sp = np.where((np.arange(2200) // 1100) % 2 == 0, 1.0, -1.0)
    trace = run_closed_loop(plant, pi, target, sp)
    direct = ((trace.y - trace.target) ** 2).reshape(2, 8, 275).mean(-1).T
    np.testing.assert_allclose(np.array(mses), direct, rtol=1e-9, atol=1e-12)
    assert env.int_e == pytest.approx(0.01 * trace.e.sum(1))


def test_env_cost_adds_the_l1_penalty_and_clips_gains():
    env = TuningEnv(EnvConfig(), np.random.default_rng(0))
    env.reset(np.array([0.5]), np.array([0.5]), np.array([0.1]), horizon=2)
    obs, cost, mse = env.step(np.array([[0.4, -10.0]]))
    assert obs[0, 0] == pytest.approx(AGENT_KP0 + 0.4) and obs[0, 1] == pytest.approx(GAIN_FLOOR)
    assert cost[0] == pytest.approx(mse[0] + 0.5 * 0.4 + 0.5 * (AGENT_KI0 - GAIN_FLOOR))


def test_oracle_table_matches_the_optimiser_and_scales_with_the_plant():
    table = oracle_table()
    assert table.shape == (ORACLE_RATIOS.size, 2)
    kp, ki, _ = oracle(0.5, 0.25, 0.125)  # theta/tau = 0.5, another K and tau
    np.testing.assert_allclose(
        oracle_gains(table, np.array([0.5]), np.array([0.25]), np.array([0.125]))[0],
        [kp, ki],
        rtol=0.02,
    )


def test_gae_is_the_discounted_sum_of_td_errors():
    T, gamma, lam = 4, 0.9, 0.8
    rewards, values = torch.randn(T, 3), torch.randn(T, 3)
    last = torch.randn(3)
    nxt = torch.cat([values[1:], last[None]])
    td = rewards + gamma * nxt - values
    want = torch.stack(
        [sum((gamma * lam) ** (k - t) * td[k] for k in range(t, T)) for t in range(T)]
    )
    torch.testing.assert_close(gae(rewards, values, last, gamma, lam), want)
    # lambda 1: advantage + value is the discounted return bootstrapped from ``last``
    ret = gae(rewards, values, last, gamma, 1.0)[0] + values[0]
    torch.testing.assert_close(ret, sum(gamma**k * rewards[k] for k in range(T)) + gamma**T * last)


def test_ppo_policy_loss_clips_the_ratio():
    adv = torch.tensor([1.0, -1.0])
    old = torch.zeros(2)
    # ratio e^0.5 on both: the positive advantage is clipped at 1.2, the negative is not
    loss = ppo_policy_loss(torch.full((2,), 0.5), old, adv, clip=0.2)
    assert loss.item() == pytest.approx(-(1.2 - math.exp(0.5)) / 2)


def _tiny(**kw):
    base = dict(
        bc_epochs=2, value_warmup=1, epochs=2, episodes=12, horizon=6, bc_horizon=6,
        bc_updates=2, bc_minibatch=5, pi_iters=3, v_iters=3, eval_every=2, eval_plants=4,
    )  # fmt: skip
    return TrainConfig(**(base | kw))


def test_smoke_training_runs_and_losses_are_finite(tmp_path):
    trainer = Trainer(_tiny(), tmp_path)
    assert trainer.run()
    rows = list(csv.DictReader((tmp_path / "metrics.csv").open()))
    assert [r["phase"] for r in rows] == ["bc", "bc", "value_warmup", "ppo", "ppo"]
    for r in rows:
        for key in ("mean_cost", "bc_loss", "v_loss", "pi_loss", "kl"):
            if r[key]:
                assert np.isfinite(float(r[key])), (key, r)
    assert (tmp_path / "best.pt").exists() and (tmp_path / "checkpoint.pt").exists()
    meta = load_agent(tmp_path / "best.pt").meta
    assert meta["train_config"]["episodes"] == 12


def test_resume_continues_exactly(tmp_path):
    straight = Trainer(_tiny(), tmp_path / "a")
    straight.run()
    interrupted = Trainer(_tiny(), tmp_path / "b")
    assert not interrupted.run(max_epochs=2)
    resumed = Trainer.resume(tmp_path / "b")
    assert resumed.cfg == _tiny() and resumed.epoch == 2
    assert resumed.run()
    for p, q in zip(straight.actor.parameters(), resumed.actor.parameters(), strict=True):
        torch.testing.assert_close(p, q, rtol=0, atol=0)
    rows = list(csv.DictReader((tmp_path / "b" / "metrics.csv").open()))
    assert [int(r["epoch"]) for r in rows] == [1, 2, 3, 4, 5]


def test_env_setpoint_jitter_draws_a_period_and_phase_per_episode():
    env = TuningEnv(EnvConfig(sp_jitter=0.3), np.random.default_rng(4))
    n = 50
    env.reset(np.full(n, 0.5), np.full(n, 0.5), np.full(n, 0.1), horizon=8, sp0=1.0)
    assert env.sp_every.min() >= 770 and env.sp_every.max() <= 1430
    assert len(set(env.sp_offset.tolist())) > 10
    for _ in range(8):
        env.step(np.zeros((n, 2)))
    k = np.arange(1, env.k)[:, None]
    flips = ((k + env.sp_offset) % env.sp_every == 0).sum(0)
    np.testing.assert_array_equal(env.sp, np.where(flips % 2 == 0, 1.0, -1.0))
