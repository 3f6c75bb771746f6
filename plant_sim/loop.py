"""Closed-loop FOPTD simulation, the paper's target trajectory and its step-test metric.

The target trajectory (paper eq. 9) is the setpoint filtered by

    exp(-theta s) / (tau_cl s + 1),     tau_cl = 2 tau by default,

which is itself an FOPTD system with unit gain, so it is simulated with the same exact
ZOH discretisation as the plant (a piecewise-constant setpoint is exact).

Sample alignment: at sample k the controller sees y[k], outputs u[k], and the plant
and the target filter both advance with the inputs of sample k. ``y[k]`` and
``target[k]`` are therefore comparable sample by sample.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from plant_sim.foptd import FOPTDBatch
from plant_sim.pi import PIBatch

STEP_TEST_HORIZON = 11.0
"""Length of the paper's step test, in time units (section 5.1)."""


def target_filter(
    tau: ArrayLike,
    theta: ArrayLike,
    *,
    dt: float,
    tau_cl: ArrayLike | None = None,
    n: int | None = None,
    max_theta: float | None = None,
) -> FOPTDBatch:
    """The paper's target-trajectory filter exp(-theta s)/(tau_cl s + 1), tau_cl = 2 tau."""
    tau_cl = 2.0 * np.asarray(tau, dtype=np.float64) if tau_cl is None else tau_cl
    return FOPTDBatch(1.0, tau_cl, theta, dt=dt, n=n, max_theta=max_theta)


@dataclass
class LoopTrace:
    """Sampled closed-loop signals, each of shape (N, n_steps)."""

    y: np.ndarray
    target: np.ndarray
    u: np.ndarray
    sp: np.ndarray

    @property
    def e(self) -> np.ndarray:
        return self.sp - self.y


def run_closed_loop(plant: FOPTDBatch, pi: PIBatch, target: FOPTDBatch, sp: ArrayLike) -> LoopTrace:
    """Run plant, PI and target filter together over a setpoint schedule.

    ``sp`` has shape (n_steps,) (the same schedule for all loops) or (N, n_steps).
    The controller acts on the *measured* output (noise included); traces hold the
    noise-free output.
    """
    sp = np.asarray(sp, dtype=np.float64)
    sp = np.broadcast_to(sp, (plant.n, sp.shape[-1]))
    n_steps = sp.shape[1]
    ys, rs, us = (np.empty((plant.n, n_steps)) for _ in range(3))
    with np.errstate(over="ignore", invalid="ignore"):  # unstable trials overflow to inf
        for k in range(n_steps):
            ys[:, k] = plant.output()
            rs[:, k] = target.output()
            us[:, k] = u = pi.step(sp[:, k] - plant.measure())
            plant.step(u)
            target.step(sp[:, k])
    return LoopTrace(y=ys, target=rs, u=us, sp=np.array(sp))


def effective_foptd(tau, theta, tau2=0.0) -> tuple[np.ndarray, np.ndarray]:
    """Skogestad's half rule: tau + tau2/2, theta + tau2/2 (the FOPTD 'true model' of a
    second-order plant; its target is exp(-theta_eff s)/(2 tau_eff s + 1))."""
    tau, theta, tau2 = (np.asarray(v, dtype=np.float64) for v in (tau, theta, tau2))
    return tau + tau2 / 2, theta + tau2 / 2


def step_test(
    K: ArrayLike,
    tau: ArrayLike,
    theta: ArrayLike,
    kp: ArrayLike,
    ki: ArrayLike,
    *,
    dt: float = 0.01,
    horizon: float = STEP_TEST_HORIZON,
    tau_cl: ArrayLike | None = None,
    tau2: ArrayLike = 0.0,
) -> LoopTrace:
    """The paper's step test: steady state at -1, setpoint step to +1 at t = 0.

    ``tau2`` > 0 adds a second lag to the plant (:class:`FOPTDBatch`); the target is then
    that of its half-rule FOPTD model (:func:`effective_foptd`). ``tau2`` = 0 is the
    paper's test, bit for bit."""
    K, tau, theta, kp, ki, tau2 = np.broadcast_arrays(
        *(np.asarray(v, np.float64) for v in (K, tau, theta, kp, ki, tau2))
    )
    K, tau, theta, kp, ki, tau2 = (np.atleast_1d(v) for v in (K, tau, theta, kp, ki, tau2))
    n = K.size
    plant = FOPTDBatch(K, tau, theta, dt=dt, n=n, tau2=tau2)
    plant.reset(-1.0)
    tau_e, theta_e = effective_foptd(tau, theta, tau2)
    target = target_filter(tau_e, theta_e, dt=dt, tau_cl=tau_cl, n=n)
    target.reset(-1.0)
    pi = PIBatch(kp, ki, dt=dt, n=n)
    pi.initialise(-1.0 / K)
    return run_closed_loop(plant, pi, target, np.ones(int(round(horizon / dt))))


