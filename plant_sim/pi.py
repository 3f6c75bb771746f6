"""Vectorised discrete PI controller: the one controller used by training, the service and the demo.

Form (parallel, position form with a separately accumulated integral term)::

    I[k] = I[k-1] + ki * e[k] * dt          (backward Euler)
    u[k] = bias + kp * e[k] + I[k]          (then clamped to [u_min, u_max])

``kp = Kc`` and ``ki = Kc / tau_I`` in terms of the standard form Kc (1 + 1/(tau_I s)).
Units: ``kp`` in output units per error unit, ``ki`` in output units per (error unit x
time unit), ``dt`` in the same time unit as ``ki``.

Bumpless gain changes, as in DCS PID blocks: because the integral *term* I (not the
integral of the error) is the state, changing ``ki`` never moves the output; changing
``kp`` moves I by ``-(kp_new - kp_old) * e_last`` so the output at the last error is
unchanged too. The tuner therefore can change gains while the loop runs.

Anti-windup by clamping (conditional integration): when the output is saturated and the
error would drive it further into saturation, the integral advances only as far as the
limit (never past it, never back): frozen where it stood, a loop whose last increment
would have crossed the limit settled short of it for good, flagged saturated below it.
A gain change while saturated is bumpless in the same sense: it may carry the integral
to the limit, not past it (kept past, the change stored windup: a tank 4 cm over its
setpoint after a valve had held its limit).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike


class PIBatch:
    """N PI controllers in lock-step.

    Parameters
    ----------
    kp, ki:
        Proportional and integral gains, scalars or arrays of length ``n``.
    dt:
        Controller sample interval.
    bias:
        Output at zero proportional and integral action (the operating point).
    u_min, u_max:
        Optional output limits; ``None`` means unlimited.
    """

    def __init__(
        self,
        kp: ArrayLike,
        ki: ArrayLike,
        *,
        dt: float,
        n: int | None = None,
        bias: ArrayLike = 0.0,
        u_min: float | None = None,
        u_max: float | None = None,
    ) -> None:
        if n is None:
            n = max(np.size(kp), np.size(ki))
        self.n = int(n)
        self.dt = float(dt)
        self.kp = np.broadcast_to(np.asarray(kp, dtype=np.float64), (self.n,)).copy()
        self.ki = np.broadcast_to(np.asarray(ki, dtype=np.float64), (self.n,)).copy()
        self.bias = np.broadcast_to(np.asarray(bias, dtype=np.float64), (self.n,)).copy()
        self.u_min = -np.inf if u_min is None else float(u_min)
        self.u_max = np.inf if u_max is None else float(u_max)
        self.integral = np.zeros(self.n)
        self.e_last = np.zeros(self.n)
        self.saturated = np.zeros(self.n, dtype=bool)

    def set_gains(self, kp: ArrayLike | None = None, ki: ArrayLike | None = None) -> None:
        """Change gains without bumping the output (see module docstring)."""
        if kp is not None:
            kp = np.broadcast_to(np.asarray(kp, dtype=np.float64), (self.n,))
            bumpless = self.integral - (kp - self.kp) * self.e_last
            self.kp = kp.copy()
            self.integral = self._limited(bumpless, self.e_last, self.integral)
        if ki is not None:
            self.ki = np.broadcast_to(np.asarray(ki, dtype=np.float64), (self.n,)).copy()

    def initialise(self, u0: ArrayLike, e0: ArrayLike = 0.0) -> None:
        """Start in steady state: output ``u0`` at error ``e0`` (bumpless switch to auto)."""
        e0 = np.broadcast_to(np.asarray(e0, dtype=np.float64), (self.n,))
        self.e_last = e0.copy()
        self.integral = np.asarray(u0, dtype=np.float64) - self.bias - self.kp * e0

    def output(self) -> np.ndarray:
        """The output the controller would give for the last error (after clamping)."""
        return np.clip(self.bias + self.kp * self.e_last + self.integral, self.u_min, self.u_max)

    def step(self, e: ArrayLike) -> np.ndarray:
        """Advance one sample with error ``e`` (setpoint minus measurement); return ``u``."""
        e = np.asarray(e, dtype=np.float64)
        self.integral = self._limited(self.integral + self.ki * e * self.dt, e, self.integral)
        raw = self.bias + self.kp * e + self.integral
        self.saturated = (raw >= self.u_max) | (raw <= self.u_min)
        self.e_last = e
        return np.clip(raw, self.u_min, self.u_max)

    def _limited(self, integral: np.ndarray, e: np.ndarray, before: np.ndarray) -> np.ndarray:
        """``integral``, moved from ``before``, as far as it may go: not past the
        integral that puts the output at error ``e`` on a limit, unless ``before`` was
        already past it (then no further than ``before``). Moving back from a limit is
        always allowed."""
        on_high = self.u_max - self.bias - self.kp * e
        on_low = self.u_min - self.bias - self.kp * e
        integral = np.minimum(integral, np.maximum(before, on_high))
        return np.maximum(integral, np.minimum(before, on_low))
