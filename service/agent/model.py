"""The meta-RL agent: recurrent actor, privileged critic, and the stable inference API.

Stable API (used by the tuner daemon and by evaluation harnesses outside this repo)::

    from service.agent import load_agent
    agent = load_agent()                      # shipped weights; load_agent(path) for another file
    state = agent.initial_state(n)            # (n, 2, 100) zeros
    delta, state = agent.act(obs, state, forgetting=1.0)

``obs`` is (n, 4) = [kp, ki, e, int_e] in the agent's (training) units, numpy or torch;
``delta`` is (n, 2) = [dkp, dki], the deterministic (mean) action, to be *added* to
the gains; numpy in gives numpy out. ``forgetting`` is the paper's gamma in
z_t = f(gamma W z_{t-1} + U x_t + b), applied by scaling each GRU layer's previous
hidden state before the step (:func:`forget`); a scalar or one value per loop.

Two departures from the paper, both recorded in the model card:

* Input features are [log kp, log ki, e, symlog(int_e)] rather than the raw state,
  because useful gains span two orders of magnitude (the paper notes this makes
  training hard).
* The policy's output ``a`` is a *relative* change: dk = k (exp(a) - 1). Gains stay
  positive by construction and one network output scale serves kp = 0.3 and ki = 8
  alike. The returned delta is still the additive [dkp, dki] of the paper's MDP.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from service import UsageError

MODELS_DIR = Path(__file__).resolve().parents[1] / "models"
DEFAULT_WEIGHTS = MODELS_DIR / "pitune_agent.pt"
V2_WEIGHTS = MODELS_DIR / "pitune_agent_v2.pt"
"""v2, shipped until session 13: the adaptation bar v3 is held to (TRAINING.md)."""
GAIN_FLOOR = 1e-3
MAX_LOG_STEP = 1.0
"""Largest relative change per RL step, in log units (a factor of e = 2.7)."""
ERROR_CLIP = 10.0
"""The error feature is clipped to +-ERROR_CLIP (agent units)."""


@dataclass(frozen=True)
class AgentConfig:
    obs_dim: int = 4
    hidden: int = 100
    layers: int = 2
    head: int = 64
    critic_hidden: int = 128
    privileged_dim: int = 3


def features(obs: torch.Tensor) -> torch.Tensor:
    """[kp, ki, e, int_e] -> [log kp, log ki, e, symlog int_e] (any leading shape)."""
    kp, ki, e, ie = obs.unbind(-1)
    return torch.stack(
        [
            torch.log(kp.clamp_min(GAIN_FLOOR)),
            torch.log(ki.clamp_min(GAIN_FLOOR)),
            e.clamp(-ERROR_CLIP, ERROR_CLIP),
            torch.sign(ie) * torch.log1p(ie.abs()),
        ],
        dim=-1,
    )


def forget(h: torch.Tensor, gamma: torch.Tensor | float) -> torch.Tensor:
    """The paper's forgetting factor: the previous hidden state ``gamma h`` a GRU step uses.

    ``h`` is (layers, B, hidden); ``gamma`` a scalar or one value per loop, (B,). The one
    place training, evaluation and inference apply it (the C kernel of
    :class:`~service.agent.fast.FastPolicy` does the same, tested against this). The float
    1.0 returns ``h`` itself: no multiplication on the common path of no forgetting.
    """
    if isinstance(gamma, float) and gamma == 1.0:
        return h
    return h * torch.as_tensor(gamma, dtype=h.dtype, device=h.device).reshape(1, -1, 1)


def relative_to_delta(gains: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    """Policy output (log-relative change, clipped) -> additive [dkp, dki]."""
    gains = gains.clamp_min(GAIN_FLOOR)
    return gains * torch.expm1(a.clamp(-MAX_LOG_STEP, MAX_LOG_STEP))


class Actor(nn.Module):
    """2-layer GRU, then two fully connected Leaky-ReLU layers to the action mean."""

    def __init__(self, cfg: AgentConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.gru = nn.GRU(cfg.obs_dim, cfg.hidden, num_layers=cfg.layers)
        self.head = nn.Sequential(
            nn.Linear(cfg.hidden, cfg.head),
            nn.LeakyReLU(),
            nn.Linear(cfg.head, cfg.head),
            nn.LeakyReLU(),
            nn.Linear(cfg.head, 2),
        )
        nn.init.uniform_(self.head[-1].weight, -1e-3, 1e-3)
        nn.init.zeros_(self.head[-1].bias)
        self.log_std = nn.Parameter(torch.full((2,), -1.0))

    def forward(
        self, obs: torch.Tensor, h0: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """obs (T, B, 4), h0 (layers, B, hidden) -> mean (T, B, 2), deep (T, B, hidden), hT."""
        deep, h_t = self.gru(features(obs), h0)
        return self.head(deep), deep, h_t

    def step(
        self, obs: torch.Tensor, h: torch.Tensor, forgetting: torch.Tensor | float = 1.0
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """One time step for B loops: obs (B, 4), h (layers, B, hidden) -> mean (B, 2), h'."""
        mean, _, h = self.forward(obs.unsqueeze(0), forget(h, forgetting))
        return mean[0], h