def step_test_mse(
    K: ArrayLike, tau: ArrayLike, theta: ArrayLike, kp: ArrayLike, ki: ArrayLike, **options
) -> np.ndarray:
    """Mean squared deviation of the output from the target over the step test (paper 5.1).

    Arguments and ``options`` (dt, horizon, tau_cl, tau2) as for :func:`step_test`.
    Vectorised: all arguments broadcast to N loops; returns shape (N,). Unstable loops
    give large (possibly ``inf``) values, never NaN.
    """
    trace = step_test(K, tau, theta, kp, ki, **options)
    with np.errstate(over="ignore", invalid="ignore"):
        mse = np.mean((trace.y - trace.target) ** 2, axis=1)
    return np.where(np.isfinite(mse), mse, np.inf)


def step_test_mse_filtered(
    K: ArrayLike, tau: ArrayLike, theta: ArrayLike, kp: ArrayLike, ki: ArrayLike, dt: float = 0.01
) -> np.ndarray:
    """:func:`step_test_mse` of FOPTD plants (no second lag, default horizon and target),
    computed as a linear filter instead of a simulation: the same recursion, so the same
    numbers to rounding (``tests/test_plant_sim.py``), but without the simulation's
    per-time-step Python cost (~30 us a step, 1,100 steps, whatever the number of loops:
    30 ms for a single loop). What the engine's model check calls for every pass that
    steps a loop with a model (:mod:`service.engine.model_check`).

    The closed loop of the exact ZOH plant ``b z^-(d+1) / (1 - a z^-1)`` (d = theta/dt
    rounded) and the backward-Euler PI ``kp + ki dt / (1 - z^-1)`` from steady state at -1
    is ``N / (D + N)`` on the setpoint step of 2, with ``N = b z^-(d+1) (kp + ki dt - kp
    z^-1)`` and ``D = (1 - a z^-1)(1 - z^-1)``, filtered per loop
    (:func:`scipy.signal.lfilter`); the target trajectory is the exact step response of
    its own ZOH filter. Unstable loops give ``inf``, never NaN. Shapes: arguments
    broadcast to (N,); returns (N,)."""
    from scipy.signal import lfilter

    K, tau, theta, kp, ki = (
        np.atleast_1d(v).astype(np.float64)
        for v in np.broadcast_arrays(*(np.asarray(v, np.float64) for v in (K, tau, theta, kp, ki)))
    )
    steps = int(round(STEP_TEST_HORIZON / dt))
    k = np.arange(steps)
    a = np.exp(-dt / tau)
    b = K * (1.0 - a)
    d = np.rint(theta / dt).astype(np.int64)
    # the target: exp(-theta s)/(2 tau s + 1) under the same ZOH, from -1 to +1
    a_cl = np.exp(-dt / (2.0 * tau))
    since = k[None, :] - d[:, None]
    with np.errstate(over="ignore", under="ignore"):
        target = np.where(since >= 1, 1.0 - 2.0 * a_cl[:, None] ** np.maximum(since, 0), -1.0)
    out = np.empty(K.size)
    step = np.full(steps, 2.0)
    with np.errstate(over="ignore", invalid="ignore"):
        for i in range(K.size):
            num = np.zeros(d[i] + 3)
            num[d[i] + 1 :] = b[i] * (kp[i] + ki[i] * dt), -b[i] * kp[i]
            den = num.copy()
            den[:3] += (1.0, -(1.0 + a[i]), a[i])
            y = lfilter(num, den, step) - 1.0
            out[i] = np.mean((y - target[i]) ** 2)
    return np.where(np.isfinite(out), out, np.inf)
