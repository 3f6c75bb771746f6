"""Batch simulator of first-order-plus-dead-time (FOPTD) plants.

Each of the N plants is

    G(s) = K exp(-theta s) / (tau s + 1)

discretised exactly under a zero-order hold at the control interval ``dt``:

    x[k+1] = a x[k] + K (1 - a) u[k - d],     a = exp(-dt / tau),   d = round(theta / dt)

so a piecewise-constant input gives the continuous-time response at the sample
instants, and the dead time is exact to one ``dt``. Optionally (``tau2`` > 0) a second
lag 1/(tau2 s + 1) follows the first (a second-order plus dead-time plant), advanced
as z[k+1] = a2 z[k] + (1 - a2) x[k+1], a2 = exp(-dt / tau2), accurate to one ``dt``;
``tau2`` = 0 is the plain FOPTD plant, bit for bit. The delay line is a ring buffer of
past inputs shared by all plants (each plant reads it at its own lag).

Units are whatever the caller uses consistently: time in the same unit as ``tau``,
``theta`` and ``dt`` (the paper's dimensionless "time units" in training), output in
units of ``K`` times the input's.

Conventions of :meth:`FOPTDBatch.step`: ``y = output()`` is the output at sample k
(before the input of sample k acts); ``step(u)`` applies ``u`` over [k dt, (k+1) dt)
and advances to k+1. Input (load) disturbances enter with the input, before the
dead time; measurement noise is added only to what :meth:`measure` returns.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike


def _as_batch(value: ArrayLike, n: int, name: str) -> np.ndarray:
    arr = np.broadcast_to(np.asarray(value, dtype=np.float64), (n,)).copy()
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite")
    return arr


class FOPTDBatch:
    """N FOPTD plants simulated in lock-step, vectorised with numpy.

    Parameters
    ----------
    K, tau, theta:
        Process gain, time constant (> 0) and dead time (>= 0); scalars or arrays of
        length ``n``.
    dt:
        Control interval (same time unit as ``tau``). Default 0.01.
    n:
        Number of plants; inferred from the parameter arrays when omitted.
    max_theta:
        Largest dead time the ring buffer must hold, so that ``theta`` can later be
        raised with :meth:`set_params`. Defaults to the largest initial ``theta``.
    noise_std:
        Standard deviation of white measurement noise added by :meth:`measure`.
    seed:
        Seed (or ``numpy.random.Generator``) for the measurement noise.
    tau2:
        Time constant of an optional second lag in series (0: none, the default).
    """

    def __init__(
        self,
        K: ArrayLike,
        tau: ArrayLike,
        theta: ArrayLike = 0.0,
        *,
        dt: float = 0.01,
        n: int | None = None,
        max_theta: float | None = None,
        noise_std: ArrayLike = 0.0,
        seed: int | np.random.Generator | None = None,
        tau2: ArrayLike = 0.0,
    ) -> None:
        if dt <= 0:
            raise ValueError("dt must be positive")
        if n is None:
            n = max(np.size(K), np.size(tau), np.size(theta))
        self.n = int(n)
        self.dt = float(dt)
        theta_arr = _as_batch(theta, self.n, "theta")
        top = float(theta_arr.max(initial=0.0)) if max_theta is None else float(max_theta)
        self._buf = np.zeros((self.n, int(round(top / self.dt)) + 1))
        self._ptr = 0
        self._rows = np.arange(self.n)
        self.x = np.zeros(self.n)
        self.x1 = self.x  # state of the first lag (the output unless a second lag follows)
        self.tau2 = _as_batch(tau2, self.n, "tau2")
        if np.any(self.tau2 < 0):
            raise ValueError("tau2 must be non-negative")
        self.lag2 = bool(np.any(self.tau2 > 0))
        self.a2 = np.exp(-self.dt / np.where(self.tau2 > 0, self.tau2, 1.0))
        self.noise_std = _as_batch(noise_std, self.n, "noise_std")
        self.rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
        self.set_params(K=K, tau=tau, theta=theta_arr)

    # -- parameters -------------------------------------------------------------------
    def set_params(
        self,
        K: ArrayLike | None = None,
        tau: ArrayLike | None = None,
        theta: ArrayLike | None = None,
    ) -> None:
        """Change plant parameters in place (e.g. a tau ramp or a K step mid-run).

        The state ``x`` is kept, so the output is continuous across the change.
        """
        if K is not None:
            self.K = _as_batch(K, self.n, "K")
        if tau is not None:
            tau = _as_batch(tau, self.n, "tau")
            if np.any(tau <= 0):
                raise ValueError("tau must be positive")
            self.tau = tau
            self.a = np.exp(-self.dt / self.tau)
        if theta is not None:
            theta = _as_batch(theta, self.n, "theta")
            if np.any(theta < 0):
                raise ValueError("theta must be non-negative")
            delay = np.rint(theta / self.dt).astype(np.int64)
            if np.any(delay >= self._buf.shape[1]):
                raise ValueError("theta exceeds max_theta given at construction")
            self.theta = theta
            self.delay = delay
        self.b = self.K * (1.0 - self.a)

    # -- state ------------------------------------------------------------------------
    def reset(self, y0: ArrayLike = 0.0) -> None:
        """Put every plant at steady state with output ``y0`` (input y0/K held forever)."""
        y0 = _as_batch(y0, self.n, "y0")
        self.x = y0.copy()
        self.x1 = self.x.copy() if self.lag2 else self.x
        self._buf[:] = (y0 / self.K)[:, None]

    def output(self) -> np.ndarray:
        """Noise-free output at the current sample."""
        return self.x

    def measure(self) -> np.ndarray:
        """Output at the current sample plus measurement noise, if configured."""
        if not np.any(self.noise_std):
            return self.x.copy()
        return self.x + self.noise_std * self.rng.standard_normal(self.n)

    def step(self, u: ArrayLike, disturbance: ArrayLike | None = None) -> np.ndarray:
        """Hold ``u`` (plus an input load disturbance) for one ``dt``; return the new output."""
        u = np.asarray(u, dtype=np.float64)
        if disturbance is not None:
            u = u + disturbance
        self._buf[:, self._ptr] = u
        delayed = self._buf[self._rows, (self._ptr - self.delay) % self._buf.shape[1]]
        self._ptr = (self._ptr + 1) % self._buf.shape[1]
        if not self.lag2:
            self.x = self.a * self.x + self.b * delayed
            self.x1 = self.x
            return self.x
        self.x1 = self.a * self.x1 + self.b * delayed
        lagged = self.a2 * self.x + (1.0 - self.a2) * self.x1
        self.x = np.where(self.tau2 > 0, lagged, self.x1)
        return self.x


def step_response(K: float, tau: float, theta: float, t: ArrayLike) -> np.ndarray:
    """Closed-form unit step response of K exp(-theta s)/(tau s + 1) at times ``t``."""
    t = np.asarray(t, dtype=np.float64)
    return np.where(t >= theta, K * (1.0 - np.exp(-(t - theta) / tau)), 0.0)
