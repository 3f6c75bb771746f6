"""The paper's adaptation experiment (experiment 3) through the tuning engine: what a
user whose plant changes gets, beside what the agent alone does (``pitune evaluate``'s
``adaptation`` and ``adaptation_spread``, :mod:`service.learn.experiments`).

The same 18 plants and protocol as those two: the paper's tau ramp (K 0.5, tau 0.4 -> 1,
theta 0.1) and K step (K 0.5 -> 1, tau 0.5, theta 0.1), then the spread's 8 K steps and 8
tau ramps (:data:`~service.learn.experiments.SPREAD_MOVES`, theta 0.2 x the first tau
throughout); 60 RL periods to settle, the change (a step, or a ramp over 40 periods),
140 in all, forgetting 0.99. Through the engine as :func:`service.learn.robust.
run_condition` runs a loop: raw samples every second, the two-tank hint, the default
guard (excitation gate, verify-or-rollback, identification checking the hint and the
model check), the paper's +-1 square wave every 11 time units, no noise. Score: the
paper's step-test MSE of the gains in force at each of the last 16 RL periods on the
plant as it is at the end, averaged (the engine has no tracking error of the agent's
episode to report; the step test of the gains is the robustness table's score).
"""

from __future__ import annotations

import numpy as np

from service.learn.closed_loop import Policy
from service.learn.experiments import SPREAD_MOVES, adaptation_protocol
from service.learn.robust import Condition, run_condition, score
from service.units import DEFAULT_FORGETTING


def plants() -> tuple[np.ndarray, ...]:
    """(K, tau, theta) before and (K, tau) after the change of the 18 plants, (18,) each:
    the paper's tau ramp, its K step, 8 K steps, 8 tau ramps."""
    start, end = SPREAD_MOVES.T
    k_at, tau_at = np.linspace(0.25, 1.0, 8), np.linspace(0.3, 0.8, 8)
    K0, tau0 = np.r_[0.5, 0.5, start, k_at], np.r_[0.4, 0.5, tau_at, start]
    theta = np.r_[0.1, 0.1, 0.2 * tau_at, 0.2 * start]
    K1, tau1 = np.r_[0.5, 1.0, end, k_at], np.r_[1.0, 0.5, tau_at, end]
    return K0, tau0, theta, K1, tau1


def run(policy: Policy, which=slice(None), guard: dict | None = None):
    """The plants ``which`` (an index into :func:`plants`) through the engine for the
    protocol's 140 RL periods: :func:`service.learn.robust.run_condition`'s run, its
    plants at the end (``run.K``, ``run.tau``, ``run.theta``)."""
    settle, change, total, _ = adaptation_protocol(quick=False)
    K0, tau0, theta, K1, tau1 = (x[which] for x in plants())

    def schedule(p: int):
        frac = np.clip((p - settle) / change, 0.0, 1.0)
        return (K1 if p >= settle else K0), tau0 + frac * (tau1 - tau0), theta

    return run_condition(policy, Condition("paper protocol"), periods=total, guard=guard,
                         plants=(K0, tau0, theta / tau0), forgetting=DEFAULT_FORGETTING,
                         schedule=schedule)  # fmt: skip


def adaptation(policy: Policy, guard: dict | None = None) -> dict:
    """Run the 18 plants through the engine; returns the paper's two runs' scores and the
    spread's geometric mean and worst per kind, each plant's score and the unstable
    count (the final gains' step test, :func:`service.learn.robust.score`)."""
    _, _, total, window = adaptation_protocol(quick=False)
    done = run(policy, guard=guard)
    changed = (done.K, done.tau, done.theta, done.lag)
    mse = np.mean([score(*changed, *g.T)[0] for g in done.gains[total - window + 1 :]], axis=0)
    unstable = score(*changed, *done.gains[-1].T)[1]

    def spread(part: np.ndarray) -> dict:
        return {"gmean": float(np.exp(np.log(part).mean())), "worst": float(part.max())}

    return {
        "tau_ramp": float(mse[0]),
        "k_step": float(mse[1]),
        "k_steps": spread(mse[2:10]),
        "tau_ramps": spread(mse[10:]),
        "mse": mse.tolist(),
        "unstable": int(unstable.sum()),
    }


def render(a: dict, v2: dict | None = None) -> list[str]:
    """Report lines of :func:`adaptation`'s result ``a``, beside ``v2``'s when given."""
    rows = [
        ("paper tau ramp (0.4 -> 1)", a["tau_ramp"], v2 and v2["tau_ramp"]),
        ("paper K step (0.5 -> 1)", a["k_step"], v2 and v2["k_step"]),
        ("8 K steps, geometric mean", a["k_steps"]["gmean"], v2 and v2["k_steps"]["gmean"]),
        ("8 K steps, worst", a["k_steps"]["worst"], v2 and v2["k_steps"]["worst"]),
        ("8 tau ramps, geometric mean", a["tau_ramps"]["gmean"], v2 and v2["tau_ramps"]["gmean"]),
        ("8 tau ramps, worst", a["tau_ramps"]["worst"], v2 and v2["tau_ramps"]["worst"]),
    ]
    lines = [
        "",
        "Adaptation through the engine (the paper's experiment 3 and the 16-plant spread,"
        " the guard above, forgetting 0.99; step-test MSE of the gains over the last 16 of"
        f" 140 RL periods on the changed plant; unstable {a['unstable']}"
        + (f", v2 {v2['unstable']}):" if v2 else "):"),
        "",
        "| run | this agent | v2 |" if v2 else "| run | this agent |",
        "|---|---|---|" if v2 else "|---|---|",
    ]
    for name, mine, theirs in rows:
        lines.append(
            f"| {name} | {mine:.3g} | {theirs:.3g} |" if v2 else f"| {name} | {mine:.3g} |"
        )
    return lines
