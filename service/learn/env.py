"""The paper's PI-tuning MDP, vectorised over a batch of FOPTD tasks.

Tasks: K ~ U[0.25, 1], tau ~ U[0.25, 1], theta/tau ~ U[0, 1]. Each episode starts with
the PI at kp = ki = 0.05 (Kc = 0.05, tau_I = 1), the plant near zero, and a setpoint
toggling between +1 and -1 every 11 time units. One RL step is 2.75 time units
(275 controller samples at dt = 0.01).

State ``s_t = [kp, ki, e_t, int_e]``: the gains in force, the mean measured error over
the last :data:`~service.units.OBS_WINDOW` of the RL period (the samples from 0.8 of the
period to its end, :func:`service.units.error_window`, as the tuning engine computes it)
and the integral of the measured error since the episode start.
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

Real-loop conditions (v3; all off by default, so the MDP above is unchanged): per
episode, measurement noise (white or low-pass), load disturbances at the plant input
(steps, a slow random walk), setpoint moves of random size, sign, hold time and ramps,
a quiet start, and plants outside the paper's box (a second lag, theta/tau up to 2, K
and tau off the scaling hint by up to 3x). :func:`sample_tasks_v3` and
:func:`sample_conditions` draw them from an :class:`EnvConfig`; ``reset(...,
conditions=...)`` takes any per-episode arrays (the robustness evaluation sets them
explicitly). The observation stays [kp, ki, e, int_e], e the *measured* error, with e
and int_e scaled by 2 / (size of the last setpoint move) exactly as the tuning engine
scales them (:func:`service.units.track_moves`): the paper's +-1 toggle is a move of 2,
so its episodes are unchanged; a move of another size looks like the paper's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from plant_sim.foptd import FOPTDBatch
from plant_sim.loop import effective_foptd, target_filter
from plant_sim.pi import PIBatch
from service.agent.model import GAIN_FLOOR
from service.learn import sample_loop
from service.units import (
    AGENT_GAIN_RANGE,
    AGENT_KI0,
    AGENT_KP0,
    EXCITATION_PERIODS,
    RL_STEP_AGENT_UNITS,
    error_window,
    ramp_gated,
    ramp_rule,
    window_error,
)

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
    # -- v3: real-loop conditions, used by sample_tasks_v3 / sample_conditions only ----
    core_share: float = 1.0
    """Share of episodes exactly as the paper's MDP (box, toggle, no noise, no load)."""
    noise_prob: float = 0.0
    """Share of the other episodes with measurement noise, sigma ~ U[0.005, noise_max]."""
    noise_max: float = 0.1
    """Upper bound of the measurement noise sigma of the noisy episodes."""
    noise_lp_prob: float = 0.3
    """Share of the noisy episodes whose noise is low-pass (filter 0.05-0.3 tau; same sigma)."""
    load_prob: float = 0.0
    """Share with input load steps: levels U[-L, L], L ~ U[0.1, load_max], mean hold 2-10 RL."""
    load_walk_prob: float = 0.0
    """Share with a slow load random walk (OU, time constant 20, std U[0.05, load_max/2])."""
    load_max: float = 0.5
    """Upper bound of the load-step level bound L and twice that of the walk's std."""
    sp_random_prob: float = 0.0
    """Share with random setpoint moves (+-A U[0.3, 1], random holds, ramps) not the toggle."""
    sp_ramp_share: float = 0.2
    """Share of those random moves that are ramps (over 0.5-3 RL periods), not steps."""
    sp_amp_prob: float = 0.0
    """Share of toggle episodes whose amplitude is log-uniform in sp_amp_range (not 1)."""
    sp_amp_range: tuple[float, float] = (0.1, 3.0)
    """Range of the log-uniform setpoint amplitude A (random moves and sp_amp_prob)."""
    sp_hold_max: float = 20.0
    """Cap of a random move's hold (RL periods; hold 1 + Exp(h - 1), h ~ U[1, 8])."""
    sp_long_prob: float = 0.0
    """Share of toggle episodes with a long period, U[11, 55] time units (4-20 RL periods)."""
    quiet_prob: float = 0.0
    """Share starting quiet: setpoint at the plant's value, no move for 5-100 RL periods."""
    wide_prob: float = 0.0
    """Share whose K and tau are each multiplied (p 0.5 each) by a factor log-U[1/3, 3]."""
    ratio_max: float = 2.0
    """Upper bound of theta/tau of the ratio_prob episodes."""
    ratio_prob: float = 0.0
    """Share with theta/tau ~ U[0, ratio_max] instead of U[0, 1]."""
    lag2_prob: float = 0.0
    """Share of second-order plants: a second lag tau2 = U[0.1, 0.5] tau."""


