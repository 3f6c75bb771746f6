"""The agent's warm start on an identified model: when a model's tuning is put in force
(:data:`service.engine.first_tuning.WARMED`), the shipped agent first tunes the *model*
offline from those gains, and the loop's agent continues from where that run ends (its
hidden state and its error integral; the gains in force stay the model's tuning).

Why: stepped from a fresh (zero) hidden state, the agent moves the gains 14-50 % a step
while it works out the plant from scratch, and on a real loop (noise, irregular
setpoint moves, the excitation gate) it often does not come back: after the model's
tuning had been verified, the two-tank demo without a hint ended at 7x the hinted run's
MSE, and issue 13's bar loops at up to 3x the true-hint result (docs/identification.md,
Warm start). Deep in an episode it moves them 0-2 % a step. The warm run puts it there.

The run is the paper's protocol in agent units (the setpoint toggling between +1 and -1
every :data:`SP_PERIOD`, plant at rest at 0, no noise), the plant the model as the
loop's scaling shows it (:func:`service.engine.box.apparent`), the agent's observation
computed as the engine computes it (the error window of :func:`service.units.error_window`,
:func:`service.units.window_error`; the toggle is a move of ``PAPER_MOVE``, so the
setpoint-move gain is 1) and the loop's own forgetting factor. It is checked in the tests
against training's environment (service.learn.env, which the engine may not import):
same observations, same states. Vectorised over every loop warmed in one pass.
"""

from __future__ import annotations

import numpy as np

from plant_sim.foptd import FOPTDBatch
from plant_sim.pi import PIBatch
from service.agent.model import GAIN_FLOOR
from service.units import AGENT_GAIN_RANGE, RL_STEP_AGENT_UNITS, error_window, window_error

STEPS = 60
"""RL steps of the warm run: where the agent's gains on the model have settled (moves
under 1 % a step from about step 30 on the model's SIMC tuning, theta/tau 0-1)."""
DT = 0.05
"""Controller sample time of the warm run (agent units): 5x training's 0.01 (the cost is
the number of samples); the bar's loops are sampled at 0.01-0.1 agent units."""
SP_PERIOD = 11.0
"""The paper's setpoint period (agent units; training's ``EnvConfig.sp_period``)."""
U_LIMIT = 100.0
"""Controller output limit (training's ``EnvConfig.u_limit``)."""


def act(tb, obs: np.ndarray, state: np.ndarray, forgetting: np.ndarray) -> np.ndarray:
    """The agent's step as :func:`service.engine.stepping.step` takes it (``state``,
    C-contiguous float32 (n, layers, hidden), updated in place); returns delta (n, 2)."""
    if tb._policy is not None:
        return tb._policy.step_inplace(obs, state, forgetting)
    delta, new = tb.agent.act(obs, state, forgetting)
    state[...] = new
    return delta


class WarmRun:
    """The warm run of a batch of loops: the agent on models (K, tau, theta) from gains
    (kp, ki), all agent units, arrays (n,), for ``steps`` RL steps. Resumable:
    :meth:`advance` takes it a few RL steps at a time (the tuner spreads it over passes of
    its worker, so that the samples never wait behind a whole run: 0.17-0.4 s on this box
    however few loops it holds); split or whole, the same arithmetic, the same result;
    :meth:`result` then holds the hidden state and the observation's error integral."""

    def __init__(
        self, tb, K, tau, theta, kp, ki, forgetting, *, steps: int = STEPS, dt: float = DT
    ) -> None:
        K, tau, theta, kp, ki = (np.asarray(v, np.float64) for v in (K, tau, theta, kp, ki))
        n = K.size
        self.tb, self.steps, self.k, self.dt = tb, steps, 0, dt
        self.forgetting = np.broadcast_to(np.asarray(forgetting, np.float64), (n,)).copy()
        self.inner = int(round(RL_STEP_AGENT_UNITS / dt))
        self.every = int(round(SP_PERIOD / dt))
        self.plant = FOPTDBatch(K, tau, theta, dt=dt)
        self.plant.reset(0.0)
        self.pi = PIBatch(kp, ki, dt=dt, n=n, u_min=-U_LIMIT, u_max=U_LIMIT)
        self.pi.initialise(np.zeros(n))
        self.state = np.zeros((n, tb.agent.cfg.layers, tb.agent.cfg.hidden), np.float32)
        # the samples of an RL period inside the observation window (sample j at j, due inner)
        _, inside = error_window(0.0, np.arange(self.inner), self.inner, self.inner, 0.0, 0.0,
                                 self.inner)  # fmt: skip
        self.window = inside.astype(bool)
        self.sp, self.int_e = 1.0, np.zeros(n)
        self.e_obs = self.sp - self.plant.measure()
        self.es = np.empty((n, self.inner))

    @property
    def done(self) -> bool:
        return self.k >= self.steps

    def advance(self, steps: int) -> bool:
        """At most ``steps`` more RL steps; whether the run is done."""
        plant, pi, inner = self.plant, self.pi, self.inner
        with np.errstate(over="ignore", invalid="ignore"):  # a diverging model stays finite-ish
            for k in range(self.k, min(self.k + steps, self.steps)):
                obs = np.column_stack([pi.kp, pi.ki, self.e_obs, self.int_e])
                delta = act(self.tb, obs, self.state, self.forgetting)
                pi.set_gains(
                    np.clip(pi.kp + delta[:, 0], GAIN_FLOOR, AGENT_GAIN_RANGE[1]),
                    np.clip(pi.ki + delta[:, 1], GAIN_FLOOR, AGENT_GAIN_RANGE[1]),
                )
                for j in range(inner):
                    if (k * inner + j) % self.every == 0 and k + j:
                        self.sp = -self.sp
                    self.es[:, j] = e = self.sp - plant.measure()
                    self.int_e += e * self.dt
                    plant.step(pi.step(e))
                total = self.es[:, self.window].sum(axis=1)
                self.e_obs = window_error(
                    total, self.window.sum(), self.sp - plant.measure(), inner, inner, -np.inf
                )
                self.k = k + 1
        return self.done

    def result(self) -> tuple[np.ndarray, np.ndarray]:
        """(hidden state (n, layers, hidden) float32, the observation's error integral
        int_e (n,)) where the run is."""
        return self.state, self.int_e
