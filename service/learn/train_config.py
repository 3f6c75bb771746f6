"""The hyperparameters of one ``pitune train`` run (:class:`TrainConfig`, checkpointed with
it; every field is a ``--flag``) and what one call does with the run (:class:`RunOptions`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from service.units import DEFAULT_FORGETTING


@dataclass
class TrainConfig:
    """One training run's hyperparameters (each is a ``pitune train --flag``)."""

    seed: int = 1
    """Seed of numpy's and torch's generators."""
    # imitation warm start (DAgger toward the step-test oracle)
    bc_epochs: int = 600
    """Imitation epochs before PPO."""
    bc_horizon: int = 60
    """RL steps per imitation episode."""
    bc_updates: int = 3
    """Passes over each imitation rollout."""
    bc_minibatch: int = 100
    """Episodes per imitation minibatch."""
    bc_explore: float = 0.1
    """Std of the noise added to the policy's mean while collecting imitation rollouts."""
    bc_lr: float = 1e-3
    """Adam learning rate of the imitation updates."""
    bc_label_gain: float = 1.0
    """Label = this share of the log-distance to the oracle's gains (clipped to one step)."""
    bc_hold_weight: float = 1.0
    """Loss weight of the hold label on quiet steps (no setpoint move seen yet; v3)."""
    # PPO (paper: 300 episodes an epoch, 40 steps, gamma 0.99, lambda 0.95, ...)
    epochs: int = 200
    """PPO epochs (policy updates) after the value warm-up."""
    episodes: int = 300
    """Episodes per epoch (imitation and PPO)."""
    horizon: int = 40
    """RL steps per PPO episode."""
    gamma: float = 0.99
    """Discount factor of the return (not the forgetting factor)."""
    gae_lambda: float = 0.95
    """GAE's lambda."""
    clip: float = 0.2
    """PPO's clip range of the probability ratio."""
    pi_lr: float = 3e-4
    """Adam learning rate of the policy."""
    v_lr: float = 1e-3
    """Adam learning rate of the critic."""
    pi_iters: int = 20
    """Most policy gradient steps per epoch (fewer on the KL early stop)."""
    v_iters: int = 40
    """Critic gradient steps per epoch."""
    target_kl: float = 0.015
    """Policy updates of an epoch stop once the KL to the rollout policy exceeds 1.5x this."""
    value_warmup: int = 20
    """Epochs that train only the critic, between imitation and PPO."""
    ppo_log_std: float = -2.5
    """Exploration log-std set when PPO starts (imitation does not train it)."""
    value_scale: float = 10.0
    """The critic predicts returns divided by this."""
    max_grad_norm: float = 0.5
    """Gradient-norm clip of every update."""
    # task distribution extras
    drift_prob: float = 0.25
    """Share of episodes whose dynamics drift (K step or tau ramp)."""
    sp_jitter: float = 0.3
    """Relative spread of the setpoint period (random phase too)."""
    forgetting_prob: float = 0.3
    """Share of episodes run with the forgetting factor below; the rest with 1."""
    forgetting: float = DEFAULT_FORGETTING
    """The forgetting factor used online."""
    # v3 real-loop conditions (service.learn.env.EnvConfig; core_share 1.0 = the paper's MDP)
    core_share: float = 1.0
    """Share of episodes exactly as the paper's MDP; below 1 turns on the v3 distribution."""
    noise_prob: float = 0.0
    """Share of the other episodes with measurement noise (EnvConfig.noise_prob)."""
    load_prob: float = 0.0
    """Share of the other episodes with input load steps (EnvConfig.load_prob)."""
    load_walk_prob: float = 0.0
    """Share of the other episodes with a slow load random walk (EnvConfig.load_walk_prob)."""
    sp_random_prob: float = 0.0
    """Share of the other episodes with random setpoint moves (EnvConfig.sp_random_prob)."""
    sp_ramp_share: float = 0.2
    """Share of those random moves that are ramps (EnvConfig.sp_ramp_share)."""
    sp_amp_prob: float = 0.0
    """Share of the other toggle episodes with a random amplitude (EnvConfig.sp_amp_prob)."""
    sp_long_prob: float = 0.0
    """Share of the other toggle episodes with a long period (EnvConfig.sp_long_prob)."""
    quiet_prob: float = 0.0
    """Share of the other episodes starting quiet (EnvConfig.quiet_prob)."""
    wide_prob: float = 0.0
    """Share of the other episodes with K and tau off the hint by up to 3x (EnvConfig)."""
    ratio_prob: float = 0.0
    """Share of the other episodes with theta/tau up to 2 (EnvConfig.ratio_prob)."""
    lag2_prob: float = 0.0
    """Share of the other episodes with a second-order plant (EnvConfig.lag2_prob)."""
    init_gain_prob: float = 0.0
    """Share of the other episodes starting at the oracle's gains x log-U[1/3, 3]."""
    excitation_gate: bool = False
    """Imitation rollouts step the agent only where the tuning engine's excitation gate
    would (RL periods ending within EXCITATION_PERIODS of a setpoint move): elsewhere the
    gains and hidden state stay as they are and the step carries no label, so long holds
    and quiet starts look to the agent as they do online. Imitation only (``epochs 0``)."""
    val_robust: bool = False
    """Validation also scores the v3 robustness conditions (:func:`validate_robust`)."""
    val_adapt: bool = False
    """Validation also scores the evaluation's tau ramp and K step against v2's
    (:func:`validate_adaptation`), so the kept epoch cannot be one that lost the adaptation."""
    keep_validated: bool = False
    """Save every validated actor as OUT/val_EPOCH.pt (for a final pick)."""
    # bookkeeping
    eval_every: int = 10
    """Validate (and maybe keep ``best.pt``) every this many epochs."""
    eval_plants: int = 64
    """Random validation plants (plus the 8 corners of the box)."""
    eval_steps: int = 100
    """RL steps of the validation's closed-loop tuning."""
    checkpoint_minutes: float = 5.0
    """Wall time between checkpoints."""
    threads: int = 1
    """Torch intra-op threads."""


@dataclass(frozen=True)
class RunOptions:
    """Where a run lives and what this call does with it (not checkpointed, unlike TrainConfig)."""

    out: Path = Path("runs/agent")
    """Run directory: checkpoint.pt, best.pt, last.pt, metrics.csv."""
    resume: bool = False
    """Continue the run in ``out`` with its own saved TrainConfig."""
    init_from: Path | None = None
    """Start a new run's actor from this agent file."""
    device: str = "cpu"
    """Torch device."""
    max_minutes: float | None = None
    """Checkpoint and stop after this much wall time (continue with ``resume``)."""
    export: Path | None = None
    """When the run has finished, copy ``out/best.pt`` here."""
