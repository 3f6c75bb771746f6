"""`pitune evaluate`: the protocol's pieces and a quick run on the shipped weights."""

import json

import numpy as np
import pytest

from service.agent import load_agent
from service.learn.closed_loop import convergence_time
from service.learn.evaluate import evaluate, evaluate_only
from service.learn.report import FIGURES, render_report, write_model_card
from service.units import RL_STEP_AGENT_UNITS


def test_convergence_time_is_last_exit_from_the_10_percent_band():
    steps = np.ones((10, 3, 2))
    steps[:, 0, 0] = [0.1, 0.5, 0.95, 1.2, 0.95, 1.0, 1.0, 1.0, 1.0, 1.0]  # leaves band at 3
    steps[:, 1, 1] = [0.1, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0]  # in from index 1
    steps[:, 2, :] = 2.0  # never outside
    np.testing.assert_allclose(
        convergence_time(steps), [4 * RL_STEP_AGENT_UNITS, RL_STEP_AGENT_UNITS, 0]
    )


@pytest.fixture(scope="module")
def quick_report(tmp_path_factory):
    out = tmp_path_factory.mktemp("reports")
    agent = load_agent()
    return out, agent, evaluate(agent, out, quick=True)


def test_quick_evaluation_writes_the_report(quick_report):
    out, _, metrics = quick_report
    for name in FIGURES:
        assert (out / name).stat().st_size > 10_000, name
    saved = json.loads((out / "metrics.json").read_text())
    assert saved["asymptotic"]["grid_size"] == 48
    report = (out / "report.md").read_text()
    assert "| Asymptotic MSE, worst |" in report and "0.03" in report
    # the quiet-loop experiment starts every plant from the oracle's (good) gains
    quiet = saved["quiet"]
    assert quiet["worst_mse_before"] < 0.003
    assert 0 < quiet["gain_ratio_min"] <= quiet["gain_ratio_max"]
    assert "quiet loop" in report


def test_shipped_agent_tunes_the_grid_and_the_tanks(quick_report):
    _, _, m = quick_report
    a = m["asymptotic"]
    # the paper's worst case over its training box is 0.030; SIMC's median is about 0.0035
    assert a["worst_mse"] <= 0.030
    assert a["median_mse"] < a["simc_median_mse"]
    assert m["convergence"]["worst_time"] <= 140.0
    tanks = m["two_tank"]
    assert tanks["meta-RL"] < 0.2 * tanks["untuned"]
    assert tanks["meta-RL, noise"] < 0.2 * tanks["untuned, noise"]


def test_only_adaptation_gives_the_full_runs_numbers(quick_report, tmp_path):
    """``--only adaptation`` (the fast check of a training checkpoint) runs the same
    protocol and seeds as the whole evaluation: the same numbers, and only its section."""
    _, agent, metrics = quick_report
    part = evaluate_only(agent, tmp_path, ("adaptation",), quick=True)
    assert part["adaptation"] == metrics["adaptation"]
    assert part["adaptation_spread"] == metrics["adaptation_spread"]
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["only"] == ["adaptation"] and "asymptotic" not in saved
    assert not (tmp_path / "report.md").exists()
    with pytest.raises(ValueError, match="grid, adaptation"):
        evaluate_only(agent, tmp_path, ("pca",), quick=True)


def test_adaptation_over_16_plants_follows_each_change(quick_report):
    """The spread of experiment 3: 8 K steps and 8 tau ramps, each tracked after the change
    inside the paper's adaptive bounds (K step 0.0032, tau ramp 0.006; shipped agent, quick
    run: worst 0.0020 and 0.0026; frozen gains score 0.04-0.1 on the one-plant runs), and
    the report says so."""
    _, _, m = quick_report
    spread, paper = m["adaptation_spread"], m["paper"]
    for name, bound in (("k_steps", paper["adapt_k_step_mse"]),
                        ("tau_ramps", paper["adapt_tau_ramp_mse"])):  # fmt: skip
        mse = np.array(spread[name]["mse"])
        assert mse.shape == (8,) and np.all(np.isfinite(mse)) and mse.min() > 0, name
        assert spread[name]["worst"] == mse.max() < bound, (name, mse)
        assert mse.min() <= spread[name]["gmean"] <= mse.max()
    assert "over 16 plants" in render_report(m)


def test_model_card_lists_training_and_results(quick_report, tmp_path):
    _, agent, metrics = quick_report
    card = tmp_path / "MODEL_CARD.md"
    write_model_card(card, agent, metrics)
    text = card.read_text()
    assert "Changes from the paper" in text and "Asymptotic MSE, worst" in text
    assert f"Epochs run: {agent.meta['epoch']}" in text


