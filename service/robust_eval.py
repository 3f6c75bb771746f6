"""Robustness of an agent beyond the paper's protocol (issue 12): ``pitune evaluate --robust``.

27 plants (K in {0.25, 0.5, 1} x tau in {0.25, 0.5, 1} x theta/tau in {0.1, 0.5, 1}); the
agent tunes each from kp = ki = 0.05 for 80 RL steps (forgetting 1.0) under one
condition at a time; the final gains are scored with the paper's step test on the
*true* plant (:func:`service.oracle.step_test_mse2`: the plain step test for FOPTD
plants; for second-order plants the target of the half-rule FOPTD model). SIMC (the
paper's variant) with the true model (half rule for second-order plants) is the
reference. All conditions run as one batch through :class:`service.env.TuningEnv`.

Conditions (agent units; "hint" = the plant the scaling assumes, the grid plant):

* ``paper``: setpoint toggling +-1 every 11 time units from +1, no noise, no load.
* ``noise_0.05`` / ``noise_0.1``: white measurement noise sigma 0.05 / 0.1.
* ``noise_0.05_lp``: noise sigma 0.05 low-pass filtered, time constant 0.1 tau.
* ``load_steps``: a load at the plant input stepping 0 -> 0.5 -> 0 ... every 7 time units.
* ``load_walk``: a slow load random walk (OU, time constant 20, std 0.25).
* ``sp_amp_0.2`` / ``sp_amp_3``: the toggle between +-0.2 / +-3.
* ``sp_hold_22``: the toggle every 22 time units (8 RL periods).
* ``sp_irregular``: random moves (size A U[0.3, 1], A = 1, random sign), held
  1 + Exp(3) RL periods (mean 4), not aligned with the RL steps.
* ``tau_x2`` / ``tau_x3`` / ``tau_/3``: true tau = 2, 3, 1/3 x hint (theta as hinted).
* ``K_x3`` / ``K_/3``: true K = 3, 1/3 x hint.
* ``ratio_2`` / ``ratio_3``: theta/tau = 2 / 3 (instead of the grid's ratio).
* ``second_order``: a second lag tau2 = 0.3 tau (theta as on the grid).

Plus two checks: ``long_run`` (400 RL steps, forgetting 0.99, noise 0.05, irregular
setpoints; wander = largest relative distance of a gain from its mean over steps
200-400, bar 15%) and ``quiet`` (start at the oracle's gains, setpoint at the plant,
no setpoint move for 100 RL periods, noise 0.05 and load steps 0.5 every 7 time units;
largest relative change of a gain, bar 10%).

A loop counts as unstable when its step test (extended to 44 time units) oscillates
without decaying: the largest |error| over 33-44 is above 0.05 and not below that
over 22-33 (or the MSE is not finite).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from plant_sim.foptd import FOPTDBatch
from plant_sim.loop import run_closed_loop, target_filter
from plant_sim.pi import PIBatch
from plant_sim.tunings import simc_paper, to_parallel
from service.env import CONDITIONS, EnvConfig, TuningEnv
from service.oracle import effective_foptd, oracle_gains3, oracle_table3, step_test_mse2

RL_PERIOD = 2.75
BAR_WORST, BAR_MEDIAN = 0.029, 0.003


def robust_grid() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The 27 plants: K x tau x theta/tau = {0.25, 0.5, 1} x {0.25, 0.5, 1} x {0.1, 0.5, 1}."""
    K, tau, r = (
        a.ravel()
        for a in np.meshgrid([0.25, 0.5, 1.0], [0.25, 0.5, 1.0], [0.1, 0.5, 1.0], indexing="ij")
    )
    return K, tau, r * tau


def conditions(K, tau, theta) -> dict[str, dict]:
    """name -> {K, tau, theta, tau2, cond} of the true plants and per-episode conditions."""
    n = K.size
    full = lambda v: np.full(n, v, dtype=float)  # noqa: E731
    z = np.zeros(n)
    base = {"K": K, "tau": tau, "theta": theta, "tau2": z, "cond": {}}
    out = {
        "paper": base,
        "noise_0.05": base | {"cond": {"noise": full(0.05)}},
        "noise_0.1": base | {"cond": {"noise": full(0.1)}},
        "noise_0.05_lp": base | {"cond": {"noise": full(0.05), "noise_tf": full(0.1)}},
        "load_steps": base
        | {
            "cond": {
                "load_step": full(0.5),
                "load_every": full(7.0),
                "load_periodic": np.ones(n, bool),
            }
        },
        "load_walk": base | {"cond": {"load_walk": full(0.25)}},
        "sp_amp_0.2": base | {"cond": {"sp_amp": full(0.2)}},
        "sp_amp_3": base | {"cond": {"sp_amp": full(3.0)}},
        "sp_hold_22": base | {"cond": {"sp_period": full(22.0)}},
        "sp_irregular": base | {"cond": {"sp_random": np.ones(n, bool), "sp_hold": full(4.0)}},
        "tau_x2": base | {"tau": 2 * tau},
        "tau_x3": base | {"tau": 3 * tau},
        "tau_/3": base | {"tau": tau / 3},
        "K_x3": base | {"K": 3 * K},
        "K_/3": base | {"K": K / 3},
        "ratio_2": base | {"theta": 2 * tau},
        "ratio_3": base | {"theta": 3 * tau},
        "second_order": base | {"tau2": 0.3 * tau},
    }
    return out


