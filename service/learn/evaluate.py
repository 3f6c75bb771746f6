"""``pitune evaluate``: the paper's section 5 on an agent, beside the paper's numbers.

Writes ``metrics.json``, PNG figures and ``report.md`` into the output directory
(``runs/evaluate/`` by default; ``--out reports`` rewrites the shipped report) and
optionally a model card. Every experiment
(:mod:`service.learn.experiments`) goes through the stable agent API
(:func:`service.agent.load_agent`) or the tuner's inference path
(:class:`service.agent.fast.FastPolicy`); :mod:`service.learn.report` renders the results.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, get_args

import numpy as np

from service.agent.fast import FastPolicy
from service.agent.model import load_agent
from service.learn.closed_loop import Policy
from service.learn.experiments import (
    PAPER,
    adaptation,
    asymptotic,
    hidden_pca,
    quiet,
    robustness,
    table2,
    two_tank,
)
from service.learn.report import render_report, write_figures, write_model_card
from service.learn.robust import robust_suite

Inference = Literal["reference", "auto", "float32", "bfloat16"]
"""``agent.act`` (reference), or the tuner's FastPolicy in this precision."""


@dataclass(frozen=True)
class EvalConfig:
    """What ``pitune evaluate`` runs and where it writes."""

    out: Path = Path("runs/evaluate")
    """Directory for metrics.json, report.md and the figures (created; the shipped
    report in ``reports/`` is rewritten only when asked for with ``--out reports``)."""
    quick: bool = False
    """Reduced version (CI, < 2 minutes): smaller grids, fewer RL steps, shorter runs."""
    weights: Path | None = None
    """Agent file; None: the shipped weights."""
    precision: Inference = "reference"
    """``agent.act`` (reference), or the tuner's FastPolicy in this precision."""
    card: Path | None = None
    """Also write a model card here."""
    robust: bool = False
    """Run the robustness suite through the tuning engine (:mod:`service.learn.robust`)
    instead of the paper's experiments."""


def evaluate(agent: Policy, out: Path, quick: bool = False) -> dict:
    """All experiments with ``agent`` (or the tuner's inference path); writes ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    start = time.monotonic()
    steps = 80 if quick else 100
    asym = asymptotic(agent, steps, quick)
    t2 = table2(agent, steps)
    robust = robustness(agent, steps, quick)
    still = quiet(agent, steps, quick)
    adapt = adaptation(agent, quick)
    pca = hidden_pca(agent, steps, quick)
    minutes = 60.0 if quick else 180.0
    tanks = {
        "untuned": two_tank(None, noise_cm=0.0, minutes=minutes),
        "meta-RL": two_tank(agent, noise_cm=0.0, minutes=minutes),
        "untuned, noise": two_tank(None, noise_cm=1.0, minutes=minutes),
        "meta-RL, noise": two_tank(agent, noise_cm=1.0, minutes=minutes),
    }
    worst, best = int(np.argmax(asym["mse"])), int(np.argmin(asym["mse"]))

    def plant(i):
        return {
            "K": float(asym["K"][i]),
            "tau": float(asym["tau"][i]),
            "theta": float(asym["theta"][i]),
        }

    metrics = {
        "agent": agent.meta.get("source", "shipped"),
        "inference": getattr(agent, "precision", "reference"),
        "quick": quick,
        "rl_steps": steps,
        "asymptotic": {
            "grid_size": int(asym["mse"].size),
            "worst_mse": float(asym["mse"][worst]),
            "worst_plant": plant(worst),
            "median_mse": float(np.median(asym["mse"])),
            "best_mse": float(asym["mse"][best]),
            "best_plant": plant(best),
            "simc_worst_mse": float(asym["simc_mse"].max()),
            "simc_median_mse": float(np.median(asym["simc_mse"])),
        },
        "convergence": {
            "worst_time": float(asym["conv"].max()),
            "median_time": float(np.median(asym["conv"])),
            "best_time": float(asym["conv"].min()),
        },
        "table2": t2,
        "adaptation": {
            name: {k: v for k, v in res.items() if k != "gains"}
            | {"improvement": res["frozen"] / max(res["adaptive"], 1e-12)}
            for name, res in adapt.items()
        },
        "hidden_pca": {"two_component_share": pca["share2"]},
        "robustness": robust,
        "quiet": still,
        "two_tank": {name: rec["mse"] for name, rec in tanks.items()},
        "paper": PAPER,
    }
    metrics["bar"] = {
        "asymptotic_worst_le_0.030": metrics["asymptotic"]["worst_mse"] <= 0.030,
        "asymptotic_median_le_0.003": metrics["asymptotic"]["median_mse"] <= 0.003,
        "convergence_worst_le_140": metrics["convergence"]["worst_time"] <= 140.0,
        "adapt_tau_below_paper_and_5x": metrics["adaptation"]["tau_ramp"]["adaptive"] < 0.006
        and metrics["adaptation"]["tau_ramp"]["improvement"] >= 5,
        "adapt_k_below_paper_and_5x": metrics["adaptation"]["k_step"]["adaptive"] < 0.0032
        and metrics["adaptation"]["k_step"]["improvement"] >= 5,
        "two_tank_tuned_better": tanks["meta-RL"]["mse"] < tanks["untuned"]["mse"]
        and tanks["meta-RL, noise"]["mse"] < tanks["untuned, noise"]["mse"],
    }
    metrics["wall_s"] = round(time.monotonic() - start, 1)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    write_figures(out, asym, adapt, pca, tanks)
    (out / "report.md").write_text(render_report(metrics))
    return metrics


def main(cfg: EvalConfig) -> int:
    """Evaluate, print the report, write the card; exit code 1 if a bar is not met (full run)."""
    agent = load_agent(cfg.weights)
    policy = agent if cfg.precision == "reference" else FastPolicy(agent, precision=cfg.precision)
    if cfg.robust:
        result = robust_suite(policy, cfg.out, quick=cfg.quick)
        print((cfg.out / "robust.md").read_text())
        return 0 if all(r["meets_bar"] for r in result["conditions"]) or cfg.quick else 1
    metrics = evaluate(policy, cfg.out, quick=cfg.quick)
    print((cfg.out / "report.md").read_text())
    if cfg.card is not None:
        write_model_card(cfg.card, agent, metrics)
    return 0 if all(metrics["bar"].values()) or cfg.quick else 1


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--weights", type=Path, default=None, help="agent file (default: shipped)")
    p.add_argument(
        "--out",
        type=Path,
        default=EvalConfig.out,
        help="output directory, created if missing (the shipped report: --out reports)",
    )
    p.add_argument(
        "--robust",
        action="store_true",
        help="the robustness suite through the tuning engine (noise, load, setpoint moves, "
        "hint errors, dead time, second-order plants) instead of the paper's section 5",
    )
    p.add_argument("--quick", action="store_true", help="reduced version (CI, < 2 minutes)")
    p.add_argument("--card", type=Path, default=None, help="also write a model card here")
    p.add_argument(
        "--precision",
        choices=get_args(Inference),
        default=EvalConfig.precision,
        help="agent.act (reference), or the tuner's FastPolicy in this precision",
    )


def run(args: argparse.Namespace) -> int:
    return main(
        EvalConfig(
            out=args.out,
            quick=args.quick,
            weights=args.weights,
            precision=args.precision,
            card=args.card,
            robust=args.robust,
        )
    )
