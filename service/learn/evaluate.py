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

from service import UsageError
from service.agent.fast import FastPolicy
from service.agent.model import load_agent
from service.engine.config import guard_option
from service.learn.closed_loop import Policy
from service.learn.experiments import (
    PAPER,
    adaptation,
    adaptation_spread,
    asymptotic,
    held_out_grid,
    hidden_pca,
    quiet,
    robustness,
    table2,
    two_tank,
)
from service.learn.integrating import integrating
from service.learn.integrating import render as render_integrating
from service.learn.report import render_report, write_figures, write_model_card
from service.learn.robust_suite import robust_suite

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
    only: tuple[str, ...] = ()
    """Run only these experiments (names of :data:`PARTS`) and write their metrics.json,
    no report or figures: a fast check of a training checkpoint, e.g. the adaptation
    experiments alone in a few seconds. Empty: everything."""
    integrating: bool = False
    """Measure the agent on integrating processes through the tuning engine
    (:mod:`service.learn.integrating`) instead of the paper's experiments."""
    guard: dict | None = None
    """With ``robust``: guard settings every loop is registered with instead of the
    defaults (checked as a loop's guard), e.g. ``{"identify": true, "auto_rescale":
    true}``: the table an opt-in measure gives."""


PARTS = ("grid", "adaptation")
"""Experiments ``--only`` can run alone: the paper grid (asymptotic MSE and convergence
time, experiments 1-2) and the adaptation runs (tau ramp and K step, experiment 3, and
the same over 16 plants)."""


def evaluate(agent: Policy, out: Path, quick: bool = False) -> dict:
    """All experiments with ``agent`` (or the tuner's inference path); writes ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    start = time.monotonic()
    steps = 80 if quick else 100
    asym = asymptotic(agent, steps, quick)
    held = grid_metrics(asymptotic(agent, steps, quick, plants=held_out_grid(32 if quick else 80)))
    t2 = table2(agent, steps)
    robust = robustness(agent, steps, quick)
    still = quiet(agent, steps, quick)
    adapt = adaptation(agent, quick)
    spread = adaptation_spread(agent, quick)
    pca = hidden_pca(agent, steps, quick)
    minutes = 60.0 if quick else 180.0
    tanks = {
        "untuned": two_tank(None, noise_cm=0.0, minutes=minutes),
        "meta-RL": two_tank(agent, noise_cm=0.0, minutes=minutes),
        "untuned, noise": two_tank(None, noise_cm=1.0, minutes=minutes),
        "meta-RL, noise": two_tank(agent, noise_cm=1.0, minutes=minutes),
    }
    metrics = {
        "agent": agent.meta.get("source", "shipped"),
        "inference": getattr(agent, "precision", "reference"),
        "quick": quick,
        "rl_steps": steps,
        **grid_metrics(asym),
        "held_out": {**held["asymptotic"], "convergence": held["convergence"]},
        "table2": t2,
        "adaptation": adaptation_metrics(adapt),
        "adaptation_spread": spread,
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


def grid_metrics(asym: dict) -> dict:
    """The ``asymptotic`` and ``convergence`` sections of metrics.json from
    :func:`~service.learn.experiments.asymptotic`'s result."""
    worst, best = int(np.argmax(asym["mse"])), int(np.argmin(asym["mse"]))

    def plant(i):
        return {k: float(asym[k][i]) for k in ("K", "tau", "theta")}

    return {
        "asymptotic": {
            "grid_size": int(asym["mse"].size),
            "worst_mse": float(asym["mse"][worst]),
            "worst_plant": plant(worst),
            "median_mse": float(np.median(asym["mse"])),
            "best_mse": float(asym["mse"][best]),
            "best_plant": plant(best),
            "simc_worst_mse": float(asym["simc_mse"].max()),
            "simc_median_mse": float(np.median(asym["simc_mse"])),
            "simc_improved_worst_mse": float(asym["simc_improved_mse"].max()),
            "simc_improved_median_mse": float(np.median(asym["simc_improved_mse"])),
            "beats_simc_improved": float(np.mean(asym["mse"] < asym["simc_improved_mse"])),
        },
        "convergence": {
            "worst_time": float(asym["conv"].max()),
            "median_time": float(np.median(asym["conv"])),
            "best_time": float(asym["conv"].min()),
        },
    }


def adaptation_metrics(adapt: dict) -> dict:
    """The ``adaptation`` section of metrics.json (adaptive and frozen tracking MSE and
    their ratio per run) from :func:`~service.learn.experiments.adaptation`'s result."""
    return {
        name: {k: v for k, v in res.items() if k != "gains"}
        | {"improvement": res["frozen"] / max(res["adaptive"], 1e-12)}
        for name, res in adapt.items()
    }