def test_robust_suite_runs_through_the_engine_and_reports(tmp_path):
    """The quick robustness suite: every condition row has its numbers, the report and
    the figure are written, and the paper protocol through the engine tunes."""
    from service.learn.robust_suite import robust_suite

    result = robust_suite(load_agent(), tmp_path, quick=True)
    rows = {r["condition"]: r for r in result["conditions"]}
    assert set(rows) == {"paper protocol", "noise 0.05"}
    for r in rows.values():
        assert 0 < r["median_mse"] <= r["worst_mse"] and 0 <= r["beats_simc"] <= 1
    assert rows["paper protocol"]["unstable"] == 0
    assert rows["paper protocol"]["worst_mse"] < 0.05  # untuned start: about 1.8
    assert (tmp_path / "robust.md").read_text().count("| noise 0.05 |") == 1
    assert result["inference"] == "reference"  # agent.act: the report names it
    assert "inference reference." in (tmp_path / "robust.md").read_text()
    assert (tmp_path / "fig10_robust_noise_load.png").stat().st_size > 10_000


def test_robust_suite_guard_option_is_checked_and_named_in_the_report(tmp_path, capsys):
    """``pitune evaluate --robust --guard JSON``: settings that are not a loop's guard are
    refused before anything runs; a table made with settings says which."""
    from service.cli import main
    from service.learn.robust_suite import render

    out = tmp_path / "robust"
    for bad in ('{"identify": 3}', '{"no_such_setting": 1}', "[1]", "{"):
        with pytest.raises(SystemExit) as exc:
            main(["evaluate", "--robust", "--out", str(out), "--guard", bad])
        assert exc.value.code == 2 and "guard settings" in capsys.readouterr().err
    assert main(["evaluate", "--out", str(out), "--guard", '{"identify": true}']) == 2
    assert "only with --robust" in capsys.readouterr().err
    assert not out.exists()
    row = {"condition": "paper protocol", "worst_mse": 0.002, "median_mse": 0.0002,
           "beats_simc": 0.8, "unstable": 0, "meets_bar": True}  # fmt: skip
    text = render({"periods": 80, "quick": False, "wall_s": 1.0, "conditions": [row],
                   "guard": {"identify": True, "auto_rescale": True}})  # fmt: skip
    assert 'guard settings {"auto_rescale": true, "identify": true}' in text
    assert "default guard" in render({"periods": 80, "quick": False, "wall_s": 1.0,
                                      "conditions": [row]})  # fmt: skip


def test_robust_report_shows_the_adaptation_through_the_engine_beside_v2():
    """The suite's adaptation section (service/learn/robust_adaptation.py): the paper's
    two runs and the spread's geometric mean and worst per kind, each beside v2's, and
    both unstable counts; the 18 plants are the paper's two then the spread's 16."""
    from service.learn import robust_adaptation
    from service.learn.experiments import SPREAD_MOVES
    from service.learn.robust_suite import render

    K0, tau0, theta, K1, tau1 = robust_adaptation.plants()
    assert (K0[:2].tolist(), K1[:2].tolist()) == ([0.5, 0.5], [0.5, 1.0])
    assert (tau0[:2].tolist(), tau1[:2].tolist()) == ([0.4, 0.5], [1.0, 0.5])
    assert np.all(np.c_[K0[2:10], K1[2:10]] == SPREAD_MOVES)
    assert np.all(np.c_[tau0[10:], tau1[10:]] == SPREAD_MOVES)
    assert np.allclose(theta[10:], 0.2 * tau0[10:])

    def result(x, unstable):
        return {"tau_ramp": x, "k_step": 2 * x, "k_steps": {"gmean": 3 * x, "worst": 4 * x},
                "tau_ramps": {"gmean": 5 * x, "worst": 6 * x}, "unstable": unstable}  # fmt: skip

    row = {"condition": "paper protocol", "worst_mse": 0.002, "median_mse": 0.0002,
           "beats_simc": 0.8, "unstable": 0, "meets_bar": True}  # fmt: skip
    text = render({"periods": 80, "quick": False, "wall_s": 1.0, "conditions": [row],
                   "adaptation": result(0.001, 0), "adaptation_v2": result(0.01, 2)})  # fmt: skip
    assert "unstable 0, v2 2" in text
    assert "| paper tau ramp (0.4 -> 1) | 0.001 | 0.01 |" in text
    assert "| 8 tau ramps, worst | 0.006 | 0.06 |" in text
