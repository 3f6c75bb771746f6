"""The pure functions of the PPO update (Spinning Up style): the recurrent actor over
a whole sequence, generalised advantage estimation and PPO-clip's policy loss. The flow
that uses them is :class:`service.learn.train.Trainer`."""

from __future__ import annotations

import torch

from service.agent.model import Actor, forget


def unroll(
    actor: Actor, obs: torch.Tensor, forgetting: torch.Tensor, stepped: torch.Tensor | None = None
):
    """Actor over a whole sequence with per-episode forgetting: obs (T, B, 4), forgetting (B,).

    ``stepped`` (T, B) bool, if given: where the rollout stepped the agent (the excitation
    gate); elsewhere the hidden state is carried unchanged, as the rollout (and the tuning
    engine) did. Returns mean (T, B, 2) and deep (T, B, hidden). Without forgetting or a
    gate the GRU runs the sequence in one call; with them, step by step as the rollout did.
    """
    h = torch.zeros(actor.cfg.layers, obs.shape[1], actor.cfg.hidden, device=obs.device)
    if stepped is None and bool((forgetting == 1.0).all()):
        mean, deep, _ = actor(obs, h)
        return mean, deep
    means, deeps = [], []
    for t in range(obs.shape[0]):
        mean, deep, h_next = actor(obs[t : t + 1], forget(h, forgetting))
        h = h_next if stepped is None else torch.where(stepped[t][None, :, None], h_next, h)
        means.append(mean)
        deeps.append(deep)
    return torch.cat(means), torch.cat(deeps)


def gae(
    rewards: torch.Tensor, values: torch.Tensor, last_value: torch.Tensor, gamma: float, lam: float
) -> torch.Tensor:
    """Generalised advantage estimates (Schulman et al. 2016) of fixed-length episodes.

    rewards, values (T, B); last_value (B,), the critic's value of the state after the
    last step (the episodes are cut, not ended). Returns advantages (T, B):
    A_t = sum_l (gamma lam)^l delta_{t+l}, delta_t = r_t + gamma V_{t+1} - V_t.
    """
    horizon = rewards.shape[0]
    adv = torch.zeros_like(rewards)
    running = torch.zeros_like(last_value)
    for t in reversed(range(horizon)):
        nxt = last_value if t == horizon - 1 else values[t + 1]
        delta = rewards[t] + gamma * nxt - values[t]
        running = delta + gamma * lam * running
        adv[t] = running
    return adv


def ppo_policy_loss(
    logp: torch.Tensor, logp_old: torch.Tensor, adv: torch.Tensor, clip: float
) -> torch.Tensor:
    """PPO-clip's policy loss (to minimise), a scalar.

    logp, logp_old: log-probabilities (T, B) of the taken actions under the current and
    the rollout policy; adv (T, B): advantages (normalised); clip: the ratio's clip range.
    """
    ratio = torch.exp(logp - logp_old)
    clipped = torch.clamp(ratio, 1 - clip, 1 + clip)
    return -torch.min(ratio * adv, clipped * adv).mean()
