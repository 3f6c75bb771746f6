"""The robustness suite, ``pitune evaluate --robust``: every condition of
:mod:`service.learn.robust`, its long run, and the loops without setpoint moves of
:mod:`service.learn.regulatory`, written as robust.json, robust.md and a figure."""

from __future__ import annotations

import json
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from service.agent.model import V2_WEIGHTS, load_agent
from service.learn import robust_adaptation
from service.learn.closed_loop import Policy
from service.learn.regulatory import regulatory
from service.learn.regulatory import render as render_regulatory
from service.learn.robust import (
    BAR_MEDIAN,
    BAR_WORST,
    CONDITIONS,
    Run,
    long_run,
    run_condition,
    summarise,
)
from service.units import RL_STEP_AGENT_UNITS


def robust_suite(policy: Policy, out: Path, quick: bool = False, guard: dict | None = None) -> dict:
    """Every condition, the long run and the loops without setpoint moves; writes
    robust.json, robust.md and a figure into ``out``. ``guard``: settings every loop is
    registered with instead of the defaults (an opt-in measure's table)."""
    out.mkdir(parents=True, exist_ok=True)
    start = time.monotonic()
    periods = 40 if quick else 80
    conditions = CONDITIONS[:2] if quick else CONDITIONS
    rows, runs = [], {}
    for cond in conditions:
        run = run_condition(policy, cond, periods=periods, guard=guard)
        runs[cond.name] = run
        rows.append(summarise(cond, run))
    result = {
        "agent": getattr(policy, "meta", {}).get("source", "shipped"),
        "inference": getattr(policy, "precision", "reference"),
        "periods": periods,
        "quick": quick,
        "guard": guard or {},
        "conditions": rows,
        "conditions_config": [asdict(c) for c in conditions],
    }
    if not quick:
        result["long_run"] = long_run(policy, guard=guard)
        result |= regulatory(policy, guard=guard)
        # v2 beside it, through the same engine: issue 12's "adaptation no worse than v2"
        result["adaptation"] = robust_adaptation.adaptation(policy, guard)
        result["adaptation_v2"] = robust_adaptation.adaptation(load_agent(V2_WEIGHTS), guard)
    result["wall_s"] = round(time.monotonic() - start, 1)
    (out / "robust.json").write_text(json.dumps(result, indent=2))
    (out / "robust.md").write_text(render(result))
    _figure(out / "fig10_robust_noise_load.png", runs)
    return result


def render(result: dict) -> str:
    guard = result.get("guard") or {}
    settings = (
        "default guard, excitation gate and verify-or-rollback"
        if not guard
        else "guard settings " + json.dumps(guard, sort_keys=True) + ", the rest default"
    )
    lines = [
        "# pitune robustness (through the tuning engine)",
        "",
        f"27 plants, {result['periods']} RL periods from kp = ki = 0.05, samples every"
        f" second in engineering units through the engine ({settings}), final gains scored"
        " by the step test on the true plant."
        + (" Quick run." if result["quick"] else "")
        + f" Agent {result.get('agent', 'shipped')},"
        + f" inference {result.get('inference', 'reference')}."
        + f" Wall time {result['wall_s']} s.",
        "",
        "| condition | worst MSE | median MSE | beats SIMC, paper's / improved (true"
        " model) | improved SIMC worst | ends on a model tuning | unstable | bar |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in result["conditions"]:
        improved = "beats_simc_improved" in r  # (results of before session 36: not kept)
        lines.append(
            f"| {r['condition']} | {r['worst_mse']:.3g} | {r['median_mse']:.3g} |"
            f" {100 * r['beats_simc']:.0f}%"
            + (f" / {100 * r['beats_simc_improved']:.0f}% |" if improved else " / - |")
            + (f" {r['simc_improved_worst_mse']:.3g} |" if improved else " - |")
            + (f" {r['on_model']} |" if improved else " - |")
            + f" {r['unstable']} | {'met' if r['meets_bar'] else 'NOT met'} |"
        )
    lines += [
        "",
        f"Bar per condition: worst <= {BAR_WORST}, median <= {BAR_MEDIAN}, none unstable.",
        "",
        "SIMC, the paper's variant (its Table 2): the original rule's gain with tau_c = 2 tau"
        " and the improved rule's integral time; it sets the issue's bar (0.029, its worst on"
        " the paper grid). Improved SIMC (Grimholt & Skogestad, tau_c = 2 tau) is much the"
        " stronger (worst 0.0014 on the paper grid) and is the engine's own model tuning:"
        " 'ends on a model tuning' counts the loops whose last gain change was the engine's"
        " tuning of an identified model (audit reason `model`), not an agent's step, so"
        " their score is identification's. Unstable: the step test's output still more than"
        " 0.5 off its target over the test's last fifth (a badly damped loop counts too)."
        " The step test runs at the paper's time step, 0.01 time units.",
    ]
    if "long_run" in result:
        lr = result["long_run"]
        lines += [
            "",
            f"Long run ({lr['periods']} RL periods, forgetting 0.99, noise 0.05, irregular"
            f" setpoints): gains wander up to {100 * lr['wander_worst']:.0f}% (median"
            f" {100 * lr['wander_median']:.0f}%) from their median over the second half"
            f" (bar 15%); final worst MSE {lr['worst_mse']:.3g}, unstable {lr['unstable']}.",
        ]
    if "adaptation" in result:
        lines += robust_adaptation.render(result["adaptation"], result.get("adaptation_v2"))
    if "quiet_loop" in result:
        lines += render_regulatory(result)
    return "\n".join(lines) + "\n"


def _figure(path: Path, runs: dict[str, Run]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    shown = [name for name in ("noise 0.05", "load steps 0.5 every 7") if name in runs]
    if not shown:
        return
    i = 13  # K = 0.5, tau = 0.5, theta/tau = 0.5
    fig, axes = plt.subplots(2, len(shown), figsize=(6 * len(shown), 6), squeeze=False)
    for col, name in enumerate(shown):
        run = runs[name]
        minutes = run.t / 60
        axes[0, col].plot(minutes, run.pv[i], lw=0.5, label="PV")
        axes[0, col].plot(minutes, run.sp[i], "k--", lw=0.8, label="setpoint")
        axes[0, col].set(title=f"{name}: K=0.5, tau=0.5, theta/tau=0.5", ylabel="PV")
        steps = np.arange(run.gains.shape[0]) * RL_STEP_AGENT_UNITS
        axes[1, col].plot(steps, run.gains[:, i, 0], label="kp (agent units)")
        axes[1, col].plot(steps, run.gains[:, i, 1], label="ki (agent units)")
        axes[1, col].set(xlabel="time units", ylabel="gain")
        for ax in axes[:, col]:
            ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
