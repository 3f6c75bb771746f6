"""The paper's PI-tuning MDP, vectorised over a batch of FOPTD tasks.

Tasks: K ~ U[0.25, 1], tau ~ U[0.25, 1], theta/tau ~ U[0, 1]. Each episode starts with
the PI at kp = ki = 0.05 (Kc = 0.05, tau_I = 1), the plant near zero, and a setpoint
toggling between +1 and -1 every 11 time units. One RL step is 2.75 time units
(275 controller samples at dt = 0.01).

State ``s_t = [kp, ki, e_t, int_e]``: the gains in force, the measured error at the
step boundary and the integral of the measured error since the episode start.
Action: additive ``[dkp, dki]``; gains are clipped to [GAIN_FLOOR, gain_max].
Cost: ``c_t = mean_k (y_desired[k] - y[k])^2 + beta_1 |dkp| + beta_2 |dki|`` where
the mean runs over the 275 samples that follow the action (so the squared-error part
is the step-test MSE of the interval and has the same scale whatever dt is); each
squared error is capped at ``err_cap`` so an unstable trial gives a large but finite
cost. The controller output is limited to +-``u_limit`` (with anti-windup), far
outside what any sane tuning of the box needs (|u| < 10), so that an unstable trial
stays bounded instead of overflowing.

Optionally (``drift_prob``) a task's dynamics change within the episode: K steps to a
new value or tau ramps to a new value, as in the paper's adaptation experiments.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from plant_sim.foptd import FOPTDBatch
from plant_sim.loop import target_filter
from plant_sim.pi import PIBatch
from service.agent.model import GAIN_FLOOR
from service.units import AGENT_GAIN_RANGE, AGENT_KI0, AGENT_KP0, RL_STEP_AGENT_UNITS

K_RANGE = (0.25, 1.0)
TAU_RANGE = (0.25, 1.0)
RATIO_RANGE = (0.0, 1.0)


@dataclass(frozen=True)
class EnvConfig:
    """The MDP's constants; time in the agent's (dimensionless) units."""

    dt: float = 0.01
    """Controller sample time."""
    rl_period: float = RL_STEP_AGENT_UNITS
    """Time between two RL steps (gain updates)."""
    sp_period: float = 11.0
    """Time between setpoint toggles (4 RL steps, as in the paper)."""
    beta_kp: float = 0.5
    """Cost per unit of |dkp| (the paper's beta_1)."""
    beta_ki: float = 0.5
    """Cost per unit of |dki| (the paper's beta_2)."""
    gain_max: float = AGENT_GAIN_RANGE[1]
    """Upper clip of kp and ki (the lower one is ``GAIN_FLOOR``)."""
    err_cap: float = 25.0
    """Cap of each squared tracking error in the cost, so unstable trials stay finite."""
    u_limit: float = 100.0
    """Controller output limit +-u_limit (with anti-windup)."""
    init_noise: float = 0.1
    """Standard deviation of the plant's initial output around 0."""
    noise_std: float = 0.0
    """Measurement noise standard deviation."""
    drift_prob: float = 0.0
    """Share of episodes whose dynamics change mid-episode (K step or tau ramp)."""
    sp_jitter: float = 0.0
    """Relative spread of each episode's setpoint period (with a random phase); 0: none."""


def sample_tasks(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """K, tau, theta drawn uniformly from the paper's training box."""
    K = rng.uniform(*K_RANGE, n)
    tau = rng.uniform(*TAU_RANGE, n)
    return K, tau, tau * rng.uniform(*RATIO_RANGE, n)


class TuningEnv:
    """B episodes of the PI-tuning MDP in lock-step."""

    def __init__(self, cfg: EnvConfig, rng: np.random.Generator) -> None:
        self.cfg = cfg
        self.rng = rng
        self.inner = int(round(cfg.rl_period / cfg.dt))
        self.sp_steps = int(round(cfg.sp_period / cfg.dt))
        if self.sp_steps * (1 - cfg.sp_jitter) <= self.inner:
            raise ValueError("setpoint periods must be longer than one RL step")

    # -- episode ----------------------------------------------------------------------
    def reset(
        self,
        K: np.ndarray,
        tau: np.ndarray,
        theta: np.ndarray,
        *,
        horizon: int,
        kp0: float | np.ndarray = AGENT_KP0,
        ki0: float | np.ndarray = AGENT_KI0,
        sp0: float | np.ndarray | None = None,
    ) -> np.ndarray:
        """Start B episodes of ``horizon`` RL steps; return the first observation (B, 4)."""
        cfg, rng = self.cfg, self.rng
        n = K.size
        self.n, self.horizon, self.t = n, horizon, 0
        self.K, self.tau, self.theta = K.copy(), tau.copy(), theta.copy()
        max_theta = float(TAU_RANGE[1] * RATIO_RANGE[1])
        self.plant = FOPTDBatch(
            K, tau, theta, dt=cfg.dt, max_theta=max_theta, noise_std=cfg.noise_std, seed=rng
        )
        y0 = cfg.init_noise * rng.standard_normal(n)
        self.plant.reset(y0)
        self.target = target_filter(tau, theta, dt=cfg.dt, n=n, max_theta=max_theta)
        self.target.reset(y0)
        self.pi = PIBatch(kp0, ki0, dt=cfg.dt, n=n, u_min=-cfg.u_limit, u_max=cfg.u_limit)
        self.pi.initialise(y0 / K)
        self.sp = rng.choice([-1.0, 1.0], n) if sp0 is None else np.broadcast_to(sp0, (n,)).copy()
        # Setpoint changes of a real loop do not line up with the RL steps: with jitter,
        # each episode gets its own period (+-sp_jitter) and phase.
        j = cfg.sp_jitter
        self.sp_every = np.rint(self.sp_steps * rng.uniform(1 - j, 1 + j, n)).astype(np.int64)
        self.sp_offset = rng.integers(0, self.sp_every) if j > 0 else np.zeros(n, dtype=np.int64)
        self.k = 0  # controller sample counter
        self.int_e = np.zeros(n)
        self.e = self.sp - self.plant.measure()
        self._plan_drift()
        return self.observe()

    def _plan_drift(self) -> None:
        """Per episode: no change, a K step at a random RL step, or a tau ramp."""
        n, rng = self.n, self.rng
        kind = np.where(rng.random(n) < self.cfg.drift_prob, rng.integers(1, 3, n), 0)
        self.drift_kind = kind
        self.drift_start = rng.integers(self.horizon // 4, max(self.horizon // 2, 2), n)
        self.drift_len = np.where(kind == 2, rng.integers(4, 12, n), 1)
        K_new, tau_new, _ = sample_tasks(n, rng)
        self.K_from, self.K_to = self.K.copy(), np.where(kind == 1, K_new, self.K)
        self.tau_from, self.tau_to = self.tau.copy(), np.where(kind == 2, tau_new, self.tau)
        # keep theta/tau of the task while tau drifts
        self.ratio = self.theta / self.tau

    def _apply_drift(self) -> None:
        if not self.drift_kind.any():
            return
        frac = np.clip((self.t - self.drift_start + 1) / self.drift_len, 0.0, 1.0)
        tau = self.tau_from + frac * (self.tau_to - self.tau_from)
        self.set_task(
            K=self.K_from + frac * (self.K_to - self.K_from), tau=tau, theta=self.ratio * tau
        )

    def set_task(self, K=None, tau=None, theta=None) -> None:
        """Change the plant's dynamics mid-episode; the target follows (tau_cl = 2 tau)."""

        def batch(value, current):
            return current if value is None else np.broadcast_to(value, (self.n,)).astype(float)

        self.K, self.tau, self.theta = (
            batch(K, self.K),
            batch(tau, self.tau),
            batch(theta, self.theta),
        )
        self.plant.set_params(K=self.K, tau=self.tau, theta=self.theta)
        self.target.set_params(tau=2.0 * self.tau, theta=self.theta)

    def observe(self) -> np.ndarray:
        return np.stack([self.pi.kp, self.pi.ki, self.e, self.int_e], axis=1)

    @property
    def privileged(self) -> np.ndarray:
        """What only the critic sees: the task's true (K, tau, theta/tau)."""
        return np.stack([self.K, self.tau, self.theta / self.tau], axis=1)

    def step(self, delta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Apply [dkp, dki], run one RL period; return (obs, cost, tracking MSE)."""
        cfg = self.cfg
        kp = np.clip(self.pi.kp + delta[:, 0], GAIN_FLOOR, cfg.gain_max)
        ki = np.clip(self.pi.ki + delta[:, 1], GAIN_FLOOR, cfg.gain_max)
        applied = np.stack([kp - self.pi.kp, ki - self.pi.ki], axis=1)
        self.pi.set_gains(kp, ki)
        plant, target, pi = self.plant, self.target, self.pi
        sq = np.zeros(self.n)
        # Periods exceed one RL step, so each episode toggles at most once in this window:
        # find that sample up front instead of testing every sample (never at k = 0).
        ahead = -(self.k + self.sp_offset) % self.sp_every
        flip_at = self.k + np.where((ahead == 0) & (self.k == 0), self.sp_every, ahead)
        flip_ks = set(flip_at[flip_at < self.k + self.inner].tolist())
        for _ in range(self.inner):
            if self.k in flip_ks:
                self.sp = np.where(flip_at == self.k, -self.sp, self.sp)
            err = target.x - plant.x
            sq += np.minimum(err * err, cfg.err_cap)
            e = self.sp - plant.measure()
            self.int_e += e * cfg.dt
            u = pi.step(e)
            plant.step(u)
            target.step(self.sp)
            self.k += 1
        self.e = self.sp - plant.measure()
        mse = sq / self.inner
        cost = mse + cfg.beta_kp * np.abs(applied[:, 0]) + cfg.beta_ki * np.abs(applied[:, 1])
        self.t += 1
        self._apply_drift()
        return self.observe(), cost, mse
