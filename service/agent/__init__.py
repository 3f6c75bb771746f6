"""The meta-RL agent: networks, weights, the stable inference API and the fast path.

Stable API (used by the tuner and by evaluation harnesses outside this repo)::

    from service.agent import load_agent
    agent = load_agent()
    delta, state = agent.act(obs, state, forgetting=0.99)

See :mod:`service.agent.model` for shapes and units, :mod:`service.agent.fast` for the
allocation-free inference the tuner uses.
"""

from service.agent.model import (
    DEFAULT_WEIGHTS,
    ERROR_CLIP,
    GAIN_FLOOR,
    MAX_LOG_STEP,
    MODELS_DIR,
    Actor,
    Agent,
    AgentConfig,
    Critic,
    features,
    forget,
    load_agent,
    relative_to_delta,
    save_actor,
    untrained_agent,
)

__all__ = [
    "DEFAULT_WEIGHTS",
    "ERROR_CLIP",
    "GAIN_FLOOR",
    "MAX_LOG_STEP",
    "MODELS_DIR",
    "Actor",
    "Agent",
    "AgentConfig",
    "Critic",
    "features",
    "forget",
    "load_agent",
    "relative_to_delta",
    "save_actor",
    "untrained_agent",
]
