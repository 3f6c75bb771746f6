"""Issue 13's bar, measured: random FOPTD loops in engineering units registered without a
hint (or with a wrong one), driven through ``TuningEngine.ingest`` by a vectorised plant
simulation (``plant_sim`` FOPTDBatch + PIBatch), compared with the same agent given the
true hint.

    python -m tests.identify_bar [--loops 60] [--seed 0]

prints the numbers docs/identification.md reports; ``tests/test_identify_bar.py`` (slow)
asserts them.

Each loop runs on its own sample clock: the simulation advances every loop by one of its
own samples per iteration (time in samples: tau/h, theta/h, ki h), and the engine sees
``t = k h`` seconds.
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import dataclass, field

import numpy as np

from plant_sim.foptd import FOPTDBatch
from plant_sim.loop import step_test_mse
from plant_sim.pi import PIBatch
from plant_sim.tunings import simc_paper, to_parallel
from service.agent import load_agent
from service.engine import LoopConfig, TuningEngine

SPAN = 100.0
NOISE = 0.01 * SPAN
MOVE = (5.0, 25.0)
"""Setpoint moves: uniform in size (PV units), random sign, kept within 10..90% of span."""
MOVE_EVERY = [3.0, 6.0]
"""Setpoint moves every this many time constants (uniform)."""
PV_SCALE = 15.0
"""The true hint's pv_scale: the typical move."""
STEPS = 60
BATCH = 4
"""Samples per loop per ingest call: gains apply up to BATCH - 1 samples late (an RL
period is at least 27 samples here), in every run alike."""
NOISE_FACTOR = 1.0
START_TUNING = 0.5
"""The loops' existing gains: this fraction of the paper's SIMC tuning (sluggish)."""


@dataclass
class Plants:
    K: np.ndarray
    tau: np.ndarray
    theta: np.ndarray
    h: np.ndarray
    kp0: np.ndarray
    ki0: np.ndarray

    @classmethod
    def random(cls, n: int, seed: int) -> Plants:
        rng = np.random.default_rng(seed)
        K = 10 ** rng.uniform(-2, 1, n)
        tau = 10 ** rng.uniform(math.log10(5), math.log10(2000), n)
        theta = tau * rng.uniform(0, 1, n)
        h = tau / rng.uniform(5, 50, n)
        kp0, ki0 = to_parallel(*simc_paper(K, tau, theta))
        return cls(K, tau, theta, h, START_TUNING * kp0, START_TUNING * ki0)

    def hint(self, i: int, k_factor: float = 1.0, tau_factor: float = 1.0) -> dict:
        return {
            "k_hat": float(self.K[i] * k_factor),
            "tau_hat": float(self.tau[i] * tau_factor),
            "pv_scale": PV_SCALE,
        }

    def agent_mse(self, kp: np.ndarray, ki: np.ndarray) -> np.ndarray:
        """The paper's step-test MSE of engineering gains, in the true hint's agent units."""
        kp_unit = (1 / PV_SCALE) / ((1 / PV_SCALE) * self.K / 0.5)
        ki_unit = kp_unit / (self.tau / 0.5)
        r = self.theta / self.tau
        return step_test_mse(0.5, 0.5, 0.5 * r, kp / kp_unit, ki / ki_unit)


@dataclass
class Run:
    kp: np.ndarray
    ki: np.ndarray
    done: np.ndarray
    moves_at_identification: np.ndarray
    identified_model: list = field(default_factory=list)
    statuses: list = field(default_factory=list)
    flagged: np.ndarray | None = None
    seconds: float = 0.0


