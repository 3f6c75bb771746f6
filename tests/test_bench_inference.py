"""FastPolicy (the daemon's inference path) equals ``Agent.act``; bfloat16 tunes alike."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from service.agent import Actor, Agent, AgentConfig, forget, load_agent, untrained_agent
from service.agent import fast as inference
from service.agent.fast import FastPolicy, cpu_has_native_bf16, resolve_precision
from service.learn.closed_loop import tune


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


def test_fast_policy_kernel_forgets_as_forget_does():
    """The C kernel's forgetting (gamma h inside the GRU step) is :func:`forget`'s."""
    agent = untrained_agent(6)
    obs, state, gamma = _inputs(50, seed=3)
    h = torch.from_numpy(state).transpose(0, 1).contiguous()  # (layers, B, hidden)
    with torch.no_grad():
        mean, _, h_ref = agent.actor(
            torch.from_numpy(obs).float().unsqueeze(0),
            forget(h, torch.from_numpy(gamma).float()),
        )
    inplace = state.copy()
    FastPolicy(agent, precision="float32").step_inplace(obs, inplace, gamma)
    np.testing.assert_allclose(inplace, h_ref.transpose(0, 1).numpy(), rtol=1e-5, atol=1e-5)
    assert not np.allclose(inplace, agent.act(obs, state, 1.0)[1], atol=1e-3)  # gamma mattered


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


needs_bf16 = pytest.mark.skipif(
    not cpu_has_native_bf16(), reason="no native bfloat16 on this CPU (emulated: slow)"
)


@needs_bf16
def test_bfloat16_gemms_stay_close_to_agent_act():
    agent = load_agent()  # the shipped weights: the real action and state scales
    obs, state, gamma = _inputs(2000, seed=5)
    ref_delta, ref_state = agent.act(obs, state, gamma)
    fast = FastPolicy(agent, block=300, precision="bfloat16")
    assert fast.precision == "bfloat16"
    delta, new_state = fast.act(obs, state, gamma)
    scale = np.abs(ref_delta).max()
    err = np.abs(delta - ref_delta).max()
    # measured: 0.8 % of the largest action, 0.011 in the state (float32: 1e-6)
    assert 1e-4 * scale < err < 0.03 * scale, "bfloat16 in use, and close"
    assert np.abs(new_state - ref_state).max() < 0.05
    two = FastPolicy(agent, block=300, workers=2, parallel_min=1000, precision="bfloat16")
    try:  # the same blocks in two threads: the same numbers
        np.testing.assert_allclose(two.act(obs, state, gamma)[0], delta, rtol=1e-6, atol=1e-7)
    finally:
        two.close()


@needs_bf16
def test_bfloat16_inference_tunes_like_the_reference():
    """Closed loop: 60 RL steps on 160 FOPTD plants, the errors do not accumulate."""
    agent = load_agent()
    rng = np.random.default_rng(7)
    plants = {
        "K": rng.uniform(0.25, 1.0, 160),
        "tau": rng.uniform(0.25, 1.0, 160),
        "theta": rng.uniform(0.0, 0.3, 160),
    }
    ref = tune(agent, **plants, steps=60)
    got = tune(FastPolicy(agent, precision="bfloat16"), **plants, steps=60)
    assert not np.allclose(got["gains"][-1], ref["gains"][-1], rtol=1e-6, atol=0)  # bf16
    np.testing.assert_allclose(got["gains"][-1], ref["gains"][-1], rtol=0.05)
    mse_ref, mse_got = ref["mse"][-8:].mean(0), got["mse"][-8:].mean(0)
    assert abs(np.median(mse_got) / np.median(mse_ref) - 1) < 0.1
    assert mse_got.max() < 1.2 * mse_ref.max()


@needs_bf16
def test_bfloat16_policy_keeps_small_blocks_in_float32_and_pads_gemm_rows():
    agent = load_agent()
    fast = FastPolicy(agent, block=1024, precision="bfloat16")
    obs, state, gamma = _inputs(1030, seed=8)
    ref_delta, ref_state = agent.act(obs, state, gamma)
    # 1,030 loops: one bfloat16 block of 1,024, then 6 loops in float32 (= agent.act)
    delta, new_state = fast.act(obs, state, gamma)
    np.testing.assert_allclose(delta[1024:], ref_delta[1024:], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(new_state[1024:], ref_state[1024:], rtol=1e-5, atol=1e-5)
    assert np.abs(delta[:1024] - ref_delta[:1024]).max() > 1e-4
    # 200 loops: a GEMM over 256 rows, 56 of them stale from the call above; the result
    # is that of a fresh policy
    small = fast.act(obs[:200], state[:200], gamma[:200])
    fresh = FastPolicy(agent, block=1024, precision="bfloat16").act(
        obs[:200], state[:200], gamma[:200]
    )
    for got, want in zip(small, fresh, strict=True):
        np.testing.assert_array_equal(got, want)


def test_auto_precision_follows_the_cpu_flags(tmp_path, monkeypatch):
    amx, avx2 = tmp_path / "amx", tmp_path / "avx2"
    amx.write_text("processor\t: 0\nflags\t\t: fpu avx512f amx_bf16 amx_tile\n")
    avx2.write_text("processor\t: 0\nflags\t\t: fpu avx2 fma\n")
    assert cpu_has_native_bf16(amx)
    assert not cpu_has_native_bf16(avx2)
    assert not cpu_has_native_bf16(tmp_path / "missing")
    for native, want in ((True, "bfloat16"), (False, "float32")):
        monkeypatch.setattr(inference, "cpu_has_native_bf16", lambda native=native: native)
        assert resolve_precision("auto") == want
        assert resolve_precision("float32") == "float32"
    with pytest.raises(ValueError, match="precision"):
        resolve_precision("float16")


def test_fast_policy_refuses_a_hidden_layer_wider_than_the_kernel():
    wide = Agent(Actor(AgentConfig(hidden=inference._gru.MAX_HIDDEN + 1)))
    with pytest.raises(ValueError, match="hidden width"):
        FastPolicy(wide)