def _stack(cases: list[dict]) -> dict:
    """Concatenate condition cases into one batch (missing condition keys neutral)."""
    out = {
        k: np.concatenate([np.asarray(c[k], float) for c in cases])
        for k in ("K", "tau", "theta", "tau2")
    }
    cond = {}
    for key, (neutral, _) in CONDITIONS.items():
        if any(key in c["cond"] for c in cases):
            cond[key] = np.concatenate(
                [np.broadcast_to(c["cond"].get(key, neutral), (c["K"].size,)) for c in cases]
            )
    out["cond"] = cond
    return out


def run_batch(agent, batch: dict, *, steps: int, forgetting: float = 1.0, gains0=None, sp0=None):
    """Tune the batch for ``steps`` RL steps; returns gains (steps+1, N, 2)."""
    K = batch["K"]
    env = TuningEnv(EnvConfig(init_noise=0.0), np.random.default_rng(0))
    if sp0 is None:
        sp0 = batch["cond"].get("sp_amp", np.ones(K.size))
    start = {} if gains0 is None else {"kp0": gains0[:, 0], "ki0": gains0[:, 1]}
    obs = env.reset(
        K, batch["tau"], batch["theta"], horizon=steps, sp0=sp0, tau2=batch["tau2"],
        conditions=batch["cond"], **start,
    )  # fmt: skip
    state = agent.initial_state(K.size)
    gains = [obs[:, :2].copy()]
    for _ in range(steps):
        delta, state = agent.act(obs, state, forgetting=forgetting)
        obs, _, _ = env.step(delta)
        gains.append(obs[:, :2].copy())
    return np.array(gains)


def unstable(K, tau, theta, kp, ki, tau2) -> np.ndarray:
    """Step test extended to 44 time units: oscillation that does not decay (see module doc)."""
    K, tau, theta, kp, ki, tau2 = (np.asarray(v, float) for v in (K, tau, theta, kp, ki, tau2))
    n, dt = K.size, 0.01
    plant = FOPTDBatch(K, tau, theta, dt=dt, n=n, tau2=tau2)
    plant.reset(-1.0)
    target = target_filter(*effective_foptd(tau, theta, tau2), dt=dt, n=n)
    target.reset(-1.0)
    pi = PIBatch(kp, ki, dt=dt, n=n)
    pi.initialise(-1.0 / K)
    y = run_closed_loop(plant, pi, target, np.ones(4400)).y
    with np.errstate(invalid="ignore"):
        a1 = np.max(np.abs(y[:, 2200:3300] - 1), axis=1)
        a2 = np.max(np.abs(y[:, 3300:] - 1), axis=1)
        return ~np.isfinite(a2) | ((a2 > 0.05) & (a2 >= a1))


def score(case: dict, kp, ki) -> dict:
    K, tau, theta, tau2 = case["K"], case["tau"], case["theta"], case["tau2"]
    mse = step_test_mse2(K, tau, theta, kp, ki, tau2)
    simc = step_test_mse2(
        K, tau, theta, *to_parallel(*simc_paper(K, *effective_foptd(tau, theta, tau2))), tau2
    )
    return {
        "worst_mse": float(mse.max()),
        "median_mse": float(np.median(mse)),
        "beats_simc": float(np.mean(mse < simc)),
        "unstable": int(unstable(K, tau, theta, kp, ki, tau2).sum()),
        "simc_worst": float(simc.max()),
    }


def robust_table(agent, *, steps: int = 80, names: list[str] | None = None, plants=None) -> dict:
    """Each condition: worst / median step-test MSE of the final gains, share beating SIMC
    with the true model, unstable count. ``plants`` (K, tau, theta) replaces the grid."""
    K, tau, theta = robust_grid() if plants is None else plants
    cases = conditions(K, tau, theta)
    names = list(cases) if names is None else names
    gains = run_batch(agent, _stack([cases[k] for k in names]), steps=steps)
    out = {}
    for i, name in enumerate(names):
        kp, ki = gains[-1, i * K.size : (i + 1) * K.size].T
        out[name] = score(cases[name], kp, ki)
    return out