def run(
    plants: Plants,
    *,
    hints: list[dict | None],
    auto_rescale: bool = False,
    steps_after_rescale: bool = False,
    seed: int = 1,
    max_tau: float = 500.0,
) -> Run:
    """Drive every loop until it has taken STEPS agent steps (counted from its last
    identification or rescale when ``steps_after_rescale``), or ``max_tau`` time constants."""
    n = plants.K.size
    engine = TuningEngine(load_agent())
    for i in range(n):
        guard = {"auto_rescale": auto_rescale}
        engine.register(
            LoopConfig(
                id=f"L{i}", kp=float(plants.kp0[i]), ki=float(plants.ki0[i]),
                sample_period_s=float(plants.h[i]), scaling=hints[i], guard=guard,
            ),
            wall=0.0,
        )  # fmt: skip
    rng = np.random.default_rng(seed)
    y0 = 50.0
    plant = FOPTDBatch(
        plants.K, plants.tau / plants.h, plants.theta / plants.h, dt=1.0, noise_std=NOISE,
        seed=rng,
    )  # fmt: skip
    plant.reset(y0)
    pi = PIBatch(plants.kp0, plants.ki0 * plants.h, dt=1.0)
    pi.initialise(y0 / plants.K)
    sp = np.full(n, y0)
    next_move = np.ceil(rng.uniform(1.0, 2.0, n) * plants.tau / plants.h)
    moves = np.zeros(n, np.int64)
    moves_at_id = np.full(n, -1)
    steps = np.zeros(n, np.int64)
    rescaled_seen = np.zeros(n, np.int64)
    out = Run(plants.kp0.copy(), plants.ki0.copy(), np.zeros(n, bool), moves_at_id)
    limit = np.ceil(max_tau * plants.tau / plants.h)
    ids = [f"L{i}" for i in range(n)]
    started = time.perf_counter()
    k = 0
    wall = 0.0
    pending: list[dict] = []
    while True:
        active = ~out.done & (k < limit)
        if not active.any():
            break
        move = active & (k >= next_move)
        if move.any():
            size = rng.uniform(*MOVE, n) * rng.choice([-1.0, 1.0], n)
            new = sp + size
            new = np.where((new < 0.1 * SPAN) | (new > 0.9 * SPAN), sp - size, new)
            sp = np.where(move, new, sp)
            moves += move
            next_move = np.where(
                move, k + np.ceil(rng.uniform(*MOVE_EVERY, n) * plants.tau / plants.h), next_move
            )
        y = plant.measure()
        t = k * plants.h
        idx = np.flatnonzero(active)
        pending.extend(
            {"loop_id": ids[i], "t": float(t[i]), "sp": float(sp[i]), "pv": float(y[i]),
             "kp": float(pi.kp[i]), "ki": float(pi.ki[i] / plants.h[i])}
            for i in idx.tolist()
        )  # fmt: skip
        if k % BATCH == BATCH - 1:
            wall += 1.0
            updates = engine.ingest(pending, wall=wall)
            pending = []
            _apply(engine, updates, pi, plants, out, steps, rescaled_seen, steps_after_rescale)
            # moves seen when the model was put in force
            tb = engine.table
            for i in np.flatnonzero((moves_at_id < 0) & active).tolist():
                if tb.n_identified[tb.slot(ids[i])] > 0:
                    moves_at_id[i] = moves[i]
        u = pi.step(sp - y)
        plant.step(u)
        k += 1
    for i in range(n):
        if not out.done[i]:  # ran out of time: the gains it has
            s = engine.table.slot(ids[i])
            out.kp[i], out.ki[i] = engine.table.kp[s], engine.table.ki[s]
    views = [engine.view(i, wall=wall) for i in ids]
    out.identified_model = [v.identification.in_force if v.identification else None for v in views]
    out.statuses = [v.status.value for v in views]
    out.flagged = np.array([v.counters.mismatches > 0 for v in views])
    out.seconds = time.perf_counter() - started
    return out


def _apply(engine, updates, pi, plants, out, steps, rescaled_seen, after_rescale) -> None:
    if not updates:
        return
    kp, ki = pi.kp.copy(), pi.ki.copy()
    for u in updates:
        i = int(u.loop_id[1:])
        kp[i], ki[i] = u.kp, u.ki * plants.h[i]
        if u.reason == "agent" and not out.done[i]:
            steps[i] += 1
    pi.set_gains(kp, ki)
    tb = engine.table
    for u in updates:
        i = int(u.loop_id[1:])
        s = tb.slot(u.loop_id)
        if after_rescale and tb.n_identified[s] > rescaled_seen[i]:
            rescaled_seen[i] = tb.n_identified[s]
            steps[i] = 1
        if steps[i] >= STEPS and not out.done[i]:
            out.done[i] = True
            out.kp[i], out.ki[i] = u.kp, u.ki