class Critic(nn.Module):
    """Feed-forward value function on the state plus privileged information.

    Input: features of the RL state, the true (K, tau, theta/tau) of the task, and the
    actor's deep hidden state (detached: the critic must not train the actor's GRU).
    """

    def __init__(self, cfg: AgentConfig) -> None:
        super().__init__()
        width = cfg.obs_dim + cfg.privileged_dim + cfg.hidden
        self.net = nn.Sequential(
            nn.Linear(width, cfg.critic_hidden),
            nn.LeakyReLU(),
            nn.Linear(cfg.critic_hidden, cfg.critic_hidden),
            nn.LeakyReLU(),
            nn.Linear(cfg.critic_hidden, 1),
        )

    def forward(self, obs: torch.Tensor, privileged: torch.Tensor, deep: torch.Tensor):
        return self.net(torch.cat([features(obs), privileged, deep.detach()], -1)).squeeze(-1)


class Agent:
    """Inference wrapper around a trained :class:`Actor` (CPU, no gradients)."""

    def __init__(self, actor: Actor, meta: dict | None = None) -> None:
        self.actor = actor.eval()
        self.cfg = actor.cfg
        self.meta = meta or {}

    def initial_state(self, n: int) -> np.ndarray:
        """Zero hidden state for ``n`` loops, shape (n, layers, hidden), float32."""
        return np.zeros((n, self.cfg.layers, self.cfg.hidden), dtype=np.float32)

    @torch.inference_mode()
    def act(self, obs, state, forgetting=1.0):
        """Step ``n`` loops at once; see the module docstring for shapes and units."""
        as_numpy = not isinstance(obs, torch.Tensor)
        obs_t = torch.as_tensor(np.asarray(obs) if as_numpy else obs, dtype=torch.float32)
        if obs_t.ndim != 2 or obs_t.shape[1] != self.cfg.obs_dim:
            raise ValueError(
                f"obs must have shape (n, {self.cfg.obs_dim}), got {tuple(obs_t.shape)}"
            )
        h = torch.as_tensor(state, dtype=torch.float32)
        if h.shape != (obs_t.shape[0], self.cfg.layers, self.cfg.hidden):
            raise ValueError(f"state must have shape (n, {self.cfg.layers}, {self.cfg.hidden})")
        if not torch.isfinite(obs_t).all():
            raise ValueError("obs must be finite")
        gamma = (
            float(forgetting)
            if np.ndim(forgetting) == 0
            else torch.as_tensor(np.asarray(forgetting), dtype=torch.float32)
        )
        mean, h_next = self.actor.step(obs_t, h.transpose(0, 1).contiguous(), gamma)
        delta = relative_to_delta(obs_t[:, :2], mean)
        h_next = h_next.transpose(0, 1)
        if as_numpy:
            return delta.numpy().astype(np.float64), h_next.numpy().copy()
        return delta, h_next.contiguous()


def save_actor(actor: Actor, path: str | Path, meta: dict | None = None) -> None:
    """Write an actor's weights and config (loadable with ``weights_only=True``)."""
    torch.save(
        {"config": asdict(actor.cfg), "actor": actor.state_dict(), "meta": json.dumps(meta or {})},
        path,
    )


def load_agent(path: str | Path | None = None, architecture: AgentConfig | None = None) -> Agent:
    """Load the shipped agent, or the agent stored at ``path`` (checked to be of
    ``architecture`` if given). FileNotFoundError for a missing file; a
    :class:`~service.UsageError` (a ValueError) for a file that is not an agent file
    (:func:`save_actor`'s) or one of another architecture."""
    path = Path(path) if path is not None else DEFAULT_WEIGHTS
    if not path.exists():
        raise FileNotFoundError(f"agent weights not found at {path}")
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except OSError:
        raise  # unreadable: the file system's own error
    except Exception as err:  # torch raises pickle, zip and runtime errors alike
        raise UsageError(f"{path} is not an agent file ({type(err).__name__})") from None
    if isinstance(blob, dict) and "opt_bc" in blob:
        raise UsageError(f"{path} is a training checkpoint, not an agent file (its best.pt is)")
    try:
        config, meta = AgentConfig(**blob["config"]), json.loads(blob.get("meta", "{}"))
        actor = Actor(config)
        actor.load_state_dict(blob["actor"])
    except (TypeError, KeyError, AttributeError, ValueError, RuntimeError) as err:
        raise UsageError(f"{path} is not an agent file ({type(err).__name__})") from None
    if architecture is not None and config != architecture:
        theirs, ours = asdict(config), asdict(architecture)
        differ = [k for k in ours if theirs[k] != ours[k]]
        raise UsageError(
            f"{path}: architecture {', '.join(f'{k} {theirs[k]}' for k in differ)} differs "
            f"from {', '.join(f'{k} {ours[k]}' for k in differ)} (required here)"
        )
    return Agent(actor, meta)


def untrained_agent(seed: int = 0) -> Agent:
    """A randomly initialised agent with the shipped architecture (tests, before training)."""
    torch.manual_seed(seed)
    return Agent(Actor(AgentConfig()))
