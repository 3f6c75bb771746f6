"""Offline training of the meta-RL tuner: ``pitune train``.

One readable flow in the style of CleanRL's ``ppo_atari_lstm.py``: roll out a batch of
episodes on freshly sampled FOPTD tasks, compute GAE, update the recurrent actor with
PPO-clip (full-sequence BPTT, KL early stop) and the privileged feed-forward critic.

Departures from the paper (Appendix A), recorded in the model card:

* **Imitation warm start (DAgger).** Before PPO, the actor is trained by supervised
  learning on its own rollouts: at every step the label is the log-ratio from the
  current gains to the best fixed PI for the task (the step-test "oracle", known
  offline like the critic's privileged information), clipped to one step's reach.
  This gives a dense learning signal and reaches the paper's asymptotic performance
  in minutes on two CPU cores instead of 2,500 PPO epochs. The online agent still
  sees only [kp, ki, e, int_e]: no model at run time.
* Relative (log-space) actions and log-gain input features (see ``service.agent``).
* Some episodes have drifting dynamics (K step, tau ramp) and run with the paper's
  forgetting factor 0.99, so adaptation is trained rather than hoped for; episodes are
  longer (60 steps) in the warm start so the hidden state stays calibrated over the
  80+ steps of the evaluation.
* Advantage normalisation, value-target scaling, gradient clipping.
"""

from __future__ import annotations

import argparse
import copy
import csv
import json
import math
import signal
import subprocess
import sys
import time
from dataclasses import asdict, fields
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.distributions import Normal

from service import UsageError
from service.agent.model import (
    MAX_LOG_STEP,
    Actor,
    AgentConfig,
    Critic,
    forget,
    load_agent,
    relative_to_delta,
    save_actor,
)
from service.learn.env import (
    EnvConfig,
    TuningEnv,
    sample_conditions,
    sample_tasks,
    sample_tasks_v3,
)
from service.learn.oracle import (
    oracle_gains,
    oracle_gains3,
    oracle_table,
    oracle_table3,
)
from service.learn.ppo import gae, ppo_policy_loss, unroll
from service.learn.train_config import RunOptions, TrainConfig, add_arguments, flag
from service.learn.validation import validate
from service.units import AGENT_KI0, AGENT_KP0

__all__ = ["Trainer", "add_arguments", "main", "run"]  # pitune train's flags live in train_config