def report(n: int = 60, seed: int = 0) -> dict:
    plants = Plants.random(n, seed)
    true = run(plants, hints=[plants.hint(i) for i in range(n)])
    blind = run(plants, hints=[None] * n)
    mse_true = plants.agent_mse(true.kp, true.ki)
    mse_blind = plants.agent_mse(blind.kp, blind.ki)
    ident = np.array([m is not None for m in blind.identified_model])
    within4 = ident & (blind.moves_at_identification >= 0) & (blind.moves_at_identification <= 4)
    k_err = np.array(
        [m.k / plants.K[i] - 1 if m else np.nan for i, m in enumerate(blind.identified_model)]
    )
    tau_err = np.array(
        [m.tau / plants.tau[i] - 1 if m else np.nan for i, m in enumerate(blind.identified_model)]
    )
    ratio = mse_blind / mse_true
    factors = [(3.0, 1.0), (1 / 3, 1.0), (1.0, 3.0), (1.0, 1 / 3)]
    wrong = [plants.hint(i, *factors[i % 4]) for i in range(n)]
    flagged = run(plants, hints=wrong, auto_rescale=False)
    rescaled = run(plants, hints=wrong, auto_rescale=True, steps_after_rescale=True)
    mse_rescaled = plants.agent_mse(rescaled.kp, rescaled.ki)
    res = {
        "loops": n,
        "identified": int(ident.sum()),
        "identified_within_4_moves": int(within4.sum()),
        "moves_at_identification": blind.moves_at_identification.tolist(),
        "k_within_30": int((np.abs(k_err[ident]) <= 0.3).sum()),
        "tau_within_30": int((np.abs(tau_err[ident]) <= 0.3).sum()),
        "k_err_worst": float(np.nanmax(np.abs(k_err))) if ident.any() else None,
        "tau_err_worst": float(np.nanmax(np.abs(tau_err))) if ident.any() else None,
        "mse_ratio_within_1.5": int((ratio <= 1.5).sum()),
        "mse_ratio_median": float(np.median(ratio)),
        "mse_ratio_worst": float(np.max(ratio)),
        "unstable_blind": int((~np.isfinite(mse_blind) | (mse_blind > 1.0)).sum()),
        "mse_true_median": float(np.median(mse_true)),
        "mse_blind_median": float(np.median(mse_blind)),
        "wrong_hint_flagged": int(
            (flagged.flagged | rescaled.flagged | (rescaled.moves_at_identification >= 0)).sum()
        ),
        "wrong_hint_flagged_no_rescale": int(flagged.flagged.sum()),
        "wrong_hint_statuses": {s: flagged.statuses.count(s) for s in set(flagged.statuses)},
        "rescaled": int(sum(m is not None for m in rescaled.identified_model)),
        "rescaled_ratio_within_1.5": int((mse_rescaled / mse_true <= 1.5).sum()),
        "rescaled_ratio_median": float(np.median(mse_rescaled / mse_true)),
        "rescaled_ratio_worst": float(np.max(mse_rescaled / mse_true)),
        "wrong_hint_no_rescale_ratio_median": float(
            np.median(plants.agent_mse(flagged.kp, flagged.ki) / mse_true)
        ),
        "seconds": [true.seconds, blind.seconds, flagged.seconds, rescaled.seconds],
        "per_loop": {
            "ratio": ratio.tolist(),
            "k_err": k_err.tolist(),
            "tau_err": tau_err.tolist(),
            "rescaled_ratio": (mse_rescaled / mse_true).tolist(),
            "theta_ratio": (plants.theta / plants.tau).tolist(),
            "samples_per_tau": (plants.tau / plants.h).tolist(),
        },
    }
    return res


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--loops", type=int, default=60)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    res = report(args.loops, args.seed)
    per = res.pop("per_loop")
    for k, v in res.items():
        print(f"{k}: {v}")
    import json

    print(json.dumps(per))


if __name__ == "__main__":
    main()