def sample_tasks(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """K, tau, theta drawn uniformly from the paper's training box."""
    K = rng.uniform(*K_RANGE, n)
    tau = rng.uniform(*TAU_RANGE, n)
    return K, tau, tau * rng.uniform(*RATIO_RANGE, n)


def sample_tasks_v3(
    n: int, rng: np.random.Generator, cfg: EnvConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(K, tau, theta, tau2, core) per :class:`EnvConfig`: the paper's box for the core
    share, widened (hint error, dead time, second lag) for the rest. ``theta`` is drawn
    against the nominal tau (the scaling hint), so a tau error also changes theta/tau."""
    K, tau, theta = sample_tasks(n, rng)
    core = rng.random(n) < cfg.core_share
    rest = ~core
    ratio = np.where(
        rest & (rng.random(n) < cfg.ratio_prob), rng.uniform(0, cfg.ratio_max, n), theta / tau
    )
    theta = ratio * tau
    wide = rest & (rng.random(n) < cfg.wide_prob)
    factor = lambda: np.exp(rng.uniform(-np.log(3), np.log(3), n))  # noqa: E731
    K = np.where(wide & (rng.random(n) < 0.5), K * factor(), K)
    tau = np.where(wide & (rng.random(n) < 0.5), tau * factor(), tau)
    tau2 = np.where(rest & (rng.random(n) < cfg.lag2_prob), rng.uniform(0.1, 0.5, n) * tau, 0.0)
    return K, tau, theta, tau2, core


def sample_conditions(n: int, rng: np.random.Generator, cfg: EnvConfig, core: np.ndarray) -> dict:
    """Per-episode real-loop conditions (keys as :data:`CONDITIONS`); none for ``core``."""
    rest = ~core
    pick = lambda p: rest & (rng.random(n) < p)  # noqa: E731
    U = lambda a, b: rng.uniform(a, b, n)  # noqa: E731
    lo, hi = np.log(cfg.sp_amp_range[0]), np.log(cfg.sp_amp_range[1])
    noisy = pick(cfg.noise_prob)
    sp_random = pick(cfg.sp_random_prob)
    loads = pick(cfg.load_prob)
    return {
        "noise": np.where(noisy, U(0.005, cfg.noise_max), 0.0),
        "noise_tf": np.where(noisy & (rng.random(n) < cfg.noise_lp_prob), U(0.05, 0.3), 0.0),
        "load_step": np.where(loads, U(0.1, cfg.load_max), 0.0),
        "load_every": U(2.0, 10.0) * cfg.rl_period,
        "load_walk": np.where(pick(cfg.load_walk_prob), U(0.05, cfg.load_max / 2), 0.0),
        "sp_random": sp_random,
        "sp_amp": np.where(sp_random | pick(cfg.sp_amp_prob), np.exp(U(lo, hi)), 1.0),
        "sp_hold": U(1.0, 8.0),
        "sp_ramp": np.where(sp_random, cfg.sp_ramp_share, 0.0),
        "sp_period": np.where(pick(cfg.sp_long_prob), U(11.0, 55.0), cfg.sp_period),
        "quiet": np.where(pick(cfg.quiet_prob), U(5.0, 100.0) * cfg.rl_period, 0.0),
    }


CONDITIONS = {
    "noise": (0.0, "measurement noise sigma (agent units)"),
    "noise_tf": (0.0, "noise low-pass time constant as a multiple of tau (0: white)"),
    "load_step": (0.0, "load steps: level magnitude bound at the plant input (0: none)"),
    "load_every": (19.25, "load steps: mean hold (time units)"),
    "load_periodic": (False, "load steps alternate 0 / +load_step every load_every exactly"),
    "load_walk": (0.0, "stationary std of the OU load walk, time constant 20 (0: none)"),
    "sp_random": (False, "random setpoint moves instead of the toggle"),
    "sp_amp": (1.0, "setpoint amplitude"),
    "sp_hold": (4.0, "random moves: mean hold in RL periods (1 + Exp(sp_hold - 1))"),
    "sp_ramp": (0.0, "random moves: probability that a move is a ramp (0.5-3 RL periods)"),
    "sp_period": (11.0, "toggle period (time units; sp_jitter applies on top)"),
    "quiet": (0.0, "time units before the first setpoint move (setpoint = plant at start)"),
}
"""Per-episode condition arrays of :meth:`TuningEnv.reset`: name -> (neutral value, meaning)."""


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
        tau2: np.ndarray | None = None,
        conditions: dict | None = None,
    ) -> np.ndarray:
        """Start B episodes of ``horizon`` RL steps; return the first observation (B, 4).

        ``tau2`` (B,) adds a second lag (0: FOPTD); ``conditions`` holds per-episode
        arrays named in :data:`CONDITIONS` (missing ones neutral)."""
        cfg, rng = self.cfg, self.rng
        n = K.size
        self.n, self.horizon, self.t = n, horizon, 0
        self.K, self.tau, self.theta = K.copy(), tau.copy(), theta.copy()
        self.tau2 = np.zeros(n) if tau2 is None else np.broadcast_to(tau2, (n,)).astype(float)
        c = {k: np.broadcast_to(v[0], (n,)) for k, v in CONDITIONS.items()}
        c["sp_period"] = np.broadcast_to(cfg.sp_period, (n,))
        c.update({k: np.broadcast_to(v, (n,)) for k, v in (conditions or {}).items()})
        self.cond = c
        max_theta = max(
            float(TAU_RANGE[1] * RATIO_RANGE[1]),
            float(np.max(theta / tau)) * TAU_RANGE[1],
            float(np.max(theta + self.tau2)),
        )
        self.plant = FOPTDBatch(
            K, tau, theta, dt=cfg.dt, max_theta=max_theta, noise_std=cfg.noise_std, seed=rng,
            tau2=self.tau2,
        )  # fmt: skip
        y0 = cfg.init_noise * rng.standard_normal(n)
        self.plant.reset(y0)
        self.target = target_filter(
            *effective_foptd(tau, theta, self.tau2), dt=cfg.dt, n=n, max_theta=max_theta
        )
        self.target.reset(y0)
        self.pi = PIBatch(kp0, ki0, dt=cfg.dt, n=n, u_min=-cfg.u_limit, u_max=cfg.u_limit)
        self.pi.initialise(y0 / K)
        if sp0 is None:
            sp0 = rng.choice([-1.0, 1.0], n) * c["sp_amp"]
        self.sp = np.broadcast_to(sp0, (n,)).copy()
        quiet = np.rint(c["quiet"] / cfg.dt).astype(np.int64)
        self.sp = np.where(quiet > 0, y0, self.sp)
        self.excited = quiet == 0  # a setpoint move has been seen (the label's gate)
        # the excitation gate's first move: the episode's start, a setpoint step (plant at
        # about 0, setpoint at +-A), unless it starts quiet. The engine opens only at the
        # first change after registration; training keeps the start's periods, which the
        # paper's protocol (and pitune evaluate's experiments, without a gate) steps.
        self.start_move_k = np.where(quiet > 0, -np.inf, 0.0)
        # Setpoint changes of a real loop do not line up with the RL steps: with jitter,
        # each episode gets its own period (+-sp_jitter) and phase.
        j = cfg.sp_jitter
        steps = self.sp_steps if conditions is None else np.rint(c["sp_period"] / cfg.dt)
        if np.any(steps * (1 - j) <= self.inner):
            raise ValueError("setpoint periods must be longer than one RL step")
        self.sp_every = np.rint(steps * rng.uniform(1 - j, 1 + j, n)).astype(np.int64)
        self.sp_offset = rng.integers(0, self.sp_every) if j > 0 else np.zeros(n, dtype=np.int64)
        # the setpoint is a ramp segment from sp_from to sp_to over [sp_start, +sp_len)
        ahead = -self.sp_offset % self.sp_every
        self.sp_next = np.where(ahead == 0, self.sp_every, ahead)
        if np.any(c["sp_random"]):
            self.sp_next = np.where(c["sp_random"], self._hold(np.arange(n)), self.sp_next)
        self.sp_next = np.where(quiet > 0, quiet, self.sp_next)
        self.sp_from, self.sp_to = self.sp.copy(), self.sp.copy()
        self.sp_start, self.sp_len = np.zeros(n), np.ones(n)
        self.load = np.zeros(n)
        self.load_walk = np.zeros(n)
        self.noise_state = (
            c["noise"] * rng.standard_normal(n) if np.any(c["noise"]) else np.zeros(n)
        )
        self.load_next = np.rint(c["load_every"] / cfg.dt)  # first load step
        if np.any(c["load_step"] > 0):
            self.load_next *= np.where(c["load_periodic"], 1.0, rng.exponential(1.0, n))
        self.k = 0  # controller sample counter
        self.int_e = np.zeros(n)
        self.e = self.sp - self.plant.measure() - self.noise_state
        # the engine's setpoint-move scaling of the observation (service.units.track_moves)
        self.sp_ref, self.sp_anchor = self.sp.copy(), self.sp.copy()
        self.move_k, self.obs_gain = np.full(n, -np.inf), np.ones(n)
        # the setpoint-ramp rule's state (service.units.ramp_rule), the samples of the last
        # change that continued a ramp and of a ramp's first
        self.sp_last, self.sp_way, self.sp_since = self.sp.copy(), np.full(n, np.nan), np.zeros(n)
        self.ramp_k, self.ramp_from_k = np.full(n, -np.inf), np.full(n, -np.inf)
        self._plan_drift()
        return self.observe()

    def _hold(self, rows) -> np.ndarray:
        """Random-move hold times in samples: 1 + Exp(sp_hold - 1) RL periods, capped."""
        mean = self.cond["sp_hold"][rows]
        periods = 1.0 + self.rng.exponential(np.maximum(mean - 1.0, 1e-6))
        return np.rint(np.minimum(periods, self.cfg.sp_hold_max) * self.inner).astype(np.int64)

    def _plan_drift(self) -> None:
        """Per episode: no change, a K step at a random RL step, or a tau ramp."""
        n, rng = self.n, self.rng
        kind = np.where(rng.random(n) < self.cfg.drift_prob, rng.integers(1, 3, n), 0)
        kind = np.where(self.tau2 > 0, 0, kind)  # second-order plants do not drift
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
        tau_e, theta_e = effective_foptd(self.tau, self.theta, self.tau2)
        self.target.set_params(tau=2.0 * tau_e, theta=theta_e)

    def gate_open(self, periods: float = EXCITATION_PERIODS) -> np.ndarray:
        """(B,) bool: where the tuning engine's excitation gate would step the agent now,
        i.e. the last setpoint move (of at least MOVE_STEP) lies within ``periods`` RL
        periods (the engine's ``excitation_periods``, service.engine.rules); an episode's
        start counts as a move unless it starts quiet (see :meth:`reset`). As in the
        engine, an RL period with a ramp running, or ending a long one, is not stepped
        (:func:`service.units.ramp_gated`)."""
        last = np.maximum(self.move_k, self.start_move_k)
        ramp = ramp_gated(self.k, self.inner, self.ramp_k, self.ramp_from_k, self.sp_since)
        return (self.k - last <= periods * self.inner) & ~ramp

    def observe(self) -> np.ndarray:
        """[kp, ki, e, int_e] (B, 4), e and int_e scaled as the engine scales them."""
        g = self.obs_gain
        return np.stack([self.pi.kp, self.pi.ki, self.e * g, self.int_e * g], axis=1)

    @property
    def privileged(self) -> np.ndarray:
        """What only the critic sees: the task's true (K, tau, theta/tau)."""
        return np.stack([self.K, self.tau, self.theta / self.tau], axis=1)

    def _setpoint_window(self) -> np.ndarray:
        """(B, inner) setpoints of the coming RL period, applying the moves that fall in it."""
        c, rng, k0 = self.cond, self.rng, self.k
        ks = k0 + np.arange(self.inner)

        def segment(rows, k):
            frac = np.clip((k - self.sp_start[rows, None] + 1) / self.sp_len[rows, None], 0.0, 1.0)
            return self.sp_from[rows, None] + (self.sp_to - self.sp_from)[rows, None] * frac

        all_rows = np.arange(self.n)
        win = segment(all_rows, ks[None])
        while True:
            rows = np.flatnonzero(self.sp_next < k0 + self.inner)
            if rows.size == 0:
                return win
            at = self.sp_next[rows]
            level = segment(rows, (at - 1)[:, None])[:, 0]
            amp = c["sp_amp"][rows]
            rand = c["sp_random"][rows]
            sign = -np.sign(level)
            if np.any(level == 0):
                sign = np.where(level == 0, rng.choice([-1.0, 1.0], rows.size), sign)
            if np.any(rand):
                sign = np.where(rand & (rng.random(rows.size) < 0.3), -sign, sign)
            # draw only for random moves: the toggle alone uses no random numbers (v2's MDP)
            size = rng.uniform(0.3, 1.0, rows.size) if np.any(rand) else 1.0
            new = np.where(rand, sign * amp * size, np.where(level == 0, sign * amp, -level))
            self.sp_from[rows], self.sp_to[rows] = level, new
            self.sp_start[rows] = at
            self.excited[rows] = True
            if np.any(rand):
                ramp = rand & (rng.random(rows.size) < c["sp_ramp"][rows])
                ramp_len = np.rint(rng.uniform(0.5, 3.0, rows.size) * self.inner)
                self.sp_len[rows] = np.where(ramp, ramp_len, 1)
                self.sp_next[rows] = at + np.where(rand, self._hold(rows), self.sp_every[rows])
            else:
                self.sp_next[rows] = at + self.sp_every[rows]
            cols = ks[None] >= at[:, None]
            win[rows] = np.where(cols, segment(rows, ks[None]), win[rows])

    def _load_window(self) -> np.ndarray:
        """(B, inner) load-step levels of the coming RL period (the walk is added per sample)."""
        c, rng, k0 = self.cond, self.rng, self.k
        ks = k0 + np.arange(self.inner)
        win = np.repeat(self.load[:, None], self.inner, axis=1)
        every = np.rint(c["load_every"] / self.cfg.dt)
        while True:
            rows = np.flatnonzero((c["load_step"] > 0) & (self.load_next < k0 + self.inner))
            if rows.size == 0:
                return win
            L = c["load_step"][rows]
            periodic = c["load_periodic"][rows]
            new = np.where(periodic, np.where(self.load[rows] == 0, L, 0.0),
                           L * rng.uniform(-1.0, 1.0, rows.size))  # fmt: skip
            self.load[rows] = new
            at = self.load_next[rows]
            win[rows] = np.where(ks[None] >= at[:, None], new[:, None], win[rows])
            gap = np.where(periodic, 1.0, np.maximum(rng.exponential(1.0, rows.size), 0.05))
            self.load_next[rows] = at + gap * every[rows]

    def step(self, delta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Apply [dkp, dki], run one RL period; return (obs, cost, tracking MSE)."""
        cfg, c = self.cfg, self.cond
        kp = np.clip(self.pi.kp + delta[:, 0], GAIN_FLOOR, cfg.gain_max)
        ki = np.clip(self.pi.ki + delta[:, 1], GAIN_FLOOR, cfg.gain_max)
        applied = np.stack([kp - self.pi.kp, ki - self.pi.ki], axis=1)
        self.pi.set_gains(kp, ki)
        plant, target, pi = self.plant, self.target, self.pi
        sq = np.zeros(self.n)
        sp = self._setpoint_window()
        sample_loop.track_moves_over(self, sp)
        r = ramp_rule(sp, self.sp_last, self.sp_way, self.sp_since)
        self.sp_last, self.sp_way, self.sp_since = r.last, r.way, r.since
        for name, hit in (("ramp_k", r.continues), ("ramp_from_k", r.changed & ~r.continues)):
            last = self.k + self.inner - 1 - np.argmax(hit[:, ::-1], axis=1)
            setattr(self, name, np.where(hit.any(axis=1), last, getattr(self, name)))
        loads = bool(np.any(c["load_step"] > 0) or np.any(c["load_walk"] > 0))
        load = self._load_window() if loads else None
        noisy = bool(np.any(c["noise"] > 0))
        if noisy:  # white: a = 0; low-pass (time constant noise_tf tau): same stationary sigma
            tf = c["noise_tf"] * self.tau
            a_n = np.where(tf > 0, np.exp(-cfg.dt / np.where(tf > 0, tf, 1.0)), 0.0)
            w_n = (
                self.rng.standard_normal((self.n, self.inner))
                * (c["noise"] * np.sqrt(1 - a_n**2))[:, None]
            )
        walking = bool(np.any(c["load_walk"] > 0))
        if walking:  # OU walk, time constant 20, stationary std load_walk
            a_w = np.exp(-cfg.dt / 20.0)
            w_w = (
                self.rng.standard_normal((self.n, self.inner))
                * (c["load_walk"] * np.sqrt(1 - a_w**2))[:, None]
            )
        due = self.k + self.inner
        total = count = np.zeros(self.n)
        if sample_loop.KERNEL and not np.any(plant.noise_std):
            noise = (a_n, w_n) if noisy else None
            walk = (a_w, w_w) if walking else None
            total, count = sample_loop.run(self, sp, sq, load, noise, walk)
        else:  # the definition: plant_sim's classes, one sample at a time
            for j in range(self.inner):
                self.sp = sp[:, j]
                err = target.x - plant.x
                sq += np.minimum(err * err, cfg.err_cap)
                y = plant.measure()
                if noisy:
                    self.noise_state = a_n * self.noise_state + w_n[:, j]
                    y = y + self.noise_state
                e = self.sp - y
                total, count = error_window(e, self.k, due, self.inner, total, count, due)
                self.int_e += e * cfg.dt
                u = pi.step(e)
                if loads:
                    if walking:
                        self.load_walk = a_w * self.load_walk + w_w[:, j]
                    plant.step(u, load[:, j] + self.load_walk)
                else:
                    plant.step(u)
                target.step(self.sp)
                self.k += 1
        y = plant.measure()
        if noisy:
            step = c["noise"] * np.sqrt(1 - a_n**2) * self.rng.standard_normal(self.n)
            self.noise_state = a_n * self.noise_state + step
            y = y + self.noise_state
        self.e = window_error(total, count, self.sp - y, due, self.inner, self.move_k)
        mse = sq / self.inner
        cost = mse + cfg.beta_kp * np.abs(applied[:, 0]) + cfg.beta_ki * np.abs(applied[:, 1])
        self.t += 1
        self._apply_drift()
        return self.observe(), cost, mse