def long_run(agent, *, steps: int = 400) -> dict:
    """400 RL steps, forgetting 0.99, noise 0.05, irregular setpoints: gain wander."""
    K, tau, theta = robust_grid()
    n = K.size
    cond = {"noise": np.full(n, 0.05), "sp_random": np.ones(n, bool), "sp_hold": np.full(n, 4.0)}
    case = {"K": K, "tau": tau, "theta": theta, "tau2": np.zeros(n), "cond": cond}
    gains = run_batch(agent, case, steps=steps, forgetting=0.99)
    late = gains[steps // 2 :]
    wander = np.max(np.abs(late / late.mean(0) - 1), axis=(0, 2))
    s = score(case, *gains[-1].T)
    return {"wander_worst": float(wander.max()), "wander_median": float(np.median(wander))} | s


def quiet(agent, *, steps: int = 100) -> dict:
    """From the oracle's gains, no setpoint move, noise 0.05 and load steps: gain change."""
    K, tau, theta = robust_grid()
    n = K.size
    g0 = oracle_gains3(oracle_table3(), K, tau, theta)
    cond = {"quiet": np.full(n, 1e9), "noise": np.full(n, 0.05), "load_step": np.full(n, 0.5),
            "load_every": np.full(n, 7.0), "load_periodic": np.ones(n, bool)}  # fmt: skip
    case = {"K": K, "tau": tau, "theta": theta, "tau2": np.zeros(n), "cond": cond}
    gains = run_batch(agent, case, steps=steps, forgetting=0.99, gains0=g0, sp0=np.zeros(n))
    change = np.max(np.abs(gains / g0 - 1), axis=(0, 2))
    return {"change_worst": float(change.max()), "change_median": float(np.median(change))}


def evaluate_robust(agent, *, quick: bool = False) -> dict:
    out = {"conditions": robust_table(agent)}
    if not quick:
        out["long_run"] = long_run(agent)
    out["quiet"] = quiet(agent)
    return out


def render(m: dict, label: str = "") -> str:
    lines = [
        f"| condition {label} | worst MSE | median MSE | beats SIMC | unstable | SIMC worst |",
        "|---|---|---|---|---|---|",
    ]
    for name, r in m["conditions"].items():
        ok = r["worst_mse"] <= BAR_WORST and r["median_mse"] <= BAR_MEDIAN and r["unstable"] == 0
        lines.append(
            f"| {name}{'' if ok else ' (miss)'} | {r['worst_mse']:.4f} | {r['median_mse']:.5f} | "
            f"{100 * r['beats_simc']:.0f}% | {r['unstable']} | {r['simc_worst']:.4f} |"
        )
    if "long_run" in m:
        lr = m["long_run"]
        lines.append(
            "\nlong run (400 steps, noise 0.05, irregular): wander worst "
            f"{100 * lr['wander_worst']:.0f}% median {100 * lr['wander_median']:.0f}% (bar 15%); "
            f"final MSE worst {lr['worst_mse']:.4f} median {lr['median_mse']:.5f}, "
            f"unstable {lr['unstable']}"
        )
    q = m["quiet"]
    lines.append(
        "\nquiet loop (noise 0.05, load steps, 100 steps): gain change worst "
        f"{100 * q['change_worst']:.0f}% median {100 * q['change_median']:.0f}% (bar 10%)"
    )
    return "\n".join(lines)


def add_arguments(p) -> None:
    """Arguments of the robustness evaluation (to wire as ``pitune evaluate --robust``)."""
    p.add_argument("--weights", type=Path, default=None, help="agent file (default: shipped)")
    p.add_argument("--quick", action="store_true", help="skip the 400-step long run")
    p.add_argument("--out", type=Path, default=None, help="write robust.json and robust.md here")


def run(args) -> int:
    """Print the robustness table; with ``--out`` also write DIR/robust.json and robust.md."""
    from service.agent import load_agent

    agent = load_agent(args.weights) if args.weights else load_agent()
    m = evaluate_robust(agent, quick=args.quick)
    text = render(m, str(args.weights or "shipped"))
    print(text)
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "robust.json").write_text(json.dumps(m, indent=1))
        (args.out / "robust.md").write_text(text + "\n")
    return 0


if __name__ == "__main__":  # python -m service.robust_eval [--weights W] [--quick] [--out DIR]
    import argparse

    parser = argparse.ArgumentParser(description="robustness table (issue 12)")
    add_arguments(parser)
    raise SystemExit(run(parser.parse_args()))