class Trainer:
    """Holds networks, optimisers, RNG and bookkeeping so a run can checkpoint and resume."""

    def __init__(self, cfg: TrainConfig, out: Path, device: str = "cpu") -> None:
        self.cfg, self.out, self.device = cfg, out, torch.device(device)
        torch.set_num_threads(cfg.threads)
        torch.manual_seed(cfg.seed)
        self.rng = np.random.default_rng(cfg.seed)
        self.actor = Actor(AgentConfig()).to(self.device)
        self.critic = Critic(AgentConfig()).to(self.device)
        self.opt_bc = torch.optim.Adam(self.actor.parameters(), lr=cfg.bc_lr)
        self.opt_pi = torch.optim.Adam(self.actor.parameters(), lr=cfg.pi_lr)
        self.opt_v = torch.optim.Adam(self.critic.parameters(), lr=cfg.v_lr)
        v3 = ("core_share", "noise_prob", "load_prob", "load_walk_prob", "sp_random_prob",
              "sp_ramp_share", "sp_amp_prob", "sp_long_prob", "quiet_prob", "wide_prob",
              "ratio_prob", "lag2_prob")  # fmt: skip
        self.env_cfg = EnvConfig(
            drift_prob=cfg.drift_prob, sp_jitter=cfg.sp_jitter, **{k: getattr(cfg, k) for k in v3}
        )
        try:  # the environment's own rule on the jitter, before the run writes anything
            TuningEnv(self.env_cfg, self.rng)
        except ValueError as err:
            raise UsageError(f"--sp-jitter {cfg.sp_jitter}: {err}") from None
        self.real = cfg.core_share < 1.0  # v3: real-loop conditions and the widened oracle
        self.table = oracle_table3() if self.real else oracle_table()
        self.epoch = 0
        self.elapsed = 0.0
        self.best = math.inf
        self.init_from: dict | None = None
        self.commit = _git_commit()  # the code this process runs, not HEAD at save time

    # -- persistence ------------------------------------------------------------------
    def state(self) -> dict:
        return {
            "config": asdict(self.cfg),
            "actor": self.actor.state_dict(),
            "critic": self.critic.state_dict(),
            "opt_bc": self.opt_bc.state_dict(),
            "opt_pi": self.opt_pi.state_dict(),
            "opt_v": self.opt_v.state_dict(),
            "epoch": self.epoch,
            "elapsed": self.elapsed,
            "best": self.best,
            "init_from": json.dumps(self.init_from),
            "rng": json.dumps(self.rng.bit_generator.state),
            "torch_rng": torch.get_rng_state(),
        }

    def save(self, name: str = "checkpoint.pt") -> None:
        tmp = self.out / (name + ".tmp")
        torch.save(self.state(), tmp)
        tmp.replace(self.out / name)

    def restore(self, blob: dict) -> None:
        """Take up the state :meth:`state` gave (the run's config aside)."""
        for key in ("actor", "critic", "opt_bc", "opt_pi", "opt_v"):
            getattr(self, key).load_state_dict(blob[key])
        self.epoch, self.elapsed, self.best = blob["epoch"], blob["elapsed"], blob["best"]
        self.init_from = json.loads(blob.get("init_from", "null"))
        self.rng.bit_generator.state = json.loads(blob["rng"])
        torch.set_rng_state(blob["torch_rng"].cpu())

    @classmethod
    def resume(cls, out: Path, device: str = "cpu", given: dict | None = None) -> Trainer:
        """The run in ``out`` as of its checkpoint, its log cut back to it. ``given``:
        config values the user gave now; any that differ from the run's own are refused
        (a run keeps the config it was started with)."""
        if not (out / "checkpoint.pt").exists():
            raise UsageError(f"{out} holds no run to resume (no checkpoint.pt)")
        blob = torch.load(out / "checkpoint.pt", map_location=device, weights_only=True)
        saved = blob["config"]
        for name, value in (given or {}).items():
            if value != saved[name]:
                raise UsageError(
                    f"{flag(name)} {value}: the run in {out} has {saved[name]}, and a resumed "
                    "run keeps its config (drop the flag, or start a new run)"
                )
        trainer = cls(TrainConfig(**saved), out, device)
        trainer.restore(blob)
        _cut_log(out / "metrics.csv", trainer.epoch)
        return trainer

    def init_actor_from(self, path: Path) -> None:
        """Warm-start the actor from an exported agent (recorded in the model card); a
        UsageError for a file that is not an agent of this architecture."""
        agent = load_agent(path, self.actor.cfg)
        self.actor.load_state_dict(agent.actor.state_dict())
        self.init_from = {"path": str(path), "meta": agent.meta}

    # -- rollouts ---------------------------------------------------------------------
    def _episode_forgetting(self, n: int) -> np.ndarray:
        use = self.rng.random(n) < self.cfg.forgetting_prob
        return np.where(use, self.cfg.forgetting, 1.0)

    def rollout(self, n: int, horizon: int, explore: float | None) -> dict:
        """Run ``n`` episodes; ``explore`` None samples the policy, else mean + N(0, explore)."""
        cfg = self.cfg
        env = TuningEnv(self.env_cfg, self.rng)
        if self.real:
            K, tau, theta, tau2, core = sample_tasks_v3(n, self.rng, self.env_cfg)
            cond = sample_conditions(n, self.rng, self.env_cfg, core)
            # a share of the real-loop episodes starts from someone's gains, not 0.05
            g0 = oracle_gains3(self.table, K, tau, theta, tau2)
            g0 = g0 * np.exp(self.rng.uniform(-np.log(3), np.log(3), (n, 2)))
            mine = ~core & (self.rng.random(n) < cfg.init_gain_prob)
            kp0, ki0 = np.where(mine[:, None], g0, [AGENT_KP0, AGENT_KI0]).T
            obs = env.reset(
                K, tau, theta, horizon=horizon, tau2=tau2, conditions=cond, kp0=kp0, ki0=ki0
            )
        else:
            obs = env.reset(*sample_tasks(n, self.rng), horizon=horizon)
        dev = self.device
        forgetting = torch.as_tensor(self._episode_forgetting(n), dtype=torch.float32, device=dev)
        h = torch.zeros(self.actor.cfg.layers, n, self.actor.cfg.hidden, device=dev)
        keys = ("obs", "act", "logp", "cost", "mse", "priv", "deep", "label", "weight", "stepped")
        buf = {k: [] for k in keys}
        std = self.actor.log_std.exp()
        with torch.no_grad():
            for _ in range(horizon):
                o = torch.as_tensor(obs, dtype=torch.float32, device=dev)
                mean, deep, h_next = self.actor(o.unsqueeze(0), forget(h, forgetting))
                mean, deep = mean[0], deep[0]
                if cfg.excitation_gate:  # where the engine would not step: nothing moves
                    gate = env.gate_open()
                    stepped = torch.as_tensor(gate, device=dev)
                    buf["stepped"].append(stepped)
                    h = torch.where(stepped[None, :, None], h_next, h)
                else:
                    h = h_next
                if explore is None:
                    dist = Normal(mean, std)
                    a = dist.sample()
                    buf["logp"].append(dist.log_prob(a).sum(-1))
                else:
                    a = mean + explore * torch.randn_like(mean)
                if cfg.excitation_gate:
                    a = torch.where(stepped[:, None], a, torch.zeros_like(a))
                if self.real:  # hold the gains until a setpoint move has been seen
                    target = oracle_gains3(self.table, env.K, env.tau, env.theta, env.tau2)
                    target = np.where(env.excited[:, None], target, obs[:, :2])
                else:
                    target = oracle_gains(self.table, env.K, env.tau, env.theta)
                label = np.clip(
                    cfg.bc_label_gain * np.log(target / obs[:, :2]), -MAX_LOG_STEP, MAX_LOG_STEP
                )
                buf["label"].append(torch.as_tensor(label, dtype=torch.float32, device=dev))
                # hold steps (no setpoint move seen yet): any bias there accumulates over
                # a long quiet stretch, so they weigh bc_hold_weight in the loss
                w = np.where(env.excited, 1.0, cfg.bc_hold_weight) if self.real else np.ones(n)
                if cfg.excitation_gate:
                    w = w * gate
                buf["weight"].append(torch.as_tensor(w, dtype=torch.float32, device=dev))
                buf["obs"].append(o)
                buf["act"].append(a)
                buf["priv"].append(torch.as_tensor(env.privileged, dtype=torch.float32, device=dev))
                buf["deep"].append(deep)
                obs, cost, mse = env.step(relative_to_delta(o[:, :2], a).double().cpu().numpy())
                buf["cost"].append(torch.as_tensor(cost, dtype=torch.float32, device=dev))
                buf["mse"].append(torch.as_tensor(mse, dtype=torch.float32, device=dev))
            o = torch.as_tensor(obs, dtype=torch.float32, device=dev)
            _, deep, _ = self.actor(o.unsqueeze(0), forget(h, forgetting))
            buf["last_obs"], buf["last_deep"] = o, deep[0]
            buf["last_priv"] = torch.as_tensor(env.privileged, dtype=torch.float32, device=dev)
        out = {k: torch.stack(v) for k, v in buf.items() if isinstance(v, list) and v}
        out.update({k: buf[k] for k in ("last_obs", "last_deep", "last_priv")})
        out["forgetting"] = forgetting
        return out

    # -- updates ----------------------------------------------------------------------
    def bc_epoch(self) -> dict:
        cfg = self.cfg
        batch = self.rollout(cfg.episodes, cfg.bc_horizon, explore=cfg.bc_explore)
        for _ in range(cfg.bc_updates):
            order = torch.randperm(cfg.episodes, device=self.device)
            for idx in order.split(cfg.bc_minibatch):
                stepped = batch["stepped"][:, idx] if "stepped" in batch else None
                mean, _ = unroll(
                    self.actor, batch["obs"][:, idx], batch["forgetting"][idx], stepped
                )
                w = batch["weight"][:, idx, None]
                loss = (w * (mean - batch["label"][:, idx]) ** 2).mean()
                self.opt_bc.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(self.actor.parameters(), cfg.max_grad_norm)
                self.opt_bc.step()
        return {
            "phase": "bc",
            "mean_cost": float(batch["cost"].sum(0).mean()),
            "final_mse": float(batch["mse"][-4:].mean()),
            "bc_loss": loss.item(),
        }

    def ppo_epoch(self, train_policy: bool) -> dict:
        cfg = self.cfg
        b = self.rollout(cfg.episodes, cfg.horizon, explore=None)
        with torch.no_grad():
            values = self.critic(b["obs"], b["priv"], b["deep"]) * cfg.value_scale
            last_v = self.critic(b["last_obs"], b["last_priv"], b["last_deep"]) * cfg.value_scale
            adv = gae(-b["cost"], values, last_v, cfg.gamma, cfg.gae_lambda)
            returns = adv + values
            adv_n = (adv - adv.mean()) / (adv.std() + 1e-8)

        kl, pi_loss, iters = 0.0, torch.tensor(0.0), 0
        if train_policy:
            for iters in range(1, cfg.pi_iters + 1):  # noqa: B007 - reported below
                mean, _ = unroll(self.actor, b["obs"], b["forgetting"])
                logp = Normal(mean, self.actor.log_std.exp()).log_prob(b["act"]).sum(-1)
                pi_loss = ppo_policy_loss(logp, b["logp"], adv_n, cfg.clip)
                kl = (b["logp"] - logp).mean().item()
                if kl > 1.5 * cfg.target_kl:
                    break
                self.opt_pi.zero_grad()
                pi_loss.backward()
                nn.utils.clip_grad_norm_(self.actor.parameters(), cfg.max_grad_norm)
                self.opt_pi.step()

        target = returns / cfg.value_scale
        for _ in range(cfg.v_iters):
            v_loss = ((self.critic(b["obs"], b["priv"], b["deep"]) - target) ** 2).mean()
            self.opt_v.zero_grad()
            v_loss.backward()
            nn.utils.clip_grad_norm_(self.critic.parameters(), cfg.max_grad_norm)
            self.opt_v.step()
        return {
            "phase": "ppo" if train_policy else "value_warmup",
            "mean_cost": float(b["cost"].sum(0).mean()),
            "final_mse": float(b["mse"][-4:].mean()),
            "kl": kl,
            "pi_iters": iters,
            "pi_loss": pi_loss.item(),
            "v_loss": v_loss.item(),
        }

    # -- main loop --------------------------------------------------------------------
    def run(self, max_minutes: float | None = None, max_epochs: int | None = None) -> bool:
        """Train until the configured total; stop early (checkpointed) after ``max_minutes``
        of wall time or ``max_epochs`` epochs in this call. Returns True when finished."""
        from tqdm import tqdm

        cfg = self.cfg
        total = cfg.bc_epochs + cfg.value_warmup + cfg.epochs
        stop_epoch = total if max_epochs is None else min(total, self.epoch + max_epochs)
        deadline = None if max_minutes is None else time.monotonic() + 60 * max_minutes
        self.out.mkdir(parents=True, exist_ok=True)
        log_path = self.out / "metrics.csv"
        columns = [
            "epoch", "phase", "wall_s", "mean_cost", "final_mse", "bc_loss", "kl",
            "pi_iters", "pi_loss", "v_loss", "val_worst", "val_median", "val_drift",
            "val_r_worst", "val_r_median", "val_r_which", "val_tau_ramp", "val_k_step",
            "val_score",
        ]  # fmt: skip
        new_log = not log_path.exists()
        if not new_log:  # a run's log keeps the columns it was started with
            with log_path.open() as head:
                columns = head.readline().strip().split(",")
        last_ckpt = time.monotonic()
        bar = tqdm(total=total, initial=self.epoch, desc="train", dynamic_ncols=True)
        # the state at the last whole epoch: a stop between epochs checkpoints it, so the
        # resumed run redoes the cut epoch exactly as the run would have done it
        boundary = copy.deepcopy(self.state())
        try:
            with log_path.open("a", newline="") as fh:
                writer = csv.DictWriter(fh, fieldnames=columns, extrasaction="ignore")
                if new_log:
                    writer.writeheader()
                while self.epoch < stop_epoch and (deadline is None or time.monotonic() < deadline):
                    self._epoch(writer, total, bar)
                    fh.flush()
                    boundary = copy.deepcopy(self.state())
                    if time.monotonic() - last_ckpt > 60 * cfg.checkpoint_minutes:
                        self.save()
                        last_ckpt = time.monotonic()
        except KeyboardInterrupt:  # Ctrl-C, or SIGTERM through main()
            self.restore(boundary)
            self.save()
            raise
        finally:
            bar.close()
        self.save()
        save_actor(self.actor, self.out / "last.pt", self.card_meta({}))
        return self.epoch >= total

    def _epoch(self, writer: csv.DictWriter, total: int, bar) -> None:
        """One epoch: train, validate when due (keeping best.pt), log its row."""
        cfg, start = self.cfg, time.monotonic()
        if self.epoch < cfg.bc_epochs:
            row = self.bc_epoch()
        else:
            if self.epoch == cfg.bc_epochs:
                # BC never trains log_std; PPO fine-tuning starts from a narrow policy
                with torch.no_grad():
                    self.actor.log_std.fill_(cfg.ppo_log_std)
            row = self.ppo_epoch(self.epoch >= cfg.bc_epochs + cfg.value_warmup)
        self.epoch += 1
        validated = self.epoch % cfg.eval_every == 0 or self.epoch == total
        if validated:
            row.update(
                validate(
                    self.actor,
                    cfg.eval_plants,
                    cfg.eval_steps,
                    cfg.sp_jitter,
                    cfg.val_robust,
                    cfg.val_adapt,
                )
            )
        # before the agent files are written: their wall_s is the log's, this epoch in
        self.elapsed += time.monotonic() - start
        row.update(epoch=self.epoch, wall_s=round(self.elapsed, 1))
        if validated:
            meta = self.card_meta(row)
            if cfg.keep_validated:  # every validated actor, for a final pick
                save_actor(self.actor, self.out / f"val_{self.epoch:04d}.pt", meta)
            # the first validated actor is kept whatever its score (inf: a loop went
            # unstable), so a run always has a best.pt to export
            if row["val_score"] < self.best or not (self.out / "best.pt").exists():
                self.best = min(self.best, row["val_score"])
                save_actor(self.actor, self.out / "best.pt", meta)
        writer.writerow(row)
        bar.set_postfix(
            phase=row["phase"], cost=f"{row['mean_cost']:.3f}",
            kl=f"{row.get('kl', 0.0):.4f}", best=f"{self.best:.4f}",
        )  # fmt: skip
        bar.update(1)

    def card_meta(self, row: dict) -> dict:
        return {
            "source": str(self.out),
            "commit": self.commit,
            "train_config": asdict(self.cfg),
            "init_from": self.init_from,
            "epoch": self.epoch,
            "episodes": self.epoch * self.cfg.episodes,
            "wall_s": round(self.elapsed, 1),
            "validation": {k: v for k, v in row.items() if k.startswith("val_")},
        }


