"""The closed-loop harness: an agent tunes a batch of FOPTD plants, RL step by RL step.

Training validates its epochs with it and the evaluation's experiments are built on it,
so both score an agent the same way. The agent is anything with ``initial_state(n)``
and ``act(obs, state, forgetting)``: :class:`service.agent.Agent` (the reference) or the
tuner's :class:`service.agent.fast.FastPolicy`.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from service.agent.fast import FastPolicy
from service.agent.model import Agent
from service.engine import TuningEngine
from service.learn.env import EnvConfig, TuningEnv
from service.units import RL_STEP_AGENT_UNITS

Policy = Agent | FastPolicy
"""``agent.act`` (the reference) or the tuner's inference path."""


def engine_of(policy: Policy, verifying: bool = False) -> TuningEngine:
    """A tuning engine computing with ``policy``: the tuner's fast path in its precision,
    or ``agent.act`` (the reference). Verification is off unless ``verifying``: the paper's
    experiments measure the agent itself (``pitune verify-eval`` measures verification),
    the robustness suite what a user gets (the guard's ``verify``, on by default)."""
    if isinstance(policy, FastPolicy):
        return TuningEngine(policy.agent, inference_precision=policy.precision, verifying=verifying)
    return TuningEngine(policy, inference_precision="reference", verifying=verifying)


def tune(
    agent: Policy,
    K,
    tau,
    theta,
    *,
    steps: int,
    forgetting: float = 1.0,
    schedule: Callable[[int, TuningEnv], None] | None = None,
    freeze_after: int | None = None,
    sp_jitter: float = 0.0,
    env_config: EnvConfig | None = None,
    gains0: np.ndarray | None = None,
    sp0: float = 1.0,
) -> dict:
    """Let the agent tune N FOPTD plants for ``steps`` RL steps.

    ``schedule(t, env)`` may change the plants before RL step ``t``; ``freeze_after``
    stops applying the agent's updates from that step on (the frozen-gains baseline).
    ``env_config`` replaces the default environment (no initial noise, ``sp_jitter``);
    ``gains0`` (N, 2) the paper's initial gains; the plants start at rest at 0 with the
    setpoint at ``sp0``.
    Returns gains (steps+1, N, 2), per-step tracking MSE (steps, N), final deep states.
    """
    K, tau, theta = (np.atleast_1d(np.asarray(v, dtype=np.float64)) for v in (K, tau, theta))
    cfg = env_config or EnvConfig(init_noise=0.0, sp_jitter=sp_jitter)
    env = TuningEnv(cfg, np.random.default_rng(0))
    start = {} if gains0 is None else {"kp0": gains0[:, 0], "ki0": gains0[:, 1]}
    obs = env.reset(K, tau, theta, horizon=steps, sp0=sp0, **start)
    state = agent.initial_state(K.size)
    gains, mses = [obs[:, :2].copy()], []
    for t in range(steps):
        if schedule is not None:
            schedule(t, env)
            obs = env.observe()
        delta, state = agent.act(obs, state, forgetting=forgetting)
        if freeze_after is not None and t >= freeze_after:
            delta = np.zeros_like(delta)
        obs, _, mse = env.step(delta)
        gains.append(obs[:, :2].copy())
        mses.append(mse)
    return {"gains": np.array(gains), "mse": np.array(mses), "deep": state[:, -1, :]}


def convergence_time(gains: np.ndarray, tol: float = 0.1) -> np.ndarray:
    """Time after which both gains stay within ``tol`` of their final values.

    ``gains`` is (steps+1, N, 2) sampled every RL step; returns agent time units, (N,).
    """
    final = gains[-1]
    inside = np.all(np.abs(gains - final) <= tol * np.abs(final), axis=2)  # (T, N)
    # last index at which the trajectory was outside the band, +1
    outside_rev = ~inside[::-1]
    last_out = np.where(outside_rev.any(0), gains.shape[0] - 1 - np.argmax(outside_rev, axis=0), -1)
    return (last_out + 1) * RL_STEP_AGENT_UNITS
