"""The step-test oracle of the training tasks, as a table shipped with the agent.

The best fixed PI gains for a simulated task (:func:`plant_sim.tunings.oracle`, a
Nelder-Mead search on the step-test MSE) are offline-only knowledge, like the critic's
privileged inputs: training imitates them and the evaluation starts from them.
"""

from __future__ import annotations

import json

import numpy as np

from plant_sim.loop import effective_foptd, step_test_mse
from plant_sim.tunings import oracle
from service.agent.model import MODELS_DIR

ORACLE_RATIOS = np.linspace(0.0, 1.0, 11)
ORACLE_TABLE = MODELS_DIR / "oracle_table.json"


def compute_oracle_table() -> np.ndarray:
    """Oracle gains normalised by the plant: (len(ORACLE_RATIOS), 2) of [kp K, ki K tau].

    The step-test optimum scales as kp* = f(theta/tau)/K and ki* = g(theta/tau)/(K tau)
    to within about 1% over the training box (checked in the tests), so a 1-D table in
    theta/tau, computed at tau = 0.5, K = 1, serves every task. About 30 s; the result
    ships as ``service/models/oracle_table.json``.
    """
    rows = []
    for r in ORACLE_RATIOS:
        kp, ki, _ = oracle(1.0, 0.5, 0.5 * r)
        rows.append([kp, ki * 0.5])
    return np.array(rows)


def oracle_table() -> np.ndarray:
    """The shipped oracle table (computed and written if missing)."""
    if not ORACLE_TABLE.exists():
        ORACLE_TABLE.write_text(json.dumps(compute_oracle_table().tolist()))
    return np.array(json.loads(ORACLE_TABLE.read_text()))


def oracle_gains(table: np.ndarray, K, tau, theta) -> np.ndarray:
    """(B, 2) oracle [kp, ki] for each task, interpolated from :func:`oracle_table`."""
    r = np.clip(theta / tau, 0.0, 1.0)
    f = np.interp(r, ORACLE_RATIOS, table[:, 0])
    g = np.interp(r, ORACLE_RATIOS, table[:, 1])
    return np.stack([f / K, g / (K * tau)], axis=1)


# -- v3: the widened training box (theta/tau up to 3, tau off by 3x, second-order plants) --
ORACLE3_RATIOS = np.array(
    [0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0, 1.25, 1.5, 2.0, 2.5, 3.0]
)
ORACLE3_TAUS = np.array([1 / 12, 1 / 6, 0.25, 0.5, 1.0, 2.0, 3.0])
ORACLE3_LAG2 = np.array([0.0, 0.1, 0.25, 0.5])
ORACLE3_TABLE = MODELS_DIR / "oracle_table_v3.json"


def batch_oracle(K, tau, theta, tau2=0.0, *, tol: float = 0.003, max_iter: int = 80):
    """Best fixed PI by step-test MSE for many plants at once: a compass search in
    (log kp, log ki) from SIMC (half-rule model), 8 directions, the step halved where
    no direction improves, until it is below ``tol`` (log units). Returns (kp, ki, mse)."""
    from plant_sim.tunings import simc_paper, to_parallel

    K, tau, theta, tau2 = (
        np.atleast_1d(np.asarray(v, np.float64)) for v in np.broadcast_arrays(K, tau, theta, tau2)
    )
    n = K.size
    z = np.log(np.stack(to_parallel(*simc_paper(K, *effective_foptd(tau, theta, tau2))), axis=1))
    best = step_test_mse(K, tau, theta, *np.exp(z).T, tau2=tau2)
    step = np.full(n, 0.4)
    dirs = np.array([[1, 0], [-1, 0], [0, 1], [0, -1], [1, 1], [-1, -1], [1, -1], [-1, 1]], float)
    for _ in range(max_iter):
        live = np.flatnonzero(step > tol)
        if live.size == 0:
            break
        cand = z[live, None, :] + step[live, None, None] * dirs[None]  # (m, 8, 2)
        Kr, taur, thetar, tau2r = (np.repeat(a[live], len(dirs)) for a in (K, tau, theta, tau2))
        kp, ki = np.exp(cand.reshape(-1, 2)).T
        mse = step_test_mse(Kr, taur, thetar, kp, ki, tau2=tau2r).reshape(-1, len(dirs))
        j = np.argmin(mse, axis=1)
        m = mse[np.arange(live.size), j]
        better = m < best[live]
        z[live[better]] = cand[np.flatnonzero(better), j[better]]
        best[live[better]] = m[better]
        step[live[~better]] *= 0.5
    kp, ki = np.exp(z).T
    return kp, ki, best


def compute_oracle_table3() -> np.ndarray:
    """Oracle gains over (theta/tau, tau, tau2/tau) at K = 1, normalised as
    [kp K, ki K tau]: shape (ratios, taus, lag2, 2). Gains scale exactly as 1/K; in tau
    only approximately (the step test lasts 11 time units whatever tau is), hence the
    tau axis. About a minute; ships as ``service/models/oracle_table_v3.json``."""
    r, t, l2 = (
        a.ravel() for a in np.meshgrid(ORACLE3_RATIOS, ORACLE3_TAUS, ORACLE3_LAG2, indexing="ij")
    )
    kp, ki, _ = batch_oracle(1.0, t, r * t, l2 * t)
    shape = (ORACLE3_RATIOS.size, ORACLE3_TAUS.size, ORACLE3_LAG2.size)
    return np.stack([kp, ki * t], axis=1).reshape(*shape, 2)


def oracle_table3() -> np.ndarray:
    """The v3 oracle table (computed and written if missing)."""
    if not ORACLE3_TABLE.exists():
        ORACLE3_TABLE.write_text(json.dumps(compute_oracle_table3().tolist()))
    return np.array(json.loads(ORACLE3_TABLE.read_text()))


def oracle_gains3(table: np.ndarray, K, tau, theta, tau2=None) -> np.ndarray:
    """(B, 2) oracle [kp, ki] for FOPTD or second-order plants (``tau2``), interpolated
    (linear in theta/tau and tau2/tau, in log tau) from :func:`oracle_table3`."""
    from scipy.interpolate import RegularGridInterpolator

    K, tau, theta = (np.asarray(v, np.float64) for v in (K, tau, theta))
    tau2 = np.zeros_like(tau) if tau2 is None else np.asarray(tau2, np.float64)
    axes = (ORACLE3_RATIOS, np.log(ORACLE3_TAUS), ORACLE3_LAG2)
    pts = np.stack(
        [
            np.clip(theta / tau, axes[0][0], axes[0][-1]),
            np.clip(np.log(tau), axes[1][0], axes[1][-1]),
            np.clip(tau2 / tau, axes[2][0], axes[2][-1]),
        ],
        axis=-1,
    )
    fg = RegularGridInterpolator(axes, table)(pts)
    return np.stack([fg[..., 0] / K, fg[..., 1] / (K * tau)], axis=-1)
