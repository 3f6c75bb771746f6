"""FastPolicy (the daemon's inference path) equals ``Agent.act``."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from service.agent import untrained_agent
from service.inference import FastPolicy


def _inputs(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    obs = np.column_stack(
        [
            np.exp(rng.normal(0.0, 2.0, (n, 2))),  # gains, some below the floor
            rng.normal(0.0, 3.0, n),  # errors, some beyond the clamp
            rng.normal(0.0, 5.0, n),  # integrals of both signs
        ]
    )
    state = rng.normal(0.0, 0.5, (n, 2, 100)).astype(np.float32)
    return obs, state, rng.uniform(0.5, 1.0, n)


@pytest.mark.parametrize(("n", "block"), [(1, 512), (7, 4), (1000, 256), (1500, 512)])
def test_fast_policy_equals_agent_act(n, block):
    agent = untrained_agent(3)
    obs, state, gamma = _inputs(n)
    ref_delta, ref_state = agent.act(obs, state, gamma)
    fast = FastPolicy(agent, block=block)
    delta, new_state = fast.act(obs, state, gamma)
    np.testing.assert_allclose(delta, ref_delta, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(new_state, ref_state, rtol=1e-5, atol=1e-5)
    assert delta.dtype == np.float64 and new_state.dtype == np.float32
    # the in-place form updates the caller's state
    inplace = state.copy()
    fast.step_inplace(obs, inplace, gamma)
    np.testing.assert_array_equal(inplace, new_state)


def test_fast_policy_scalar_forgetting_and_a_trained_like_actor():
    agent = untrained_agent(5)
    for p in agent.actor.head[-1].parameters():  # a head with real output, not ~1e-3
        p.data.normal_(0.0, 0.5)
    obs, state, _ = _inputs(300, seed=1)
    ref = agent.act(obs, state, 0.97)
    got = FastPolicy(agent).act(obs, state, 0.97)
    for a, b in zip(got, ref, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-5)


def test_fast_policy_rejects_bad_input():
    fast = FastPolicy(untrained_agent(0))
    obs, state, gamma = _inputs(3)
    with pytest.raises(ValueError, match="finite"):
        fast.step_inplace(np.where(obs == obs[0, 0], np.nan, obs), state.copy(), gamma)
    with pytest.raises(ValueError, match="state"):
        fast.step_inplace(obs, state.astype(np.float64), gamma)
    with pytest.raises(ValueError, match="obs"):
        fast.step_inplace(obs[:, :3], state.copy(), gamma)


def test_two_workers_split_large_batches_with_identical_results():
    agent = untrained_agent(4)
    obs, state, gamma = _inputs(1500, seed=2)
    ref_delta, ref_state = agent.act(obs, state, gamma)
    one = FastPolicy(agent, block=256)
    two = FastPolicy(agent, block=256, workers=2, parallel_min=1000)
    try:
        assert two._pool.submit(torch.get_num_threads).result() == 1  # helper: 1 intra-op
        delta, new_state = two.act(obs, state, gamma)
        np.testing.assert_allclose(delta, ref_delta, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(new_state, ref_state, rtol=1e-5, atol=1e-5)
        # the same blocks, whichever thread steps them: the single-thread result (up to the
        # last bits: MKL's kernels may round differently on differently aligned buffers)
        for got, want in zip(two.act(obs, state, gamma), one.act(obs, state, gamma), strict=True):
            np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-7)
        # below parallel_min the caller steps the batch alone
        two._pool.submit = None
        small = two.act(obs[:999], state[:999], gamma[:999])
        np.testing.assert_allclose(
            small[0], one.act(obs[:999], state[:999], gamma[:999])[0], 1e-6, 1e-7
        )
    finally:
        two.close()