def _git_commit() -> str:
    """The commit of the checkout this package runs from ("unknown" outside one), whatever
    the current directory."""
    try:
        done = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, timeout=5,
            cwd=Path(__file__).resolve().parent,
        )  # fmt: skip
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return done.stdout.strip() if done.returncode == 0 and done.stdout.strip() else "unknown"


def _cut_log(path: Path, epoch: int) -> None:
    """Drop the log's rows after checkpoint ``epoch`` (a run stopped between checkpoints,
    or in the middle of a row), so that the resumed run logs those epochs once."""
    if not path.exists():
        return
    lines = path.read_text().splitlines(keepends=True)
    at = next(csv.reader(lines[:1])).index("epoch")
    keep = 1
    while keep < len(lines) and lines[keep].endswith("\n"):
        if int(next(csv.reader([lines[keep]]))[at]) > epoch:
            break
        keep += 1
    if keep < len(lines):
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text("".join(lines[:keep]))
        tmp.replace(path)


INTERRUPTED = 130
"""Exit status of a run stopped by Ctrl-C or SIGTERM (checkpointed), as a shell's 128 + SIGINT."""


def main(cfg: TrainConfig, opts: RunOptions, given: tuple[str, ...] = ()) -> int:
    """Start (or resume) a run, train it within ``opts.max_minutes``, export when finished.
    ``given``: the config fields set on the command line (a resumed run refuses any that
    differ from its own). Ctrl-C or SIGTERM checkpoints the last whole epoch and exits
    with :data:`INTERRUPTED`."""
    if opts.resume:
        trainer = Trainer.resume(opts.out, opts.device, {k: getattr(cfg, k) for k in given})
        print(f"resumed {opts.out} at epoch {trainer.epoch}")
    else:
        if (opts.out / "checkpoint.pt").exists():
            raise UsageError(f"{opts.out} already holds a run: use --resume or another --out")
        trainer = Trainer(cfg, opts.out, opts.device)
        if opts.init_from is not None:
            trainer.init_actor_from(opts.init_from)
    previous = signal.signal(signal.SIGTERM, _stop)
    try:
        finished = trainer.run(max_minutes=opts.max_minutes)
    except KeyboardInterrupt:
        print(
            f"interrupted: checkpointed at epoch {trainer.epoch}; continue with "
            f"pitune train --out {opts.out} --resume",
            file=sys.stderr,
        )
        return INTERRUPTED
    finally:
        signal.signal(signal.SIGTERM, previous)
    if not finished:
        print(f"stopped at epoch {trainer.epoch}; continue with --resume")
        return 0
    if opts.export is not None:
        opts.export.write_bytes((opts.out / "best.pt").read_bytes())
        print(f"exported {opts.out / 'best.pt'} -> {opts.export}")
    return 0


def _stop(signum: int, frame: object) -> None:
    """SIGTERM (a service manager's stop, ``kill``) as Ctrl-C: checkpoint and exit."""
    raise KeyboardInterrupt


def run(args: argparse.Namespace) -> int:
    def pick(config):
        return config(**{f.name: getattr(args, f.name) for f in fields(config)})

    return main(pick(TrainConfig), pick(RunOptions), getattr(args, "given", ()))
