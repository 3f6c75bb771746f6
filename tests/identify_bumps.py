"""Bump tests on issue 13's bar loops, measured through the engine: each of the bar's
random FOPTD loops (engineering units, noise 1 % of span) registered without a hint and
held in manual, its output stepped by an operator every 3-6 time constants by an amount
whose steady effect on the PV is a bar move (5-25 PV units, random sign, kept within
10-90 % of span), the samples carrying ``op`` (docs/identification.md, Bump tests).

    python -m tests.identify_bumps [--loops 60] [--seed 0] [--steps 4] [--ramp 1]

Counted: loops identified from their first 2, 3, 4 steps (the data before the model's
time), the first model's K and tau against the truth (the bar's 30 %). ``--ramp N``: each
step made as a ramp over N samples (an operator holding a raise/lower button)."""

from __future__ import annotations

import argparse
import json

import numpy as np

from plant_sim.foptd import FOPTDBatch
from service.agent import untrained_agent
from service.engine import LoopConfig, TuningEngine
from tests.identify_bar import MOVE, MOVE_EVERY, NOISE, Plants, moved

MISS = 0.3
"""The bar's tolerance on K and tau (relative)."""


def run(plants: Plants, steps: int, seed: int, ramp: int = 1) -> dict:
    """Drive every loop in manual through ``steps`` output steps, each over ``ramp``
    samples (and ``MOVE_EVERY`` after the last); the first model put in force and the
    steps before its time."""
    n = plants.K.size
    engine = TuningEngine(untrained_agent(0))  # (the agent takes no step in manual)
    ids = [f"L{i}" for i in range(n)]
    for i in range(n):
        engine.register(LoopConfig(id=ids[i], kp=float(plants.kp0[i]),
                                   ki=float(plants.ki0[i]), sample_period_s=float(plants.h[i])),
                        wall=0.0)  # fmt: skip
    rng = np.random.default_rng(seed)
    plant = FOPTDBatch(plants.K, plants.tau / plants.h, plants.theta / plants.h, dt=1.0,
                       noise_std=NOISE, seed=rng)  # fmt: skip
    y0 = 50.0
    plant.reset(y0)
    u, level = y0 / plants.K, np.full(n, y0)
    goal, rate = u.copy(), np.zeros(n)  # the output an operator is ramping to, per sample
    gap = lambda: np.ceil(rng.uniform(*MOVE_EVERY, n) * plants.tau / plants.h)  # noqa: E731
    next_step, made = np.ceil(rng.uniform(1.0, 2.0, n) * plants.tau / plants.h), np.zeros(n, int)
    step_t: list[list[float]] = [[] for _ in range(n)]
    first: list[dict | None] = [None] * n
    end = next_step + steps * np.ceil(MOVE_EVERY[1] * plants.tau / plants.h)
    k = 0
    while (k < end).any():
        due = (k >= next_step) & (made < steps)
        if due.any():
            target = moved(level, rng.uniform(*MOVE, n) * rng.choice([-1.0, 1.0], n))
            goal = np.where(due, u + (target - level) / plants.K, goal)
            rate = np.where(due, (goal - u) / ramp, rate)
            level = np.where(due, target, level)
            made += due
            for i in np.flatnonzero(due).tolist():
                step_t[i].append(float(k * plants.h[i]))
            next_step = np.where(due, k + gap(), next_step)
        u = np.where(np.abs(goal - u) > np.abs(rate) / 2, u + rate, goal)
        y = plant.measure()
        live = np.flatnonzero(k < end)
        # a DCS tracking the setpoint to the PV in manual
        engine.ingest([{"loop_id": ids[i], "t": float(k * plants.h[i]), "sp": float(y[i]),
                        "pv": float(y[i]), "op": float(u[i]), "auto": False}
                       for i in live.tolist()], wall=float(k))  # fmt: skip
        for i in live.tolist():
            s = engine.table.slot(ids[i])
            if first[i] is None and engine.table.n_identified[s] > 0:
                m = engine.table.ident[s].in_force
                t_model = engine.table.ident[s].in_force_t
                first[i] = {"k_err": m.k / plants.K[i] - 1, "tau_err": m.tau / plants.tau[i] - 1,
                            "steps_in_data": sum(x < t_model for x in step_t[i])}  # fmt: skip
        plant.step(u)
        k += 1
    got = [f for f in first if f is not None]
    within = [f for f in got if max(abs(f["k_err"]), abs(f["tau_err"])) <= MISS]
    return {
        "loops": n,
        "identified": len(got),
        "identified_from_first": {
            m: sum(f["steps_in_data"] <= m for f in got) for m in range(2, steps + 1)
        },
        "k_and_tau_within_30pct": len(within),
        "abs_err_p50_p90_max": {
            x: np.quantile([abs(f[f"{x}_err"]) for f in got], [0.5, 0.9, 1.0]).round(3).tolist()
            for x in ("k", "tau")
        }
        if got
        else {},
        "misses": [
            (i, round(f["k_err"], 3), round(f["tau_err"], 3))
            for i, f in enumerate(first)
            if f and max(abs(f["k_err"]), abs(f["tau_err"])) > MISS
        ],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--loops", type=int, default=60)
    ap.add_argument("--seed", type=int, default=0, help="the bar's loops (Plants.random)")
    ap.add_argument("--steps", type=int, default=4, help="output steps per loop")
    ap.add_argument("--ramp", type=int, default=1, help="samples each step is ramped over")
    a = ap.parse_args()
    print(json.dumps(run(Plants.random(a.loops, a.seed), a.steps, a.seed + 1, a.ramp), indent=1))


if __name__ == "__main__":
    main()