def evaluate_only(agent: Policy, out: Path, parts: tuple[str, ...], quick: bool = False) -> dict:
    """Only the named experiments of :data:`PARTS`, with the same protocol (and seeds) as
    :func:`evaluate`; writes ``out/metrics.json`` with their sections, no report."""
    unknown = set(parts) - set(PARTS)
    if unknown or not parts:
        raise ValueError(f"--only takes some of {', '.join(PARTS)}; got {', '.join(parts)}")
    out.mkdir(parents=True, exist_ok=True)
    start = time.monotonic()
    steps = 80 if quick else 100
    metrics = {
        "agent": agent.meta.get("source", "shipped"),
        "inference": getattr(agent, "precision", "reference"),
        "quick": quick,
        "only": list(parts),
    }
    if "grid" in parts:
        metrics |= {"rl_steps": steps, **grid_metrics(asymptotic(agent, steps, quick))}
    if "adaptation" in parts:
        metrics["adaptation"] = adaptation_metrics(adaptation(agent, quick))
        metrics["adaptation_spread"] = adaptation_spread(agent, quick)
    metrics["wall_s"] = round(time.monotonic() - start, 1)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    return metrics


def main(cfg: EvalConfig) -> int:
    """Evaluate, print the report, write the card; exit code 1 if a bar is not met (full run)."""
    if cfg.robust and cfg.only:
        raise UsageError("--only selects among the paper's experiments; not with --robust")
    if cfg.guard is not None and not cfg.robust:
        raise UsageError("--guard sets the robustness suite's loops; only with --robust")
    if cfg.integrating and (cfg.robust or cfg.only):
        raise UsageError("--integrating is a measurement of its own: not with --robust or --only")
    agent = load_agent(cfg.weights)
    policy = agent if cfg.precision == "reference" else FastPolicy(agent, precision=cfg.precision)
    if cfg.robust:
        result = robust_suite(policy, cfg.out, quick=cfg.quick, guard=cfg.guard)
        print((cfg.out / "robust.md").read_text())
        return 0 if all(r["meets_bar"] for r in result["conditions"]) or cfg.quick else 1
    if cfg.integrating:
        cfg.out.mkdir(parents=True, exist_ok=True)
        result = integrating(policy, periods=40 if cfg.quick else 80)
        (cfg.out / "integrating.json").write_text(json.dumps(result, indent=2))
        (cfg.out / "integrating.md").write_text(render_integrating(result))
        print((cfg.out / "integrating.md").read_text())
        return 0
    if cfg.only:
        print(json.dumps(evaluate_only(policy, cfg.out, cfg.only, quick=cfg.quick), indent=2))
        return 0
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
    p.add_argument(
        "--integrating",
        action="store_true",
        help="the agent on integrating processes (levels) through the tuning engine, "
        "beside SIMC for integrating processes, and the check that pauses them",
    )
    p.add_argument("--quick", action="store_true", help="reduced version (CI, < 2 minutes)")
    p.add_argument(
        "--only",
        type=_parts,
        default=EvalConfig.only,
        metavar="PART[,PART]",
        help=f"run only these experiments ({', '.join(PARTS)}) and write their metrics.json "
        "(no report or figures; not with --robust)",
    )
    p.add_argument("--card", type=Path, default=None, help="also write a model card here")
    p.add_argument(
        "--guard",
        type=guard_option,
        default=None,
        metavar="JSON",
        help="with --robust: guard settings for every loop instead of the defaults, e.g. "
        '\'{"identify": true, "auto_rescale": true}\'',
    )
    p.add_argument(
        "--precision",
        choices=get_args(Inference),
        default=EvalConfig.precision,
        help="agent.act (reference), or the tuner's FastPolicy in this precision",
    )


def _parts(value: str) -> tuple[str, ...]:
    """``--only``'s comma-separated list, checked against :data:`PARTS`."""
    parts = tuple(x.strip() for x in value.split(",") if x.strip())
    if not parts or set(parts) - set(PARTS):
        raise argparse.ArgumentTypeError(f"choose from {', '.join(PARTS)} (got {value!r})")
    return parts


def run(args: argparse.Namespace) -> int:
    return main(
        EvalConfig(
            out=args.out,
            quick=args.quick,
            weights=args.weights,
            precision=args.precision,
            card=args.card,
            robust=args.robust,
            integrating=args.integrating,
            only=args.only,
            guard=args.guard,
        )
    )
