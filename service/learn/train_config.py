"""The hyperparameters of one ``pitune train`` run (:class:`TrainConfig`, checkpointed with
it; every field is a ``--flag``), what one call does with the run (:class:`RunOptions`),
their ranges, and the command's flags (:func:`add_arguments`)."""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass, fields
from pathlib import Path

import torch

from service import UsageError
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

    def __post_init__(self) -> None:
        """Every value in its range (a flag's value or a checkpoint's config), else a
        UsageError naming the flag."""
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool):
                continue
            low, high, open_low = _limits(f.name)
            inside = low < value if open_low else low <= value
            if not (math.isfinite(value) and inside and value <= high):
                raise UsageError(f"{flag(f.name)} {value}: must be {_say(low, high, open_low)}")
        if self.excitation_gate and self.epochs > 0:
            raise UsageError("--excitation-gate applies to the imitation warm start: --epochs 0")


_COUNT, _AT_LEAST_1, _POSITIVE = (0, math.inf, False), (1, math.inf, False), (0, math.inf, True)
_SHARE = (0, 1, False)
_LIMITS = {
    "seed": _COUNT, "bc_epochs": _COUNT, "bc_horizon": _AT_LEAST_1, "bc_updates": _AT_LEAST_1,
    "bc_minibatch": _AT_LEAST_1, "bc_explore": _COUNT, "bc_lr": _POSITIVE,
    "bc_label_gain": _POSITIVE, "bc_hold_weight": _COUNT, "epochs": _COUNT,
    "episodes": _AT_LEAST_1, "horizon": _AT_LEAST_1, "gamma": _SHARE, "gae_lambda": _SHARE,
    "clip": _POSITIVE, "pi_lr": _POSITIVE, "v_lr": _POSITIVE, "pi_iters": _COUNT,
    "v_iters": _AT_LEAST_1, "target_kl": _POSITIVE, "value_warmup": _COUNT,
    "value_scale": _POSITIVE, "max_grad_norm": _POSITIVE, "forgetting": (0, 1, True),
    "eval_every": _AT_LEAST_1, "eval_plants": _COUNT, "eval_steps": _AT_LEAST_1,
    "checkpoint_minutes": _COUNT, "threads": _AT_LEAST_1,
    # sp_jitter's upper bound depends on the setpoint and RL periods: TuningEnv checks it
    "sp_jitter": _COUNT,
}  # fmt: skip
"""TrainConfig's ranges: (low, high, low excluded). Shares (``*_prob``, ``*_share``) lie
in [0, 1]; any other field takes any finite value."""


def _limits(name: str) -> tuple[float, float, bool]:
    if name.endswith(("_prob", "_share")):
        return _SHARE
    return _LIMITS.get(name, (-math.inf, math.inf, False))


def _say(low: float, high: float, open_low: bool) -> str:
    if math.isinf(low):
        return "finite"
    if math.isinf(high):
        return f"> {low:g}" if open_low else f"at least {low:g}"
    return f"in {'(' if open_low else '['}{low:g}, {high:g}]"


def flag(name: str) -> str:
    """The ``pitune train`` flag of a TrainConfig or RunOptions field."""
    return "--" + name.replace("_", "-")


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

    def __post_init__(self) -> None:
        """A UsageError for options that cannot run, before anything is written."""
        if self.max_minutes is not None and not (0 < self.max_minutes < math.inf):
            raise UsageError(f"--max-minutes {self.max_minutes}: must be > 0")
        if self.resume and self.init_from is not None:
            raise UsageError("--init-from starts a new run: not with --resume")
        try:
            torch.empty(0, device=self.device)
        except (RuntimeError, AssertionError, NotImplementedError) as err:
            # torch says so in a paragraph; its first line names the reason
            raise UsageError(f"--device {self.device}: {str(err).splitlines()[0]}") from None


def switch(value: str) -> bool:
    """A boolean flag's value; anything but these words is a bad command line."""
    words = {"true": True, "1": True, "yes": True, "false": False, "0": False, "no": False}
    if value.lower() not in words:
        raise argparse.ArgumentTypeError(f"{value!r}: give true/false, 1/0 or yes/no")
    return words[value.lower()]


class _Given(argparse.Action):
    """Stores a config flag's value and notes that it was given (``main``'s ``given``)."""

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        setattr(namespace, self.dest, values)
        namespace.given = (*getattr(namespace, "given", ()), self.dest)


def add_arguments(p: argparse.ArgumentParser) -> None:
    """``pitune train``'s flags: RunOptions', then one for each TrainConfig field (its
    type; booleans by :func:`switch`)."""
    p.add_argument("--out", type=Path, default=RunOptions.out, help="run directory")
    p.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt")
    p.add_argument(
        "--init-from", type=Path, default=None, help="start the actor from this agent file"
    )
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument(
        "--max-minutes", type=float, default=None, help="checkpoint and stop after this long"
    )
    p.add_argument(
        "--export",
        type=Path,
        default=None,
        help="after training, copy OUT/best.pt to this path: the best-scoring validated "
        "actor, or the first validated one if no validation scored finite",
    )
    for f in fields(TrainConfig):
        kind = switch if type(f.default) is bool else type(f.default)
        p.add_argument(flag(f.name), type=kind, default=f.default, action=_Given)
