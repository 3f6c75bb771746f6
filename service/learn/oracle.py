"""The step-test oracle of the training tasks, as a table shipped with the agent.

The best fixed PI gains for a simulated task (:func:`plant_sim.tunings.oracle`, a
Nelder-Mead search on the step-test MSE) are offline-only knowledge, like the critic's
privileged inputs: training imitates them and the evaluation starts from them.
"""

from __future__ import annotations

import json

import numpy as np

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
