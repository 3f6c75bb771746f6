"""What ``pitune evaluate`` writes besides ``metrics.json``: figures, report, model card.

Everything here renders the results of :mod:`service.learn.experiments`; nothing runs
an agent.
"""

from __future__ import annotations

import json
import textwrap
from pathlib import Path

import numpy as np

from plant_sim.loop import step_test
from service.agent.model import Agent
from service.learn.env import EnvConfig
from service.learn.experiments import PAPER
from service.learn.validation import VAL_DRIFT_BAR, VAL_MSE_BAR, VAL_SETTLED_TIME
from service.units import AGENT_KI0, AGENT_KP0, DEFAULT_FORGETTING, RL_STEP_AGENT_UNITS


def _edges(centres: np.ndarray) -> np.ndarray:
    """Cell edges around sorted grid centres, for pcolormesh."""
    mid = (centres[1:] + centres[:-1]) / 2
    return np.concatenate([[2 * centres[0] - mid[0]], mid, [2 * centres[-1] - mid[-1]]])


def write_figures(out: Path, asym: dict, adapt: dict, pca: dict, tanks: dict) -> None:
    """The report's figures (:data:`FIGURES`) from the experiments' results, into ``out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    K, tau, theta, mse, conv = asym["K"], asym["tau"], asym["theta"], asym["mse"], asym["conv"]
    ratio = np.divide(theta, tau)
    for values, label, fname in (
        (mse, "step-test MSE", "fig3_asymptotic_mse.png"),
        (conv, "convergence time", "fig5_convergence_time.png"),
    ):
        fig, axes = plt.subplots(1, 2, figsize=(10, 4))
        for ax, sel, xv, yv, xl, yl in (
            (axes[0], np.isclose(K, 0.5), tau, ratio, "tau", "theta/tau (K = 0.5)"),
            (axes[1], np.isclose(ratio, 0.5), tau, K, "tau", "K (theta/tau = 0.5)"),
        ):
            xs, ys = np.unique(xv[sel]), np.unique(yv[sel])
            img = np.full((ys.size, xs.size), np.nan)
            for x, y, v in zip(xv[sel], yv[sel], values[sel], strict=True):
                img[np.searchsorted(ys, y), np.searchsorted(xs, x)] = v
            im = ax.pcolormesh(_edges(xs), _edges(ys), img, cmap="viridis")
            ax.set(xlabel=xl, ylabel=yl)
            fig.colorbar(im, ax=ax, label=label)
        fig.tight_layout()
        fig.savefig(out / fname, dpi=110)
        plt.close(fig)

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, idx, name in (
        (axes[0], int(np.argmax(mse)), "worst"),
        (axes[1], int(np.argmin(mse)), "best"),
    ):
        args = (K[idx], tau[idx], theta[idx])
        tuned = step_test(*args, asym["kp"][idx], asym["ki"][idx])
        init = step_test(*args, AGENT_KP0, AGENT_KI0)
        t = 0.01 * np.arange(tuned.y.shape[1])
        ax.plot(t, tuned.target[0], "k--", label="target")
        ax.plot(t, tuned.y[0], label=f"meta-RL (MSE {mse[idx]:.4f})")
        ax.plot(t, init.y[0], alpha=0.6, label="initial tuning")
        ax.set(title=f"{name}: K={args[0]:.2f} tau={args[1]:.2f} theta={args[2]:.2f}",
               xlabel="time", ylabel="y")  # fmt: skip
        ax.legend()
    fig.tight_layout()
    fig.savefig(out / "fig4_trajectories.png", dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(2, 2, figsize=(10, 6), sharex="col")
    for col, name in enumerate(("tau_ramp", "k_step")):
        for mode, style in (("adaptive", "-"), ("frozen", "-.")):
            g = np.array(adapt[name]["gains"][mode])
            t = RL_STEP_AGENT_UNITS * np.arange(g.shape[0])
            axes[0, col].plot(t, g[:, 0], style, label=f"kp {mode}")
            axes[1, col].plot(t, g[:, 1], style, label=f"ki {mode}")
        axes[0, col].set(title=name)
        axes[1, col].set(xlabel="time")
        for ax in axes[:, col]:
            ax.legend()
    fig.tight_layout()
    fig.savefig(out / "fig7_adaptation.png", dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, c, name in ((axes[0], pca["K"], "K"), (axes[1], pca["tau"], "tau")):
        sc = ax.scatter(pca["proj"][:, 0], pca["proj"][:, 1], c=c, cmap="viridis")
        ax.set(xlabel="PC1", ylabel="PC2", title=f"deep hidden state coloured by {name}")
        fig.colorbar(sc, ax=ax, label=name)
    fig.tight_layout()
    fig.savefig(out / "fig8_hidden_pca.png", dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(3, 1, figsize=(10, 8), sharex=True)
    for name, rec in tanks.items():
        tmin = rec["t"] / 60
        axes[0].plot(tmin, rec["pv"], label=f"{name} (MSE {rec['mse']:.2f})", lw=0.8)
        axes[1].plot(tmin, rec["kp"], label=name)
        axes[2].plot(tmin, rec["ki"], label=name)
    first = next(iter(tanks.values()))
    axes[0].plot(first["t"] / 60, first["sp"], "k:", label="setpoint")
    axes[0].plot(first["t"] / 60, first["target"], "k--", label="target", lw=0.8)
    axes[0].set(ylabel="level, cm")
    axes[1].set(ylabel="kp, (L/min)/cm")
    axes[2].set(ylabel="ki, (L/min)/(cm s)", xlabel="time, min")
    for ax in axes:
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "fig9_two_tank.png", dpi=110)
    plt.close(fig)


INFERENCE_NOTE = {
    "float32": " Inference: the tuner's FastPolicy, float32.",
    "bfloat16": " Inference: the tuner's FastPolicy with bfloat16 GEMMs.",
}


def _plant(p: dict) -> str:
    return ", ".join(f"{k} = {v:.3g}" for k, v in p.items())


def _held_out(m: dict) -> list[str]:
    """The held-out plants' lines (metrics of before session 36 have none)."""
    if "held_out" not in m:
        return []
    h = m["held_out"]
    return [
        "In sample, and out: the paper grid, the adaptation runs and the robustness"
        " conditions served to pick the shipped weights among checkpoints and weight"
        " averages (service/models/TRAINING.md, sessions 22-23), so the numbers above are"
        f" in-sample. On {h['grid_size']} plants drawn at random over the same box, which"
        " no selection saw (`held_out_grid`): worst"
        f" {h['worst_mse']:.4g} ({_plant(h['worst_plant'])}), median {h['median_mse']:.4g},"
        f" convergence worst {h['convergence']['worst_time']:.4g}; improved SIMC with the"
        f" true model worst {h['simc_improved_worst_mse']:.4g}, median"
        f" {h['simc_improved_median_mse']:.4g}, beaten on"
        f" {100 * h['beats_simc_improved']:.0f}%.",
        "",
    ]


