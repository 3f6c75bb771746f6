"""Reference PI tunings for FOPTD plants K exp(-theta s)/(tau s + 1).

All functions return ``(Kc, tau_I)`` of the standard form Kc (1 + 1/(tau_I s)); use
:func:`to_parallel` for the ``(kp, ki) = (Kc, Kc/tau_I)`` of :mod:`plant_sim.pi`.
Inputs may be numpy arrays (vectorised).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy.optimize import minimize

from plant_sim.loop import step_test_mse


def to_parallel(Kc: ArrayLike, tau_I: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """(Kc, tau_I) -> (kp, ki)."""
    Kc = np.asarray(Kc, dtype=np.float64)
    return Kc, Kc / np.asarray(tau_I, dtype=np.float64)


def simc(K: ArrayLike, tau: ArrayLike, theta: ArrayLike, tau_c: ArrayLike):
    """Original SIMC (Skogestad 2003).

    Kc = tau/(K(tau_c+theta)), tau_I = min(tau, 4(tau_c+theta)).
    """
    K, tau, theta, tau_c = (np.asarray(v, dtype=np.float64) for v in (K, tau, theta, tau_c))
    return tau / (K * (tau_c + theta)), np.minimum(tau, 4.0 * (tau_c + theta))


def simc_improved(K: ArrayLike, tau: ArrayLike, theta: ArrayLike, tau_c: ArrayLike):
    """Improved SIMC (Grimholt & Skogestad 2012), PI for FOPTD: tau -> tau + theta/3.

    Kc = (tau + theta/3)/(K(tau_c+theta)), tau_I = min(tau + theta/3, 4(tau_c+theta)).
    """
    K, tau, theta, tau_c = (np.asarray(v, dtype=np.float64) for v in (K, tau, theta, tau_c))
    tau1 = tau + theta / 3.0
    return tau1 / (K * (tau_c + theta)), np.minimum(tau1, 4.0 * (tau_c + theta))


def simc_paper(K: ArrayLike, tau: ArrayLike, theta: ArrayLike):
    """The SIMC variant the paper compares against (its Table 2).

    Kc = tau/(K(2 tau + theta)) (original SIMC with tau_c = 2 tau, the target's
    closed-loop time constant) and tau_I = tau + theta/3 (the improved rule).
    """
    K, tau, theta = (np.asarray(v, dtype=np.float64) for v in (K, tau, theta))
    return tau / (K * (2.0 * tau + theta)), tau + theta / 3.0


def oracle(
    K: float, tau: float, theta: float, *, dt: float = 0.01, tau_cl: float | None = None
) -> tuple[float, float, float]:
    """Best fixed PI for the step-test metric, by Nelder-Mead on (log kp, log ki).

    Starts from :func:`simc_paper`. Returns ``(kp, ki, mse)``.
    """
    kp0, ki0 = to_parallel(*simc_paper(K, tau, theta))

    def cost(z: np.ndarray) -> float:
        kp, ki = np.exp(z)
        return float(step_test_mse(K, tau, theta, kp, ki, dt=dt, tau_cl=tau_cl)[0])

    res = minimize(
        cost,
        np.log([float(kp0), float(ki0)]),
        method="Nelder-Mead",
        options={"xatol": 1e-4, "fatol": 1e-10, "maxiter": 400},
    )
    kp, ki = np.exp(res.x)
    return float(kp), float(ki), float(res.fun)