def render_report(m: dict) -> str:
    a, c, ad, p = m["asymptotic"], m["convergence"], m["adaptation"], PAPER
    sp = m["adaptation_spread"]
    rows = [
        ("Asymptotic MSE, worst", a["worst_mse"], p["asymptotic_worst_mse"]),
        ("Asymptotic MSE, median", a["median_mse"], None),
        ("Asymptotic MSE, best", a["best_mse"], p["asymptotic_best_mse"]),
        ("Convergence time, worst", c["worst_time"], p["convergence_worst_time"]),
        ("Convergence time, best", c["best_time"], p["convergence_best_time"]),
        ("Tau ramp MSE, adaptive", ad["tau_ramp"]["adaptive"], p["adapt_tau_ramp_mse"]),
        ("Tau ramp MSE, frozen gains", ad["tau_ramp"]["frozen"], p["frozen_tau_ramp_mse"]),
        ("K step MSE, adaptive", ad["k_step"]["adaptive"], p["adapt_k_step_mse"]),
        ("K step MSE, frozen gains", ad["k_step"]["frozen"], p["frozen_k_step_mse"]),
        ("PCA: variance share of 2 PCs", m["hidden_pca"]["two_component_share"],
         p["pca_two_component_share"]),
    ]  # fmt: skip
    lines = [
        "# pitune evaluation (paper section 5)",
        "",
        f"Grid: {a['grid_size']} plants, {m['rl_steps']} RL steps of tuning each"
        + (" (quick run)" if m["quick"] else "")
        + f". Wall time {m['wall_s']} s."
        + INFERENCE_NOTE.get(m.get("inference", "reference"), ""),
        "",
        "| quantity | pitune | paper |",
        "|---|---|---|",
    ]
    for name, ours, paper in rows:
        lines.append(f"| {name} | {ours:.4g} | {'' if paper is None else f'{paper:.4g}'} |")
    lines += [
        "",
        f"The agent's worst plant: {_plant(a['worst_plant'])}. With the true model on the"
        f" same grid, SIMC as the paper ran it (its Table 2: the original rule's gain, the improved"
        f" rule's integral time) scores worst {a['simc_worst_mse']:.4g}, median"
        f" {a['simc_median_mse']:.4g}; improved SIMC with tau_c = 2 tau (the engine's own"
        f" model tuning) worst {a['simc_improved_worst_mse']:.4g}, median"
        f" {a['simc_improved_median_mse']:.4g}, and the agent beats it on"
        f" {100 * a['beats_simc_improved']:.0f}% of the plants. The step test runs at the"
        " paper's time step, 0.01 time units.",
        "",
        *_held_out(m),
        "Not in the paper: with setpoint changes at arbitrary times (period 11 +-30%, random"
        f" phase, forgetting {DEFAULT_FORGETTING:g}) the same grid scores worst"
        f" {m['robustness']['worst_mse']:.4g}, median {m['robustness']['median_mse']:.4g}.",
        "",
        "Not in the paper: the adaptation experiment over 16 plants (8 K steps and 8 tau"
        " ramps, 2x and 4x up and down across the box), tracking MSE geometric mean / worst:"
        f" K steps {sp['k_steps']['gmean']:.2g} / {sp['k_steps']['worst']:.2g}, tau ramps"
        f" {sp['tau_ramps']['gmean']:.2g} / {sp['tau_ramps']['worst']:.2g}.",
        "",
        "Not in the paper: on a quiet loop (settled at its setpoint with the oracle's gains,"
        f" no setpoint change, noise {m['quiet']['noise']:g}) {m['rl_steps']} RL steps move"
        f" the gains by factors {m['quiet']['gain_ratio_min']:.2f} to"
        f" {m['quiet']['gain_ratio_max']:.2f} (worst step-test MSE"
        f" {m['quiet']['worst_mse_before']:.2g} -> {m['quiet']['worst_mse_after']:.2g}):"
        " the agent needs setpoint changes to learn from, so the tuner steps a loop only"
        " after one (its excitation gate).",
        "",
        "## Table 2: gains beside SIMC",
        "",
        "| system | Kc ours | Kc paper | Kc SIMC | tau_I ours | tau_I paper | tau_I SIMC "
        "| MSE ours |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, r in m["table2"].items():
        lines.append(
            f"| {name} {r['plant']} | {r['ours']['Kc']:.3f} | {r['paper']['Kc']:.3f} | "
            f"{r['simc']['Kc']:.3f} | {r['ours']['tau_I']:.3f} | {r['paper']['tau_I']:.3f} | "
            f"{r['simc']['tau_I']:.3f} | {r['mse']:.2g} |"
        )
    lines += [
        "",
        "## Two-tank level loop (MSE vs target after the first setpoint change, cm^2)",
        "",
    ]
    lines += [f"- {name}: {v:.3f}" for name, v in m["two_tank"].items()]
    lines += ["", "## Bar", ""]
    lines += [f"- {k}: {'met' if v else 'NOT met'}" for k, v in m["bar"].items()]
    lines += [
        "",
        "Figures (beside this report): " + ", ".join(sorted(f"`{f}`" for f in FIGURES)),
        "",
    ]
    return "\n".join(lines)


FIGURES = (
    "fig3_asymptotic_mse.png",
    "fig4_trajectories.png",
    "fig5_convergence_time.png",
    "fig7_adaptation.png",
    "fig8_hidden_pca.png",
    "fig9_two_tank.png",
)


CHANGES_FROM_PAPER = """\
- **Imitation warm start (DAgger).** Before PPO the actor learns on its own rollouts to
  move the gains toward the best fixed PI of each simulated task (the step-test optimum,
  tabulated over theta/tau and scaled by K and tau). Like the critic's privileged inputs
  this is offline-only knowledge; online the agent sees only [kp, ki, e, int_e]. Why: the
  paper needed 2,500 PPO epochs (750k episodes); a dense supervised signal reaches its
  asymptotic performance on two CPU cores within the time budget.
- **The shipped weights are the warm start's.** PPO fine-tuning from them lowered the
  policy's own episode cost but worsened the settled gains (validation worst case
  0.001 -> 0.005-0.037, convergence time 66 -> 270) in the epochs we could afford, so
  imitation checkpoints ship (v6: a weight average of three); `TRAINING.md` has the
  numbers.
- **Relative actions, log-gain features.** The policy outputs a log-relative change
  (dk = k (exp(a) - 1), at most a factor e per step) and reads log kp, log ki and a
  signed log of int_e. Gains stay positive by construction and one output scale serves
  kp = 0.3 and ki = 8 alike (the paper names this range as a main difficulty).
- **Setpoint-move scaling (online, in the engine).** The tuning engine shows the agent
  e and int_e multiplied by 2 / (size of the last setpoint move, agent units), bounded to
  [0.25, 4]: a linear loop's response to any move then has the shape of the +-1 square
  wave's the agent was trained on (docs/tuner.md). The paper's protocol is unchanged by it.
- **Error observation averaged over the period's end (online and in training).** The
  agent's e is the mean measured error over the last 20 % of the RL period (the sample at
  the period's end where the setpoint moved inside that window), not the single end
  sample it was trained on: measurement noise reaches it sqrt(n) times smaller (5.7x at
  33 samples), and the paper grid improved with the weights of the time (v2, when it was
  introduced: worst 0.0027 -> 0.0012, median 0.00034 -> 0.00020). One implementation
  (`service.units.error_window`) for the engine and the training environment;
  docs/tuner.md, Robustness measures 5.
{distribution}
- **Imitation label.** In the later stages the label is half the log-distance to the
  oracle's gains (still clipped to one step's reach): a gentler approach that lost less
  precision when the setpoint timing varies.
{selection}
- **PPO details** (of a stage with a PPO phase: `epochs` > 0 in its configuration; see
  the epochs above for this one). Advantage normalisation, value targets scaled by 1/10,
  gradient-norm clipping 0.5, critic learning rate 1e-3, 20 value-only warm-up epochs
  before the policy is updated, exploration std reset to exp(-2.5) at the start of PPO.
- **Cost aggregation.** The squared tracking error in the cost is the mean over the 275
  controller samples of each RL step, so it has the scale of the step-test MSE.
- **Controller output limit.** +-100 (far outside any sane tuning of the box) so an
  unstable trial stays finite.
"""
"""The model card's changes from the paper; ``{distribution}`` and ``{selection}`` are
stated from the weights' own training config (:func:`_distribution`, :func:`_selection`)."""


def _distribution(cfg: dict) -> str:
    """The training distribution of the run that made the weights (``cfg``: its config)."""
    if not cfg:
        return "- **Training distribution.** Not recorded with these weights."
    text = (
        f"- **Training distribution.** In the run that made these weights,"
        f" {100 * cfg['drift_prob']:.0f}% of the episodes have drifting dynamics (K step or"
        f" tau ramp) and {100 * cfg['forgetting_prob']:.0f}% run with the forgetting factor"
        f" {cfg['forgetting']:g} used online (earlier runs of the lineage: `TRAINING.md`);"
        f" warm-start episodes are {cfg['bc_horizon']} RL steps (the paper: 40) so the"
        " hidden state stays calibrated over long runs."
    )
    period = EnvConfig().sp_period
    if not cfg["sp_jitter"]:
        return _bullet(text + f" The setpoint moves every {period:g} time units, as in the paper.")
    return _bullet(
        text
        + (
            f" The setpoint period is drawn per episode from {period:g} time units"
            f" +-{100 * cfg['sp_jitter']:.0f}% with a random phase (the paper: exactly every"
            f" {period / RL_STEP_AGENT_UNITS:g} RL steps), because a real loop's setpoint does"
            " not move on the agent's clock; agents trained on the fixed clock score 50x worse"
            " when it moves at other times."
        )
    )


def _selection(cfg: dict, averaged: bool) -> str:
    """How the weights were kept: the validation score's terms in their run's config
    (``val_robust``, ``val_adapt``), and whether they are a weight average instead."""
    terms = [
        f"(worst step-test MSE / {VAL_MSE_BAR:g})",
        f"(largest gain drift after {VAL_SETTLED_TIME:g} time units / {VAL_DRIFT_BAR:.0%})",
    ]
    if cfg.get("val_robust"):
        terms.append("(the robustness conditions' worst and median MSE / their bars)")
    if cfg.get("val_adapt"):
        terms.append("(the tau ramp's and the K step's adaptive MSE / v2's)")
    worst = "worse" if len(terms) == 2 else "worst"
    text = (
        f"- **Epoch selection.** The kept epoch minimises the {worst} of"
        f" {', '.join(terms[:-1])} and {terms[-1]} on a fixed validation set, with and"
        " without setpoint jitter, so that it is both precise and settled."
    )
    if averaged:
        text += (
            " These weights are not one kept epoch but the element-wise mean of the kept"
            " actors named above, which no validation scored."
        )
    return _bullet(
        text + " The validation set shares 8 plants with the paper grid, and the choice among kept"
        " epochs and weight averages was made on the paper grid, its adaptation runs and the"
        " robustness conditions themselves (`TRAINING.md`, sessions 22-23): those numbers"
        " are in-sample. The held-out plants of `reports/report.md` are not."
    )


def _bullet(text: str) -> str:
    """A list item wrapped as the card's fixed ones are."""
    return textwrap.fill(text, width=88, subsequent_indent="  ", break_on_hyphens=False)


def write_model_card(path: Path, agent: Agent, metrics: dict) -> None:
    """``MODEL_CARD.md`` beside the weights: training facts, changes, evaluation numbers."""
    meta = agent.meta
    cfg = meta.get("train_config", {})
    mix = cfg.get("core_share", 1.0) < 1.0  # the real-loop episodes beside the paper's
    lines = [
        "# pitune agent: model card",
        "",
        "Recurrent meta-RL PI tuner after McClement et al. (J. Process Control 2022): a",
        "2-layer GRU (100 units) and two Leaky-ReLU layers (64 units) to the action mean;",
        "trained offline on FOPTD plants K in [0.25, 1], tau in [0.25, 1], theta/tau in",
        "[0, 1]"
        + (
            f" ({100 * cfg['core_share']:.0f}% of the episodes) and on real loops beside"
            " them: measurement noise, load disturbances, setpoint moves of any size and"
            " timing, hints off by up to 3x, theta/tau up to 2, second-order plants"
            " (TRAINING.md)"
            if mix
            else ""
        )
        + f"; one RL step every {RL_STEP_AGENT_UNITS:g} time units. Use it through"
        " `service.agent.load_agent`. Off the paper's protocol: `reports/robust.md`.",
        "",
        "## Training",
        "",
        f"- Source run: `{meta.get('source', '?')}` at commit `{meta.get('commit', '?')}`,"
        f" warm-started from: `{(meta.get('init_from') or {}).get('path', 'none')}`",
        *(
            [
                "- Weights: the element-wise mean (`pitune average`) of "
                + ", ".join(
                    f"`{a['path']}` (epoch {a['epoch']}, {a['wall_s']} s into its run)"
                    for a in meta["average_of"]
                )
                + "; the facts below are the latest one's"
            ]
            if meta.get("average_of")
            else []
        ),
        f"- Epochs run: {meta.get('epoch', '?')} (the configuration allowed up to"
        f" {cfg.get('bc_epochs', '?')} imitation epochs, then {cfg.get('value_warmup', '?')}"
        f" value warm-up and {cfg.get('epochs', '?')} PPO epochs"
        + ("; no PPO phase" if cfg.get("epochs") == 0 else "")
        + f"); episodes: {meta.get('episodes', '?')}; wall time of this run:"
        f" {meta.get('wall_s', '?')} s on 2 CPU cores (1 torch thread)",
        f"- Validation at export (64 random plants + 8 corners,"
        f" {cfg.get('eval_steps', 80)} RL steps): "
        + str(meta.get("validation", "none (a weight average; the evaluation below)")),
        "- Runs warm-started from earlier runs, and the PPO fine-tuning attempts: see"
        " `TRAINING.md` beside this card.",
        "",
        "Training configuration:",
        "",
        "```json",
        json.dumps(cfg, indent=2),
        "```",
        "",
        "## Changes from the paper",
        "",
        CHANGES_FROM_PAPER.format(
            distribution=_distribution(cfg),
            selection=_selection(cfg, bool(meta.get("average_of"))),
        ),
        "## Evaluation (`pitune evaluate`)",
        "",
        render_report(metrics).split("\n", 2)[2],
    ]
    path.write_text("\n".join(lines))
